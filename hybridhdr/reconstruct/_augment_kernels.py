"""Numba kernels of EDI deblurring and frame augmentation (private; wrappers in ``edi``/``augment``).

Every kernel takes separate contiguous 1-D event arrays: ``t`` (int64 µs), ``x``, ``y`` (uint16)
and ``p`` (int8, ±1), and processes the time-sorted events ``[i0, i1)``. Pixels are flattened
row-major (``y * width + x``). The per-pixel "event walk" keeps, for every pixel, the time of its
last event and its signed event count since the window start, so one pass in time order gives
the exact piecewise-constant integral of exp(c E(t)) for all pixels at once.

References
----------
L. Pan et al., "Bringing a Blurry Frame Alive at High Frame-Rate with an Event Camera",
CVPR 2019, doi:10.1109/CVPR.2019.00698 (the double integral, EDI).
Z. Wang, Y. Ng, C. Scheerlinck, R. Mahony, "An Asynchronous Kalman Filter for Hybrid Event
Cameras", ICCV 2021, doi:10.1109/ICCV48922.2021.00050 (§4.1, eqs. 10-13).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def event_counts(x, y, p, i0, i1, width, signed, total):
    """Add, per pixel, the signed count Σσ to ``signed`` and the number of events to ``total``.

    Events ``[i0, i1)``; both outputs are int64 of shape (H*W,). Returns the number of events.
    """
    for i in range(i0, i1):
        pix = np.int64(y[i]) * width + np.int64(x[i])
        total[pix] += 1
        if p[i] > 0:
            signed[pix] += 1
        else:
            signed[pix] -= 1
    return i1 - i0


@njit(cache=True, nogil=True)
def edi_walk(t, x, y, p, i0, i1, width, t_s, t_e, c, count, t_last, acc):
    """Exact ∫_{t_s}^{t_e} exp(c E(t)) dt per pixel (µs), E(t) = Σσ of the pixel's events in [t_s, t).

    The events ``[i0, i1)`` must lie in ``[t_s, t_e)``. ``count`` (int64), ``t_last`` and ``acc``
    (float64), all of shape (H*W,), are work arrays the caller zeroes (``t_last`` set to ``t_s``);
    on return ``acc`` holds the integral and ``count`` the signed count over the exposure. E is
    piecewise constant between a pixel's events, so the integral is the exact sum
    Σ_j exp(c E_j) (t_{j+1} - t_j) (the double integral of EDI, Pan et al. 2019).
    """
    for i in range(i0, i1):
        pix = np.int64(y[i]) * width + np.int64(x[i])
        ti = np.float64(t[i])
        acc[pix] += math.exp(c * count[pix]) * (ti - t_last[pix])
        t_last[pix] = ti
        if p[i] > 0:
            count[pix] += 1
        else:
            count[pix] -= 1
    te = np.float64(t_e)
    for pix in range(acc.shape[0]):
        acc[pix] += math.exp(c * count[pix]) * (te - t_last[pix])
    return i1 - i0


@njit(cache=True, nogil=True)
def calibrate_threshold(delta_ld, sum_sigma, any_events, c, scale_min, scale_max, c_eff, category):
    """Per-pixel contrast-threshold calibration of eq. 12 with explicit fallbacks.

    For each pixel, the scale ``r = ΔL^D / (c Σσ)`` (eq. 12's c_p^k) gives ``c_eff = r c`` when
    ``scale_min <= 1/r <= scale_max`` (the reference code stores 1/r and accepts [0.6, 100]).
    Otherwise ``c_eff = c`` and ``category`` records why:

    * 0 - calibrated;
    * 1 - no events in the interval;
    * 2 - events but Σσ = 0 (zero denominator);
    * 3 - ΔL^D = 0 or sign(ΔL^D) ≠ sign(Σσ) (r <= 0);
    * 4 - 1/r outside [scale_min, scale_max].

    No division by zero is ever performed. Returns the number of calibrated pixels.
    """
    n_ok = 0
    for pix in range(delta_ld.shape[0]):
        s = sum_sigma[pix]
        if not any_events[pix]:
            c_eff[pix] = c
            category[pix] = 1
            continue
        if s == 0:
            c_eff[pix] = c
            category[pix] = 2
            continue
        d = delta_ld[pix]
        den = c * s
        if d == 0.0 or (d > 0.0) != (den > 0.0):
            c_eff[pix] = c
            category[pix] = 3
            continue
        r = d / den
        inv = 1.0 / r
        if inv < scale_min or inv > scale_max:
            c_eff[pix] = c
            category[pix] = 4
            continue
        c_eff[pix] = r * c
        category[pix] = 0
        n_ok += 1
    return n_ok


@njit(cache=True, nogil=True)
def edi_walk_asym(t, x, y, p, i0, i1, width, t_s, t_e, c_on, c_off, count, level, t_last, acc):
    """:func:`edi_walk` with per-pixel ON and OFF thresholds (float64 (H*W,) each):
    ∫ exp(E(t)) dt with E(t) = c_on N_on(t) - c_off N_off(t) of the pixel's events in [t_s, t).
    ``level`` (float64, zeroed by the caller) ends as E(t_e); ``count`` as the signed count."""
    for i in range(i0, i1):
        pix = np.int64(y[i]) * width + np.int64(x[i])
        ti = np.float64(t[i])
        acc[pix] += math.exp(level[pix]) * (ti - t_last[pix])
        t_last[pix] = ti
        if p[i] > 0:
            count[pix] += 1
            level[pix] += c_on[pix]
        else:
            count[pix] -= 1
            level[pix] -= c_off[pix]
    te = np.float64(t_e)
    for pix in range(acc.shape[0]):
        acc[pix] += math.exp(level[pix]) * (te - t_last[pix])
    return i1 - i0


@njit(cache=True, nogil=True)
def calibrate_scale(delta_ld, nominal, any_events, scale_min, scale_max, scale, category):
    """Eq. 12 with ON and OFF thresholds: per pixel, ``r = ΔL^D / D`` with D the nominal change
    ``c_on N_on - c_off N_off`` of the interval's events; ``scale = r`` when ``scale_min <= 1/r
    <= scale_max``, else 1 with the reason in ``category`` (as :func:`calibrate_threshold`;
    2 is now D = 0). The calibrated thresholds are ``r c_on`` and ``r c_off``: one equation per
    interval fixes their common scale, their ratio is the sensor's. Returns the number of
    calibrated pixels."""
    n_ok = 0
    for pix in range(delta_ld.shape[0]):
        if not any_events[pix]:
            scale[pix] = 1.0
            category[pix] = 1
            continue
        den = nominal[pix]
        if den == 0.0:
            scale[pix] = 1.0
            category[pix] = 2
            continue
        d = delta_ld[pix]
        if d == 0.0 or (d > 0.0) != (den > 0.0):
            scale[pix] = 1.0
            category[pix] = 3
            continue
        r = d / den
        inv = 1.0 / r
        if inv < scale_min or inv > scale_max:
            scale[pix] = 1.0
            category[pix] = 4
            continue
        scale[pix] = r
        category[pix] = 0
        n_ok += 1
    return n_ok
