"""Numba kernels of the reconstruction filters (private; use the wrappers in ``akf``/``baselines``).

Every kernel takes separate contiguous 1-D arrays: events as ``t`` (int64 µs), ``x``, ``y``
(uint16) and ``p`` (int8, ±1); per-pixel state flattened row-major (index ``y * width + x``).
Rates are per second and are applied to Δt converted from µs to s inside the kernel.

Event kernels process the events ``[i0, i1)`` whose row lies in ``[row_lo, row_hi)``; events in
the two neighbouring *ghost* rows ``row_lo - 1`` and ``row_hi`` only update the last-event time
``te`` (which the isolated-pixel noise reads), and all other events are skipped. With
``row_lo = 0, row_hi = height`` this is the serial filter; two workers on disjoint row bands,
each with its own ``te`` array, therefore do exactly the serial arithmetic for their pixels and
produce bit-identical results.

Equation numbers refer to Wang, Ng, Scheerlinck, Mahony, "An Asynchronous Kalman Filter for
Hybrid Event Cameras", ICCV 2021, doi:10.1109/ICCV48922.2021.00050.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

US = 1e-6  # seconds per microsecond

NOISE_PAPER = 0
NOISE_REFERENCE = 1


@njit(cache=True, nogil=True)
def log1p_over_x(x):
    """``log1p(x) / x`` with its limit 1 at ``x = 0`` (series below |x| < 1e-4, error < 1e-17)."""
    if abs(x) < 1e-4:
        return 1.0 - x * (0.5 - x * (1.0 / 3.0 - x * 0.25))
    return math.log1p(x) / x


@njit(cache=True, nogil=True)
def rinv_integral(rinv, beta, t0, t1, seg_t0, seg_inv_t):
    """∫ R⁻¹(s) ds over [t0, t1] (µs in, seconds out) for R(t) = R_k (1 + beta u), eq. 7.

    ``u = (t - seg_t0) * seg_inv_t`` runs from 0 at τ_k to 1 at τ_{k+1}; ``rinv`` is 1/R_k in
    1/(log² s). Exact: ∫ = rinv Δt / (1 + beta u0) · log1p(x)/x with x = beta Δu / (1 + beta u0).
    ``beta = 0`` (held covariance) gives ``rinv * Δt``.
    """
    dt_s = (t1 - t0) * US
    if beta == 0.0:
        return rinv * dt_s
    w0 = 1.0 + beta * ((t0 - seg_t0) * seg_inv_t)
    x = beta * ((t1 - t0) * seg_inv_t) / w0
    return rinv * dt_s / w0 * log1p_over_x(x)


@njit(cache=True, nogil=True)
def akf_events(t, x, y, p, i0, i1, row_lo, row_hi, width, height,
               L, P, tu, te, la, rinv, beta, la_step, has_la_step, seg_t0, seg_inv_t,
               c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form):
    """AKF update at each event (eqs. 15, 17, 20, 21 with Q of eq. 2 / §3.1.1).

    For the event at pixel p and time t_i, in order: propagate L̂ and P from the last update
    ``tu`` with the stable closed forms of eqs. 17 and 20 (g = P ∫R⁻¹, P ← P/(1+g),
    L̂ ← L^A + (L̂ - L^A)/(1+g)); add Q = Q_proc + Q_iso + Q_ref to P (eq. 21); jump L̂ by
    +c_on or -c_off (eq. 15); set ``tu = te = t_i``; advance L^A by ``σ la_step`` when the
    measurement is event-driven (frame augmentation hook).

    Returns the number of events applied to pixels of the band.
    """
    n = 0
    for i in range(i0, i1):
        yy = np.int64(y[i])
        if yy + 1 < row_lo or yy > row_hi:
            continue
        xx = np.int64(x[i])
        ti = t[i]
        pix = yy * width + xx
        if yy < row_lo or yy >= row_hi:  # ghost row: neighbour time only
            te[pix] = ti
            continue
        # -- propagate to t_i (eqs. 17, 20) --------------------------------------------------
        tu0 = tu[pix]
        integ = rinv_integral(rinv[pix], beta[pix], tu0, ti, seg_t0, seg_inv_t)
        d = 1.0 / (1.0 + P[pix] * integ)
        lav = la[pix]
        lhat = lav + (L[pix] - lav) * d
        pp = P[pix] * d
        # -- event noise (eq. 2, §3.1.1) ------------------------------------------------------
        te0 = te[pix]
        tstar = te0
        ylo = yy - 1 if yy > 0 else yy
        yhi = yy + 1 if yy + 1 < height else yy
        xlo = xx - 1 if xx > 0 else xx
        xhi = xx + 1 if xx + 1 < width else xx
        for yn in range(ylo, yhi + 1):
            base = yn * width
            for xn in range(xlo, xhi + 1):
                v = te[base + xn]
                if v > tstar:
                    tstar = v
        dte = ti - te0
        q_iso = s_iso * ((ti - tstar) * US)
        if noise_form == 0:
            q = s_proc * (dte * US) + q_iso
            if dte <= rho_us:
                q += s_ref
        else:
            q = s_proc * ((ti - tu0) * US) + q_iso
            if dte <= rho_us:
                q += s_ref * (dte * US)
        P[pix] = pp + q
        # -- event jump (eq. 15) --------------------------------------------------------------
        if p[i] > 0:
            L[pix] = lhat + c_on
            if has_la_step:
                la[pix] = lav + la_step[pix]
        else:
            L[pix] = lhat - c_off
            if has_la_step:
                la[pix] = lav - la_step[pix]
        tu[pix] = ti
        te[pix] = ti
        n += 1
    return n


@njit(cache=True, nogil=True)
def akf_propagate(L, P, tu, la, rinv, beta, seg_t0, seg_inv_t, t_to, pix_lo, pix_hi):
    """Propagate pixels ``[pix_lo, pix_hi)`` to ``t_to`` (eqs. 17, 20) and set ``tu = t_to``.

    Used only where L^A or R changes (a frame switch), never at output times.
    """
    for pix in range(pix_lo, pix_hi):
        integ = rinv_integral(rinv[pix], beta[pix], tu[pix], t_to, seg_t0, seg_inv_t)
        d = 1.0 / (1.0 + P[pix] * integ)
        lav = la[pix]
        L[pix] = lav + (L[pix] - lav) * d
        P[pix] = P[pix] * d
        tu[pix] = t_to
    return pix_hi - pix_lo


@njit(cache=True, nogil=True)
def akf_output(L, P, tu, la, rinv, beta, seg_t0, seg_inv_t, t_out, offset, out, pix_lo, pix_hi):
    """Write ``exp(L̂(t_out)) - I0`` (float32) into ``out`` without changing the state (eq. 17)."""
    for pix in range(pix_lo, pix_hi):
        integ = rinv_integral(rinv[pix], beta[pix], tu[pix], t_out, seg_t0, seg_inv_t)
        d = 1.0 / (1.0 + P[pix] * integ)
        lav = la[pix]
        out[pix] = math.exp(lav + (L[pix] - lav) * d) - offset
    return pix_hi - pix_lo


@njit(cache=True, nogil=True)
def cf_events(t, x, y, p, i0, i1, row_lo, row_hi, width, L, tu, lf, alpha, c_on, c_off, event_decay):
    """Complementary filter per event (Scheerlinck et al. 2018): dL̂/dt = e - α(L̂ - L^F).

    Between events L̂ = L^F + (L̂_u - L^F) exp(-α Δt - event_decay) (exact; ``event_decay`` is
    the per-event decay of the high-pass variant, 0 for CF), then L̂ += +c_on / -c_off.
    """
    n = 0
    for i in range(i0, i1):
        yy = np.int64(y[i])
        if yy < row_lo or yy >= row_hi:
            continue
        ti = t[i]
        pix = yy * width + np.int64(x[i])
        lfv = lf[pix]
        b = math.exp(-alpha[pix] * ((ti - tu[pix]) * US) - event_decay)
        lhat = lfv + (L[pix] - lfv) * b
        if p[i] > 0:
            L[pix] = lhat + c_on
        else:
            L[pix] = lhat - c_off
        tu[pix] = ti
        n += 1
    return n


@njit(cache=True, nogil=True)
def cf_propagate(L, tu, lf, alpha, t_to, pix_lo, pix_hi):
    """Propagate the CF state of pixels ``[pix_lo, pix_hi)`` to ``t_to`` (exact exponential)."""
    for pix in range(pix_lo, pix_hi):
        lfv = lf[pix]
        L[pix] = lfv + (L[pix] - lfv) * math.exp(-alpha[pix] * ((t_to - tu[pix]) * US))
        tu[pix] = t_to
    return pix_hi - pix_lo


@njit(cache=True, nogil=True)
def cf_output(L, tu, lf, alpha, t_out, offset, out, pix_lo, pix_hi):
    """Write ``exp(L̂(t_out)) - offset`` (float32) without changing the CF state."""
    for pix in range(pix_lo, pix_hi):
        lfv = lf[pix]
        out[pix] = math.exp(lfv + (L[pix] - lfv) * math.exp(-alpha[pix] * ((t_out - tu[pix]) * US))) - offset
    return pix_hi - pix_lo


