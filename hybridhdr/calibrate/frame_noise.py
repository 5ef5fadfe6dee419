"""The frames' noise and the unreported drift, measured on the recording itself.

The AKF weighs a frame against its state by two variances the paper sets by hand (Wang et al.,
ICCV 2021, §6): the frame noise σ²_im of eq. 6 (``frame_precision_scale`` = 1/σ²_im, 7e5 for
their DAVIS240C) and the process noise σ²_proc of §3.1.1, the change of log intensity that no
event reports. Their ratio decides how many past frames the filter averages at a pixel without
events: a frame noise set 25-100x below the real one and a process noise set 50x above the
real drift (both measured on ``davis346_street`` and ``ecd_slider_depth``) make the filter
restart from each new frame, so the frames' own temporal noise reaches the output untouched.

**Model.** At a pixel without events the frames' log ``L_k = ln(I_k + I0)`` follow the local
level model (a random walk observed in white noise; Harvey, *Forecasting, Structural Time
Series Models and the Kalman Filter*, CUP 1989, §2.3.1; Durbin & Koopman, *Time Series Analysis
by State Space Methods*, OUP 2012, §2.1)::

    L_k = x_k + ε_k,   ε_k ~ N(0, ρ R_k),   x_{k+1} = x_k + η_k,   η_k ~ N(0, q Δt_k)

with ``R_k`` the camera profile's log-domain frame variance of eq. 9 (``R̄(code)/(I + I0)²``, its
shape over the codes from the profile's weighting) and ρ the unknown scale of σ²_im. Successive
differences ``a = L_k - L_{k-1}``, ``b = L_{k+1} - L_k`` then have the moments::

    E[a b] = -ρ R_k,    E[a²] = q Δt_{k-1} + ρ (R_{k-1} + R_k)

so ρ and q follow from sums over pixel-triples (method of moments; ρ from the lag-one
autocovariance of the first differences, the MA(1) form of the model's differences), without
any ground truth and without a free parameter:

    ρ = Σ(-a b) / Σ R_k,    q = Σ(a² + b² - ρ (R_{k-1} + 2 R_k + R_{k+1})) / Σ(Δt_{k-1} + Δt_k)

**Samples.** Pixel-triples of consecutive frames (k-1, k, k+1) with no event from the start of
frame k-1's exposure to the end of frame k+1's (so no reported change, and the exposure-mean
correction of the AKF does not touch them), all three codes well exposed
(:func:`~hybridhdr.camera.encoding.well_exposed_range`: no clipping, no censored bound), and
the three frames inside the events' span (where a pixel without events did not change by a
threshold). At most ``max_triples`` triples of frames, evenly spread, bound the work.

**Identifiability.** ρ is identified when at least ``min_samples`` pixel-triples hold and its
estimate exceeds two standard errors (the standard error from the samples' spread, treating
pixel-triples as independent: an underestimate where noise is spatially correlated); else the
record says why and the caller keeps its values. A negative q (sampling noise around no drift)
is reported as 0.
"""

from __future__ import annotations

import math

import numpy as np

from ..camera.encoding import frames_to_codes, well_exposed_range
from ..camera.profile import CameraProfile, profile_for_frames
from ..model import Frames

__all__ = ["estimate_frame_noise", "MIN_SAMPLES", "MAX_TRIPLES"]

#: Fewest pixel-triples for an estimate.
MIN_SAMPLES = 1000
#: Most frame triples read (evenly spread over the recording).
MAX_TRIPLES = 32


def _event_free(t, x, y, width: int, n_pix: int, t0: int, t1: int) -> np.ndarray:
    """Pixels (flattened) with no event in ``[t0, t1)``."""
    i0, i1 = np.searchsorted(t, [t0, t1], side="left")
    busy = np.zeros(n_pix, bool)
    if i1 > i0:
        busy[y[i0:i1].astype(np.int64) * width + x[i0:i1].astype(np.int64)] = True
    return ~busy


