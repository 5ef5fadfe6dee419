"""Frame measurements for the filters: the hook between frames (raw or augmented) and the AKF.

A *measurement provider* is any object with

* ``times_us`` - int64 array (K,), strictly increasing: the times τ_k at which the measurement
  changes (segment k is ``[τ_k, τ_{k+1})``; the last one is open-ended);
* ``segment(k)`` - a :class:`Segment` with the per-pixel measurement on segment k;
* optionally ``segment_codes(k)`` - the :class:`SegmentCodes` (pixel codes and per-code
  tables) that ``segment(k)`` is built from, or None. The AKF then builds each row band's part
  of the measurement in the same pass that propagates and loads it (no intermediate arrays,
  and the whole frame switch runs in parallel).

:class:`FrameMeasurements` implements the zero-order hold of raw frames (L^A(t) = L^F(τ_k) on
segment k). Frame augmentation (§4.1 of the paper: EDI deblurring plus event
interpolation) plugs in by returning segments whose ``la_step`` is the calibrated per-pixel
threshold c_p^k c (eq. 12): the AKF kernel then moves L^A by ±la_step at every event (eqs. 10, 11)
and no kernel change is needed.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..model import Frames
from ._kernels import lut_segment
from ..camera.encoding import frames_to_codes  # noqa: F401 - the frames' codes (re-exported here)
from ..camera.profile import CameraProfile, check_codes_in_profile, profile_for_frames

__all__ = ["Segment", "SegmentCodes", "FrameMeasurements", "frames_to_codes"]


@dataclass(frozen=True, eq=False)
class Segment:
    """Per-pixel measurement on ``[t0_us, t1_us)`` (flattened row-major, float64, shape (H*W,)).

    Attributes
    ----------
    t0_us, t1_us : int, int or None
        τ_k and τ_{k+1} in µs (``None`` for the last, open-ended segment).
    log_frame : ndarray
        L^A at τ_k in log units: log(I + I0), minus R/2 when bias-corrected (eq. 8).
    intensity : ndarray
        Scaled irradiance I = CRF⁻¹(I^F) (eq. 3) of frame k.
    rinv : ndarray or None
        1/R at τ_k, log-domain (eq. 9), in 1/(log² s); None for providers without a noise model.
    beta : ndarray or None
        Relative change of R̄ over the segment, R̄_{k+1}/R̄_k - 1 (eq. 7); zeros when held.
    la_step : ndarray or None
        Per-event step of L^A in log units (frame augmentation); None for zero-order hold.
    censor : ndarray or None
        Per pixel +1 where ``log_frame`` is a lower bound (a clipped bright code), -1 where it is
        an upper bound (a clipped dark code), 0 for a value; None: no pixel is censored.
    frame_update : bool
        The segment starts at a frame time τ_k: a discrete frame update applies there (AKF
        ``frame_update="discrete"``); False for the sub-segments of frame augmentation.
    update_log_frame : ndarray or None
        The log frame the discrete update uses when it differs from ``log_frame`` (frame
        augmentation: the plain frame at τ_k, while L^A is the augmented estimate); None: L^A.
    """

    t0_us: int
    t1_us: int | None
    log_frame: np.ndarray
    intensity: np.ndarray
    rinv: np.ndarray | None = None
    beta: np.ndarray | None = None
    la_step: np.ndarray | None = None
    censor: np.ndarray | None = None
    frame_update: bool = True
    update_log_frame: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class SegmentCodes:
    """What a look-up-table segment is built from (see :func:`~._kernels.lut_segment`).

    ``code`` / ``code_next`` are the flattened pixel codes of frames k and k+1 (``code_next``
    empty when β is held at 0); codes are clipped to ``[0, max_code]``. ``rbar``, ``log_frame``
    and ``rinv`` are the per-code tables of R̄ (eq. 6), L^F (eq. 8) and 1/R (eq. 9); ``censor``
    the per-code censoring direction (empty: none).
    """

    code: np.ndarray
    code_next: np.ndarray
    max_code: int
    rbar: np.ndarray
    log_frame: np.ndarray
    rinv: np.ndarray
    censor: np.ndarray
    la_step: float = 0.0
    intensity: np.ndarray | None = None  # per-code linear intensity (eq. 3), when known


class FrameMeasurements:
    """Zero-order-hold frame measurements with the noise model of eqs. 6-9.

    Parameters
    ----------
    frames : Frames
        Frames (K, H, W) of raw codes; τ_k is the mid-exposure time (``frames.t_mid_us``).
        Frames sharing a τ keep the last one. Frames of unequal exposure × gain are read in the
        units of their median (``frames.exposure_scale()``, as the camera model reads them), on
        the per-pixel path.
    sensor_shape : (int, int)
        (H, W) of the event sensor.
    profile : CameraProfile
        Weighting LUT, inverse CRF and precision scale (eqs. 3-6). The built-in default profile
        is adapted to ``frames.encoding`` (gamma frames get the gamma inverse CRF, see
        :func:`~hybridhdr.camera.profile.profile_for_frames`); the profile used is
        ``self.profile``.
    intensity_offset : float
        I0 of eq. 8.
    bias_correction : bool
        Apply eq. 8's -R/2.
    interpolate_covariance : bool
        R̄ linear in time between frames (eq. 7; needs frame k+1, so offline only).
    precision_scale : float or None
        Override of ``profile.frame_precision_scale``.
    saturation : {"bound", "value"}
        "bound": a clipped code (``profile.clip_low_code``/``clip_high_code``) is a censored
        measurement, the bound of :meth:`CameraProfile.bounds` with the precision of a fully
        weighted code, acting only on a state that violates it (see ``docs/reconstruct.md``);
        "value": the paper's reading, the clipped code's intensity with the floored weight.
    min_weighting : float or None
        Override of ``profile.min_weighting`` (eq. 6's floor on f_w).
    event_step : float
        Per-event step of L^A in log units: 0 holds each frame (the paper's zero-order hold); a
        positive value moves L^A by ± that step at each event; -1 makes L^A follow each event's
        own jump (the filter's ON / OFF threshold, per pixel when a threshold map is set). The
        last two carry the frame forward with the events since it (eq. 10's forward
        interpolation from the frame itself, causal), so that an edge that arrives between two
        frames is not pulled back to the old frame's value.
    log_corrections : dict or None
        The exposure model: ``{k: (pixels, correction)}`` per frame index k of ``frames``
        (:func:`~hybridhdr.reconstruct.edi.exposure_log_corrections`), added to L^F (and to a
        clipped code's bound) at those pixels, so that a frame exposed over ``[s_k, e_k)`` is
        read as the mean of the intensity over its exposure and L^A(τ_k) is the latent image at
        its mid-exposure (EDI's double integral). None or empty: each frame is the intensity at
        τ_k. Frames with a correction take the per-pixel path instead of the per-code tables.
    """

    def __init__(self, frames: Frames, sensor_shape, profile: CameraProfile, *,
                 intensity_offset: float, bias_correction: bool = True,
                 interpolate_covariance: bool = True, precision_scale: float | None = None,
                 saturation: str = "value", min_weighting: float | None = None, event_step: float = 0.0,
                 log_corrections: dict | None = None):
        if not isinstance(frames, Frames):
            raise TypeError(f"frames must be a hybridhdr Frames, got {type(frames).__name__}")
        if len(frames) == 0:
            raise ValueError("the recording has no frames; this method needs at least one frame")
        codes = frames_to_codes(frames, sensor_shape)
        if not isinstance(profile, CameraProfile):
            raise TypeError(f"profile must be a CameraProfile, got {type(profile).__name__}")
        profile = profile_for_frames(profile, frames)
        check_codes_in_profile(codes, profile)  # never clipped to the profile's top code without a word
        tau = frames.t_mid_us
        order = np.argsort(tau, kind="stable")
        tau, codes_idx = tau[order], order
        keep = np.ones(len(tau), bool)
        keep[:-1] = tau[1:] != tau[:-1]
        self.times_us = np.ascontiguousarray(tau[keep], dtype=np.int64)
        self._idx = codes_idx[keep]
        self._corr = {}
        for j, v in (log_corrections or {}).items():
            if isinstance(j, bool) or not isinstance(j, (int, np.integer)) or not 0 <= int(j) < len(frames):
                raise ValueError(f"log_corrections: frame index {j!r} is not among the {len(frames)} frames")
            pix, corr = (np.asarray(a) for a in v)
            n_pix = int(np.prod(tuple(sensor_shape)))
            if pix.shape != corr.shape or pix.ndim != 1 or (pix.size and (pix.min() < 0 or pix.max() >= n_pix)):
                raise ValueError(f"log_corrections[{j}]: expected equal-length 1-D pixel indices in [0, {n_pix}) and "
                                 f"corrections, got shapes {pix.shape} and {corr.shape}")
            if not np.all(np.isfinite(corr)):
                raise ValueError(f"log_corrections[{j}]: corrections must be finite")
            if pix.size:
                self._corr[int(j)] = (pix.astype(np.int64), corr.astype(np.float64))
        self._codes = codes
        # each frame's intensity in the median frame's units (Frames.exposure_scale: a frame is the mean
        # intensity over its exposure times the exposure and gain), as the camera model reads it; frames
        # of unequal exposure take the per-pixel path (the per-code tables hold one scale)
        self._escale = frames.exposure_scale()
        self._uniform = not bool(np.any(self._escale != 1.0))
        self.profile = profile
        self.offset = float(intensity_offset)
        self.bias_correction = bool(bias_correction)
        self.interpolate_covariance = bool(interpolate_covariance)
        if saturation not in ("bound", "value"):
            raise ValueError(f"saturation must be 'bound' or 'value', got {saturation!r}")
        self.saturation = saturation
        if not (np.isfinite(event_step) and (event_step >= 0 or event_step == -1.0)):
            raise ValueError(f"event_step must be a finite number >= 0 (log units) or -1 (follow each event's "
                             f"jump), got {event_step!r}")
        self.event_step = float(event_step)
        if min_weighting is not None:
            if not 0 < float(min_weighting) <= 1:
                raise ValueError(f"min_weighting must be in (0, 1], got {min_weighting}")
            self.profile = profile = dataclasses.replace(profile, min_weighting=float(min_weighting))
        self.scale_factor = 1.0 if precision_scale is None else profile.frame_precision_scale / float(precision_scale)
        self.shape = tuple(sensor_shape)
        self._lut = None
        if codes.dtype.kind in "ui" and profile.max_code <= 65535:
            # every per-pixel quantity of a frame depends only on its code: tabulate once
            c = np.arange(profile.max_code + 1)
            inten, rbar, logf, rinv, cens = self._measure(c)
            self._lut = tuple(np.ascontiguousarray(a, dtype=np.float64) for a in (inten, rbar, logf, rinv, cens))

    def _measure(self, codes, scale: float = 1.0):
        """(I, R̄, L^F, 1/R, censor) of eq. 3, 6, 8, 9 for raw ``codes`` (flattened float64), the
        intensity times ``scale`` (the frame's :meth:`Frames.exposure_scale`; its variance by
        ``scale²``)."""
        prof = self.profile
        c = np.asarray(codes).reshape(-1)
        inten = prof.intensity(c)
        rbar = prof.variance(c) * self.scale_factor
        cens = prof.censor(c) if self.saturation == "bound" else np.zeros(c.shape[0])
        if self.saturation == "bound":
            # a bound at the quantisation edge next to the clip level, as precise as a fully
            # weighted code (eq. 6 with f_w = 1), and no eq. 8 correction (it is not a mean)
            lo, hi = prof.bounds()
            inten = np.where(cens > 0, hi, np.where(cens < 0, lo, inten))
            rbar = np.where(cens != 0, self.scale_factor / prof.frame_precision_scale, rbar)
        if scale != 1.0:
            inten = inten * scale
            rbar = rbar * (scale * scale)
        ip = inten + self.offset
        r_log = rbar / (ip * ip)  # eq. 9
        logf = np.log(ip)
        if self.bias_correction:
            logf = logf - np.where(cens != 0, 0.0, 0.5 * r_log)  # eq. 8
        return inten, rbar, logf, 1.0 / r_log, cens

    def __len__(self) -> int:
        return int(self.times_us.shape[0])


    def segment_codes(self, k: int) -> SegmentCodes | None:
        """Codes and per-code tables of segment ``k``; None when the frames are not integer codes
        or frame k has an exposure correction (``log_corrections``: per pixel, not per code)."""
        if not 0 <= k < len(self):
            raise IndexError(f"segment {k} out of range 0..{len(self) - 1}")
        if int(self._idx[k]) in self._corr:
            return None
        return self._codes_of(k)

    def _codes_of(self, k: int) -> SegmentCodes | None:
        if self._lut is None or not self._uniform:
            return None
        code = np.ascontiguousarray(self._codes[self._idx[k]]).reshape(-1)
        last = k + 1 >= len(self)
        nxt = (np.ascontiguousarray(self._codes[self._idx[k + 1]]).reshape(-1)
               if self.interpolate_covariance and not last else code[:0])
        _, rbar_l, logf_l, rinv_l, cens_l = self._lut
        return SegmentCodes(code, nxt, int(self.profile.max_code), rbar_l, logf_l, rinv_l,
                            cens_l if self.saturation == "bound" else cens_l[:0], self.event_step,
                            intensity=self._lut[0])

    def segment(self, k: int) -> Segment:
        """Measurement on ``[τ_k, τ_{k+1})``: L^F (eq. 8), 1/R (eq. 9), β of eq. 7."""
        if not 0 <= k < len(self):
            raise IndexError(f"segment {k} out of range 0..{len(self) - 1}")
        seg = self._segment(k)
        corr = self._corr.get(int(self._idx[k]))
        if corr is None:
            return seg
        lf = np.array(seg.log_frame, dtype=np.float64, copy=True)
        lf[corr[0]] += corr[1]  # the exposure mean's log -> the latent log at mid-exposure (EDI)
        return dataclasses.replace(seg, log_frame=lf)

    def _segment(self, k: int) -> Segment:
        sc = self._codes_of(k)
        code = self._codes[self._idx[k]]
        last = k + 1 >= len(self)
        if sc is not None:
            n = code.size
            lf, inten, rinv, beta = (np.empty(n) for _ in range(4))
            lut_segment(sc.code, sc.code_next, sc.max_code, self._lut[0], sc.rbar, sc.log_frame, sc.rinv,
                        sc.censor, lf, inten, rinv, beta)
            cens = None
            if self.saturation == "bound":
                cens = self._lut[4][np.clip(sc.code.astype(np.int64), 0, sc.max_code)]
            step = np.full(n, self.event_step) if self.event_step else None
            return Segment(t0_us=int(self.times_us[k]), t1_us=None if last else int(self.times_us[k + 1]),
                           log_frame=lf, intensity=inten, rinv=rinv, beta=beta, la_step=step, censor=cens)
        inten, rbar, logf, rinv, cens = self._measure(code, float(self._escale[self._idx[k]]))
        if self.interpolate_covariance and not last:
            _, rbar1, _, _, cens1 = self._measure(self._codes[self._idx[k + 1]], float(self._escale[self._idx[k + 1]]))
            beta = np.where((cens != 0) | (cens1 != 0), 0.0, rbar1 / rbar - 1.0)  # eq. 7, R̄ linear in t
        else:
            beta = np.zeros_like(rbar)
        return Segment(t0_us=int(self.times_us[k]), t1_us=None if last else int(self.times_us[k + 1]),
                       log_frame=logf, intensity=inten, rinv=rinv, beta=beta,
                       la_step=np.full(inten.shape[0], self.event_step) if self.event_step else None,
                       censor=cens if self.saturation == "bound" else None)
