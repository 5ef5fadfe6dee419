"""Frame augmentation for the AKF (Wang et al., ICCV 2021, §4.1, eqs. 10-13).

For frames k with exposure ``[s_k, e_k)`` (``T_k = e_k - s_k``, each frame's own exposure):

* **Deblur** (EDI, :mod:`.edi`): ``L^D(s_k)`` and ``L^D(e_k) = L^D(s_k) + c Σσ[s_k, e_k)``.
* **Interpolate** (eqs. 10, 11): on interval k, ``[s_k, e_{k+1})``, the forward estimate
  ``A_k(t) = L^D(s_k) + c_k Σσ[s_k, t)``; with the calibrated threshold it equals the backward
  estimate ``L^D(e_{k+1}) - c_k Σσ[t, e_{k+1})`` exactly.
* **Calibrate** (eq. 12): ``c_k = ΔL^D / Σσ`` per pixel, ``ΔL^D = L^D(e_{k+1}) - L^D(s_k)``, kept
  when the scale ``c / c_k`` lies in ``[calibration_scale_min, calibration_scale_max]`` (the
  reference code's [0.6, 100], ``ziweiWWANG/AKF:compute_ct_scale.m``); otherwise ``c_k = c`` with the reason counted
  (no events, Σσ = 0, ΔL^D = 0 or opposite sign, out of range) in :class:`AugmentStats`.
  With ON and OFF thresholds (the AKF's ``c_on``/``c_off`` or a per-pixel map) ON events
  step by c_on and OFF events by c_off everywhere (EDI, interpolation, the filter's L^A), and
  eq. 12 becomes ``r_k = ΔL^D / (c_on N_on - c_off N_off)``, calibrating both to ``r_k c_on``,
  ``r_k c_off``: one equation per interval fixes their common scale, their ratio is the
  sensor's (a real DAVIS can be far from symmetric). Equal thresholds give the paper's form.
* **Blend** (eq. 13): inside exposure k, ``L^A = w A_{k-1} + (1 - w) A_k`` with
  ``w = (e_k - t)/T_k``; in the gap ``[e_k, s_{k+1})``, ``L^A = A_k``. Where frame k-1 clipped
  the pixel, A_{k-1} starts from a bound, not a value, and ``L^A = A_k`` (counted).

:class:`AugmentedMeasurements` gives this L^A to the AKF through the measurement-provider hook
(``Segment.la_step``: the filter moves L^A by ±la_step at each event), with R from the camera
profile exactly as :class:`~.measurement.FrameMeasurements` (eqs. 6-9, eq. 7 across frames).
The cross-fade weight of eq. 13 is held piecewise constant on ``blend_steps`` sub-intervals of
each exposure (the filter holds L^A between events), so L^A jumps by at most
``|A_{k-1} - A_k| / blend_steps`` at sub-interval boundaries; both estimates agree on
noise-free data.

Augmentation is non-causal (interval k needs frame k+1), so it runs in ``offline`` mode only,
and it needs the events in memory (13 bytes per event).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..model import Frames
from . import _augment_kernels as AK
from .edi import edi_log_latent, estimate_threshold
from .event_arrays import EventArrays
from .measurement import FrameMeasurements, Segment
from .params import _ParamsMixin

__all__ = ["AugmentParams", "AugmentStats", "AugmentedMeasurements", "calibrate_thresholds", "deblur_min_events",
           "CALIBRATION_CATEGORIES"]

#: reasons of :func:`calibrate_thresholds`, in the order of the kernel's category codes
CALIBRATION_CATEGORIES = ("calibrated", "no_events", "zero_net_events", "sign_mismatch", "out_of_range",
                          "too_few_events")


@dataclass(frozen=True, kw_only=True)
class AugmentParams(_ParamsMixin):
    """Frame augmentation of the AKF (Wang et al., ICCV 2021, §4.1, doi:10.1109/ICCV48922.2021.00050).

    Parameters
    ----------
    enabled : bool
        Use the augmented frame as the AKF measurement in offline mode. Off by default: with
        hybridhdr's measurement model (saturation as a bound, discrete frame updates, frames
        carried forward by the events) the plain frames already score within 0.3 % of it on
        every suite of ``benchmarks/accuracy.py`` (MSE augmented / plain 0.998-1.0; see
        ``docs/reconstruct.md``); ``augment=True`` turns it on.
    deblur : bool
        EDI-deblur each frame (§4.1 "Deblur"); False takes the blurred frame as sharp at both
        ends of its exposure.
    interpolate : bool
        Event interpolation between frames (eqs. 10, 11, 13); False holds the (deblurred)
        mid-exposure image from τ_k to τ_{k+1}.
    calibrate : bool
        Per-pixel threshold calibration (eq. 12, ON and OFF thresholds scaled together, their
        ratio the sensor's). Off by default, because measured it does not pay: on the four
        suites of ``benchmarks/accuracy.py`` it never lowered the MSE (edge sweep, HDR and AHDR
        sets within 0.01 %), and on ``ecd_slider_depth`` it raised it by 0.11 % (0.85 % without
        ``calibration_min_events``) while raising SSIM by 0.02-0.5 %: eq. 12's estimate from two
        noisy frame ends and a quantised event count is no better than the nominal thresholds
        there. True interpolates with the calibrated thresholds, as the paper does.
    contrast_threshold : float or None
        One c for both polarities in EDI and interpolation, log units; None uses the AKF's ON
        and OFF thresholds (and a per-pixel map when the engine is given one).
    search_threshold : bool
        Estimate c per frame for EDI by the sharpness search (:func:`.edi.estimate_threshold`)
        instead of using ``contrast_threshold``. The reference code fixes c.
    threshold_min, threshold_max : float
        Bounds of that search, log units.
    tv_weight : float
        λ of the sharpness energy (Pan et al.: 0.2).
    calibration_scale_min, calibration_scale_max : float
        Accepted range of c / c_k (the reference code's stored 1/c_p^k: [0.6, 100],
        ``ziweiWWANG/AKF:compute_ct_scale.m``).
    blend_steps : int
        Sub-intervals of each exposure on which eq. 13's weight is held.
    deblur_min_events : int or None
        EDI-deblur a pixel of frame k only when at least this many events fell in its exposure;
        below it the frame is taken as sharp at τ_k (``L^D(τ_k) = log B_k``, counted as
        ``pixels_deblur_fallback``). None (default): ``n* = ceil(sqrt(24 / (√12 c)))`` for EDI's
        c (6 at c = 0.2, 9 at c = 0.1), where deblurring starts to pay: a frame blurred by a
        log-intensity ramp of Δ = n c over its exposure is off its mid-exposure value by only
        ``ln(sinh(Δ/2)/(Δ/2)) ≈ Δ²/24``, since the filter anchors a frame at τ_k and carries it
        with the events, while EDI reads each event as a change of exactly c and so adds a
        threshold-quantisation error of about ``c/√12``; ``Δ²/24 > c/√12`` gives n*. 0 deblurs
        every pixel, as the paper does.
    calibration_min_events : int
        Calibrate a pixel's interval (eq. 12) only when its net event count |Σσ| reaches this;
        below it the nominal thresholds are kept (counted as ``too_few_events``). Each end of
        ΔL^D carries a sub-threshold residual uniform over one threshold, so eq. 12's 1/r is off
        by about 1/(√6 |Σσ|): 5 keeps that under 10 %, the size of the threshold errors the
        calibration is meant to correct. 0 calibrates every pixel, as the paper does.
    interpolation_anchor : {"mid", "start"}
        Where A_k is anchored: ``"mid"`` (default) ``A_k(t) = L^D(τ_k) + c_k Σσ[τ_k, t)``, so
        A_k(τ_k) is the deblurred frame at its mid-exposure whatever the calibrated c_k;
        ``"start"`` ``A_k(t) = L^D(s_k) + c_k Σσ[s_k, t)`` (eq. 10 as the paper writes it),
        which at τ_k is off the deblurred frame by ``(c_k - c) Σσ[s_k, τ_k)`` (EDI deblurs with
        c, the interval is interpolated with c_k).
    """

    _toml_table = "augment"

    enabled: bool = False  # opt-in, see the docstring
    deblur: bool = True  # §4.1 Deblur (EDI)
    interpolate: bool = True  # eqs. 10, 11, 13
    calibrate: bool = False  # eq. 12 (off: measured not to pay, see the docstring)
    contrast_threshold: float | None = None  # log units; None: the AKF's c
    search_threshold: bool = False  # the reference code fixes c
    threshold_min: float = 0.05
    threshold_max: float = 0.5
    tv_weight: float = 0.2  # λ, Pan et al. TVnorm.m
    calibration_scale_min: float = 0.6  # ziweiWWANG/AKF:compute_ct_scale.m
    calibration_scale_max: float = 100.0  # idem
    blend_steps: int = 2  # eq. 13 held on T/2 halves (cost: one AKF segment switch each)
    deblur_min_events: int | None = None  # below: taken as sharp; None: n* from c (docstring); 0: the paper
    interpolation_anchor: str = "mid"  # A_k anchored at L^D(τ_k); "start": at L^D(s_k), the paper
    calibration_min_events: int = 5  # |Σσ| below: nominal thresholds (0: calibrate every pixel, the paper)

    def __post_init__(self):
        for name in ("enabled", "deblur", "interpolate", "calibrate", "search_threshold"):
            self._bool(name)
        self._threshold_search()
        self._num("calibration_scale_min", lo=0, lo_open=True)
        self._num("calibration_scale_max", lo=0, lo_open=True)
        if self.calibration_scale_min > self.calibration_scale_max:
            raise ValueError(f"AugmentParams.calibration_scale_min ({self.calibration_scale_min}) must not "
                             f"exceed calibration_scale_max ({self.calibration_scale_max})")
        v = self.blend_steps
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"AugmentParams.blend_steps must be an int >= 1, got {v!r}")
        if self.interpolation_anchor not in ("mid", "start"):
            raise ValueError(f"AugmentParams.interpolation_anchor must be 'mid' or 'start', got "
                             f"{self.interpolation_anchor!r}")
        v = self.calibration_min_events
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ValueError(f"AugmentParams.calibration_min_events must be an int >= 0, got {v!r}")
        v = self.deblur_min_events
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0):
            raise ValueError(f"AugmentParams.deblur_min_events must be None or an int >= 0, got {v!r}")

    @classmethod
    def off(cls) -> "AugmentParams":
        """Augmentation disabled (zero-order-hold frames)."""
        return cls(enabled=False)


@dataclass
class AugmentStats:
    """Counts of the calibration outcome over all (interval, pixel) pairs, and EDI thresholds.

    Attributes
    ----------
    calibrated, no_events, zero_net_events, sign_mismatch, out_of_range : int
        Pixel-intervals per outcome of eq. 12 (all but ``calibrated`` fall back to c).
    intervals : int
        Calibrated intervals (frame pairs).
    frames_deblurred : int
    pixels_censored : int
        Pixel-segments whose frame clipped them: augmented as the plain bound carried by the
        events (no deblurring, no calibration).
    pixels_deblur_fallback : int
        Pixel-frames with fewer than ``deblur_min_events`` events in the exposure: taken as
        sharp at τ_k instead of EDI-deblurred.
    pixels_blend_fallback : int
        Pixel-segments inside exposure k where eq. 13's blend is replaced by A_k alone: the
        previous frame k-1 clipped them (A_{k-1} starts from a bound, not a value), or frame k
        is sharp there (``deblur_min_events``; A_k is then the frame itself, while A_{k-1} adds
        the error of a whole interval of event integration).
    pixels_censor_kept_value : int
        Pixel-segments inside exposure k before τ_k that frame k clips but frame k-1 saw, where
        A_{k-1} (frame k-1's value carried by the events) satisfies frame k's bound and is kept
        as a value instead of the bound (before τ_k the plain filter still holds frame k-1).
    thresholds : dict
        EDI threshold used per frame index (log units).
    """

    calibrated: int = 0
    no_events: int = 0
    zero_net_events: int = 0
    sign_mismatch: int = 0
    out_of_range: int = 0
    too_few_events: int = 0
    intervals: int = 0
    frames_deblurred: int = 0
    pixels_censored: int = 0
    pixels_blend_fallback: int = 0
    pixels_deblur_fallback: int = 0
    pixels_censor_kept_value: int = 0
    thresholds: dict = field(default_factory=dict)

    @property
    def fallbacks(self) -> int:
        return self.no_events + self.zero_net_events + self.sign_mismatch + self.out_of_range + self.too_few_events

    def add(self, category: np.ndarray) -> None:
        n = np.bincount(category, minlength=len(CALIBRATION_CATEGORIES))
        for name, v in zip(CALIBRATION_CATEGORIES, n):
            setattr(self, name, getattr(self, name) + int(v))
        self.intervals += 1

    def to_dict(self) -> dict:
        d = {name: getattr(self, name) for name in CALIBRATION_CATEGORIES}
        d.update(fallbacks=self.fallbacks, intervals=self.intervals, frames_deblurred=self.frames_deblurred,
                 pixels_censored=self.pixels_censored, pixels_blend_fallback=self.pixels_blend_fallback,
                 pixels_deblur_fallback=self.pixels_deblur_fallback,
                 pixels_censor_kept_value=self.pixels_censor_kept_value)
        if self.thresholds:
            v = np.array(list(self.thresholds.values()))
            d["edi_threshold"] = {"min": float(v.min()), "median": float(np.median(v)), "max": float(v.max())}
        return d


def deblur_min_events(contrast_threshold: float, given: int | None = None) -> int:
    """Fewest events in an exposure for EDI deblurring to pay (:class:`AugmentParams`): ``given``
    when set, else ``ceil(sqrt(24 / (√12 c)))``.

    >>> deblur_min_events(0.2), deblur_min_events(0.1), deblur_min_events(0.1, 0)
    (6, 9, 0)
    """
    if given is not None:
        return int(given)
    return int(math.ceil(math.sqrt(24.0 / (math.sqrt(12.0) * float(contrast_threshold)))))


def calibrate_thresholds(delta_ld, sum_sigma, n_events, contrast_threshold: float, *,
                         scale_min: float = 0.6, scale_max: float = 100.0):
    """Per-pixel calibrated threshold of eq. 12, ``c_k = ΔL^D / Σσ``, with explicit fallbacks.

    Parameters
    ----------
    delta_ld : array_like of shape (N,), float
        ΔL^D = L^D(e_{k+1}) - L^D(s_k), log units.
    sum_sigma : array_like of shape (N,), int
        Σσ, the signed event count over ``[s_k, e_{k+1})``.
    n_events : array_like of shape (N,), int
        Number of events over the same interval (0 selects the "no events" fallback).
    contrast_threshold : float
        Nominal c, log units (> 0).
    scale_min, scale_max : float
        Accepted range of c / c_k.

    Returns
    -------
    c_eff : ndarray of shape (N,), float64
        Calibrated threshold, or c where a fallback applies.
    category : ndarray of shape (N,), int64
        Index into :data:`CALIBRATION_CATEGORIES`.

    Examples
    --------
    >>> c, cat = calibrate_thresholds([0.5, 0.5, 0.5, -0.5], [4, 2, 0, 4], [4, 2, 2, 4], 0.1)
    >>> c.round(12).tolist(), [CALIBRATION_CATEGORIES[i] for i in cat]
    ([0.125, 0.1, 0.1, 0.1], ['calibrated', 'out_of_range', 'zero_net_events', 'sign_mismatch'])
    """
    d = np.ascontiguousarray(delta_ld, dtype=np.float64).ravel()
    s = np.ascontiguousarray(sum_sigma, dtype=np.int64).ravel()
    a = np.ascontiguousarray(n_events, dtype=np.int64).ravel() != 0
    if not (d.shape == s.shape == a.shape):
        raise ValueError(f"delta_ld, sum_sigma and n_events must have one shape, got {d.shape}, {s.shape}, "
                         f"{a.shape}")
    c = float(contrast_threshold)
    if not c > 0:
        raise ValueError(f"contrast_threshold must be > 0 (log units), got {c}")
    c_eff = np.empty(d.shape[0])
    cat = np.empty(d.shape[0], np.int64)
    AK.calibrate_threshold(d, s, a, c, float(scale_min), float(scale_max), c_eff, cat)
    return c_eff, cat


@dataclass(frozen=True, eq=False)
class _FrameAug:
    """Frame k for the augmentation: L^D(s_k), L^D(e_k), the signed and total event counts of
    its exposure, the pixels taken as sharp (or None), the anchor of A_k with the counts from
    s_k to it, and the counts of [s_k, τ_k)."""

    lds: np.ndarray
    lde: np.ndarray
    cnt: np.ndarray
    tot: np.ndarray
    sharp: np.ndarray | None
    ldm: np.ndarray
    a_sg: np.ndarray
    a_tot: np.ndarray
    mid_sg: np.ndarray
    mid_tot: np.ndarray


class AugmentedMeasurements:
    """Measurement provider (see :mod:`.measurement`) giving the AKF the augmented frame L^A.

    Parameters
    ----------
    frames : Frames
        Frames (K, H, W) with each frame's own exposure ``[t_start_us, t_end_us)``; exposures
        must not overlap and start times must increase.
    events : EventArrays
        All events of the recording, in memory.
    sensor_shape : (int, int)
    profile : CameraProfile
        Inverse CRF (B = CRF⁻¹(code), eq. 3) and noise model (R, eqs. 6-9).
    akf_params : AKFParams
        I0, bias correction (eq. 8), covariance interpolation (eq. 7), nominal c.
    params : AugmentParams

    Attributes
    ----------
    times_us : ndarray of int64
        Segment starts: each exposure split into ``blend_steps`` pieces (and at τ_k, where R
        changes its linear piece), then the gap ``[e_k, s_{k+1})``.
    frame_times_us : ndarray of int64
        τ_k, the default output times.
    stats : AugmentStats
        Calibration fallbacks, filled as segments are requested.
    """

    def __init__(self, frames: Frames, events: EventArrays, sensor_shape, profile, *, akf_params, params=None):
        params = AugmentParams() if params is None else params
        if not isinstance(params, AugmentParams):
            raise TypeError(f"params must be AugmentParams, got {type(params).__name__}")
        if not isinstance(frames, Frames):
            raise TypeError(f"frames must be a hybridhdr Frames, got {type(frames).__name__}")
        if len(frames) == 0:
            raise ValueError("frame augmentation needs at least one frame")
        s, e = frames.t_start_us, frames.t_end_us
        if len(frames) > 1:
            bad = np.flatnonzero(s[1:] <= s[:-1])
            if bad.size:
                i = int(bad[0]) + 1
                raise ValueError(f"frame augmentation needs increasing exposure starts; frame {i} starts at "
                                 f"{int(s[i])} µs, not after frame {i - 1} ({int(s[i - 1])} µs)")
            bad = np.flatnonzero(e[:-1] > s[1:])
            if bad.size:
                i = int(bad[0])
                raise ValueError(f"frame augmentation needs non-overlapping exposures; frame {i} ends at "
                                 f"{int(e[i])} µs after frame {i + 1} starts ({int(s[i + 1])} µs); "
                                 f"disable augmentation for this recording")
        self.params = params
        self.akf = akf_params
        self.events = events
        self.shape = tuple(sensor_shape)
        self.n = self.shape[0] * self.shape[1]
        if params.contrast_threshold is not None:
            self._set_pair(float(params.contrast_threshold), float(params.contrast_threshold))
        else:
            self._set_pair(float(akf_params.c_on), float(akf_params.c_off))
        self.fm = FrameMeasurements(frames, sensor_shape, profile, intensity_offset=akf_params.intensity_offset,
                                    bias_correction=akf_params.bias_correction,
                                    interpolate_covariance=akf_params.covariance_interpolation == "linear",
                                    precision_scale=akf_params.frame_precision_scale,
                                    saturation=akf_params.saturation, min_weighting=akf_params.min_weighting)
        self.ts = s.astype(np.int64)
        self.te = e.astype(np.int64)
        self.tau = frames.t_mid_us.astype(np.int64)
        self.K = len(frames)
        self.frame_times_us = self.tau.copy()
        self.stats = AugmentStats()
        self._frames_cache: dict = {}
        self._interval_cache: dict = {}
        self._count_cache = None
        self._pre = None
        self._fm_cache: dict = {}
        self._build_segments()

    # -- thresholds -------------------------------------------------------------------------
    def _set_pair(self, c_on, c_off) -> None:
        """ON and OFF thresholds (scalars or (H*W,) arrays); c is their mean (EDI's when they
        are equal, the n* of ``deblur_min_events``)."""
        self.c_on, self.c_off = c_on, c_off
        scalar = np.ndim(c_on) == 0 and np.ndim(c_off) == 0
        self._asym = not (scalar and float(c_on) == float(c_off))
        self.c = float(c_on) if not self._asym else 0.5 * (float(np.mean(c_on)) + float(np.mean(c_off)))
        self._cbar = 0.5 * (np.asarray(c_on, np.float64) + np.asarray(c_off, np.float64))
        self._cdelta = 0.5 * (np.asarray(c_on, np.float64) - np.asarray(c_off, np.float64))

    def _inc(self, signed, total):
        """The nominal log change ``c_on N_on - c_off N_off`` of ``signed`` = N_on - N_off and
        ``total`` = N_on + N_off events (``c Σσ`` when the thresholds are one scalar)."""
        if not self._asym:
            return self.c * signed
        return self._cbar * signed + self._cdelta * total

    def set_thresholds(self, c_on, c_off) -> None:
        """Per-pixel ON and OFF thresholds (log units, (H, W) or (H*W,)), as the AKF engine's
        :meth:`~._engine.AKFEngine.set_thresholds` (None: the parameters'); before any segment
        is read."""
        if self._frames_cache or self._interval_cache:
            raise RuntimeError("set_thresholds must be called before the first segment")
        if c_on is None and c_off is None:
            return
        self._set_pair(*(np.ascontiguousarray(np.asarray(a, np.float64).reshape(-1)) for a in (c_on, c_off)))

    # -- segment layout ---------------------------------------------------------------------
    def _build_segments(self):
        segs = []  # (t0, kind, k, w): kind 0 exposure piece, 1 gap, 2 hold (no interpolation)
        if not self.params.interpolate:
            for k in range(self.K):
                segs.append((int(self.tau[k]), 2, k, 0.0))
        else:
            J = int(self.params.blend_steps)
            for k in range(self.K):
                a, b = int(self.ts[k]), int(self.te[k])
                T = b - a
                if T > 0:
                    cuts = sorted({a + (j * T) // J for j in range(J)} | {int(self.tau[k])})
                    cuts = [u for u in cuts if a <= u < b]
                    for i, u in enumerate(cuts):
                        v = cuts[i + 1] if i + 1 < len(cuts) else b
                        w = 0.0 if k == 0 else (b - 0.5 * (u + v)) / T  # eq. 13 weight of A_{k-1}
                        segs.append((u, 0, k, w))
                if k + 1 < self.K:
                    if self.ts[k + 1] > b:
                        segs.append((b, 1, k, 0.0))
                else:
                    segs.append((b, 1, k, 0.0))
            # a zero-length final gap would duplicate the last exposure end; keep strictly increasing
            out = []
            for sg in segs:
                if out and sg[0] <= out[-1][0]:
                    out[-1] = sg
                else:
                    out.append(sg)
            segs = out
        self._segs = segs
        self.times_us = np.array([sg[0] for sg in segs], dtype=np.int64)

    def __len__(self) -> int:
        return int(self.times_us.shape[0])

    # -- per-frame and per-interval quantities ----------------------------------------------
    def _frame(self, k: int) -> "_FrameAug":
        """EDI and the anchor of frame k (:class:`_FrameAug`)."""
        if k in self._frames_cache:
            return self._frames_cache[k]
        seg = self._fm_segment(k)
        logb = seg.log_frame  # log(B + I0), bias-corrected (eq. 8)
        a, b = int(self.ts[k]), int(self.te[k])
        cnt, tot = self.events.counts(a, b)
        mid_sg, mid_tot = self.events.counts(a, int(self.tau[k])) if b > a else (np.zeros_like(cnt), np.zeros_like(tot))
        if self.params.deblur and b > a:
            c = self.c
            thr = (self.c_on, self.c_off) if self._asym else None  # edi_integral broadcasts scalars
            if self.params.search_threshold:  # one searched c for both polarities
                c, _ = estimate_threshold(seg.intensity, self.events, a, b,
                                          bounds=(self.params.threshold_min, self.params.threshold_max),
                                          tv_weight=self.params.tv_weight, intensity_offset=self.akf.intensity_offset,
                                          log_blurred=logb)
                thr = None
            inc = (lambda sg, n: c * sg) if thr is None else self._inc  # noqa: E731
            lds, _ = edi_log_latent(None, self.events, a, b, c, log_blurred=logb, thresholds=thr)
            few = tot < deblur_min_events(c, self.params.deblur_min_events)
            sharp = few if np.any(few) else None
            if sharp is not None:  # too few events to tell blur from threshold quantisation: sharp at τ_k
                lds = np.where(few, logb - inc(mid_sg, mid_tot), lds)
                self.stats.pixels_deblur_fallback += int(np.count_nonzero(few))
            self.stats.frames_deblurred += 1
            self.stats.thresholds[k] = float(c)
            lde = lds + inc(cnt, tot)
            ldm = lds + inc(mid_sg, mid_tot)
        else:
            lds = lde = ldm = logb
            sharp = None
        if self.params.interpolation_anchor == "start":  # the paper: A_k anchored at L^D(s_k)
            out = _FrameAug(lds, lde, cnt, tot, sharp, lds, np.zeros_like(cnt), np.zeros_like(tot), mid_sg, mid_tot)
        else:
            out = _FrameAug(lds, lde, cnt, tot, sharp, ldm, mid_sg, mid_tot, mid_sg, mid_tot)
        self._frames_cache[k] = out
        for old in [j for j in self._frames_cache if j < k - 2]:
            del self._frames_cache[old]
        return out

    def _interval(self, k: int):
        """(L^D(s_k), r_k) of interval k = [s_k, e_{k+1}): eq. 12's scale of the ON and OFF
        thresholds (1 for the last frame and wherever calibration falls back)."""
        if k in self._interval_cache:
            return self._interval_cache[k]
        fk = self._frame(k)
        if k + 1 >= self.K or not self.params.calibrate:
            scale = np.ones(self.n)
        else:
            f1 = self._frame(k + 1)
            g, gt = self.events.counts(int(self.te[k]), int(self.ts[k + 1]))
            net, total = fk.cnt + g + f1.cnt, fk.tot + gt + f1.tot
            nominal = np.ascontiguousarray(self._inc(net, total), dtype=np.float64)
            scale = np.empty(self.n)
            cat = np.empty(self.n, np.int64)
            AK.calibrate_scale(np.ascontiguousarray(f1.lde - fk.lds, dtype=np.float64), nominal,
                               total != 0, float(self.params.calibration_scale_min),
                               float(self.params.calibration_scale_max), scale, cat)
            # too few net events: eq. 12's ratio is mostly the thresholds' quantisation of the two
            # ends (each end's sub-threshold residual is uniform over one threshold, so 1/r is off
            # by about 1/(√6 |Σσ|)), not the threshold error it is meant to correct
            m = self.params.calibration_min_events
            if m > 0:
                few = (cat == 0) & (np.abs(net) < m)
                scale = np.where(few, 1.0, scale)
                cat = np.where(few, CALIBRATION_CATEGORIES.index("too_few_events"), cat)
            # a clipped end is a bound, not a value: ΔL^D says nothing there, keep c
            ca, cb = self._fm_segment(k).censor, self._fm_segment(k + 1).censor
            if ca is not None and cb is not None:
                cz = (ca != 0) | (cb != 0)
                scale = np.where(cz, 1.0, scale)
                cat = np.where(cz & (cat == 0), CALIBRATION_CATEGORIES.index("out_of_range"), cat)
            self.stats.add(cat)
        out = (fk.lds, scale)
        self._interval_cache[k] = out
        for old in [j for j in self._interval_cache if j < k - 2]:
            del self._interval_cache[old]
        return out

    def _count_since(self, k: int, t_us: int):
        """(Σσ, number of events) over [s_k, t_us) (incremental when called with increasing t
        for one k)."""
        cc = self._count_cache
        a = int(self.ts[k])
        if cc is not None and cc[0] == k and cc[1] <= t_us:
            d, dn = self.events.counts(cc[1], t_us)
            cnt, tot = cc[2] + d, cc[3] + dn
        else:
            cnt, tot = self.events.counts(a, t_us)
        self._count_cache = (k, int(t_us), cnt, tot)
        return cnt, tot

    def _estimate(self, k: int, t_us: int):
        """A_k(t) = L^D(τ_k) + r_k (c_on N_on - c_off N_off)[τ_k, t) (eq. 10 anchored at
        mid-exposure; ``interpolation_anchor="start"``: from L^D(s_k) and s_k, as the paper),
        and its ON step r_k c_on."""
        _, r = self._interval(k)
        f = self._frame(k)
        cnt, tot = self._count_since(k, t_us)
        return f.ldm + r * self._inc(cnt - f.a_sg, tot - f.a_tot), r * self.c_on

    def _fm_segment(self, j: int) -> Segment:
        """Zero-order-hold measurement of frame j (cached: two frames are live at a time)."""
        seg = self._fm_cache.get(j)
        if seg is None:
            seg = self.fm.segment(j)
            self._fm_cache[j] = seg
            for old in [i for i in self._fm_cache if i < j - 1]:
                del self._fm_cache[old]
        return seg

    def _r_pieces(self, t0: int, t1: int | None):
        """1/R at t0 and β over [t0, t1) following eq. 7's linear R̄ between the τ_j."""
        j = max(int(np.searchsorted(self.tau, t0, side="right")) - 1, 0)
        seg = self._fm_segment(j)
        rinv_j, beta_j = seg.rinv, seg.beta
        if t1 is None or seg.t1_us is None or t0 < int(self.tau[j]):
            return rinv_j, np.zeros(self.n)  # before the first τ or after the last: R held
        if t0 == seg.t0_us and t1 == seg.t1_us:
            return rinv_j, beta_j
        span = float(seg.t1_us - seg.t0_us)
        w0 = 1.0 + beta_j * ((t0 - seg.t0_us) / span)
        w1 = 1.0 + beta_j * ((t1 - seg.t0_us) / span)
        return rinv_j / w0, w1 / w0 - 1.0

    def segment(self, i: int) -> Segment:
        """Measurement on ``[times_us[i], times_us[i+1])``: L^A at its start and its per-event step."""
        if not 0 <= i < len(self):
            raise IndexError(f"segment {i} out of range 0..{len(self) - 1}")
        t0, kind, k, w = self._segs[i]
        t1 = int(self.times_us[i + 1]) if i + 1 < len(self) else None
        rinv, beta = self._r_pieces(t0, t1)
        prev = None  # inside exposure k before τ_k: (A_{k-1}(t0), its ON step, frame k-1's censoring)
        if kind == 2:  # no interpolation: hold the (deblurred) image at τ_k
            f = self._frame(k)
            la = f.lds + self._inc(f.mid_sg, f.mid_tot) if self.params.deblur else f.lds
            step = None
        else:
            ak, ck = self._estimate(k, t0)
            if kind == 0 and w > 0.0:
                # A_{k-1}(t0) from its anchor over [s_{k-1}, s_k) and [s_k, t0)
                _, r_p = self._interval(k - 1)
                fp = self._frame(k - 1)
                if self._pre is None or self._pre[0] != k:
                    self._pre = (k,) + self.events.counts(int(self.ts[k - 1]), int(self.ts[k]))
                _, pre, pre_n = self._pre
                cnt_k, tot_k = self._count_cache[2], self._count_cache[3]
                ap = fp.ldm + r_p * self._inc(pre + cnt_k - fp.a_sg, pre_n + tot_k - fp.a_tot)
                la = w * ap + (1.0 - w) * ak  # eq. 13
                step = w * (r_p * self.c_on) + (1.0 - w) * ck
                # where frame k-1 clipped the pixel, A_{k-1} starts from the clip level (a bound,
                # not a value) and would drag the blend towards it: A_k alone there
                cp = self._fm_segment(k - 1).censor
                sharp = self._frame(k).sharp
                if (cp is not None and np.any(cp != 0)) or sharp is not None:
                    bad = np.zeros(self.n, bool) if cp is None else cp != 0
                    if sharp is not None:  # frame k is sharp there: A_k(τ_k) is the frame itself
                        bad |= sharp
                    la = np.where(bad, ak, la)
                    step = np.where(bad, ck, step)
                    self.stats.pixels_blend_fallback += int(np.count_nonzero(bad))
                if t0 < int(self.tau[k]):
                    prev = (ap, r_p * self.c_on, cp)
            else:
                la = ak
                step = ck
        # ``intensity`` is the blurred frame's B (the AKF reads log_frame; other engines read B).
        # A pixel that frame k clips carries a bound, not a value: there the augmented frame is
        # the plain bound carried by the events (EDI of a clipped value is meaningless), censored.
        fseg = self._fm_segment(k)
        cens = fseg.censor
        if cens is not None and np.any(cens != 0):
            cz = cens != 0
            # the bound frame k states at τ_k, carried to t0 by the events (as the plain frames)
            if kind != 2:
                f = self._frame(k)
                cnt, tot = self._count_since(k, t0)
                la = np.where(cz, fseg.log_frame + self._inc(cnt - f.mid_sg, tot - f.mid_tot), la)
            else:
                la = np.where(cz, fseg.log_frame, la)
            if step is not None:
                step = np.where(cz, self.c_on, step)
            if prev is not None:
                # before τ_k (this stretch is frame k-1's interval in the plain filter) a pixel that
                # frame k clips but frame k-1 saw keeps A_{k-1}, frame k-1's value carried by the
                # events, as a value, wherever it satisfies frame k's bound; where it violates the
                # bound, the value is wrong and the bound is kept
                ap, sp, cp = prev
                use = cz & (cens * (ap - la) >= 0.0)  # a new array: cz is updated from it below
                if cp is not None:
                    use &= cp == 0
                if np.any(use):
                    la = np.where(use, ap, la)
                    step = np.where(use, sp, step)
                    cens = np.where(use, cens.dtype.type(0), cens)  # a copy: fseg.censor is cached
                    cz &= ~use
                    self.stats.pixels_censor_kept_value += int(np.count_nonzero(use))
            self.stats.pixels_censored += int(np.count_nonzero(cz))
        return Segment(t0_us=int(t0), t1_us=t1, log_frame=np.ascontiguousarray(la, dtype=np.float64),
                       intensity=fseg.intensity, rinv=np.ascontiguousarray(rinv, dtype=np.float64),
                       beta=np.ascontiguousarray(beta, dtype=np.float64),
                       la_step=None if step is None else np.ascontiguousarray(step, dtype=np.float64),
                       censor=cens, frame_update=(t0 == int(self.tau[k])))
