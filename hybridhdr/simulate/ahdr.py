"""AHDR builder: real HDR images moved by a synthetic camera into events, LDR frames and references.

The AKF paper's artificial HDR (AHDR) data (Wang et al., ICCV 2021, §5 "Hybrid Event/Frame
Dataset" and §6, Fig. 6) simulate an LDR camera "by applying an artificial camera response
function and using the original images as HDR references"; the LDR images are "artificially
saturated (pixel values higher than 160 or lower than 100 of an 8-bit image)". We reproduce it:

1. :class:`ImageMotionSource` turns one linear HDR image (``.hdr`` Radiance RGBE, ``.exr``,
   or an 8/16-bit PNG/JPEG/TIFF linearised with the sRGB curve) into a
   :class:`~hybridhdr.simulate.source.RadianceSource`: the sensor looks at a window of the
   image that pans, zooms and rotates smoothly (a similarity transform, i.e. a special
   homography) over the duration; each render is a bilinear warp (``cv2.warpAffine``) of the
   image, first area-resampled so that one sensor pixel is about one image pixel (no aliasing).
   :class:`ImageSequenceSource` plays a sequence of images as a video instead.
2. :func:`build_ahdr` simulates events (any sensor preset), 8-bit frames through a gamma-2.2 CRF
   whose codes outside ``saturation = (100, 160)`` are clipped, and stores the warped HDR
   radiance at every frame's mid-exposure as the HDR reference.

The released AHDR sequences also use S-curve CRFs (``s_curve_*``, see
:func:`hybridhdr.simulate.camera.crf_forward`); pass ``crf="akf_s_curve_80"`` for that variant.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._util.checks import check_shape
from ..errors import FormatError
from ..events import SensorSize
from ..formats.rgbe import read_rgbe as read_rgbe_repairing
from .camera import FrameCameraParams
from .pipeline import simulate, simulate_to_file

__all__ = ["MotionParams", "ImageMotionSource", "ImageSequenceSource", "build_ahdr", "load_linear_image",
           "read_rgbe", "to_luminance", "AHDR_SATURATION"]

#: The paper's artificial saturation of 8-bit codes (§6, Fig. 6 caption and text).
AHDR_SATURATION = (100, 160)

_REC709 = np.array([0.2126, 0.7152, 0.0722])


def read_rgbe(path) -> np.ndarray:
    """Read a Radiance ``.hdr``/``.pic`` (RGBE, run-length or flat) as float32 (H, W, 3) linear RGB.

    Accepts headers with lines before ``#?RADIANCE`` (as in Debevec's ``memorial.hdr``, which
    OpenCV rejects) and the ``-Y H +X W`` orientation only.
    """
    from . import _kernels as K
    path = Path(path)
    data = np.fromfile(path, dtype=np.uint8)
    raw = data.tobytes()
    end = raw.find(b"\n\n")
    end_crlf = raw.find(b"\r\n\r\n")
    if end_crlf >= 0 and (end < 0 or end_crlf < end):
        hdr_end = end_crlf + 4
    elif end >= 0:
        hdr_end = end + 2
    else:
        raise FormatError(path, "no Radiance header end (blank line) found")
    header = raw[:hdr_end]
    if b"#?" not in header[:4096]:
        raise FormatError(path, "not a Radiance RGBE file (no '#?' signature in the header)")
    if b"FORMAT=" in header and b"32-bit_rle_rgbe" not in header:
        raise FormatError(path, "only FORMAT=32-bit_rle_rgbe is supported")
    nl = raw.find(b"\n", hdr_end)
    if nl < 0:
        raise FormatError(path, "missing resolution line after the header")
    res = raw[hdr_end:nl].decode("ascii", "replace").split()
    if len(res) != 4 or res[0] != "-Y" or res[2] != "+X":
        raise FormatError(path, f"resolution line must be '-Y H +X W', got {' '.join(res)!r}")
    h, w = int(res[1]), int(res[3])
    out = np.zeros((h, w, 4), np.uint8)
    r = K.decode_rgbe(data, nl + 1, h, w, out)
    if r == -2 and raw.count(b"\r\n") and raw.count(b"\r") == raw.count(b"\r\n"):
        # damaged by a text-mode copy (every CR/LF became CR LF, like shared/data's memorial.hdr):
        # the pure-Python reader searches for the consistent decoding (slower)
        return read_rgbe_repairing(path, repair_newlines=True)
    if r < 0:
        raise FormatError(path, f"{'truncated' if r == -1 else 'corrupt run-length'} RGBE pixel data")
    e = out[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return ((out[..., :3].astype(np.float64) + 0.5) * scale[..., None]).astype(np.float32)


def _srgb_to_linear(v):
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def load_linear_image(path) -> np.ndarray:
    """Linear radiance of an image file: float32 (H, W) or (H, W, 3).

    ``.hdr``/``.pic`` are read by :func:`read_rgbe`, ``.exr`` with OpenCV (OpenEXR enabled),
    anything else (PNG, JPEG, TIFF; 8 or 16 bit) with OpenCV and linearised with the sRGB curve
    (IEC 61966-2-1).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such image")
    ext = path.suffix.lower()
    if ext in (".hdr", ".pic", ".rgbe"):
        return read_rgbe(path)
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2
    im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if im is None:
        raise FormatError(path, "OpenCV cannot read this image")
    if im.ndim == 3:
        im = im[..., :3][..., ::-1]  # BGR(A) -> RGB
    if ext == ".exr" or im.dtype.kind == "f":
        return np.ascontiguousarray(im, dtype=np.float32)
    top = 255.0 if im.dtype == np.uint8 else 65535.0
    return _srgb_to_linear(im.astype(np.float64) / top).astype(np.float32)


