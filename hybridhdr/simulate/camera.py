"""Frame-camera model: exposure, motion blur, noise, CRF and quantisation.

The chain follows ``docs/simulate-sensor.md`` ("Frame camera"):

1. linear radiance from the renders;
2. **exposure**: the time average of the radiance over the exposure interval, with the radiance
   piecewise linear in time between the renders (trapezoids), i.e. motion blur from
   sub-renders as ESIM's ``camera_simulator.cpp`` does (Mitsuba has no animated transforms);
3. optional **rolling shutter**: row ``y`` of an ``H``-row frame is exposed over the row-0
   interval shifted by ``y * rolling_shutter_readout_us / H``;
4. **electrons** ``e = I * t_exp * electrons_per_radiance_s``;
5. **noise**: Poisson photon shot noise (optional), clipping at the full well, then Gaussian read
   noise ``N(0, read_noise_e)``;
6. analogue **gain**: the normalised signal ``v = clip(e * gain / full_well_e, 0, 1)``;
7. a **CRF** ``y = CRF(v)`` in [0, 1];
8. **quantisation** to ``bit_depth`` bits: ``code = round(y * (2**bit_depth - 1))``;
9. optional **artificial saturation**: codes outside ``code_clip`` are clipped (the AKF paper's
   AHDR data, §6 and Fig. 6: "pixel values higher than 160 or lower than 100 of an 8-bit
   image").

Frames are stamped with their (row-0) exposure interval ``[t_start_us, t_end_us]``. Frame ``k``
starts at ``round(k * 1e6 / frame_rate_hz)`` µs. With auto-exposure the exposure of frame
``k + 1`` is chosen from frame ``k``: ``e_{k+1} = e_k * (target / m_k) ** ae_damping`` where
``m_k`` is the mean linear signal (inverse CRF of the codes), clamped to
``[ae_min_exposure_us, frame period]``.

References
----------
H. Rebecq, D. Gehrig, D. Scaramuzza, "ESIM: an Open Event Camera Simulator", CoRL 2018.
Z. Wang, Y. Ng, C. Scheerlinck, R. Mahony, "An Asynchronous Kalman Filter for Hybrid Event
Cameras", ICCV 2021, doi:10.1109/ICCV48922.2021.00050 (§3.2.1 CRF; §6 AHDR saturation).
IEC 61966-2-1:1999 (sRGB transfer function).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass

import numpy as np

from .._util.checks import check_shape
from ..camera import profile_from_inverse_crf
from ..camera.profile import CameraProfile
from ..events import SensorSize
from ..model import Frames

__all__ = ["FrameCameraParams", "FrameCamera", "crf_forward", "crf_inverse_table", "CRF_NAMES",
           "ExposureAccumulator"]

CRF_NAMES = ("linear", "gamma", "srgb", "table", "akf_s_curve_30", "akf_s_curve_50", "akf_s_curve_80",
             "akf_s_curve_100", "akf_s_curve_115")
_S_CURVE = re.compile(r"^akf_s_curve_(\d+(?:\.\d+)?)$")
#: Width (in normalised code units) of the logistic AKF S-curve stand-in (see :func:`crf_forward`).
S_CURVE_WIDTH = 0.1


@dataclass(frozen=True, kw_only=True)
class FrameCameraParams:
    """Frame-camera parameters (all noise off unless set).

    Parameters
    ----------
    frame_rate_hz : float
        Frame rate (DAVIS346 APS: up to ~50 Hz; 20 Hz default).
    exposure_us : int
        Exposure time (the first frame's with auto-exposure).
    bit_depth : {8, 10, 12}
    crf : str
        "linear", "gamma" (``v ** (1/gamma)``), "srgb" (IEC 61966-2-1), "akf_s_curve_<K>" (a
        logistic S-curve with its inflection at code K of 255; stand-in for the AKF AHDR curves,
        see :func:`crf_forward`) or "table" (``inverse_crf`` below, e.g. a measured profile).
    gamma : float
        Exponent of the "gamma" CRF (2.2).
    inverse_crf : tuple of float, optional
        For ``crf="table"``: irradiance per code (``2**bit_depth`` entries, non-decreasing),
        any scale (normalised to its last entry), as in a camera profile (docs/camera-profile.md).
    full_well_e : float
        Full-well capacity in electrons (10 000: a typical small-pixel CMOS value; our choice).
    electrons_per_radiance_s : float
        Electrons per second per unit radiance (quantum efficiency and optics folded in). The
        default fills half the well at radiance 1 with a 10 ms exposure.
    read_noise_e : float
        σ of the read noise in electrons (0 = off).
    shot_noise : bool
        Poisson photon shot noise.
    gain : float
        Analogue gain (linear); ``iso = 100 * gain`` is recorded.
    rolling_shutter_readout_us : int
        Time between the first and last row starting their exposure (0 = global shutter).
    auto_exposure : bool
    ae_target : float
        Target mean linear signal in [0, 1] (0.18: middle grey).
    ae_damping : float
        Exponent of the exposure update, in (0, 1] (1 = jump to target).
    ae_min_exposure_us : int
    code_clip : (int, int), optional
        Artificial saturation: codes below/above are clipped (AKF AHDR: (100, 160) at 8 bits).
    """

    frame_rate_hz: float = 20.0
    exposure_us: int = 10_000
    bit_depth: int = 8
    crf: str = "linear"
    gamma: float = 2.2
    inverse_crf: tuple | None = None
    full_well_e: float = 10_000.0
    electrons_per_radiance_s: float = 5e5
    read_noise_e: float = 0.0
    shot_noise: bool = False
    gain: float = 1.0
    rolling_shutter_readout_us: int = 0
    auto_exposure: bool = False
    ae_target: float = 0.18
    ae_damping: float = 0.7
    ae_min_exposure_us: int = 10
    code_clip: tuple | None = None

    def __post_init__(self):
        def pos(name, zero_ok=False):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v) \
                    or (v < 0 if zero_ok else v <= 0):
                rel = ">= 0" if zero_ok else "> 0"
                raise ValueError(f"FrameCameraParams.{name} must be a finite number {rel}, got {v!r}")

        for n in ("frame_rate_hz", "gamma", "full_well_e", "electrons_per_radiance_s", "gain", "ae_target",
                  "ae_damping"):
            pos(n)
        pos("read_noise_e", zero_ok=True)
        for n in ("exposure_us", "rolling_shutter_readout_us", "ae_min_exposure_us"):
            v = getattr(self, n)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (0 if n == "rolling_shutter_readout_us" else 1):
                raise ValueError(f"FrameCameraParams.{n} must be an int number of µs "
                                 f"{'>= 0' if n == 'rolling_shutter_readout_us' else '>= 1'}, got {v!r}")
        period = 1e6 / self.frame_rate_hz
        if self.exposure_us + self.rolling_shutter_readout_us > period:
            raise ValueError(f"exposure_us + rolling_shutter_readout_us = "
                             f"{self.exposure_us + self.rolling_shutter_readout_us} µs exceeds the frame period "
                             f"{period:.0f} µs at {self.frame_rate_hz} Hz")
        if self.bit_depth not in (8, 10, 12):
            raise ValueError(f"FrameCameraParams.bit_depth must be 8, 10 or 12, got {self.bit_depth!r}")
        if self.ae_target >= 1 or self.ae_damping > 1:
            raise ValueError("FrameCameraParams.ae_target must be < 1 and ae_damping <= 1")
        if self.crf == "table":
            if self.inverse_crf is None:
                raise ValueError("crf='table' needs inverse_crf (one irradiance per code)")
            inv = np.asarray(self.inverse_crf, dtype=np.float64)
            n = 1 << self.bit_depth
            check_shape(inv, "N", "inverse_crf (2**bit_depth entries)", sizes={"N": n})
            if not np.all(np.isfinite(inv)) or np.any(np.diff(inv) < 0) or inv[0] < 0 or inv[-1] <= 0:
                raise ValueError("inverse_crf must be finite, >= 0, non-decreasing and end above 0")
            object.__setattr__(self, "inverse_crf", tuple(float(v) for v in inv))
        elif self.crf not in ("linear", "gamma", "srgb") and not _S_CURVE.match(str(self.crf)):
            raise ValueError(f"FrameCameraParams.crf must be one of {CRF_NAMES[:4]} or 'akf_s_curve_<K>', "
                             f"got {self.crf!r}")
        if self.code_clip is not None:
            lo, hi = (int(v) for v in self.code_clip)
            if not 0 <= lo < hi <= (1 << self.bit_depth) - 1:
                raise ValueError(f"code_clip must be (lo, hi) with 0 <= lo < hi <= {(1 << self.bit_depth) - 1}, "
                                 f"got {self.code_clip!r}")
            object.__setattr__(self, "code_clip", (lo, hi))

    @property
    def max_code(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def frame_period_us(self) -> float:
        return 1e6 / self.frame_rate_hz

    @property
    def encoding(self) -> str:
        """``Frames.encoding`` of the output: "linear", "gamma" (γ = 2.2), "srgb" or "unknown"."""
        if self.code_clip is None and self.crf == "linear":
            return "linear"
        if self.code_clip is None and self.crf == "gamma" and abs(self.gamma - 2.2) < 1e-12:
            return "gamma"
        if self.code_clip is None and self.crf == "srgb":
            return "srgb"
        return "unknown"

    @classmethod
    def from_profile(cls, path, **changes) -> "FrameCameraParams":
        """Use the measured inverse CRF of a camera profile JSON (``docs/camera-profile.md``)."""
        prof = CameraProfile.load(path)
        if prof.inverse_crf is None:
            inv = np.arange(prof.max_code + 1, dtype=np.float64) / prof.max_code
        else:
            inv = prof.inverse_crf
        bits = int(round(math.log2(prof.max_code + 1)))
        return cls(crf="table", inverse_crf=tuple(inv), bit_depth=bits, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        return d

    def replace(self, **changes) -> "FrameCameraParams":
        return dataclasses.replace(self, **changes)


def crf_forward(v, params: FrameCameraParams) -> np.ndarray:
    """The CRF: normalised linear signal ``v`` in [0, 1] -> normalised code value in [0, 1].

    ``akf_s_curve_K``: the AKF authors' released AHDR data apply S-curves named
    ``s_curve_{30,50,80,100,115}`` (``ziweiWWANG/AKF`` README), whose formulas are not published
    in the references we have. We substitute a documented logistic S-curve with its inflection
    at code ``K/255`` and width :data:`S_CURVE_WIDTH`, rescaled to map 0 -> 0 and 1 -> 1:
    ``y = (σ((v - m)/w) - σ(-m/w)) / (σ((1 - m)/w) - σ(-m/w))``.
    """
    v = np.clip(np.asarray(v, dtype=np.float64), 0.0, 1.0)
    c = params.crf
    if c == "linear":
        return v
    if c == "gamma":
        return v ** (1.0 / params.gamma)
    if c == "srgb":
        return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1.0 / 2.4) - 0.055)
    m = _S_CURVE.match(c)
    if m:
        mid = float(m.group(1)) / 255.0
        w = S_CURVE_WIDTH
        sig = lambda z: 1.0 / (1.0 + np.exp(-z))  # noqa: E731
        lo, hi = sig(-mid / w), sig((1.0 - mid) / w)
        return (sig((v - mid) / w) - lo) / (hi - lo)
    # table: invert the (normalised) inverse CRF by interpolation
    inv = np.asarray(params.inverse_crf, dtype=np.float64)
    inv = inv / inv[-1]
    codes = np.arange(inv.size, dtype=np.float64) / (inv.size - 1)
    # np.interp needs increasing x: take the last code of flat runs
    keep = np.concatenate([np.diff(inv) > 0, [True]])
    return np.interp(v, inv[keep], codes[keep])


def crf_inverse_table(params: FrameCameraParams) -> np.ndarray:
    """Normalised linear signal per output code (``2**bit_depth`` entries), including the code
    clip: this is the ``inverse_crf`` of a camera profile for the simulated frames."""
    n = params.max_code + 1
    if params.crf == "table":
        inv = np.asarray(params.inverse_crf, dtype=np.float64)
        inv = inv / inv[-1]
    else:
        # invert the monotone forward curve on a fine grid
        v = np.linspace(0.0, 1.0, 1 << 16)
        y = crf_forward(v, params) * params.max_code
        inv = np.interp(np.arange(n, dtype=np.float64), y, v)
    if params.code_clip is not None:
        lo, hi = params.code_clip
        inv = inv.copy()
        inv[:lo] = inv[lo]
        inv[hi + 1:] = inv[hi]
    return inv


class ExposureAccumulator:
    """Integrates piecewise-linear radiance over one exposure, row by row.

    Row ``y`` is exposed over ``[t_start + o_y, t_end + o_y]`` with ``o_y = y * readout / H``
    (``readout = 0``: global shutter). Feed consecutive samples with :meth:`add`; a segment
    ``[ta, tb]`` contributes, per row, the exact integral of the linear interpolation over its
    overlap with the row's window: ``len * (R_a (1 - f) + R_b f)`` with ``f`` the overlap's
    midpoint fraction.
    """

    def __init__(self, shape, t_start_us: int, t_end_us: int, readout_us: int = 0):
        self.h, self.w = shape
        self.t_start, self.t_end = int(t_start_us), int(t_end_us)
        if self.t_end <= self.t_start:
            raise ValueError(f"exposure [{t_start_us}, {t_end_us}] µs must have a positive length")
        self.readout = int(readout_us)
        self.off = (np.arange(self.h, dtype=np.float64) * self.readout / self.h)[:, None] if self.readout else None
        self.acc = np.zeros(shape, np.float64)
        self.covered = 0.0

    @property
    def t_last_row_end(self) -> float:
        return self.t_end + (self.readout * (self.h - 1) / self.h if self.readout else 0.0)

    def add(self, ta, ra, tb, rb) -> None:
        """Add the segment from sample ``(ta, ra)`` to ``(tb, rb)`` (radiance arrays (H, W))."""
        if tb <= ta:
            return
        if self.off is None:
            lo, hi = max(ta, self.t_start), min(tb, self.t_end)
            if hi <= lo:
                return
            f = ((lo + hi) * 0.5 - ta) / (tb - ta)
            self.acc += (hi - lo) * ((1.0 - f) * ra + f * rb)
            self.covered += hi - lo
        else:
            lo = np.maximum(ta, self.t_start + self.off)
            hi = np.minimum(tb, self.t_end + self.off)
            ln = np.clip(hi - lo, 0.0, None)
            if not np.any(ln > 0):
                return
            f = ((lo + hi) * 0.5 - ta) / (tb - ta)
            self.acc += ln * ((1.0 - f) * ra + f * rb)
            self.covered += float(ln[0, 0])

    def mean(self) -> np.ndarray:
        """Time-averaged radiance over the exposure (H, W)."""
        return self.acc / float(self.t_end - self.t_start)


class FrameCamera:
    """A frame camera fed with radiance samples; yields frames as their exposures complete.

    Parameters
    ----------
    params : FrameCameraParams
    sensor_size : SensorSize or (height, width)
    seed : int, SeedSequence or None
    duration_us : int, optional
        Frames whose exposure would end after it are not planned. Without it (or with
        auto-exposure) only the next frame is planned at any time.
    """

    def __init__(self, params: FrameCameraParams, sensor_size, seed=0, duration_us: int | None = None):
        if not isinstance(params, FrameCameraParams):
            raise TypeError(f"params must be FrameCameraParams, got {type(params).__name__}")
        self.params = params
        self.sensor_size = SensorSize.from_any(sensor_size)
        self.rng = np.random.default_rng(seed)
        self.duration = duration_us
        self._k = 0
        self._exposure = int(params.exposure_us)
        self._active: list[tuple[int, ExposureAccumulator]] = []
        self._new_intervals: list[tuple[int, int]] = []
        self._last = None
        self.n_frames = 0
        # without auto-exposure and with a known duration every exposure is planned now;
        # otherwise each frame plans the next when it completes (pop_new_intervals)
        self._planned_all = not params.auto_exposure and duration_us is not None
        if self._planned_all:
            k = 0
            while True:
                iv = self._interval(k, self._exposure)
                if iv is None:
                    break
                self._open(k, iv)
                k += 1
        else:
            iv = self._interval(0, self._exposure)
            if iv is not None:
                self._open(0, iv)

    # -- planning -------------------------------------------------------------------------------
    def _interval(self, k: int, exposure_us: int):
        t0 = int(round(k * self.params.frame_period_us))
        t1 = t0 + int(exposure_us)
        end = t1 + self.params.rolling_shutter_readout_us
        if self.duration is not None and end > self.duration:
            return None
        return t0, t1

    def _open(self, k, iv):
        acc = ExposureAccumulator(self.sensor_size.shape, iv[0], iv[1], self.params.rolling_shutter_readout_us)
        self._active.append((k, acc))
        self._new_intervals.append(iv)

    def exposure_intervals(self) -> list[tuple[int, int]]:
        """Row-0 exposure intervals (µs) of the frames planned so far and not yet captured (with
        auto-exposure only the next one is known)."""
        return [(a.t_start, a.t_end) for _, a in self._active]

    def pop_new_intervals(self) -> list[tuple[int, int]]:
        """Intervals planned since the last call (the pipeline makes their bounds and
        mid-exposures mandatory render times)."""
        out, self._new_intervals = self._new_intervals, []
        return out

    def mandatory_times(self, interval) -> list[int]:
        """Render times an exposure needs: start, mid-exposure (ground truth) and end, plus the
        last row's end with a rolling shutter."""
        t0, t1 = interval
        ts = [t0, t0 + (t1 - t0) // 2, t1]
        if self.params.rolling_shutter_readout_us:
            h = self.sensor_size.height
            ts.append(t1 + int(math.ceil(self.params.rolling_shutter_readout_us * (h - 1) / h)))
        return ts

    # -- exposure -------------------------------------------------------------------------------
    def integrate(self, samples, t0_us: int, t1_us: int) -> np.ndarray:
        """Mean radiance over ``[t0_us, t1_us]`` (per-row shifted with a rolling shutter) from
        ``samples``, a time-sorted sequence of ``(t_us, radiance (H, W))`` covering the window,
        piecewise linear in time between samples (motion blur)."""
        samples = list(samples)
        if len(samples) < 2:
            raise ValueError(f"integrate needs at least 2 samples, got {len(samples)}")
        acc = ExposureAccumulator(self.sensor_size.shape, t0_us, t1_us, self.params.rolling_shutter_readout_us)
        if samples[0][0] > t0_us or samples[-1][0] < acc.t_last_row_end:
            raise ValueError(f"samples span [{samples[0][0]}, {samples[-1][0]}] µs but the exposure needs "
                             f"[{t0_us}, {acc.t_last_row_end:.0f}] µs")
        for (ta, ra), (tb, rb) in zip(samples[:-1], samples[1:]):
            if tb < ta:
                raise ValueError(f"samples must be sorted by time; {tb} µs follows {ta} µs")
            acc.add(ta, np.asarray(ra, np.float64), tb, np.asarray(rb, np.float64))
        return acc.mean()

    def capture(self, mean_radiance, exposure_us: int, rng: np.random.Generator | None = None) -> np.ndarray:
        """Codes of one frame from its exposure-averaged radiance (steps 4-9 of the chain).

        Returns
        -------
        ndarray (H, W), uint8 for 8 bits else uint16
        """
        p = self.params
        rng = self.rng if rng is None else rng
        rad = np.asarray(mean_radiance, dtype=np.float64)
        check_shape(rad, "H W", "mean_radiance", sizes=dict(zip("HW", self.sensor_size.shape)))
        e = np.clip(rad, 0.0, None) * (exposure_us * 1e-6) * p.electrons_per_radiance_s
        if p.shot_noise:
            e = rng.poisson(np.minimum(e, 1e15)).astype(np.float64)
        e = np.minimum(e, p.full_well_e)
        if p.read_noise_e > 0:
            e = e + rng.normal(0.0, p.read_noise_e, e.shape)
        v = np.clip(e * p.gain / p.full_well_e, 0.0, 1.0)
        y = crf_forward(v, p)
        codes = np.rint(y * p.max_code)
        if p.code_clip is not None:
            codes = np.clip(codes, p.code_clip[0], p.code_clip[1])
        return codes.astype(np.uint8 if p.bit_depth == 8 else np.uint16)

    def linear_signal(self, codes) -> np.ndarray:
        """Normalised linear signal ``v`` of codes (inverse CRF table lookup)."""
        inv = crf_inverse_table(self.params)
        return inv[np.asarray(codes, dtype=np.int64)]

    def _next_exposure(self, codes, exposure_us: int) -> int:
        p = self.params
        m = float(np.mean(self.linear_signal(codes)))
        m = max(m, 1e-4)
        new = exposure_us * (p.ae_target / m) ** p.ae_damping
        hi = int(p.frame_period_us) - p.rolling_shutter_readout_us
        return int(min(max(round(new), p.ae_min_exposure_us), hi))

    # -- streaming -------------------------------------------------------------------------------
    def feed(self, t_us: int, radiance) -> list[Frames]:
        """Add a radiance sample; return the frames whose exposures completed (each a one-frame
        :class:`Frames`). Samples must arrive in increasing time; exposure bounds must be among
        them (the pipeline makes them mandatory)."""
        r = np.asarray(radiance, dtype=np.float64)
        done: list[Frames] = []
        if self._last is not None:
            ta, ra = self._last
            for _, acc in self._active:
                acc.add(ta, ra, t_us, r)
        self._last = (int(t_us), r)
        current, self._active = self._active, []
        keep = []
        for k, acc in current:
            if t_us >= acc.t_last_row_end:
                exp = acc.t_end - acc.t_start
                codes = self.capture(acc.mean(), exp)
                done.append(Frames(codes[None], np.array([acc.t_start]), np.array([acc.t_end]),
                                   gain=np.array([self.params.gain]), iso=np.array([100.0 * self.params.gain]),
                                   encoding=self.params.encoding))
                self.n_frames += 1
                if not self._planned_all:
                    iv = self._interval(k + 1, self._next_exposure(codes, exp))
                    if iv is not None:
                        self._open(k + 1, iv)  # appends to self._active
            else:
                keep.append((k, acc))
        self._active = keep + self._active
        return done

    def crf_metadata(self) -> dict:
        """The CRF as stored in the recording's provenance (``inverse_crf`` per code)."""
        return {"crf": self.params.crf, "gamma": self.params.gamma, "bit_depth": self.params.bit_depth,
                "code_clip": self.params.code_clip, "encoding": self.params.encoding,
                "inverse_crf": [float(v) for v in crf_inverse_table(self.params)]}

    def camera_profile(self, frame_precision_scale: float = 7e5):
        """A :class:`~hybridhdr.camera.profile.CameraProfile` for the simulated frames
        (inverse CRF from :func:`crf_inverse_table`; weighting from eqs. 4-5)."""
        return profile_from_inverse_crf(crf_inverse_table(self.params), clip_codes=self.params.code_clip,
                                        frame_precision_scale=frame_precision_scale,
                                        name=f"simulated-{self.params.crf}", source="hybridhdr.simulate.camera")