def estimate_frame_noise(frames: Frames, t, x, y, profile: CameraProfile, intensity_offset: float, *,
                         min_samples: int = MIN_SAMPLES, max_triples: int = MAX_TRIPLES) -> dict:
    """The frames' noise scale and the drift rate of the local level model (module docstring).

    Parameters
    ----------
    frames : Frames
        The frames as the filter reads them (already shifted by any frame time offset).
    t, x, y : arrays
        Event times (µs, non-decreasing), columns and rows.
    profile : CameraProfile
        The camera profile the filter uses (its inverse CRF, weighting and precision scale).
    intensity_offset : float
        I0 of the log model ln(I + I0).
    min_samples, max_triples : int
        Fewest pixel-triples for an estimate; most frame triples read.

    Returns
    -------
    dict with ``identifiable`` (bool), ``reason`` (when not), ``samples`` (pixel-triples),
    ``triples`` (frame triples read), ``variance_scale`` (ρ) and its ``variance_scale_se``,
    ``frame_precision_scale`` (the profile's, ``profile_precision_scale``, divided by ρ: 1/σ²_im
    in eq. 6's units),
    ``process_noise_per_s`` (q, log²/s, >= 0) and ``process_noise_raw_per_s`` (before the clip
    at 0), ``frame_variance_log`` (the measured mean frame variance, log²) and
    ``profile_variance_log`` (the profile's over the same samples).
    """
    if not isinstance(frames, Frames):
        raise TypeError(f"frames must be a hybridhdr Frames, got {type(frames).__name__}")
    if not isinstance(profile, CameraProfile):
        raise TypeError(f"profile must be a CameraProfile, got {type(profile).__name__}")
    if not (math.isfinite(float(intensity_offset)) and float(intensity_offset) > 0):
        raise ValueError(f"intensity_offset must be a finite number > 0, got {intensity_offset!r}")
    if int(min_samples) < 1 or int(max_triples) < 1:
        raise ValueError(f"min_samples and max_triples must be >= 1, got {min_samples} and {max_triples}")
    t = np.asarray(t)
    out = {"identifiable": False, "samples": 0, "triples": 0, "method": "local level model, moments of the "
           "frames' log differences at pixels without events (Harvey 1989)"}
    if len(frames) < 3 or t.size == 0:
        out["reason"] = f"needs 3 frames and events, got {len(frames)} frames and {t.size} events"
        return out
    h, w = frames.shape[:2] if frames.images.ndim == 3 else frames.images.shape[1:3]
    n_pix = int(h) * int(w)
    prof = profile_for_frames(profile, frames)
    lo, hi = well_exposed_range(prof.max_code)
    tau = frames.t_mid_us
    order = np.argsort(tau, kind="stable")
    t_first, t_last = int(t[0]), int(t[-1])
    inside = [int(k) for k in order if t_first <= int(frames.t_start_us[k]) and int(frames.t_end_us[k]) <= t_last]
    cand = [(inside[j - 1], inside[j], inside[j + 1]) for j in range(1, len(inside) - 1)
            if tau[inside[j - 1]] < tau[inside[j]] < tau[inside[j + 1]]]
    if not cand:
        out["reason"] = "no three consecutive frames inside the events' span"
        return out
    if len(cand) > max_triples:
        cand = [cand[int(i)] for i in np.linspace(0, len(cand) - 1, int(max_triples)).round()]
    i0 = float(intensity_offset)
    x = np.asarray(x)
    y = np.asarray(y)
    codes_all = np.asarray(frames_to_codes(frames, (h, w)))
    lut = codes_all.dtype.kind in "ui" and prof.max_code <= 65535
    if lut:  # every quantity depends only on the code: tabulate once
        cc = np.arange(prof.max_code + 1)
        ip_t = prof.intensity(cc) + i0
        log_t, r_t = np.log(ip_t), prof.variance(cc) / (ip_t * ip_t)
    s_ab = s_ab2 = s_r = s_sq = s_rsum = s_dt = 0.0
    n = 0
    for ka, kb, kc in cand:
        free = _event_free(t, x, y, int(w), n_pix, int(frames.t_start_us[ka]), int(frames.t_end_us[kc]))
        codes = codes_all[[ka, kb, kc]].reshape(3, -1)
        ok = free & np.all((codes >= lo) & (codes <= hi), axis=0)
        m = int(np.count_nonzero(ok))
        if m == 0:
            continue
        c = codes[:, ok]
        if lut:
            ci = c.astype(np.int64)
            logv, r = log_t[ci], r_t[ci]
        else:
            ip = prof.intensity(c) + i0
            logv = np.log(ip)
            r = prof.variance(c) / (ip * ip)  # eq. 9 with the profile's σ²_im
        a = logv[1] - logv[0]
        b = logv[2] - logv[1]
        ab = a * b
        s_ab += float(np.sum(ab))
        s_ab2 += float(np.sum(ab * ab))
        s_r += float(np.sum(r[1]))
        s_sq += float(np.sum(a * a + b * b))
        s_rsum += float(np.sum(r[0] + 2.0 * r[1] + r[2]))
        s_dt += m * (float(tau[kc] - tau[ka]) * 1e-6)
        n += m
        out["triples"] += 1
    out["samples"] = n
    if n < int(min_samples):
        out["reason"] = f"{n} pixel-triples without events and well exposed, fewer than {int(min_samples)}"
        return out
    rho = -s_ab / s_r
    var_ab = max(s_ab2 / n - (s_ab / n) ** 2, 0.0)
    se = math.sqrt(var_ab * n) / s_r
    q_raw = (s_sq - rho * s_rsum) / s_dt if rho > 0 else float("nan")
    out.update(variance_scale=rho, variance_scale_se=se, frame_variance_log=-s_ab / n,
               profile_variance_log=s_r / n, process_noise_raw_per_s=q_raw)
    if not rho > 2.0 * se:
        out["reason"] = (f"the frames' lag-one covariance does not identify their noise: scale {rho:.3g} "
                         f"± {se:.2g} (needs > 2 standard errors)")
        return out
    out.update(identifiable=True, profile_precision_scale=float(prof.frame_precision_scale),
               frame_precision_scale=float(prof.frame_precision_scale) / rho,
               process_noise_per_s=max(q_raw, 0.0))
    return out
