"""Writing reconstructions: float32 linear EXR sequences, tone-mapped PNG and MP4 previews.

Two ways in:

* :class:`VideoWriter` streams frames to a folder as the filter produces them (memory bounded by
  ``queue_frames`` frames, independent of the video's length): EXR files are encoded by a
  bounded pool of writer processes (the OpenEXR binding holds the GIL while it compresses, so
  threads would stall the filter), ``timestamps.txt`` is written line by line, and the previews
  are tone-mapped from a spill file once the whole video is known (their limits are percentiles
  over the whole video). ``writers=0`` is the serial path (everything in the calling thread);
  the pool writes the same bytes. :class:`OutputFolder` gives the command line its
  ``OUT.partial/`` → ``OUT`` semantics.
* :func:`write_exr_sequence`, :func:`write_png_previews`, :func:`write_mp4` write an in-memory
  :class:`~hybridhdr.reconstruct.api.Video`; each file goes to a temporary name in the target
  folder and is renamed into place, so a crash never leaves a truncated file under the final
  name.

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
The streaming writer computes the same percentiles exactly (:class:`LogPercentiles`: a
two-level histogram of the float32 bit patterns), so its previews equal :func:`tone_map` of the
whole video.
"""

from __future__ import annotations

import errno
import os
import queue
import shutil
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from .._atomic import umask_file_mode

__all__ = ["tone_map", "write_exr_sequence", "read_exr", "write_png_previews", "write_mp4", "write_timestamps",
           "write_exr", "exr_compressions", "DEFAULT_EXR_COMPRESSION", "LOSSY_EXR_COMPRESSIONS",
           "LogPercentiles", "VideoWriter", "OutputFolder", "write_video"]

#: name -> OpenEXR constant name; only those the installed OpenEXR has are offered
_EXR_COMPRESSION_NAMES = {
    "none": "NO_COMPRESSION", "rle": "RLE_COMPRESSION", "zips": "ZIPS_COMPRESSION", "zip": "ZIP_COMPRESSION",
    "piz": "PIZ_COMPRESSION", "pxr24": "PXR24_COMPRESSION", "zstd": "ZSTD_COMPRESSION",
    "htj2k": "HTJ2K256_COMPRESSION",
}
#: lossy for float32 data (PXR24 rounds to 24 bits)
LOSSY_EXR_COMPRESSIONS = frozenset({"pxr24"})
#: lossless, readable by every OpenEXR reader, and on reconstructed float32 frames the fastest of
#: the classic lossless codecs (benchmarks/reconstruct_io.py: ZIP 2.5 ms/frame, ZIPS 4.3, PIZ 9.0 at
#: 240x180; zstd and htj2k are smaller but need OpenEXR >= 3.4 to read)
DEFAULT_EXR_COMPRESSION = "zip"

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


def _exr_compression(name: str):
    import OpenEXR
    key = str(name).lower()
    if key not in _EXR_COMPRESSION_NAMES or not hasattr(OpenEXR, _EXR_COMPRESSION_NAMES[key]):
        raise ValueError(f"unknown EXR compression {name!r}; expected one of {exr_compressions()}")
    return getattr(OpenEXR, _EXR_COMPRESSION_NAMES[key])


def _check_frame(img) -> np.ndarray:
    a = np.ascontiguousarray(img, dtype=np.float32)
    if a.ndim != 2 and not (a.ndim == 3 and a.shape[2] == 3):
        raise ValueError(f"a frame must have shape (H, W) or (H, W, 3), got {a.shape}")
    return a


