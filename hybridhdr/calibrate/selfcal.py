"""Event/frame self-calibration: what a recording's own frames say about its events.

A real hybrid recording rarely states the three things that decide whether its events and frames
agree (measured on ``ecd_slider_depth``, ``benchmarks/real_diagnostics.py``):

1. **The time a frame stands for.** A frame integrates light over its exposure; the recording
   may stamp it at the exposure start, the readout, or give one time and no exposure (the ECD
   text layout). The events explain the frames' changes best when the frames' times are shifted
   by ``time_offset_us``.
2. **The log model the events follow.** A DVS pixel responds to ``ln(I + I_dark)``: its
   photocurrent includes a dark current, so in the dark a change of the frames' ``ln I`` needs
   far more events than in the light. In the AKF this is the intensity offset I0 of eq. 8
   (``AKFParams.intensity_offset``), in frame-linear units of the recording's own frames.
3. **The contrast thresholds** c_on, c_off in that log model (eq. 1).

Model, between consecutive frame times τ_k + δ < τ_{k+1} + δ (mid-exposures shifted by δ), at a
pixel both frames show well exposed (codes 20-235 of 8 bits scaled to the bit depth, the
threshold estimator's choice, :mod:`hybridhdr.calibrate.thresholds`):

    ln(I_{k+1} + I0) − ln(I_k + I0) = c_on·N_on,k − c_off·N_off,k + ε,

with N the event counts in ``[τ_k + δ, τ_{k+1} + δ)``. For each (δ, I0) of a grid the pooled
least squares (non-negative, the estimator's closed form) gives (c_on, c_off) and the fraction
of the frames' log-change variance the events explain, R² = 1 − SS_res/SS_tot. The calibration
is the grid point of largest R²; (c_on, c_off) are its least-squares thresholds (the best linear
predictor of a frame change from the counts, which is what the filter does with them).

Only intervals whose shifted ends lie inside the events' span for **every** δ of the grid are
used, so each grid point is scored on the same pixel-intervals. ``exclude_frames`` removes
frames before anything is estimated (leave-one-out scoring: the scored frame never informs its
own calibration; the two intervals around it become one).

What this does not estimate: per-pixel thresholds (on short recordings a pixel has a few events:
``benchmarks/real_diagnostics.py`` measures what a per-pixel oracle would add) and the exposure
length (the diagnostics sweep it; the mid-exposure shift captures nearly all of its effect).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..camera import load_profile, profile_for_frames
from ..camera.encoding import DEFAULT_INTENSITY_OFFSET, frames_to_codes, well_exposed_range
from ..model import Recording
from .thresholds import _nnls2

__all__ = ["EventFrameCalibration", "estimate_event_frame_calibration", "apply_time_offset",
           "DEFAULT_INTENSITY_OFFSETS", "SCHEMA"]

SCHEMA = "hybridhdr.selfcal/1"

#: Intensity offsets I0 tried, as fractions of the frames' clip level (frame-linear units).
DEFAULT_INTENSITY_OFFSETS = (1e-3, 2.5e-3, 5e-3, 1e-2, 2e-2, 4e-2, 8e-2, 0.16, 0.32, 0.64)

#: Largest number of frame intervals used (evenly spread): bounds the work on long recordings.
MAX_INTERVALS = 64


@dataclasses.dataclass(frozen=True)
class EventFrameCalibration:
    """The result of :func:`estimate_event_frame_calibration` (module docstring)."""

    time_offset_us: int
    intensity_offset: float
    c_on: float
    c_off: float
    r2: float
    r2_nominal: float
    n_pixel_intervals: int
    n_intervals: int
    excluded_frames: tuple
    offsets_us: tuple
    intensity_offsets: tuple
    r2_grid: tuple  # (len(offsets_us), len(intensity_offsets)) as nested tuples

    def to_dict(self) -> dict:
        """JSON-ready record (``run.json``'s ``self_calibration``)."""
        d = dataclasses.asdict(self)
        d["schema"] = SCHEMA
        d["excluded_frames"] = [int(k) for k in self.excluded_frames]
        d["offsets_us"] = [int(v) for v in self.offsets_us]
        d["intensity_offsets"] = [float(v) for v in self.intensity_offsets]
        d["r2_grid"] = [[float(v) for v in row] for row in self.r2_grid]
        return d

    def akf_overrides(self) -> dict:
        """AKF parameters this calibration sets (log model and thresholds)."""
        return {"intensity_offset": float(self.intensity_offset), "contrast_threshold_on": float(self.c_on),
                "contrast_threshold_off": float(self.c_off)}


def _default_offsets(period_us: float, fraction: float = 0.5) -> tuple:
    """δ from −fraction·period to +fraction·period in 41 steps (at least 1 µs apart)."""
    half = max(int(round(period_us * fraction)), 1)
    return tuple(sorted(set(int(round(v)) for v in np.linspace(-half, half, 41))))


def estimate_event_frame_calibration(recording, *, profile=None, exclude_frames=(), offsets_us=None,
                                     intensity_offsets=DEFAULT_INTENSITY_OFFSETS, well_exposed=None,
                                     c_range=(0.01, 3.0)) -> EventFrameCalibration:
    """Estimate (δ, I0, c_on, c_off) from a recording's own frames and events (module docstring).

    Parameters
    ----------
    recording : Recording
        Events and at least three frames (two intervals) registered to the event sensor.
    profile : CameraProfile, path or None
        Camera profile for ``I = CRF⁻¹(code)``; None: the built-in one of the frames' encoding.
    exclude_frames : sequence of int
        Frame indices (into ``recording.frames``) left out of the estimate (leave-one-out).
    offsets_us : sequence of int, optional
        Time offsets δ tried (µs, added to the frames' mid-exposures); default ±half the median
        frame period in 41 steps.
    intensity_offsets : sequence of float
        I0 values tried, frame-linear units (clip level 1).
    c_range : (float, float)
        A best grid point whose thresholds fall outside is an error (too little information).

    Raises
    ------
    ValueError
        Fewer than two usable frame intervals, no events, or no usable pixel-interval.
    """
    rec = recording
    fr = rec.frames
    if fr is None or len(fr) < 3:
        raise ValueError("self-calibration needs at least three frames (two intervals); the recording has "
                         f"{0 if fr is None else len(fr)}")
    ev = rec.events
    if len(ev) == 0:
        raise ValueError("self-calibration needs events; the recording has none")
    excl = sorted({int(k) for k in exclude_frames})
    for k in excl:
        if not 0 <= k < len(fr):
            raise ValueError(f"exclude_frames: frame {k} is not among the recording's {len(fr)} frames")
    i0s = tuple(float(v) for v in intensity_offsets)
    if not i0s or any(not (math.isfinite(v) and v > 0) for v in i0s):
        raise ValueError(f"intensity_offsets must be finite and > 0, got {intensity_offsets}")
    keep = np.setdiff1d(np.arange(len(fr)), np.asarray(excl, np.int64))
    sub = fr.select(keep)
    tau = sub.t_mid_us.astype(np.int64)
    order = np.argsort(tau, kind="stable")
    tau = tau[order]
    if np.any(np.diff(tau) <= 0):
        raise ValueError("self-calibration needs frames with distinct times")
    period = float(np.median(np.diff(tau))) if len(tau) > 1 else 0.0
    t = ev["t"]
    t0_ev, t1_ev = int(t[0]), int(t[-1])

    def covered(offs):  # intervals covered by the events for every offset of the grid (module docstring)
        return [j for j in range(len(tau) - 1) if tau[j] + offs[0] >= t0_ev and tau[j + 1] + offs[-1] <= t1_ev]

    if offsets_us is None:
        # ±half a frame period; on recordings too short for it (events covering few frames), a
        # narrower grid keeps two intervals scored at every offset
        for frac in (0.5, 0.25, 0.125):
            offs = _default_offsets(period, frac)
            ints = covered(offs)
            if len(ints) >= 2:
                break
    else:
        offs = tuple(sorted({int(v) for v in offsets_us}))
        if not offs:
            raise ValueError("offsets_us is empty")
        ints = covered(offs)
    if len(ints) < 2:
        raise ValueError(f"self-calibration needs two frame intervals inside the events' span ({t0_ev}..{t1_ev} µs) "
                         f"for every offset tried ({offs[0]}..{offs[-1]} µs); found {len(ints)}")
    if len(ints) > MAX_INTERVALS:
        ints = [ints[i] for i in np.linspace(0, len(ints) - 1, MAX_INTERVALS).round().astype(int)]
    h, w = sub.shape
    n = h * w
    prof = profile_for_frames(load_profile(profile), sub)
    lo, hi = well_exposed_range(prof.max_code) if well_exposed is None else (int(well_exposed[0]), int(well_exposed[1]))
    codes = frames_to_codes(sub, (h, w))
    lin, good = {}, {}

    def frame(j):
        if j not in lin:
            c = np.asarray(codes[order[j]]).reshape(-1)
            lin[j] = prof.intensity(c).astype(np.float64)
            good[j] = (c >= lo) & (c <= hi)
        return lin[j], good[j]

    # per interval: the usable pixels and their log changes per I0 (independent of δ)
    dls, masks = [], []
    for j in ints:
        a, ga = frame(j)
        b, gb = frame(j + 1)
        m = np.flatnonzero(ga & gb)
        masks.append(m)
        dls.append(np.stack([np.log(b[m] + i0) - np.log(a[m] + i0) for i0 in i0s]))  # (nI0, m)
    npi = int(sum(len(m) for m in masks))
    if npi == 0:
        raise ValueError("self-calibration found no pixel both frames of an interval show well exposed")
    pix = ev["y"].astype(np.int64) * w + ev["x"].astype(np.int64)
    on = ev["p"] > 0
    sll = np.array([sum(float(d[i] @ d[i]) for d in dls) for i in range(len(i0s))])
    sl = np.array([sum(float(d[i].sum()) for d in dls) for i in range(len(i0s))])
    sstot = sll - sl ** 2 / npi
    r2 = np.full((len(offs), len(i0s)), np.nan)
    coefs = np.full((len(offs), len(i0s), 2), np.nan)
    for a_i, dt in enumerate(offs):
        soo = sff = sof = 0.0
        bo = np.zeros(len(i0s))
        bf = np.zeros(len(i0s))
        for j, m, d in zip(ints, masks, dls):
            e0, e1 = np.searchsorted(t, [tau[j] + dt, tau[j + 1] + dt])
            p_, o_ = pix[e0:e1], on[e0:e1]
            non = np.bincount(p_[o_], minlength=n)[m].astype(np.float64)
            noff = np.bincount(p_[~o_], minlength=n)[m].astype(np.float64)
            soo += non @ non
            sff += noff @ noff
            sof += non @ noff
            bo += d @ non
            bf += d @ noff
        for i in range(len(i0s)):
            ca, cb = (float(np.asarray(v).reshape(-1)[0]) for v in _nnls2(
                np.array([soo]), np.array([sff]), np.array([sof]), np.array([bo[i]]), np.array([bf[i]])))
            ssres = sll[i] - 2 * ca * bo[i] + 2 * cb * bf[i] + ca * ca * soo + cb * cb * sff - 2 * ca * cb * sof
            r2[a_i, i] = 1.0 - ssres / sstot[i] if sstot[i] > 0 else np.nan
            coefs[a_i, i] = (ca, cb)
    if not np.isfinite(r2).any():
        raise ValueError("self-calibration: the frames show no log change to explain")
    a_i, i = np.unravel_index(np.nanargmax(r2), r2.shape)
    c_on, c_off = (float(v) for v in coefs[a_i, i])
    lo_c, hi_c = c_range
    if not (lo_c <= c_on <= hi_c and lo_c <= c_off <= hi_c):
        raise ValueError(f"self-calibration: the best fit's thresholds (c_on {c_on:.3g}, c_off {c_off:.3g}) are outside "
                         f"{tuple(c_range)}: the recording has too little usable information")
    # the nominal model for comparison: no shift, the default I0 (its nearest grid point)
    a0 = int(np.argmin(np.abs(np.asarray(offs))))
    i_def = int(np.argmin(np.abs(np.log(np.asarray(i0s)) - math.log(DEFAULT_INTENSITY_OFFSET))))
    return EventFrameCalibration(
        time_offset_us=int(offs[a_i]), intensity_offset=float(i0s[i]), c_on=c_on, c_off=c_off,
        r2=float(r2[a_i, i]), r2_nominal=float(r2[a0, i_def]), n_pixel_intervals=npi, n_intervals=len(ints),
        excluded_frames=tuple(excl), offsets_us=offs, intensity_offsets=i0s,
        r2_grid=tuple(tuple(float(v) for v in row) for row in r2))


def apply_time_offset(recording, time_offset_us: int) -> Recording:
    """The recording with every frame's exposure interval shifted by ``time_offset_us`` (events,
    triggers and HDR references unchanged); provenance records the shift."""
    fr = recording.frames
    if fr is None or int(time_offset_us) == 0:
        return recording
    dt = int(time_offset_us)
    shifted = fr.shifted(dt)
    md = recording.metadata
    if md is not None and isinstance(md.provenance, dict):
        prov = dict(md.provenance)
        prov["frame_time_offset_us"] = int(prov.get("frame_time_offset_us", 0)) + dt
        md = dataclasses.replace(md, provenance=prov)
    return dataclasses.replace(recording, frames=shifted, metadata=md)


def self_calibration(recording, *, profile=None, intensity_offset: float | None = None, exclude_frames=()) -> dict:
    """What a method needs from :func:`estimate_event_frame_calibration`, as one record.

    ``intensity_offset=None`` (the AKF): the log model's I0 is calibrated with the time offset.
    A number (a method whose log model is fixed, e.g. CF's published ``ln(I + 1)``): the time offset
    is the recording's (estimated with I0 free, as for the AKF) and the thresholds are re-fitted
    at that offset in the method's own model. Returns ``{"time_offset_us", "intensity_offset",
    "c_on", "c_off", "r2", "r2_nominal", "calibration"}`` (the last: the full record)."""
    cal = estimate_event_frame_calibration(recording, profile=profile, exclude_frames=exclude_frames)
    rec = cal.to_dict()
    if intensity_offset is not None:
        own = estimate_event_frame_calibration(recording, profile=profile, exclude_frames=exclude_frames,
                                               offsets_us=(cal.time_offset_us,),
                                               intensity_offsets=(float(intensity_offset),))
        cal_used = own
    else:
        cal_used = cal
    return {"time_offset_us": int(cal.time_offset_us), "intensity_offset": float(cal_used.intensity_offset),
            "c_on": float(cal_used.c_on), "c_off": float(cal_used.c_off), "r2": float(cal_used.r2),
            "r2_nominal": float(cal.r2_nominal), "calibration": rec}
