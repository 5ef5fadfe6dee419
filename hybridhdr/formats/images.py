"""Image files: float32 linear EXR (frames and sequences with ``timestamps.txt``), tone-mapped
8-bit PNG and H.264 MP4 previews.

:func:`write_exr_sequence`, :func:`write_png_previews`, :func:`write_mp4` write an in-memory video
(``video.frames``, ``video.t_us``: a :class:`~hybridhdr.reconstruct.api.Video`); each file goes
to a temporary name in the target folder and is renamed into place
(:func:`hybridhdr._util.atomic.atomic_path`), so a crash never leaves a truncated file under the
final name. The streaming writer of the reconstruction, which uses these, is
:class:`hybridhdr.reconstruct.output.VideoWriter`.

Every file is created with the mode ``open()`` gives (``0o666 & ~umask``).

Frames are (H, W) float32 (EXR channel ``Y``) or (H, W, 3) linear RGB (channels ``R``, ``G``,
``B``; previews are 8-bit RGB tone-mapped with one set of limits over all channels).

Tone mapping (previews only; the EXR files hold the linear values untouched):
``v = clip((log I - lo) / (hi - lo), 0, 1) ** (1 / gamma)`` with ``lo`` and ``hi`` the
``low_percentile`` and ``high_percentile`` of ``log I`` over the *valid* pixels of the whole video
(finite and above the 1e-6 floor the reconstruction clamps to; fixed over time so brightness
changes stay visible), ``gamma = 1`` by default, then ``round(255 v)`` as 8-bit grey. Invalid
pixels do not move the limits: NaN, -inf and values <= 1e-6 show black, +inf white. (With the
floor counted, a reconstruction whose clamped or NaN pixels exceed 1 % of the video had its low
limit pinned at log 1e-6, washing the picture out.)
A stream computes the same percentiles exactly (:class:`LogPercentiles`: a two-level histogram
of the float32 bit patterns), so its previews equal :func:`tone_map` of the whole video.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np

from .._util.atomic import atomic_path
from .._util.checks import check_shape

__all__ = ["tone_map", "display_map", "display_map_from", "display_map_centred", "display_gamma", "apply_display_map", "LOG_MAP_RATIO", "LogPercentiles",
           "write_exr", "read_exr", "write_exr_sequence", "write_timestamps",
           "write_png_previews", "write_mp4", "exr_compressions", "DEFAULT_EXR_COMPRESSION",
           "LOSSY_EXR_COMPRESSIONS", "TIMESTAMPS_HEADER", "read_timestamps", "write_png", "MP4Stream", "check_frame",
           "check_tone", "exr_compression"]

#: name -> OpenEXR constant name; only those the installed OpenEXR has are offered
_EXR_COMPRESSION_NAMES = {
    "none": "NO_COMPRESSION", "rle": "RLE_COMPRESSION", "zips": "ZIPS_COMPRESSION", "zip": "ZIP_COMPRESSION",
    "piz": "PIZ_COMPRESSION", "pxr24": "PXR24_COMPRESSION", "zstd": "ZSTD_COMPRESSION",
    "htj2k": "HTJ2K256_COMPRESSION",
}
#: lossy for float32 data (PXR24 rounds to 24 bits)
LOSSY_EXR_COMPRESSIONS = frozenset({"pxr24"})
#: the default: lossless, readable by every OpenEXR reader, and the fastest. Reconstructed float32
#: frames carry noise in their low mantissa bits, so the lossless codecs barely shrink them: on
#: ecd_slider_depth's AKF output (240x180) ZIP saves 7 % of the bytes for 3.5x the encoding time
#: (3.1 vs 0.9 ms/frame), ZIPS 0 % (5.0 ms), PIZ 3 % (9.6 ms), zstd 14 % (4.1 ms, OpenEXR >= 3.4
#: only); on benchmarks/cli.py's 346x260 recording ZIP saves 4.5 %. Measurements in
#: docs/reconstruct.md ("EXR compression"); ``--exr-compression zip`` remains for smaller files.
DEFAULT_EXR_COMPRESSION = "none"

_FLOOR = 1e-6  # tone_map's floor of I (log 1e-6)
# smallest float32 >= 1e-6 (float64) and the float32 just below it: the key of every value the floor raises
_C32 = np.float32(1e-6) if float(np.float32(1e-6)) >= 1e-6 else np.nextafter(np.float32(1e-6), np.float32(1))
_SENTINEL32 = np.nextafter(_C32, np.float32(0))
_SENTINEL_KEY = int(np.array(_SENTINEL32, np.float32).view(np.uint32))


def exr_compressions() -> list[str]:
    """EXR compression names the installed OpenEXR supports (``--exr-compression`` choices)."""
    try:
        import OpenEXR
    except ImportError:  # pragma: no cover
        return list(_EXR_COMPRESSION_NAMES)
    return [k for k, v in _EXR_COMPRESSION_NAMES.items() if hasattr(OpenEXR, v)]


def exr_compression(name: str):
    import OpenEXR
    key = str(name).lower()
    if key not in _EXR_COMPRESSION_NAMES or not hasattr(OpenEXR, _EXR_COMPRESSION_NAMES[key]):
        raise ValueError(f"unknown EXR compression {name!r}; expected one of {exr_compressions()}")
    return getattr(OpenEXR, _EXR_COMPRESSION_NAMES[key])


def check_frame(img) -> np.ndarray:
    a = np.ascontiguousarray(img, dtype=np.float32)
    check_shape(a, "H W | H W 3", "a frame")
    return a


def write_exr(path, img, *, compression: str = DEFAULT_EXR_COMPRESSION, channel: str = "Y") -> Path:
    """Write one float32 frame to ``path`` (not atomic): (H, W) as ``channel``, (H, W, 3) as R, G, B.

    OpenEXR's errors (a RuntimeError) become OSError, ENOSPC when the disk is full.
    """
    try:
        import OpenEXR
    except ImportError as e:  # pragma: no cover
        raise ImportError("writing EXR needs the OpenEXR package (pip install 'hybridhdr[images]')") from e
    a = check_frame(img)
    header = {"compression": exr_compression(compression), "type": OpenEXR.scanlineimage}
    chans = ({channel: a} if a.ndim == 2 else
             {c: np.ascontiguousarray(a[..., i]) for i, c in enumerate("RGB")})
    try:
        OpenEXR.File(header, chans).write(str(path))
    except RuntimeError as e:
        msg = str(e)
        code = errno.ENOSPC if "space" in msg.lower() else errno.EIO
        raise OSError(code, f"{os.strerror(code)}: writing {path} ({msg})") from None
    return Path(path)


def tone_map(frames: np.ndarray, *, low_percentile: float = 1.0, high_percentile: float = 99.0,
             gamma: float = 1.0, limits: tuple[float, float] | None = None) -> tuple[np.ndarray, tuple[float, float]]:
    """Global log tone mapping of linear frames to uint8; returns (images, (lo, hi)).

    ``frames``: (K, H, W), (H, W), (K, H, W, 3) or (H, W, 3) (elementwise, one set of limits for
    all channels). The percentiles are over the finite values above 1e-6 only (NaN, -inf and
    values <= 1e-6 map to 0, +inf to 255; see the module docstring). ``limits`` (in log units)
    overrides the percentiles, e.g. to tone-map two videos alike.
    """
    f = np.asarray(frames, dtype=np.float64)
    check_shape(f, "K H W | H W | K H W 3 | H W 3", "frames")
    check_tone(low_percentile, high_percentile, gamma)
    valid = np.isfinite(f) & (f > _FLOOR)
    lg = np.log(np.where(valid, f, 1.0))
    if limits is None:
        if valid.any():
            lo, hi = (float(v) for v in np.percentile(lg[valid], [low_percentile, high_percentile]))
        else:
            lo = hi = float(np.log(_FLOOR))
    else:
        lo, hi = float(limits[0]), float(limits[1])
    if hi <= lo:
        hi = lo + 1e-6
    v = np.clip((lg - lo) / (hi - lo), 0.0, 1.0) ** (1.0 / gamma)
    v = np.where(valid, v, np.where(np.isposinf(f), 1.0, 0.0))
    return np.round(255.0 * v).astype(np.uint8), (lo, hi)


def check_tone(low_percentile, high_percentile, gamma):
    if not 0 <= low_percentile < high_percentile <= 100:
        raise ValueError(f"need 0 <= low_percentile < high_percentile <= 100, got {low_percentile}, {high_percentile}")
    if gamma <= 0:
        raise ValueError(f"gamma must be > 0, got {gamma}")


#: A video is shown with the log map only when the 99.5th percentile of its finite positive pixels
#: is above the frame camera's clip level (1.0 in frame-linear units) and exceeds the 5th by more
#: than this (an HDR video); otherwise linearly (:func:`display_map`).
LOG_MAP_RATIO = 100.0


def display_map_from(p5: float, p995: float, log_limits: tuple[float, float], *, gamma: float = 1.0,
                     log_gamma: float = 1.0) -> dict:
    """The display map of a video whose finite positive pixels have 5th / 99.5th percentiles
    ``p5`` / ``p995`` (linear) and whose log tone-map limits are ``log_limits``:
    ``{"mode": "log", "limits": (lo, hi), "gamma": log_gamma}`` for an HDR video (above the clip level and more than
    :data:`LOG_MAP_RATIO` from end to end), else ``{"mode": "linear", "hi": max(1, p995),
    "gamma": gamma}``: 1.0 is the frame camera's clip level in frame-linear units, so a low-range
    scene looks like its frames instead of having its dark tail lifted to mid grey."""
    if p995 > 1.0 and p995 > LOG_MAP_RATIO * p5:
        return {"mode": "log", "limits": (float(log_limits[0]), float(log_limits[1])), "gamma": float(log_gamma)}
    return {"mode": "linear", "hi": max(1.0, float(p995)), "gamma": float(gamma)}


def display_gamma(encoding) -> float:
    """The display gamma of the linear map that shows a reconstruction as its frames look:
    2.2 for frames stored as display codes (``Frames.encoding`` "gamma" or "srgb"), else 1.0
    (linear, raw or unknown codes: the frame-anchored outputs are in the frames' own linear
    units, so ``I / hi`` is already the frame's code). Shared by the previews and ``view``."""
    return 2.2 if str(encoding) in ("gamma", "srgb") else 1.0


def display_map_centred(log_lo: float, log_mid: float, log_hi: float) -> dict:
    """The display map of an events-only reconstruction (high-pass, E2VID, FireNet): its
    intensity has no absolute scale (it starts from a constant), only changes of log intensity
    mean something, so the log map is centred on the median ``log_mid`` (mid grey, code 128)
    and spans the larger of its distances to ``log_lo`` / ``log_hi`` (1st / 99th percentiles)
    on both sides: the unchanged background is grey, brighter spots lighter, darker ones darker."""
    r = max(float(log_mid) - float(log_lo), float(log_hi) - float(log_mid), 1e-6)
    return {"mode": "log", "limits": (float(log_mid) - r, float(log_mid) + r), "gamma": 1.0, "centre": "median"}


def display_map(sample, *, gamma: float = 1.0, low_percentile: float = 1.0, high_percentile: float = 99.0,
                events_only: bool = False) -> dict:
    """:func:`display_map_from` of a sample of linear frames (any shape), or with ``events_only``
    :func:`display_map_centred`; no valid pixel: linear."""
    a = np.asarray(sample, dtype=np.float64)
    v = a[np.isfinite(a) & (a > _FLOOR)]
    if v.size == 0:
        return {"mode": "linear", "hi": 1.0, "gamma": float(gamma)}
    lo, mid, hi = (float(x) for x in np.percentile(np.log(v), [low_percentile, 50.0, high_percentile]))
    if events_only:
        return display_map_centred(lo, mid, hi)
    p5, p995 = (float(x) for x in np.percentile(v, [5.0, 99.5]))
    return display_map_from(p5, p995, (lo, hi), gamma=gamma)


def apply_display_map(img, m: dict) -> np.ndarray:
    """uint8 image of linear ``img`` under a :func:`display_map` (NaN and -inf black, +inf white)."""
    if m["mode"] == "log":
        return tone_map(img, limits=m["limits"], gamma=m.get("gamma", 1.0))[0]
    f = np.asarray(img, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        v = np.clip(np.nan_to_num(f, nan=0.0, posinf=np.inf, neginf=0.0) / m["hi"], 0.0, 1.0) ** (1.0 / m["gamma"])
    return np.round(255.0 * v).astype(np.uint8)


class LogPercentiles:
    """Exact percentiles of :func:`tone_map`'s ``log I`` over the valid values (finite, > 1e-6) of
    a stream of frames.

    ``log`` and the floor are monotone, so an order statistic of log I is the log of the order
    statistic of I. Every value is mapped to an order-preserving 32-bit key (its float32 bit
    pattern after the floor, NaN and +inf handling of :func:`tone_map`); :meth:`add` counts the
    keys' top 16 bits (invalid values are left out), and :meth:`limits` finds the exact keys at the needed ranks with one more
    pass that counts the low 16 bits inside the (at most four) top bins concerned. The result is
    ``np.percentile``'s linear interpolation of those values, bit for bit (tested). Memory: two
    65,536-bin histograms.
    """

    def __init__(self):
        self.counts = np.zeros(1 << 16, np.int64)
        self.n = 0

    @staticmethod
    def keys(frame) -> np.ndarray:
        """Order-preserving uint32 keys of tone_map's valid values (flattened; finite and > 1e-6,
        which for float32 is ``x >= _C32``)."""
        x = np.asarray(frame, dtype=np.float32).reshape(-1)
        return np.ascontiguousarray(x[np.isfinite(x) & (x >= _C32)]).view(np.uint32)

    @staticmethod
    def key_log(key: int) -> float:
        if key == _SENTINEL_KEY:
            return float(np.log(np.float64(_FLOOR)))
        return float(np.log(np.float64(np.array(key, np.uint32).view(np.float32))))

    def add(self, frame) -> None:
        k = self.keys(frame)
        self.counts += np.bincount(k >> 16, minlength=1 << 16)
        self.n += k.size

    def limits(self, frames_iter, low_percentile: float = 1.0, high_percentile: float = 99.0) -> tuple[float, float]:
        """(lo, hi) = ``np.percentile(log I, [low, high])`` of everything added; ``frames_iter()``
        must yield the same frames again (any order). Without any valid value: (log 1e-6, log 1e-6),
        as :func:`tone_map`."""
        lo, hi = self.percentiles(frames_iter, (low_percentile, high_percentile))
        return lo, hi

    def percentiles(self, frames_iter, percentiles) -> list[float]:
        """``np.percentile(log I, percentiles)`` of everything added, in one more pass over
        ``frames_iter()`` (see :meth:`limits`)."""
        if self.n == 0:
            return [float(np.log(_FLOOR))] * len(percentiles)
        n = self.n
        q = np.true_divide(list(percentiles), 100)
        vi = (n - 1) * q  # numpy's 'linear' method (Hyndman & Fan 7)
        prev = np.floor(vi)
        nxt = prev + 1
        above = vi >= n - 1
        prev[above] = nxt[above] = n - 1
        below = vi < 0
        prev[below] = nxt[below] = 0
        gamma = vi - np.where(above, -1.0, prev)  # as numpy (irrelevant where prev == next)
        ranks = sorted({int(r) for r in np.concatenate([prev, nxt])})
        cum = np.cumsum(self.counts)
        top = {r: int(np.searchsorted(cum, r, side="right")) for r in ranks}
        low_counts = {b: np.zeros(1 << 16, np.int64) for b in set(top.values())}
        for fr in frames_iter():
            k = self.keys(fr)
            hi16 = k >> 16
            for b, c in low_counts.items():
                sel = k[hi16 == b]
                if sel.size:
                    c += np.bincount(sel & 0xFFFF, minlength=1 << 16)
        value = {}
        for r in ranks:
            b = top[r]
            before = int(cum[b - 1]) if b > 0 else 0
            lowbits = int(np.searchsorted(np.cumsum(low_counts[b]), r - before, side="right"))
            value[r] = self.key_log((b << 16) | lowbits)
        a = np.array([value[int(r)] for r in prev])
        bb = np.array([value[int(r)] for r in nxt])
        diff = bb - a
        res = a + diff * gamma
        res = np.where(gamma >= 0.5, bb - diff * (1 - gamma), res)
        return [float(v) for v in res]


def write_timestamps(t_us, names, path) -> Path:
    """``timestamps.txt``: a header line, then ``t_us filename`` per frame."""
    path = Path(path)
    with atomic_path(path, ".txt") as tmp, open(tmp, "w", encoding="utf-8") as f:
        f.write(TIMESTAMPS_HEADER)
        for t, n in zip(np.asarray(t_us, np.int64), names):
            f.write(f"{int(t)} {n}\n")
    return path


TIMESTAMPS_HEADER = "# t_us filename (t in microseconds, the state at t includes events before t)\n"


def read_timestamps(path) -> tuple[np.ndarray, list[str]]:
    """``(t_us (K,) int64, file names)`` of a ``timestamps.txt`` written with
    :data:`TIMESTAMPS_HEADER` (``t_us filename`` lines; ``#`` comments); every name must stay
    inside the file's folder."""
    from .._util.confine import inside_folder
    ts, names = [], []
    from .._util.limits import read_text_bounded
    text = read_text_bounded(path, "timestamps file")  # a regular file within bounds (never a FIFO)
    for i, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) != 2:
            raise ValueError(f"{path}:{i}: expected 't_us filename', found {s!r}")
        try:
            ts.append(int(parts[0]))
        except ValueError:
            raise ValueError(f"{path}:{i}: t_us must be an integer (µs), found {parts[0]!r}") from None
        inside_folder(parts[1], Path(path).parent, what=f"line {i}: output", source=path)
        names.append(parts[1])
    return np.asarray(ts, np.int64), names


def write_exr_sequence(video, out_dir, *, prefix: str = "frame_", channel: str = "Y",
                       compression: str = DEFAULT_EXR_COMPRESSION) -> list[Path]:
    """Write each frame as a float32 EXR (``channel``, or R, G, B for colour) plus ``timestamps.txt``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    exr_compression(compression)
    paths, names = [], []
    for i, img in enumerate(video.frames):
        name = f"{prefix}{i:06d}.exr"
        path = out / name
        with atomic_path(path, ".exr") as tmp:
            write_exr(tmp, img, compression=compression, channel=channel)
        paths.append(path)
        names.append(name)
    write_timestamps(video.t_us, names, out / "timestamps.txt")
    return paths


def read_exr(path, channel: str = "Y") -> np.ndarray:
    """Read one channel of an EXR file as float32 (H, W); a colour file without ``Y`` (R, G, B) as (H, W, 3)."""
    import OpenEXR
    with OpenEXR.File(str(path)) as f:
        ch = f.channels()
        if channel not in ch and channel == "Y":
            if "RGB" in ch:
                return np.asarray(ch["RGB"].pixels, dtype=np.float32)
            if all(c in ch for c in "RGB"):
                return np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in "RGB"], axis=-1)
        return np.asarray(ch[channel].pixels, dtype=np.float32)


def write_png(path, img_u8) -> None:
    from PIL import Image
    Image.fromarray(img_u8).save(str(path), format="PNG")


def write_png_previews(video, out_dir, *, every: int = 1, prefix: str = "preview_", **tone) -> list[Path]:
    """Tone-mapped 8-bit PNGs of every ``every``-th frame (see the module docstring)."""
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    imgs, _ = tone_map(video.frames, **tone)
    paths = []
    for i in range(0, len(imgs), every):
        path = out / f"{prefix}{i:06d}.png"
        with atomic_path(path, ".png") as tmp:
            write_png(tmp, imgs[i])
        paths.append(path)
    return paths


class MP4Stream:
    """H.264 through an ffmpeg process (``imageio-ffmpeg``), fed one tone-mapped frame at a time;
    odd sizes are padded (edge) to even.

    ffmpeg's messages go to a temporary file (not the terminal) and its exit status is checked
    on :meth:`close`: a failure (a full disk, a killed encoder) is one ``OSError`` line naming
    ffmpeg's last message, and the caller's atomic writer then leaves nothing at the final name."""

    def __init__(self, path, shape, fps: float):
        import imageio_ffmpeg
        import tempfile
        if fps <= 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.path = Path(path)
        self.h, self.w = int(shape[0]), int(shape[1])
        self.colour = len(shape) == 3
        size = (self.w + self.w % 2, self.h + self.h % 2)
        self._log = tempfile.TemporaryFile()
        self.gen = imageio_ffmpeg.write_frames(str(path), size, pix_fmt_in="rgb24" if self.colour else "gray",
                                               fps=float(fps), codec="libx264", macro_block_size=1,
                                               ffmpeg_log_level="error")
        import signal
        import threading
        self._proc = None
        main = threading.current_thread() is threading.main_thread()
        sigs = {getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)}
        # no interrupt while ffmpeg starts: one that lands between its start and our handle on it
        # would leave it running, to write the output file after this process has removed it
        old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs) if main else None
        saved = os.dup(2)
        try:
            try:  # ffmpeg inherits stderr when it starts (in the first send): give it the log file
                os.dup2(self._log.fileno(), 2)
                self.gen.send(None)
            finally:
                os.dup2(saved, 2)
                os.close(saved)
            frame = getattr(self.gen, "gi_frame", None)
            self._proc = frame.f_locals.get("p") if frame is not None else None
        finally:
            if old is not None:
                try:
                    signal.pthread_sigmask(signal.SIG_SETMASK, old)  # a pending signal is raised here
                except BaseException:
                    self.abort()
                    raise

    def abort(self) -> None:
        """Stop ffmpeg now (killed and waited for, so it writes nothing more); never raises."""
        if getattr(self, "_done", False):
            return
        self._done = True
        try:
            if self._proc is not None and self._proc.poll() is None:
                self._proc.kill()
            if self._proc is not None:
                self._proc.wait()
        except Exception:
            pass
        try:
            self.gen.close()
        except Exception:
            pass
        try:
            self._log.close()
        except Exception:
            pass

    def _failed(self, what: str) -> OSError:
        msg = ""
        try:
            self._log.seek(0)
            lines = [ln.strip() for ln in self._log.read().decode("utf-8", "replace").splitlines() if ln.strip()]
            msg = lines[-1] if lines else ""
        except (OSError, ValueError):
            pass
        return OSError(errno.EIO, f"ffmpeg failed while writing {self.path.name} ({what})"
                                  + (f": {msg[:200]}" if msg else ""))

    def write(self, u8) -> None:
        pad = ((0, self.h % 2), (0, self.w % 2)) + (((0, 0),) if self.colour else ())
        try:
            self.gen.send(np.ascontiguousarray(np.pad(u8, pad, mode="edge")))
        except OSError:
            raise self._failed("it stopped reading frames") from None

    def close(self) -> None:
        if getattr(self, "_done", False):  # a second close (an error path) does nothing
            return
        self._done = True
        try:
            try:
                self.gen.close()
            except (RuntimeError, OSError) as e:
                raise self._failed(str(e).splitlines()[0] if str(e) else type(e).__name__) from None
            rc = None
            if self._proc is not None:
                rc = self._proc.wait()
            if rc not in (0, None):
                raise self._failed(f"exit status {rc}")
        finally:
            self._log.close()


def write_mp4(video, path, *, fps: float = 30.0, **tone) -> Path:
    """Tone-mapped H.264 preview (needs ``imageio-ffmpeg``) playing at ``fps`` frames per second;
    odd sizes are padded."""
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imgs, _ = tone_map(video.frames, **tone)
    with atomic_path(path, ".mp4") as tmp:
        s = MP4Stream(tmp, imgs.shape[1:], fps)
        try:
            for im in imgs:
                s.write(im)
        finally:
            s.close()
    return path
