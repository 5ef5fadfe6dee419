"""``hybridhdr simulate VIDEO``: events (and frames) from a user's own footage.

Input: a video file (read with imageio's ffmpeg plugin: its frames and frame rate), or a folder
of images with their times: ``images.txt`` (the ECD/RPG layout, "seconds relative/path" per
line), ``timestamps.txt`` (one time in seconds per line for the folder's images in name order),
or ``--input-fps`` for evenly spaced images. 8/16-bit images and video are taken as sRGB-encoded
and linearised with the sRGB curve (IEC 61966-2-1), then scaled so that the median radiance is 1
(the frame camera's default sensitivity is set for radiances of that order); an **EXR sequence
is HDR input**: its values are used as the radiance itself (unscaled) and also written as the HDR
references, at every input frame's time and every output frame's mid-exposure. Colour input is
reduced to luminance (Rec. 709 weights).

**Interpolation** (:class:`VideoSource`): linear in log intensity between consecutive input
frames, per pixel, ``L(t) = (1 - a) L_i + a L_{i+1}`` with ``L = ln(I + ε)`` and ``ε`` the event
model's own ``log_eps``, so the log signal the sensor model sees is exactly piecewise linear with
its corners at the input frames. No optical flow (OpenCV's would add a motion model): where the
footage moves more than about a pixel per input frame, linear interpolation cross-fades an edge
instead of moving it (event timing within a frame interval is then spread out; counts per pixel
still follow the total log change).

**Time resolution**: the input frame times are mandatory render times, and between them the
simulator's adaptive sampler (:mod:`hybridhdr.simulate.sampling`) steps so that no pixel (above
the robust quantile) changes by more than C/4 between renders, and by at most ``τ/3`` of the
photoreceptor low-pass when it is on; the event sensor places each threshold crossing at its
analytic time on the linear log segment between two renders (µs resolution). For the ideal
sensor this is exact for the piecewise-linear log signal, however few renders there are; the
extra renders serve the low-pass filter, the refractory period and the noise tiers, which are the
same sensor model and profiles (``--preset``, ``--sensor``, v2e's flags) as for rendered scenes.
"""

from __future__ import annotations

import bisect
import json
import math
from pathlib import Path

import numpy as np

__all__ = ["VideoSource", "load_video", "is_video_input", "run_video"]

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".gif")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr", ".hdr", ".pgm", ".ppm")


def is_video_input(s) -> bool:
    """Whether the ``simulate`` argument is footage (a video file or an image folder), not a scene."""
    s = str(s)
    if s.startswith("builtin:") or s.endswith(".toml"):
        return False
    p = Path(s)
    return p.is_dir() or p.suffix.lower() in VIDEO_EXTENSIONS