def to_luminance(image) -> np.ndarray:
    """Rec. 709 luminance of linear RGB (H, W, 3); (H, W) images pass through. float32."""
    im = np.asarray(image, dtype=np.float64)
    check_shape(im, "H W | H W 3", "image")
    if im.ndim == 3:
        im = im @ _REC709
    if not np.all(np.isfinite(im)):
        raise ValueError("image has non-finite values")
    return np.clip(im, 0.0, None).astype(np.float32)


@dataclass(frozen=True, kw_only=True)
class MotionParams:
    """A smooth synthetic camera motion over the whole duration.

    The sensor pixel ``q`` sees the (resampled) image point
    ``p = C + pan(s) + R(θ(s)) (q - c) / z(s)`` with ``s`` the motion profile (0 -> 1), ``pan =
    s (pan_x_px, pan_y_px)``, ``θ = s rotation_deg``, ``z = zoom ** s``. ``profile="cosine"``:
    ``s = (1 - cos(π t/T))/2`` (starts and ends at rest, peak speed π/2 times the mean);
    ``"linear"``: ``s = t/T``.

    Parameters
    ----------
    pan_x_px, pan_y_px : float
        Total pan in sensor pixels (at zoom 1).
    zoom : float
        Final magnification (> 0; 1 = none).
    rotation_deg : float
        Total roll.
    profile : {"cosine", "linear"}
    view_fraction : float
        Fraction of the image's shorter extent that the sensor's matching extent covers at the
        start (room to pan without leaving the image).
    """

    pan_x_px: float = 40.0
    pan_y_px: float = 0.0
    zoom: float = 1.0
    rotation_deg: float = 0.0
    profile: str = "cosine"
    view_fraction: float = 0.7

    def __post_init__(self):
        for n in ("pan_x_px", "pan_y_px", "zoom", "rotation_deg", "view_fraction"):
            v = getattr(self, n)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"MotionParams.{n} must be a finite number, got {v!r}")
        if self.zoom <= 0 or not 0 < self.view_fraction <= 1:
            raise ValueError("MotionParams.zoom must be > 0 and view_fraction in (0, 1]")
        if self.profile not in ("cosine", "linear"):
            raise ValueError(f"MotionParams.profile must be 'cosine' or 'linear', got {self.profile!r}")

    def s(self, u):
        """Profile value at normalised time ``u`` in [0, 1]."""
        u = min(max(u, 0.0), 1.0)
        return 0.5 * (1.0 - math.cos(math.pi * u)) if self.profile == "cosine" else u

    def max_ds(self, u0, u1) -> float:
        """Maximum of ds/du over [u0, u1]."""
        if self.profile == "linear":
            return 1.0
        u0, u1 = min(max(u0, 0.0), 1.0), min(max(u1, 0.0), 1.0)
        m = 0.5 if u0 <= 0.5 <= u1 else (u0 if abs(u0 - 0.5) < abs(u1 - 0.5) else u1)
        return 0.5 * math.pi * math.sin(math.pi * m)