def write_exr(path, img, *, compression: str = DEFAULT_EXR_COMPRESSION, channel: str = "Y") -> Path:
    """Write one float32 frame to ``path`` (not atomic): (H, W) as ``channel``, (H, W, 3) as R, G, B.

    OpenEXR's errors (a RuntimeError) become OSError, ENOSPC when the disk is full.
    """
    try:
        import OpenEXR
    except ImportError as e:  # pragma: no cover
        raise ImportError("writing EXR needs the OpenEXR package (pip install 'hybridhdr[images]')") from e
    a = _check_frame(img)
    header = {"compression": _exr_compression(compression), "type": OpenEXR.scanlineimage}
    chans = ({channel: a} if a.ndim == 2 else
             {c: np.ascontiguousarray(a[..., i]) for i, c in enumerate("RGB")})
    try:
        OpenEXR.File(header, chans).write(str(path))
    except RuntimeError as e:
        msg = str(e)
        code = errno.ENOSPC if "space" in msg.lower() else errno.EIO
        raise OSError(code, f"{os.strerror(code)}: writing {path} ({msg})") from None
    return Path(path)


def _atomic_target(path: Path, suffix: str):
    fd, tmp = tempfile.mkstemp(prefix="." + path.stem + ".", suffix=".partial" + suffix, dir=path.parent)
    try:
        os.fchmod(fd, umask_file_mode())  # the mode open() would give, not mkstemp's 0600
    finally:
        os.close(fd)
    return tmp


def _finish(tmp: str, path: Path) -> None:
    os.replace(tmp, path)


def _cleanup(tmp: str) -> None:
    if os.path.exists(tmp):
        os.unlink(tmp)


def tone_map(frames: np.ndarray, *, low_percentile: float = 1.0, high_percentile: float = 99.0,
             gamma: float = 1.0, limits: tuple[float, float] | None = None) -> tuple[np.ndarray, tuple[float, float]]:
    """Global log tone mapping of linear frames to uint8; returns (images, (lo, hi)).

    ``frames``: (K, H, W), (H, W), (K, H, W, 3) or (H, W, 3) (elementwise, one set of limits for
    all channels). The percentiles are over the finite values above 1e-6 only (NaN, -inf and
    values <= 1e-6 map to 0, +inf to 255; see the module docstring). ``limits`` (in log units)
    overrides the percentiles, e.g. to tone-map two videos alike.
    """
    f = np.asarray(frames, dtype=np.float64)
    if f.ndim not in (2, 3, 4) or (f.ndim == 4 and f.shape[3] != 3):
        raise ValueError(f"frames must have shape (K, H, W), (H, W) or with a last axis of 3, got {f.shape}")
    _check_tone(low_percentile, high_percentile, gamma)
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


def _check_tone(low_percentile, high_percentile, gamma):
    if not 0 <= low_percentile < high_percentile <= 100:
        raise ValueError(f"need 0 <= low_percentile < high_percentile <= 100, got {low_percentile}, {high_percentile}")
    if gamma <= 0:
        raise ValueError(f"gamma must be > 0, got {gamma}")


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
        if self.n == 0:
            lf = float(np.log(_FLOOR))
            return lf, lf
        n = self.n
        q = np.true_divide([low_percentile, high_percentile], 100)
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
        return float(res[0]), float(res[1])


def write_timestamps(t_us, names, path) -> Path:
    """``timestamps.txt``: a header line, then ``t_us filename`` per frame."""
    path = Path(path)
    tmp = _atomic_target(path, ".txt")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(_TIMESTAMPS_HEADER)
            for t, n in zip(np.asarray(t_us, np.int64), names):
                f.write(f"{int(t)} {n}\n")
        _finish(tmp, path)
    except BaseException:
        _cleanup(tmp)
        raise
    return path


_TIMESTAMPS_HEADER = "# t_us filename (t in microseconds, the state at t includes events before t)\n"