def _folder_frames(folder: Path, input_fps: float | None) -> tuple[list[Path], np.ndarray]:
    """(image paths, times in µs) of an image folder (module notes)."""
    idx = folder / "images.txt"
    if idx.exists():
        paths, ts = [], []
        for n, line in enumerate(idx.read_text(encoding="utf-8").splitlines(), 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            if len(parts) < 2:
                raise ValueError(f"{idx} line {n}: expected 'seconds path', found {line!r}")
            try:
                t = float(parts[0])
            except ValueError:
                raise ValueError(f"{idx} line {n}: expected a time in seconds, found {parts[0]!r}") from None
            p = (folder / parts[1]).resolve()
            if folder.resolve() not in p.parents:
                raise ValueError(f"{idx} line {n}: {parts[1]} lies outside {folder}")
            paths.append(p)
            ts.append(t)
        return paths, np.round(np.asarray(ts, np.float64) * 1e6).astype(np.int64)
    imgs = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not imgs:
        raise ValueError(f"{folder}: no images ({', '.join(IMAGE_EXTENSIONS)}) and no images.txt")
    tfile = folder / "timestamps.txt"
    if tfile.exists():
        vals = [ln.split()[0] for ln in tfile.read_text(encoding="utf-8").splitlines()
                if ln.strip() and not ln.startswith("#")]
        if len(vals) != len(imgs):
            raise ValueError(f"{tfile}: {len(vals)} times for {len(imgs)} images; expected one per image")
        try:
            ts = np.asarray([float(v) for v in vals])
        except ValueError as e:
            raise ValueError(f"{tfile}: expected one time in seconds per line ({e})") from None
        return imgs, np.round(ts * 1e6).astype(np.int64)
    if input_fps is None:
        raise ValueError(f"{folder}: the images' times are needed: an images.txt ('seconds path' per line), a "
                         f"timestamps.txt (seconds, one per image in name order), or --input-fps")
    return imgs, np.round(np.arange(len(imgs)) * 1e6 / input_fps).astype(np.int64)


def _read_image(p: Path) -> np.ndarray:
    """Linear radiance of one image: EXR with the OpenEXR package (the container's EXR reader), others
    with :func:`hybridhdr.simulate.ahdr.load_linear_image` (sRGB-linearised)."""
    if p.suffix.lower() == ".exr":
        from ..formats.images import read_exr
        try:
            return read_exr(p)  # Y, or R, G, B
        except KeyError as e:
            raise ValueError(f"{p}: an EXR without a Y or R, G, B channels ({e})") from None
    from .ahdr import load_linear_image
    return load_linear_image(p)


def _luminance(im: np.ndarray) -> np.ndarray:
    from .ahdr import to_luminance
    return np.asarray(to_luminance(im), np.float32)


def load_video(path, *, input_fps: float | None = None, max_frames: int | None = None, start_frame: int = 0):
    """Linear luminance frames of footage: ``(frames (N, H, W) float32, times_us (N,) int64 from 0,
    hdr: bool, info: dict)`` (module notes). Memory is bounded before decoding (``--allow-huge``)."""
    from .._util.limits import check_frame_bytes, check_frame_shape
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such video file or image folder")
    if max_frames is not None and max_frames < 2:
        raise ValueError(f"--max-input-frames: expected at least 2, found {max_frames}")
    if path.is_dir():
        paths, ts = _folder_frames(path, input_fps)
        paths, ts = paths[start_frame:], ts[start_frame:]
        if max_frames is not None:
            paths, ts = paths[:max_frames], ts[:max_frames]
        if len(paths) < 2:
            raise ValueError(f"{path}: at least 2 frames are needed, found {len(paths)}")
        hdr = {p.suffix.lower() for p in paths} <= {".exr", ".hdr"}
        first = _luminance(_read_image(paths[0]))
        check_frame_shape((len(paths),) + first.shape, path)
        check_frame_bytes(len(paths) * first.size * 4, path)
        frames = np.empty((len(paths),) + first.shape, np.float32)
        frames[0] = first
        for i, p in enumerate(paths[1:], 1):
            im = _luminance(_read_image(p))
            if im.shape != first.shape:
                raise ValueError(f"{p}: {im.shape[1]}x{im.shape[0]} image in a {first.shape[1]}x{first.shape[0]} "
                                 f"sequence")
            frames[i] = im
        info = {"input": str(path), "kind": "hdr image sequence" if hdr else "image sequence",
                "first_image": paths[0].name, "last_image": paths[-1].name}
    else:
        try:
            import imageio_ffmpeg
        except ImportError as e:
            raise ImportError("reading a video file needs imageio-ffmpeg: pip install 'hybridhdr[simulate]'") from e
        from .ahdr import _srgb_to_linear
        gen = imageio_ffmpeg.read_frames(str(path), pix_fmt="gray16le", bpp=2)
        frames_l = []
        try:
            try:
                meta = next(gen)
            except (RuntimeError, OSError, StopIteration) as e:
                raise ValueError(f"{path}: cannot read this video ({e})") from None
            fps = input_fps or meta.get("fps")
            if not fps or not math.isfinite(float(fps)) or fps <= 0:
                raise ValueError(f"{path}: the video states no frame rate; give --input-fps")
            w, h = (int(x) for x in meta["size"])
            check_frame_shape((1, h, w), path)
            n_est = max_frames or max(1, int(round(float(meta.get("duration") or 0) * fps)) - start_frame)
            check_frame_bytes(n_est * w * h * 4, path)
            for i, buf in enumerate(gen):
                if i < start_frame:
                    continue
                if max_frames is not None and len(frames_l) >= max_frames:
                    break
                a = np.frombuffer(buf, np.uint16).reshape(h, w)  # luma (Rec. 709 weights), sRGB-encoded
                frames_l.append(_srgb_to_linear(a.astype(np.float64) / 65535.0).astype(np.float32))
                check_frame_bytes(len(frames_l) * w * h * 4, path)
        finally:
            gen.close()
        if len(frames_l) < 2:
            raise ValueError(f"{path}: at least 2 frames are needed, found {len(frames_l)}")
        frames = np.stack(frames_l)
        ts = np.round(np.arange(len(frames)) * 1e6 / float(fps)).astype(np.int64)
        hdr = False
        info = {"input": str(path), "kind": "video", "fps": float(fps)}
    ts = ts - ts[0]
    if np.any(np.diff(ts) <= 0):
        k = int(np.argmax(np.diff(ts) <= 0))
        raise ValueError(f"{path}: frame times must increase (by at least 1 µs); frame {k + 1} is at {ts[k + 1]} µs "
                         f"after {ts[k]} µs")
    if not np.isfinite(frames).all() or (frames < 0).any():
        raise ValueError(f"{path}: radiance must be finite and >= 0")
    scale = 1.0
    if not hdr:
        med = float(np.median(frames))
        scale = 1.0 / med if med > 0 else 1.0
        frames *= np.float32(scale)
    info.update(n_frames=len(frames), start_frame=int(start_frame), radiance_scale=scale, hdr=hdr)
    return frames, ts, hdr, info


class VideoSource:
    """A :class:`~hybridhdr.simulate.source.RadianceSource` of footage: radiance interpolated linearly
    in ``ln(I + log_eps)`` between input frames (module notes). ``times_us`` start at 0."""

    def __init__(self, frames, times_us, *, log_eps: float, info: dict | None = None):
        from ..events import SensorSize
        frames = np.asarray(frames, np.float32)
        if frames.ndim != 3 or len(frames) < 2:
            raise ValueError(f"frames: expected (N >= 2, H, W), found shape {frames.shape}")
        self.times = [int(t) for t in times_us]
        if len(self.times) != len(frames) or self.times[0] != 0 or any(b <= a for a, b in zip(self.times, self.times[1:])):
            raise ValueError("times_us: one increasing time per frame, starting at 0")
        self.eps = float(log_eps)
        self.frames = frames  # returned as they are at the input times (the HDR references there)
        self.logs = np.log(frames.astype(np.float64) + self.eps)
        self.sensor_size = SensorSize(*frames.shape[1:])
        self.duration_us = self.times[-1]
        self.renders = 0
        self.info = dict(info or {})

    def render(self, t_us: int) -> np.ndarray:
        self.renders += 1
        t = min(max(int(t_us), 0), self.duration_us)
        i = min(bisect.bisect_right(self.times, t) - 1, len(self.times) - 2)
        t0, t1 = self.times[i], self.times[i + 1]
        a = (t - t0) / (t1 - t0)
        if a == 0.0:
            return self.frames[i].copy()
        if a == 1.0:
            return self.frames[i + 1].copy()
        lg = (1.0 - a) * self.logs[i] + a * self.logs[i + 1]
        return np.maximum(np.exp(lg) - self.eps, 0.0).astype(np.float32)

    def max_image_speed_px_per_s(self, t0_us, t1_us) -> float:
        # no motion model: the brightness rule is exact on a piecewise-linear log signal (module notes)
        return 0.0

    def describe(self) -> dict:
        return {"name": "video", "source": "video", "log_eps": self.eps, "times_us_first_last": [0, self.duration_us],
                "n_input_frames": len(self.times), **self.info}


def run_video(args, say) -> int:
    """``hybridhdr simulate VIDEO --out REC.h5`` (the command's footage path)."""
    from .._util.atomic import refuse_existing_output, refuse_overwriting_inputs
    from .camera import FrameCameraParams
    from .runner import run_simulation, sensor_params
    from .resume import partial_path
    from .sampling import SamplingParams
    if args.out is None:
        raise ValueError("--out REC.h5 is required")
    refuse_overwriting_inputs({"--out": args.out}, [args.scene])
    refuse_existing_output(args.out, overwrite=args.overwrite, flag="--out", command="simulate")
    sensor = sensor_params(args)
    frames, ts, hdr, info = load_video(args.scene, input_fps=args.input_fps, max_frames=args.max_input_frames,
                                       start_frame=args.start_frame)
    src = VideoSource(frames, ts, log_eps=sensor.log_eps, info=info)
    partial = partial_path(args.out)
    if partial.exists() and not args.resume:
        if not args.overwrite:
            raise ValueError(f"{partial} exists (an interrupted run's partial): pass --resume to finish it, or "
                             f"--overwrite to start again")
        partial.unlink()
    mean_rate = (len(ts) - 1) * 1e6 / ts[-1]
    camera = None
    if not args.no_frames:
        fps = args.frame_rate_hz or mean_rate
        exp_us = args.exposure_us or int(min(10_000, 0.5e6 / fps))
        ckw = dict(frame_rate_hz=fps, exposure_us=exp_us, crf=args.crf, bit_depth=args.bit_depth,
                   auto_exposure=args.auto_exposure)
        if args.electrons_per_radiance_s is not None:
            ckw["electrons_per_radiance_s"] = args.electrons_per_radiance_s
        camera = FrameCameraParams(**ckw)
    kw = {k: getattr(args, a) for k, a in (("min_rate_hz", "min_rate_hz"), ("max_rate_hz", "max_rate_hz"),
                                           ("robust_quantile", "robust_quantile")) if getattr(args, a) is not None}
    sampling = (SamplingParams(mode="fixed", fixed_rate_hz=args.fixed_rate_hz) if args.fixed_rate_hz is not None
                else SamplingParams(mode="adaptive", **kw))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    say(f"{info['kind']} {args.scene}: {len(ts)} frames of {src.sensor_size.width}x{src.sensor_size.height} over "
        f"{ts[-1] / 1e6:.3g} s ({mean_rate:.3g} frames/s), interpolated linearly in ln(I + {sensor.log_eps:g}); "
        + ("HDR input: HDR references written" if hdr else "LDR input (sRGB-linearised): no HDR references"),
        err=True)
    _, summary = run_simulation(src, args.out, partial, resume=args.resume, sensor=sensor, camera=camera,
                                sampling=sampling, gt_times_us=ts, seed=args.seed, progress=not args.no_progress,
                                say=lambda s: say(s, err=True), estimate=False, write_hdr=hdr)
    summary = {"out": str(args.out), "input": str(args.scene), "input_frames": len(ts), "hdr_input": hdr, **summary}
    say(f"wrote {args.out}: {summary['events']} events, {summary['frames']} frames, {summary['hdr_references']} HDR "
        f"references from {len(ts)} input frames, {summary['renders']} interpolated renders, {summary['wall_s']:.2f} s")
    if args.json:
        print(json.dumps(summary))
    return 0