class ImageMotionSource:
    """A :class:`~hybridhdr.simulate.source.RadianceSource` moving a fixed HDR image.

    Parameters
    ----------
    image : ndarray (H, W) or (H, W, 3), or path
        Linear radiance (RGB is reduced to Rec. 709 luminance).
    sensor_size : SensorSize or (height, width)
    duration_us : int
    motion : MotionParams
    radiance_scale : float or None
        Multiplier of the image; None normalises the median of the image to 1.
    """

    def __init__(self, image, sensor_size=(260, 346), *, duration_us: int = 1_000_000,
                 motion: MotionParams | None = None, radiance_scale: float | None = None):
        import cv2
        self._cv2 = cv2
        self.image_path = None
        if isinstance(image, (str, os.PathLike)):
            self.image_path = str(image)
            image = load_linear_image(image)
        lum = to_luminance(image)
        self.sensor_size = SensorSize.from_any(sensor_size)
        if isinstance(duration_us, bool) or int(duration_us) <= 0:
            raise ValueError(f"duration_us must be a positive int, got {duration_us!r}")
        self.duration_us = int(duration_us)
        self.motion = motion or MotionParams()
        if radiance_scale is None:
            med = float(np.median(lum))
            radiance_scale = 1.0 / med if med > 0 else 1.0
        self.radiance_scale = float(radiance_scale)
        h, w = self.sensor_size.shape
        ih, iw = lum.shape
        # resample so that the sensor spans view_fraction of the image: 1 sensor px ~ 1 image px
        f = self.motion.view_fraction * min(ih / h, iw / w)
        if f > 1:
            lum = cv2.resize(lum, (max(1, round(iw / f)), max(1, round(ih / f))), interpolation=cv2.INTER_AREA)
        else:
            lum = cv2.resize(lum, (max(1, round(iw / f)), max(1, round(ih / f))), interpolation=cv2.INTER_LINEAR)
        self.image = np.ascontiguousarray(lum * self.radiance_scale, dtype=np.float32)
        self.renders = 0
        self._c_img = np.array([(self.image.shape[1] - 1) / 2.0, (self.image.shape[0] - 1) / 2.0])
        self._c_out = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
        self._r_max = math.hypot(w / 2.0, h / 2.0)

    def _affine(self, t_us) -> np.ndarray:
        """2x3 matrix mapping sensor pixel (x, y) to image coordinates at ``t_us``."""
        m = self.motion
        s = m.s(t_us / self.duration_us)
        th = math.radians(m.rotation_deg) * s
        z = m.zoom ** s
        c, si = math.cos(th) / z, math.sin(th) / z
        a = np.array([[c, -si], [si, c]])
        off = self._c_img + s * np.array([m.pan_x_px, m.pan_y_px]) - a @ self._c_out
        return np.hstack([a, off[:, None]])

    def render(self, t_us: int) -> np.ndarray:
        self.renders += 1
        cv2 = self._cv2
        h, w = self.sensor_size.shape
        out = cv2.warpAffine(self.image, self._affine(t_us), (w, h),
                             flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)
        return out

    def max_image_speed_px_per_s(self, t0_us: int, t1_us: int) -> float:
        """Exact bound: ``max ds/dt * (|ln zoom| r + |θ| r + z_max |pan|)`` with ``r`` the
        sensor's half-diagonal (the farthest visible point from the centre)."""
        m = self.motion
        T = self.duration_us * 1e-6
        ds = m.max_ds(t0_us / self.duration_us, t1_us / self.duration_us) / T
        z_max = max(m.zoom ** m.s(t0_us / self.duration_us), m.zoom ** m.s(t1_us / self.duration_us))
        return ds * (abs(math.log(m.zoom)) * self._r_max + abs(math.radians(m.rotation_deg)) * self._r_max
                     + z_max * math.hypot(m.pan_x_px, m.pan_y_px))

    def describe(self) -> dict:
        return {"name": "image_motion", "image": self.image_path, "image_shape": list(self.image.shape),
                "radiance_scale": self.radiance_scale, "motion": dataclasses.asdict(self.motion),
                "duration_us": self.duration_us}