def write_exr_sequence(video, out_dir, *, prefix: str = "frame_", channel: str = "Y",
                       compression: str = DEFAULT_EXR_COMPRESSION) -> list[Path]:
    """Write each frame as a float32 EXR (``channel``, or R, G, B for colour) plus ``timestamps.txt``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    _exr_compression(compression)
    paths, names = [], []
    for i, img in enumerate(video.frames):
        name = f"{prefix}{i:06d}.exr"
        path = out / name
        tmp = _atomic_target(path, ".exr")
        try:
            write_exr(tmp, img, compression=compression, channel=channel)
            _finish(tmp, path)
        except BaseException:
            _cleanup(tmp)
            raise
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


def _write_png(path, img_u8) -> None:
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
        tmp = _atomic_target(path, ".png")
        try:
            _write_png(tmp, imgs[i])
            _finish(tmp, path)
        except BaseException:
            _cleanup(tmp)
            raise
        paths.append(path)
    return paths


class _MP4Stream:
    """H.264 through an ffmpeg process (``imageio-ffmpeg``), fed one tone-mapped frame at a time;
    odd sizes are padded (edge) to even."""

    def __init__(self, path, shape, fps: float):
        import imageio_ffmpeg
        if fps <= 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.h, self.w = int(shape[0]), int(shape[1])
        self.colour = len(shape) == 3
        size = (self.w + self.w % 2, self.h + self.h % 2)
        self.gen = imageio_ffmpeg.write_frames(str(path), size, pix_fmt_in="rgb24" if self.colour else "gray",
                                               fps=float(fps), codec="libx264", macro_block_size=1,
                                               ffmpeg_log_level="error")
        self.gen.send(None)

    def write(self, u8) -> None:
        pad = ((0, self.h % 2), (0, self.w % 2)) + (((0, 0),) if self.colour else ())
        self.gen.send(np.ascontiguousarray(np.pad(u8, pad, mode="edge")))

    def close(self) -> None:
        try:
            self.gen.close()
        except (RuntimeError, BrokenPipeError) as e:
            raise OSError(errno.EIO, f"ffmpeg failed while writing the MP4 preview: {e}") from None


def write_mp4(video, path, *, fps: float = 30.0, **tone) -> Path:
    """Tone-mapped H.264 preview (needs ``imageio-ffmpeg``) playing at ``fps`` frames per second;
    odd sizes are padded."""
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imgs, _ = tone_map(video.frames, **tone)
    tmp = _atomic_target(path, ".mp4")
    try:
        s = _MP4Stream(tmp, imgs.shape[1:], fps)
        try:
            for im in imgs:
                s.write(im)
        finally:
            s.close()
        _finish(tmp, path)
    except BaseException:
        _cleanup(tmp)
        raise
    return path


# -- the streaming writer --------------------------------------------------------------------------

def _task_exr(path, img, compression, channel):
    write_exr(path, img, compression=compression, channel=channel)
    return 1


def _task_png(spill, shape, index, path, limits, gamma):
    fr = _read_spill(spill, shape, index)
    u8, _ = tone_map(fr, limits=limits, gamma=gamma)
    _write_png(path, u8)
    return 1


def _read_spill(spill, shape, index) -> np.ndarray:
    n = int(np.prod(shape))
    with open(spill, "rb") as f:
        f.seek(int(index) * n * 4)
        b = f.read(n * 4)
    if len(b) != n * 4:
        raise OSError(errno.EIO, f"{spill}: short read of frame {index}")
    return np.frombuffer(b, np.float32).reshape(shape)


def _worker_init(umask: int | None = None):
    import signal
    if umask is not None:  # a forkserver child inherits the server's umask, not this run's
        os.umask(umask)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and shuts the pool down
    for name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_DFL)


def _make_pool(n: int, backend: str):
    """(executor, kind): processes (fork when this process runs one thread, else forkserver), or threads."""
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
    if backend == "thread":
        return ThreadPoolExecutor(n, thread_name_prefix="hybridhdr-writer"), "thread"
    import multiprocessing as mp
    methods = mp.get_all_start_methods()
    if "fork" in methods and threading.active_count() == 1 and sys.platform.startswith("linux"):
        ctx, kind = mp.get_context("fork"), "process (fork)"
    elif "forkserver" in methods:
        ctx, kind = mp.get_context("forkserver"), "process (forkserver)"
        ctx.set_forkserver_preload(["hybridhdr.reconstruct.output"])
    else:  # pragma: no cover - spawn platforms
        ctx, kind = mp.get_context("spawn"), "process (spawn)"
    from .._atomic import current_umask
    ex = ProcessPoolExecutor(n, mp_context=ctx, initializer=_worker_init, initargs=(current_umask(),))
    # start every worker now, while this process may still be single-threaded (3.11 forks them all
    # at the first submit): later forks would copy a process whose other threads hold locks
    for f in [ex.submit(int, 0) for _ in range(n)]:
        f.result()
    return ex, kind


class VideoWriter:
    """Stream reconstructed frames into ``out_dir`` (an existing, preferably empty folder).

    ``write(t_us, frame)`` for each frame in time order, then ``close()`` (returns what was
    written) or ``abort()``; also a context manager (aborts on an exception). Files:
    ``frame_NNNNNN.exr`` (if ``exr``), ``timestamps.txt`` (``t_us filename`` per frame, every
    frame even without EXR), ``previews/preview_NNNNNN.png`` (``png``), ``preview.mp4``
    (``mp4``, every frame, playing at ``playback_fps``).

    Parameters
    ----------
    writers : int or None
        Writer processes (or threads, ``backend="thread"``); 0 writes everything in the calling
        thread (the serial path, same bytes). None: ``min(2, os.cpu_count())``.
    queue_frames : int or None
        Frames waiting for a writer at most (``write`` blocks beyond that); default
        ``2 * writers + 2``. Memory stays bounded by it whatever the video's length.
    on_written : callable(int), optional
        Called with the number of images written (EXR files, PNG files, MP4 frames) as they
        complete, from any thread.
    low_percentile, high_percentile, gamma
        Preview tone mapping (:func:`tone_map`).

    With previews, the frames are also appended to a spill file in ``out_dir``
    (``.preview-spill.f32``, 4 bytes per value, removed by ``close``/``abort``): the previews'
    tone-mapping limits are percentiles over the whole video, so they are made after the last
    frame, by the pool (PNG) and an ffmpeg process (MP4) in parallel.
    """

    SPILL_NAME = ".preview-spill.f32"

    def __init__(self, out_dir, *, exr: bool = True, compression: str = DEFAULT_EXR_COMPRESSION,
                 png: bool = False, mp4: bool = False, playback_fps: float = 30.0, writers: int | None = None,
                 backend: str = "process", queue_frames: int | None = None, on_written=None,
                 prefix: str = "frame_", channel: str = "Y", low_percentile: float = 1.0,
                 high_percentile: float = 99.0, gamma: float = 1.0):
        self.out = Path(out_dir)
        if not self.out.is_dir():
            raise FileNotFoundError(f"output folder {self.out} does not exist")
        if exr:
            _exr_compression(compression)
        if mp4 and not playback_fps > 0:
            raise ValueError(f"playback_fps must be > 0, got {playback_fps}")
        _check_tone(low_percentile, high_percentile, gamma)
        if backend not in ("process", "thread"):
            raise ValueError(f"backend must be 'process' or 'thread', got {backend!r}")
        if writers is None:
            writers = min(2, os.cpu_count() or 1)
        if isinstance(writers, bool) or not isinstance(writers, (int, np.integer)) or writers < 0:
            raise ValueError(f"writers must be an int >= 0, got {writers!r}")
        self.exr, self.compression, self.png, self.mp4 = bool(exr), str(compression).lower(), bool(png), bool(mp4)
        self.playback_fps = float(playback_fps)
        self.prefix, self.channel = prefix, channel
        self.tone = dict(low_percentile=low_percentile, high_percentile=high_percentile, gamma=gamma)
        self.n_writers = int(writers)
        self.queue_frames = int(queue_frames) if queue_frames else 2 * self.n_writers + 2
        self.on_written = on_written
        self.n = 0
        self.shape = None
        self.t_first = self.t_last = None
        self.error: BaseException | None = None
        self._closed = False
        self._pending = set()
        self._lock = threading.Lock()
        self._slots = threading.BoundedSemaphore(self.queue_frames)
        self._pool, self.backend = (None, "serial")
        self._spill_path = self.out / self.SPILL_NAME
        self._spill = None
        self._spill_q = None
        self._spill_thread = None
        self._hist = LogPercentiles() if (png or mp4) else None
        self.timings = {}
        self._t0 = time.perf_counter()
        self._ts = open(self.out / "timestamps.txt", "w", encoding="utf-8")
        try:
            self._ts.write(_TIMESTAMPS_HEADER)
            if self._hist is not None:
                self._spill = open(self._spill_path, "wb")
            if self.n_writers > 0:
                self._pool, self.backend = _make_pool(self.n_writers, backend)
                if self._hist is not None:
                    self._spill_q = queue.Queue(maxsize=4)
                    self._spill_thread = threading.Thread(target=self._spill_loop, name="hybridhdr-spill",
                                                          daemon=True)
                    self._spill_thread.start()
        except BaseException:
            self.abort()
            raise

    # -- producer side
    def __enter__(self):
        return self

    def __exit__(self, et, ev, tb):
        if et is not None:
            self.abort()
        elif not self._closed:
            self.close()

    def _written(self, k: int = 1) -> None:
        if self.on_written is not None:
            self.on_written(k)

    def _raise_pending_error(self) -> None:
        if self.error is not None:
            raise self.error

    def _done(self, fut) -> None:
        with self._lock:
            self._pending.discard(fut)
        self._slots.release()
        if fut.cancelled():
            return
        e = fut.exception()
        if e is not None:
            if self.error is None:
                self.error = e
        else:
            self._written(1)

    def _submit(self, fn, *args) -> None:
        while not self._slots.acquire(timeout=0.2):
            self._raise_pending_error()
        self._raise_pending_error()
        try:
            fut = self._pool.submit(fn, *args)
        except BaseException:
            self._slots.release()
            raise
        with self._lock:
            self._pending.add(fut)
        fut.add_done_callback(self._done)

    def write(self, t_us: int, frame) -> None:
        """Queue one frame (blocks while ``queue_frames`` frames wait); raises a writer's error."""
        if self._closed:
            raise ValueError("write() on a closed VideoWriter")
        self._raise_pending_error()
        a = _check_frame(frame)
        if self.shape is None:
            self.shape = a.shape
        elif a.shape != self.shape:
            raise ValueError(f"frame {self.n} has shape {a.shape}, the first had {self.shape}")
        t = int(t_us)
        if self.t_last is not None and t <= self.t_last:
            raise ValueError(f"frame times must increase: {t} after {self.t_last}")
        name = f"{self.prefix}{self.n:06d}.exr"
        self._ts.write(f"{t} {name}\n")
        if self.exr:
            if self._pool is None:
                write_exr(self.out / name, a, compression=self.compression, channel=self.channel)
                self._written(1)
            else:
                self._submit(_task_exr, str(self.out / name), a, self.compression, self.channel)
        if self._hist is not None:
            if self._spill_q is None:
                self._spill_one(a)
            else:
                while True:
                    self._raise_pending_error()
                    try:
                        self._spill_q.put(a, timeout=0.2)
                        break
                    except queue.Full:
                        continue
        if self.t_first is None:
            self.t_first = t
        self.t_last = t
        self.n += 1

    def _spill_one(self, a) -> None:
        self._spill.write(a.tobytes())
        self._hist.add(a)

    def _spill_loop(self) -> None:
        while True:
            a = self._spill_q.get()
            if a is None:
                return
            if self.error is not None:
                continue  # drain
            try:
                self._spill_one(a)
            except BaseException as e:  # noqa: BLE001 - handed to the producer
                if self.error is None:
                    self.error = e

    def _spill_frames(self):
        for i in range(self.n):
            yield _read_spill(self._spill_path, self.shape, i)

    def _wait_pending(self) -> None:
        while True:
            with self._lock:
                fs = list(self._pending)
            if not fs:
                break
            for f in fs:
                try:
                    f.result()
                except BaseException:  # noqa: BLE001 - recorded by _done
                    pass
        self._raise_pending_error()

    def close(self) -> dict:
        """Finish every file; returns ``{"exr": n, "exr_compression", "png": n, "mp4": name, ...}``."""
        if self._closed:
            raise ValueError("VideoWriter already closed")
        try:
            res = self._close()
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return res

    def _close(self) -> dict:
        if self._spill_thread is not None:
            self._spill_q.put(None)
            self._spill_thread.join()
            self._spill_thread = None
        if self._pool is not None:
            self._wait_pending()
        self._raise_pending_error()
        self._ts.close()
        self.timings["frames_s"] = time.perf_counter() - self._t0
        written = {"frames": self.n, "backend": self.backend, "writers": self.n_writers}
        if self.exr:
            written["exr"] = self.n
            written["exr_compression"] = self.compression
        if self._hist is not None:
            self._spill.close()
            self._spill = None
            if self.n:
                written.update(self._previews())
            os.unlink(self._spill_path)
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        self.timings["total_s"] = time.perf_counter() - self._t0
        return written

    def _previews(self) -> dict:
        t0 = time.perf_counter()
        lo, hi = self._hist.limits(self._spill_frames, self.tone["low_percentile"], self.tone["high_percentile"])
        if hi <= lo:
            hi = lo + 1e-6
        lim, gamma = (lo, hi), self.tone["gamma"]
        out = {"preview_log_limits": [lo, hi]}
        mp4_thread = None
        mp4_err = []
        if self.mp4:
            def encode():
                try:
                    s = _MP4Stream(self.out / "preview.mp4", self.shape, self.playback_fps)
                    try:
                        for i, fr in enumerate(self._spill_frames()):
                            if mp4_err:
                                break
                            s.write(tone_map(fr, limits=lim, gamma=gamma)[0])
                            self._written(1)
                    finally:
                        s.close()
                except BaseException as e:  # noqa: BLE001 - re-raised below
                    mp4_err.append(e)
            if self._pool is None:
                encode()
            else:
                mp4_thread = threading.Thread(target=encode, name="hybridhdr-mp4", daemon=True)
                mp4_thread.start()
        try:
            if self.png:
                d = self.out / "previews"
                d.mkdir(exist_ok=True)
                for i in range(self.n):
                    p = str(d / f"preview_{i:06d}.png")
                    if self._pool is None:
                        _task_png(str(self._spill_path), self.shape, i, p, lim, gamma)
                        self._written(1)
                    else:
                        self._submit(_task_png, str(self._spill_path), self.shape, i, p, lim, gamma)
                    if mp4_err:
                        break
                if self._pool is not None:
                    self._wait_pending()
                out["png"] = self.n
        finally:
            if mp4_thread is not None:
                if self.error is not None:
                    mp4_err.append(self.error)
                mp4_thread.join()
        if mp4_err:
            raise mp4_err[0]
        if self.mp4:
            out["mp4"] = "preview.mp4"
            out["mp4_playback_fps"] = self.playback_fps
        self.timings["previews_s"] = time.perf_counter() - t0
        return out

    def abort(self) -> None:
        """Stop: cancel queued work, end the pool, close and remove the spill file. Written files stay
        (the caller removes its folder)."""
        self._closed = True
        if self._spill_thread is not None:
            if self.error is None:
                self.error = RuntimeError("aborted")
            try:
                while True:
                    self._spill_q.get_nowait()
            except queue.Empty:
                pass
            self._spill_q.put(None)
            self._spill_thread.join()
            self._spill_thread = None
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        for f in (self._spill, self._ts):
            if f is not None:
                try:
                    f.close()
                except OSError:
                    pass
        self._spill = None
        try:
            os.unlink(self._spill_path)
        except FileNotFoundError:
            pass


