"""Writing reconstructions: float32 linear EXR sequences, tone-mapped PNG and MP4 previews.

Every file is written under a temporary name in the target folder and renamed into place, so
a crash never leaves a truncated file under the final name.

Tone mapping (previews only; the EXR files hold the linear values untouched):
``v = clip((log(max(I, 1e-6)) - lo) / (hi - lo), 0, 1) ** (1 / gamma)`` with ``lo`` and ``hi`` the
``low_percentile`` and ``high_percentile`` of ``log I`` over the whole video (fixed over time so
brightness changes stay visible), ``gamma = 1`` by default, then ``round(255 v)`` as 8-bit grey.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["tone_map", "write_exr_sequence", "read_exr", "write_png_previews", "write_mp4", "write_timestamps"]


def _atomic_target(path: Path, suffix: str):
    fd, tmp = tempfile.mkstemp(prefix="." + path.stem + ".", suffix=".partial" + suffix, dir=path.parent)
    os.close(fd)
    return tmp


def _finish(tmp: str, path: Path) -> None:
    os.replace(tmp, path)


def _cleanup(tmp: str) -> None:
    if os.path.exists(tmp):
        os.unlink(tmp)


def tone_map(frames: np.ndarray, *, low_percentile: float = 1.0, high_percentile: float = 99.0,
             gamma: float = 1.0, limits: tuple[float, float] | None = None) -> tuple[np.ndarray, tuple[float, float]]:
    """Global log tone mapping of linear frames (K, H, W) to uint8; returns (images, (lo, hi)).

    ``limits`` (in log units) overrides the percentiles, e.g. to tone-map two videos alike.
    """
    f = np.asarray(frames, dtype=np.float64)
    if f.ndim not in (2, 3):
        raise ValueError(f"frames must have shape (K, H, W) or (H, W), got {f.shape}")
    if not 0 <= low_percentile < high_percentile <= 100:
        raise ValueError(f"need 0 <= low_percentile < high_percentile <= 100, got {low_percentile}, {high_percentile}")
    if gamma <= 0:
        raise ValueError(f"gamma must be > 0, got {gamma}")
    lg = np.log(np.maximum(np.nan_to_num(f, nan=1e-6, posinf=1e6), 1e-6))
    if limits is None:
        lo, hi = (float(v) for v in np.percentile(lg, [low_percentile, high_percentile]))
    else:
        lo, hi = float(limits[0]), float(limits[1])
    if hi <= lo:
        hi = lo + 1e-6
    v = np.clip((lg - lo) / (hi - lo), 0.0, 1.0) ** (1.0 / gamma)
    return np.round(255.0 * v).astype(np.uint8), (lo, hi)


def write_timestamps(t_us, names, path) -> Path:
    """``timestamps.txt``: a header line, then ``t_us filename`` per frame."""
    path = Path(path)
    tmp = _atomic_target(path, ".txt")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write("# t_us filename (t in microseconds, the state at t includes events before t)\n")
            for t, n in zip(np.asarray(t_us, np.int64), names):
                f.write(f"{int(t)} {n}\n")
        _finish(tmp, path)
    except BaseException:
        _cleanup(tmp)
        raise
    return path


def write_exr_sequence(video, out_dir, *, prefix: str = "frame_", channel: str = "Y") -> list[Path]:
    """Write each frame as a float32 single-channel EXR (ZIP) plus ``timestamps.txt``."""
    try:
        import OpenEXR
    except ImportError as e:  # pragma: no cover
        raise ImportError("writing EXR needs the OpenEXR package (pip install 'hybridhdr[images]')") from e
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    paths, names = [], []
    for i, img in enumerate(video.frames):
        name = f"{prefix}{i:06d}.exr"
        path = out / name
        tmp = _atomic_target(path, ".exr")
        try:
            OpenEXR.File(header, {channel: np.ascontiguousarray(img, dtype=np.float32)}).write(tmp)
            _finish(tmp, path)
        except BaseException:
            _cleanup(tmp)
            raise
        paths.append(path)
        names.append(name)
    write_timestamps(video.t_us, names, out / "timestamps.txt")
    return paths


def read_exr(path, channel: str = "Y") -> np.ndarray:
    """Read one channel of an EXR file as float32 (H, W)."""
    import OpenEXR
    with OpenEXR.File(str(path)) as f:
        return np.asarray(f.channels()[channel].pixels, dtype=np.float32)


def write_png_previews(video, out_dir, *, every: int = 1, prefix: str = "preview_", **tone) -> list[Path]:
    """Tone-mapped 8-bit PNGs of every ``every``-th frame (see the module docstring)."""
    import imageio.v3 as iio
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
            iio.imwrite(tmp, imgs[i], extension=".png")
            _finish(tmp, path)
        except BaseException:
            _cleanup(tmp)
            raise
        paths.append(path)
    return paths


def write_mp4(video, path, *, fps: float = 30.0, **tone) -> Path:
    """Tone-mapped H.264 preview (needs ``imageio-ffmpeg``); even sizes are padded."""
    import imageio.v3 as iio
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imgs, _ = tone_map(video.frames, **tone)
    h, w = imgs.shape[1:]
    imgs = np.pad(imgs, ((0, 0), (0, h % 2), (0, w % 2)), mode="edge")
    rgb = np.repeat(imgs[..., None], 3, axis=3)
    tmp = _atomic_target(path, ".mp4")
    try:
        iio.imwrite(tmp, rgb, extension=".mp4", fps=fps, codec="libx264", macro_block_size=1)
        _finish(tmp, path)
    except BaseException:
        _cleanup(tmp)
        raise
    return path