class ImageSequenceSource:
    """A :class:`~hybridhdr.simulate.source.RadianceSource` playing images as a video at
    ``frame_rate_hz`` with radiance linearly interpolated between consecutive images.

    The image motion is unknown, so ``max_image_speed_px_per_s`` is infinite and the sampler relies
    on the brightness rule.
    """

    def __init__(self, images, frame_rate_hz: float, sensor_size=None, radiance_scale: float | None = None):
        import cv2
        ims = [to_luminance(load_linear_image(p) if isinstance(p, (str, os.PathLike)) else p) for p in images]
        if len(ims) < 2:
            raise ValueError(f"an image sequence needs at least 2 images, got {len(ims)}")
        ss = SensorSize.from_any(sensor_size) or SensorSize(*ims[0].shape)
        ims = [im if im.shape == ss.shape else cv2.resize(im, (ss.width, ss.height), interpolation=cv2.INTER_AREA)
               for im in ims]
        stack = np.stack(ims)
        if radiance_scale is None:
            med = float(np.median(stack))
            radiance_scale = 1.0 / med if med > 0 else 1.0
        self.frames = (stack * radiance_scale).astype(np.float32)
        self.sensor_size = ss
        self.period_us = 1e6 / float(frame_rate_hz)
        self.duration_us = int(round((len(ims) - 1) * self.period_us))
        self.renders = 0
        self.paths = [str(p) for p in images if isinstance(p, (str, os.PathLike))]

    def render(self, t_us: int) -> np.ndarray:
        self.renders += 1
        x = min(max(t_us / self.period_us, 0.0), len(self.frames) - 1.0)
        i = min(int(x), len(self.frames) - 2)
        f = x - i
        return ((1.0 - f) * self.frames[i] + f * self.frames[i + 1]).astype(np.float32)

    def max_image_speed_px_per_s(self, t0_us, t1_us) -> float:
        return math.inf

    def describe(self) -> dict:
        return {"name": "image_sequence", "images": self.paths, "n_images": len(self.frames),
                "period_us": self.period_us}


def build_ahdr(image_or_path, *, sensor_size=(260, 346), duration_us: int = 1_000_000,
               motion: MotionParams | None = None, frame_rate_hz: float = 20.0, exposure_us: int = 10_000,
               saturation=AHDR_SATURATION, crf: str = "gamma", sensor="clean", sampling=None,
               gt_times_us=None, seed: int | None = 0, progress: bool = False, path=None):
    """Build an AHDR recording (AKF paper §5-6) from one real image and a synthetic motion.

    Parameters
    ----------
    image_or_path : ndarray, path, or list of paths/arrays
        One linear HDR image (moved by ``motion``) or, for a list, an image sequence played at
        ``frame_rate_hz`` (``motion`` ignored).
    sensor_size : (height, width)
    duration_us : int
    motion : MotionParams
    frame_rate_hz, exposure_us : frame camera timing.
    saturation : (lo, hi) or None
        8-bit codes below ``lo`` or above ``hi`` are clipped (paper: 100 and 160).
    crf : str
        CRF before the clip; "gamma" (2.2) makes the unclipped codes a well-exposed image.
    sensor : preset name or EventSensorParams
    sampling : SamplingParams, optional
    gt_times_us : extra HDR reference times
    seed : int or None
    path : path, optional
        Write the recording there (streaming, atomic) instead of returning it in memory.

    Returns
    -------
    Recording (or the written Path)
        Events, 8-bit LDR frames (encoding "unknown": the clipped CRF, stored with its inverse
        table in ``metadata.provenance["camera"]``) and the warped HDR radiance at every frame's
        mid-exposure as HDR references.

    Notes
    -----
    The image radiance is normalised to a median of 1 and the camera's electrons per radiance are
    set so that radiance 1 over ``exposure_us`` gives the signal ``0.5 ** 2.2`` (code 128 through
    the gamma CRF): a well-exposed picture before the artificial saturation.
    """

    ss = SensorSize.from_any(sensor_size)
    if isinstance(image_or_path, (list, tuple)):
        src = ImageSequenceSource(image_or_path, frame_rate_hz, ss)
    else:
        src = ImageMotionSource(image_or_path, ss, duration_us=duration_us, motion=motion)
    full_well = 10_000.0
    k = (0.5 ** 2.2) * full_well / (exposure_us * 1e-6)
    cam = FrameCameraParams(frame_rate_hz=frame_rate_hz, exposure_us=int(exposure_us), crf=crf, bit_depth=8,
                            full_well_e=full_well, electrons_per_radiance_s=k,
                            code_clip=None if saturation is None else tuple(saturation))
    kw = dict(sensor=sensor, camera=cam, sampling=sampling, gt_times_us=gt_times_us, seed=seed, progress=progress)
    if path is not None:
        simulate_to_file(src, path, **kw)
        return Path(path)
    return simulate(src, **kw).recording