def write_video(video, out_dir, **kw) -> dict:
    """Write an in-memory Video with :class:`VideoWriter` (same files as the command line)."""
    with VideoWriter(out_dir, **kw) as w:
        for t, f in zip(video.t_us, video.frames):
            w.write(int(t), f)
        return w.close()


# -- the output folder: OUT.partial -> OUT ----------------------------------------------------------

_MARKER = ".hybridhdr-partial"


def _our_output(rel: str) -> bool:
    """Names a reconstruct run writes (the only files ``overwrite`` replaces or removes)."""
    import fnmatch
    return any(fnmatch.fnmatchcase(rel, p) for p in ("frame_*.exr", "timestamps.txt", "run.json", "preview.mp4",
                                                       "previews/preview_*.png"))


class OutputFolder:
    """``OUT.partial/`` while running, ``OUT`` when complete.

    * OUT absent: ``OUT.partial`` (beside OUT, created here, mode from the umask) is renamed to
      OUT by :meth:`commit`.
    * OUT an empty folder: its entries are moved in (``run.json`` last); the folder itself (its
      owner and mode) is kept.
    * OUT non-empty: refused (ValueError) unless ``overwrite``; then on commit, ``run.json`` is
      removed first, then the files a reconstruct run writes (``frame_*.exr``, ``timestamps.txt``,
      ``preview.mp4``, ``previews/preview_*.png``), then the new files are moved in, ``run.json``
      last. Other files and every folder are left alone.
    * ``OUT.partial`` already there (an interrupted run, or not ours): refused; nothing is deleted.
    * :meth:`abort` removes ``OUT.partial``, which this object created; never anything else.
    """

    def __init__(self, out, *, overwrite: bool = False):
        out = Path(out)
        self.requested = out
        self.target = Path(os.path.realpath(out)) if out.exists() else Path(os.path.abspath(out))
        self.overwrite = bool(overwrite)
        if self.target.exists():
            if not self.target.is_dir():
                raise ValueError(f"--out {out} exists and is not a folder")
            if any(self.target.iterdir()) and not self.overwrite:
                raise ValueError(f"--out {out} exists and is not empty; choose another folder or pass --overwrite "
                                 f"(replaces the files a reconstruct run writes, keeps everything else)")
        self.path = self.target.with_name(self.target.name + ".partial")
        if self.path.exists() or self.path.is_symlink():
            raise ValueError(f"{self.path} exists (left by an interrupted run?); remove it first")
        self.target.parent.mkdir(parents=True, exist_ok=True)
        os.mkdir(self.path)  # exclusive: fails if another run took the name meanwhile
        self._created = True
        try:
            (self.path / _MARKER).write_text(f"pid {os.getpid()} host {socket.gethostname()} "
                                              f"started {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")
        except BaseException:
            self.abort()
            raise

    def commit(self) -> Path:
        """Move the finished output to OUT (see the class docstring); returns OUT."""
        os.unlink(self.path / _MARKER)
        if not self.target.exists():
            try:
                os.rename(self.path, self.target)
                self._created = False
                return self.target
            except OSError:
                if not self.target.exists():
                    raise
        if not self.target.is_dir() or (any(self.target.iterdir()) and not self.overwrite):
            raise OSError(errno.EEXIST, f"{self.target} appeared while reconstructing; the complete output is "
                                        f"left in {self.path}")
        if self.overwrite:
            old_run = self.target / "run.json"
            if old_run.is_file() or old_run.is_symlink():
                os.unlink(old_run)
            for p in list(self.target.iterdir()) + (list((self.target / "previews").iterdir())
                                                    if (self.target / "previews").is_dir() else []):
                rel = p.relative_to(self.target).as_posix()
                if _our_output(rel) and (p.is_file() or p.is_symlink()) and not p.is_dir():
                    os.unlink(p)
        entries = sorted(self.path.iterdir(), key=lambda p: p.name == "run.json")  # run.json last
        for p in entries:
            dst = self.target / p.name
            if p.is_dir() and dst.is_dir():
                for q in sorted(p.iterdir()):
                    os.replace(q, dst / q.name)
                os.rmdir(p)
            else:
                os.replace(p, dst)
        os.rmdir(self.path)
        self._created = False
        return self.target

    def abort(self) -> None:
        """Remove ``OUT.partial`` (created by this object) and its contents."""
        if self._created and self.path.is_dir() and not self.path.is_symlink():
            shutil.rmtree(self.path, ignore_errors=True)
        self._created = False
