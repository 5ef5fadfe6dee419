"""Numba kernels of the reconstruction filters (private; the wrappers are in ``akf``/``baselines``).

Every kernel takes separate contiguous 1-D event arrays: ``t`` (int64 µs), ``x``, ``y`` (uint16)
and ``p`` (int8, ±1). Per-pixel state is flattened row-major (index ``y * width + x``) and packed
one record per pixel (array-of-structures, 64 bytes = one cache line for the AKF), because the
event stream touches pixels in random order and one cache miss per event beats eight. Times in
the state are float64 µs (exact below 2**53 µs, checked by the wrappers); rates are per second
and are applied to Δt converted from µs to s inside the kernels.

Event kernels process the events ``[i0, i1)`` whose row lies in ``[row_lo, row_hi)``. For the AKF,
events in the two *ghost* rows ``row_lo - 1`` and ``row_hi`` only update the last-event time
``te`` read by the isolated-pixel noise, and all other events are skipped. With ``row_lo = 0,
row_hi = height`` this is the serial filter; workers on disjoint row bands, each with its own
``te`` array, do exactly the serial arithmetic for their pixels, so the result is bit-identical.
The parallel engines do not make every worker scan the whole stream: each worker first selects
its band's events (plus ghost rows) with the branch-free :func:`band_select`, then runs the
``*_indexed`` kernel over that index list only.

Equation numbers refer to Wang, Ng, Scheerlinck, Mahony, "An Asynchronous Kalman Filter for
Hybrid Event Cameras", ICCV 2021, doi:10.1109/ICCV48922.2021.00050.
"""

from __future__ import annotations

import math
import types

import numpy as np
from numba import njit

from .._util.nbprefetch import prefetch

US = 1e-6  # seconds per microsecond
#: events ahead whose pixel state the event kernels prefetch (1280x720: 2x the events/s; results
#: unchanged, a prefetch is only a hint)
PREFETCH_AHEAD = 8
ONE = np.uint64(1)  # unsigned index arithmetic: no negative-index wraparound code in the kernels

NOISE_PAPER = 0
NOISE_REFERENCE = 1

# AKF record fields (columns of the (n_pixels, 8) float64 state array)
A_L, A_P, A_LA, A_RINV, A_BETA, A_TU, A_KLOG, A_LASTEP = range(8)

#: Largest P (log²) at which a censored frame moves the state to its conditional mean beyond the
#: bound (:func:`frame_update`); above it (σ > 1 ln: a pixel never seen unclipped starts at
#: ``censored_initial_covariance`` = 1e3) the state says nothing of how far beyond the bound the
#: intensity is, and the bound itself is taken.
TOBIT_MAX_P = 1.0
AKF_FIELDS = 8
# CF record fields (columns of the (n_pixels, 4) float64 state array)
C_L, C_LF, C_ALPHA, C_TU = range(4)
CF_FIELDS = 4


# -- the per-pixel arithmetic, written once ----------------------------------------------------
#
# Plain Python functions of one pixel's numbers: the integral of R⁻¹ (eq. 7), the propagation
# (eqs. 17, 20), the event step (eqs. 2, 15, 21), the frame switch and discrete frame update, the
# closed-form output, the isolated-pixel term's walk over a pixel's grouped events, and the CF's
# exact decay. Each is compiled twice from this one source: for the CPU kernels of this module
# with ``njit(inline="always")`` (bound to these names at the end of the section), and for the
# CUDA kernels with ``cuda.jit(device=True)`` (:func:`compile_pixel_functions`, used by
# ``_cuda_kernels``). They call each other by the names below, which each compilation binds to
# its own versions, so a change to an equation is made once and both targets get it.

def rinv_integral(rinv, beta, klog, tu0, t1, seg_t0, seg_inv_t):
    """∫ R⁻¹(s) ds over [tu0, t1] (µs in, s·R⁻¹ out) for R(t) = R_k (1 + beta u), eq. 7.

    ``u = (t - seg_t0) * seg_inv_t`` runs from 0 at τ_k to 1 at τ_{k+1}; ``rinv = 1/R_k`` in
    1/(log² s) and ``klog = rinv T_s / beta`` (``T_s`` the segment length in s). The integral is
    ``rinv Δt / w0 · log1p(x)/x = klog · log1p(x)`` with ``w0 = 1 + beta u0`` and
    ``x = beta Δu / w0``; for |x| < 1e-2 an 8-term series of log1p(x)/x is used (truncation
    < 1e-17). ``beta = 0`` (covariance held, or causal mode) gives ``rinv Δt``.
    """
    dt = t1 - tu0
    if beta == 0.0:
        return rinv * (dt * US)
    iw0 = 1.0 / (1.0 + beta * ((tu0 - seg_t0) * seg_inv_t))  # one division, two uses
    x = beta * (dt * seg_inv_t) * iw0
    if abs(x) < 1e-2:
        s = 1.0 - x * (0.5 - x * (1.0 / 3.0 - x * (0.25 - x * (0.2 - x * (1.0 / 6.0 - x * (
            1.0 / 7.0 - x * 0.125))))))
        return rinv * (dt * US) * iw0 * s
    return klog * math.log1p(x)


def pull_integral(lh, la, rinv, beta, klog, tu0, t_to, seg_t0, seg_inv_t):
    """∫ R⁻¹ ds from the pixel's last update ``tu0`` to ``t_to`` µs, or 0 where a censored frame's bound holds.

    A saturated code is a bound, not a value (``docs/reconstruct.md``, "Saturation as a bound"):
    the segment stores the bound's direction in ``klog`` with β = 0 (+1: L ≥ L^A, a clipped
    bright pixel; -1: L ≤ L^A, a clipped dark pixel; 0: an ordinary two-sided measurement). Where
    the state ``lh`` satisfies the bound the frame carries no information and the pull is off;
    where it violates it the ordinary update of eqs. 17 and 20 pulls it towards the bound, which
    it approaches monotonically without crossing, so testing at the start of the interval is
    exact for the whole interval (a projection onto the constraint; Simon 2010, Allik et al.
    2016). A bound moves L̂ but leaves P alone: it says nothing of how far above (below) it the
    intensity is, so P is not shrunk for a censored pixel (:func:`propagated`).
    """
    if beta == 0.0:
        if klog * (lh - la) > 0.0:
            return 0.0
        return rinv * ((t_to - tu0) * US)
    return rinv_integral(rinv, beta, klog, tu0, t_to, seg_t0, seg_inv_t)


def propagated(lh, pp, la, rinv, beta, klog, tu0, t_to, seg_t0, seg_inv_t):
    """(L̂, P) carried from ``tu0`` to ``t_to`` µs (eqs. 17, 20): g = P ∫R⁻¹, P ← P/(1+g),
    L̂ ← L^A + (L̂ - L^A)/(1+g); a censored pixel's P is held (a bound moves L̂, not P)."""
    integ = pull_integral(lh, la, rinv, beta, klog, tu0, t_to, seg_t0, seg_inv_t)
    d = 1.0 / (1.0 + pp * integ)
    lh = la + (lh - la) * d
    if beta != 0.0 or klog == 0.0:
        pp = pp * d
    return lh, pp


def akf_event_step(lh, pp, la, tu0, ti, dte, dtstar, positive, rinv, beta, klog, lastep, has_la_step, seg_t0,
                   seg_inv_t, jump_on, jump_off, s_proc, s_iso, s_ref, rho_us, noise_form):
    """One AKF event at time ``ti`` µs: the new (L̂, P, L^A) of the pixel (its update time becomes ``ti``).

    In order: propagate L̂ and P from the last update ``tu0`` (:func:`propagated`, eqs. 17, 20);
    add Q = Q_proc + Q_iso + Q_ref to P (eq. 21 with the Q of eq. 2 and §3.1.1); jump L̂ by
    ``jump_on`` (ON) or ``jump_off`` (OFF, negative) (eq. 15); with ``has_la_step`` (the
    measurement is event-driven, frame augmentation) move L^A by ``lastep`` (ON) or by
    -``lastep`` c_off/c_on (OFF: ``lastep`` is the calibrated ON step, the OFF step keeps the
    thresholds' ratio), or by the event's own jump where ``lastep`` is negative.

    ``dte = t_i - t_{i-1}`` (the pixel's previous event, or the filter's start) and
    ``dtstar = t_i - t*`` (t*: the latest event time in the 3×3 window before this event,
    the pixel included) are integer µs, computed by the caller's schedule. Q (``noise_form`` 0,
    paper §3.1.1): σ²_proc Δt_e + σ²_iso (t_i - t*) + σ²_ref·[Δt_e ≤ ρ]; ``noise_form`` 1
    (reference code): σ_p (t_i - tu) + σ_i (t_i - t*) + σ_r Δt_e·[Δt_e ≤ ρ].
    """
    tif = np.float64(ti)
    lhat, pp = propagated(lh, pp, la, rinv, beta, klog, tu0, tif, seg_t0, seg_inv_t)
    q = s_iso * (dtstar * US)
    if noise_form == 0:
        q += s_proc * (dte * US)
        if dte <= rho_us:
            q += s_ref
    else:
        q += s_proc * ((tif - tu0) * US)
        if dte <= rho_us:
            q += s_ref * (dte * US)
    jump = jump_on if positive else jump_off
    if has_la_step:
        if lastep < 0.0:  # L^A follows the event's own jump (frames carried forward by the events)
            la = la + jump
        elif positive:
            la = la + lastep
        else:  # the ON step times c_off/c_on (1 when symmetric: the same bits)
            la = la - lastep * ((-jump_off) / jump_on)
    return lhat + jump, pp + q, la


def akf_walk_pixel(S, pix, t, p, a, grp, g, hi, wb, te0, t_quiet, nb_pos, nb_hi, nb_te, n_nb, has_la_step,
                   seg_t0, seg_inv_t, jump_on, jump_off, s_proc, s_iso, s_ref, rho_us, noise_form):
    """Pixel ``pix``'s grouped events ``grp[g:hi]`` with stream index below ``wb``, in stream order,
    each by :func:`akf_event_step`; returns (the next position in ``grp``, the last event time).

    The pixel-parallel schedule (one thread per pixel, a group of event indices relative to ``a``
    per pixel, in stream order; the event at group position ``g`` is event ``a + grp[g]`` of ``t``
    and ``p``). ``te0``: the pixel's last event time before these events. The
    isolated-pixel term's t* at event i is the latest event time in the 3×3 window over the
    events before i in the stream: ``t_quiet`` folds in the neighbours without events here (their
    earlier last-event times, and ``te0``), and for the ``n_nb`` others ``nb_pos[k]`` /
    ``nb_hi[k]`` bound their groups' unread part and ``nb_te[k]`` holds the last time read: each
    neighbour's position only moves forward as the pixel's events come (a merge, O(events of p
    and q) per window where a binary search per event costs O(events of p × log events of q)).
    The state record is held in registers for the walk and stored once at the end.
    """
    sl = S[pix, A_L]
    sp = S[pix, A_P]
    sla = S[pix, A_LA]
    stu = S[pix, A_TU]
    rinv = S[pix, A_RINV]
    beta = S[pix, A_BETA]
    klog = S[pix, A_KLOG]
    lastep = S[pix, A_LASTEP]
    while g < hi:
        i = grp[g]
        if i >= wb:
            break
        e = a + i
        ti = t[e]
        tstar = te0 if te0 > t_quiet else t_quiet
        for k in range(n_nb):
            kk = nb_pos[k]
            hk = nb_hi[k]
            if kk < hk and grp[kk] < i:
                kk += 1
                while kk < hk and grp[kk] < i:
                    kk += 1
                nb_pos[k] = kk
                nb_te[k] = t[a + grp[kk - 1]]
            tq = nb_te[k]
            if tq > tstar:
                tstar = tq
        sl, sp, sla = akf_event_step(sl, sp, sla, stu, ti, ti - te0, ti - tstar, p[e] > 0, rinv, beta, klog,
                                     lastep, has_la_step, seg_t0, seg_inv_t, jump_on, jump_off, s_proc, s_iso,
                                     s_ref, rho_us, noise_form)
        stu = np.float64(ti)
        te0 = ti
        g += 1
    S[pix, A_L] = sl
    S[pix, A_P] = sp
    S[pix, A_LA] = sla
    S[pix, A_TU] = stu
    return g, te0


def window_neighbours(pix, height, width, glo, ghi, te_in, nb_pos, nb_hi, nb_te):
    """The 3×3 neighbours of ``pix`` (clipped at the border) for :func:`akf_walk_pixel` over one
    window grouped by pixel (pixel q's group is ``[glo[q], ghi[q])`` of the group array, empty for
    a pixel without events; ``te_in``: last event times before the window): returns ``(n_nb, t_quiet)``, the neighbours with events in the window
    listed in ``nb_*``, the others' times (and the pixel's own) folded into ``t_quiet``."""
    yy = pix // width
    xx = pix - yy * width
    ylo = max(yy - 1, 0)
    yhi = min(yy + 1, height - 1)
    xlo = max(xx - 1, 0)
    xhi = min(xx + 1, width - 1)
    n_nb = 0
    t_quiet = te_in[pix]
    for qy in range(ylo, yhi + 1):
        for qx in range(xlo, xhi + 1):
            q = qy * width + qx
            if q != pix:
                q_lo = glo[q]
                q_hi = ghi[q]
                if q_lo == q_hi:
                    if te_in[q] > t_quiet:
                        t_quiet = te_in[q]
                else:
                    nb_pos[n_nb] = q_lo
                    nb_hi[n_nb] = q_hi
                    nb_te[n_nb] = te_in[q]
                    n_nb += 1
    return n_nb, t_quiet


def inverse_mills(a):
    """λ(a) = φ(a) / (1 - Φ(a)) of the standard normal, for a >= 0 (the mean of N(0, 1) truncated
    to [a, ∞)); beyond a = 25 its asymptote a + 1/a (relative error < 1e-3 there, and the erfc
    form would underflow further out)."""
    if a > 25.0:
        return a + 1.0 / a
    return 0.7978845608028654 * math.exp(-0.5 * a * a) / math.erfc(a * 0.7071067811865476)


def frame_update(lh, pp, r_log, cz, lf):
    """Discrete Kalman update of one pixel with the just-loaded frame (continuous-discrete KF).

    The switch has added the process noise σ²_proc accrued since the pixel's last update to P
    (changes below the threshold that no event reported). The frame ``lf`` (log) is one
    measurement of L at τ_k with log variance ``r_log`` (eq. 9's R): gain κ = P/(P + R),
    L̂ ← L̂ + κ(lf - L̂), P ← (1 - κ)P. A censored frame (``cz`` ≠ 0: ``lf`` is a bound, the
    measurement z = L + v says only ``cz (z - lf) >= 0``) acts only where the state violates its
    bound, and there moves L̂ to the conditional mean given the bound (the Tobit Kalman filter's
    update, Allik et al., IEEE TCST 24(1), 2016): with s = √(P + R) and a = cz (lf - L̂)/s >= 0,
    ``L̂ ← L̂ + cz (P/s) λ(a)`` (:func:`inverse_mills`), which lies beyond the bound by
    ``(P/s)(λ(a) - a)`` (up to 0.8 P/s): the intensity of a clipped pixel is above the clip level,
    not at it. P is left alone as for the continuous pull (:func:`pull_integral`): a bound says
    little of how far beyond it the intensity is. Above :data:`TOBIT_MAX_P` the bound is taken
    as a plain measurement (projection towards it).
    """
    if cz * (lh - lf) > 0.0:
        return lh, pp
    if cz != 0.0:  # the Tobit update: the mean of the state given the bound; P unchanged
        sd = math.sqrt(pp + r_log)
        if sd > 0.0 and pp < TOBIT_MAX_P:
            return lh + cz * (pp / sd) * inverse_mills(cz * (lf - lh) / sd), pp
        return lh + pp / (pp + r_log) * (lf - lh), pp
    g = pp / (pp + r_log)
    return lh + g * (lf - lh), pp - g * pp


def akf_switch_pixel(S, pix, propagate, seg_t0, seg_inv_t, t_to, s_proc, la, r, b, cz, lastep, seg_t_s, discrete,
                     uf):
    """Frame switch of pixel ``pix``: propagate, then load the new segment (see :func:`akf_switch`).

    When ``propagate``, the pixel is carried to ``t_to`` µs under the current segment
    (:func:`propagated`), ``s_proc`` times the time since its last update is added to P, and
    ``tu = t_to``. Then L^A = ``la``, 1/R = ``r``, β = ``b``, ``klog = r T / β`` (β ≠ 0, T =
    ``seg_t_s``) else the censoring direction ``cz``, the L^A step ``lastep``; with
    ``discrete``, the frame ``uf`` (log) is applied as one measurement (:func:`frame_update`).
    """
    if propagate:
        tu0 = S[pix, A_TU]
        q = s_proc * ((t_to - tu0) * US)
        lh, pp = propagated(S[pix, A_L], S[pix, A_P], S[pix, A_LA], S[pix, A_RINV], S[pix, A_BETA], S[pix, A_KLOG],
                            tu0, t_to, seg_t0, seg_inv_t)
        S[pix, A_L] = lh
        S[pix, A_P] = pp + q
        S[pix, A_TU] = t_to
    S[pix, A_LA] = la
    S[pix, A_RINV] = r
    S[pix, A_BETA] = b
    S[pix, A_KLOG] = r * seg_t_s / b if b != 0.0 else cz
    S[pix, A_LASTEP] = lastep
    if discrete:
        lh, pp = frame_update(S[pix, A_L], S[pix, A_P], 1.0 / r, cz, uf)
        S[pix, A_L] = lh
        S[pix, A_P] = pp

def akf_switch_arrays_pixel(S, pix, propagate, seg_t0, seg_inv_t, t_to, s_proc, log_frame, rinv, beta, la_step,
                            censor, update_frame, seg_t_s, discrete, has_beta, has_step, has_cens, has_uf):
    """:func:`akf_switch_pixel` with the new segment read from per-pixel arrays (:func:`akf_switch`):
    β is 0 where the frame is censored; an empty array (its ``has_*`` false) reads as zeros, and
    the discrete update uses ``update_frame`` where given, else ``log_frame``."""
    lf = log_frame[pix]
    b = beta[pix] if has_beta else 0.0
    cz = censor[pix] if has_cens else 0.0
    if cz != 0.0:
        b = 0.0
    akf_switch_pixel(S, pix, propagate, seg_t0, seg_inv_t, t_to, s_proc, lf, rinv[pix], b, cz,
                     la_step[pix] if has_step else 0.0, seg_t_s, discrete, update_frame[pix] if has_uf else lf)


def akf_switch_codes_pixel(S, pix, propagate, seg_t0, seg_inv_t, t_to, s_proc, code, code_next, max_code, rbar_l,
                           logf_l, rinv_l, cens_l, la_step, seg_t_s, discrete, has_beta, has_cens):
    """:func:`akf_switch_pixel` with the new segment looked up from the pixel's clipped code in
    per-code tables (:func:`akf_switch_lut`): β = R̄(code_next)/R̄(code) - 1 of eq. 7, 0 where
    either frame is censored."""
    c = min(max(np.int64(code[pix]), 0), max_code)
    lf = logf_l[c]
    cz = cens_l[c] if has_cens else 0.0
    b = 0.0
    if has_beta and cz == 0.0:
        c1 = min(max(np.int64(code_next[pix]), 0), max_code)
        if not (has_cens and cens_l[c1] != 0.0):
            b = rbar_l[c1] / rbar_l[c] - 1.0
    akf_switch_pixel(S, pix, propagate, seg_t0, seg_inv_t, t_to, s_proc, lf, rinv_l[c], b, cz, la_step, seg_t_s,
                     discrete, lf)


def akf_initial_covariance(la, beta, klog, p0, p_cens, has_off, log_off):
    """P of a pixel initialised from the first frame (:func:`akf_start`): ``p0``; clipped in that
    frame (β = 0, ``klog`` ≠ 0) ``p_cens``, and clipped dark (``klog`` < 0, ``has_off``)
    max(w², ``p0``) with w = L^A - ``log_off`` (the interval ln I0 <= L <= L^A as one standard
    deviation; NaN as np.maximum gives it)."""
    pp = p0
    if beta == 0.0 and klog != 0.0:
        pp = p_cens
        if has_off and klog < 0.0:
            w = la - log_off
            ww = w * w
            pp = p0 if ww < p0 else ww
    return pp


def output_pixel(lh, pp, la, rinv, beta, kl, tu0, t_out, seg_t0, seg_inv_t):
    """(L̂, P) at ``t_out`` µs in closed form (eqs. 17, 20), the state unchanged; P of a censored
    pixel is its held P (a bound moves L̂, not P).

    The values of :func:`propagated`, arranged for the output loops: for R held (β = 0, most
    pixels) whether a bound holds is a select rather than a branch (data dependent: its
    mispredictions cost more than the product), 20-25 % less time per 346x260 image. Same bits.
    """
    held = rinv * ((t_out - tu0) * US)
    integ = 0.0 if kl * (lh - la) > 0.0 else held
    if beta != 0.0:
        integ = rinv_integral(rinv, beta, kl, tu0, t_out, seg_t0, seg_inv_t)
    d = 1.0 / (1.0 + pp * integ)
    cens = (beta == 0.0) & (kl != 0.0)
    return la + (lh - la) * d, (pp if cens else pp * d)

def akf_output_store(S, pix, seg_t0, seg_inv_t, t_out, out_l32, out_log, out_var, want_log, want_var):
    """:func:`output_pixel` of record ``pix`` of ``S`` into ``out_l32`` (L̂ rounded to float32) and,
    when wanted, ``out_log`` (L̂) and ``out_var`` (P)."""
    lhat, pv = output_pixel(S[pix, A_L], S[pix, A_P], S[pix, A_LA], S[pix, A_RINV], S[pix, A_BETA], S[pix, A_KLOG],
                            S[pix, A_TU], t_out, seg_t0, seg_inv_t)
    out_l32[pix] = np.float32(lhat)
    if want_log:
        out_log[pix] = lhat
    if want_var:
        out_var[pix] = pv



def cf_decayed(lh, lf, alpha, tu0, t, extra):
    """CF estimate at ``t`` µs: L^F + (L̂ - L^F) exp(-α (t - tu) - ``extra``), exact for a held
    L^F (Scheerlinck et al. 2018; ``extra``: the high-pass variant's per-event decay, else 0)."""
    return lf + (lh - lf) * math.exp(-alpha * ((t - tu0) * US) - extra)


def cf_event_step(lh, lf, alpha, tu0, tif, positive, j_on, j_off, event_decay):
    """CF at an event at ``tif`` µs: the exact decay towards L^F, then the jump +``j_on`` or -``j_off``."""
    lhat = cf_decayed(lh, lf, alpha, tu0, tif, event_decay)
    return lhat + j_on if positive else lhat - j_off


#: the functions above, in an order in which each calls only earlier ones
PIXEL_FUNCTIONS = (rinv_integral, pull_integral, propagated, akf_event_step, akf_walk_pixel, window_neighbours,
                   inverse_mills, frame_update, akf_switch_pixel, akf_switch_arrays_pixel,
                   akf_switch_codes_pixel, akf_initial_covariance, output_pixel, akf_output_store, cf_decayed,
                   cf_event_step)


def compile_pixel_functions(jit) -> dict:
    """``{name: jit(function)}`` for :data:`PIXEL_FUNCTIONS`, each calling the others' ``jit``
    versions: copies of the plain functions whose globals are this module's with those names
    rebound (the CUDA kernels' device functions: ``compile_pixel_functions(cuda.jit(device=True))``)."""
    ns = dict(globals())
    out = {}
    for f in PIXEL_FUNCTIONS:
        g = types.FunctionType(f.__code__, ns, f.__name__, f.__defaults__, f.__closure__)
        g.__doc__, g.__qualname__ = f.__doc__, f.__qualname__
        out[f.__name__] = ns[f.__name__] = jit(g)
    return out


_cpu_inline = njit(cache=True, nogil=True, inline="always")
rinv_integral = _cpu_inline(rinv_integral)
pull_integral = _cpu_inline(pull_integral)
propagated = _cpu_inline(propagated)
akf_event_step = _cpu_inline(akf_event_step)
akf_walk_pixel = _cpu_inline(akf_walk_pixel)
window_neighbours = _cpu_inline(window_neighbours)
inverse_mills = _cpu_inline(inverse_mills)
frame_update = _cpu_inline(frame_update)
akf_switch_pixel = _cpu_inline(akf_switch_pixel)
akf_switch_arrays_pixel = _cpu_inline(akf_switch_arrays_pixel)
akf_switch_codes_pixel = _cpu_inline(akf_switch_codes_pixel)
akf_initial_covariance = _cpu_inline(akf_initial_covariance)
output_pixel = _cpu_inline(output_pixel)
akf_output_store = _cpu_inline(akf_output_store)
cf_decayed = _cpu_inline(cf_decayed)
cf_event_step = _cpu_inline(cf_event_step)


@njit(cache=True, nogil=True)
def band_select(y, i0, i1, row_lo, row_hi, out):
    """Indices (relative to ``i0``) of the events ``[i0, i1)`` whose row lies in ``[row_lo, row_hi)``.

    Writes them, in order, to ``out`` (int32, at least ``i1 - i0`` long) and returns their count.
    Branch-free (one store per event, the count advances only on a match), so it runs at memory
    speed whatever the band layout. Used by the row-band parallel filters: each worker selects
    its band (plus ghost rows for the AKF) and processes only those events.
    """
    m = 0
    for i in range(i0, i1):
        yy = np.int64(y[i])
        out[m] = np.int32(i - i0)
        m += np.int64((yy >= row_lo) & (yy < row_hi))
    return m


@njit(cache=True, nogil=True)
def band_split(y, i0, j0, j1, row_lo, row_hi, out, counts):
    """:func:`band_select` for every band at once, over a part ``[j0, j1)`` of a batch.

    For each band ``b``, the indices (relative to ``i0``, the batch start) of the part's events
    whose row lies in ``[row_lo[b], row_hi[b])`` are written in order to ``out[b]`` (int32, each
    row at least ``j1 - j0`` long) and their count to ``counts[b]``. Branch-free like
    :func:`band_select`. The parallel AKF splits a batch into one part per worker, each worker
    splits its part for all bands, and each band then reads the parts in order: every event's
    row is read once in all, not once per band.
    """
    nb = row_lo.shape[0]
    if nb == 2:  # the common case, with the counters in registers
        lo0, hi0, lo1, hi1 = np.int64(row_lo[0]), np.int64(row_hi[0]), np.int64(row_lo[1]), np.int64(row_hi[1])
        m0 = 0
        m1 = 0
        for i in range(j0, j1):
            yy = np.int64(y[i])
            r = np.int32(i - i0)
            out[0, m0] = r
            out[1, m1] = r
            m0 += np.int64((yy >= lo0) & (yy < hi0))
            m1 += np.int64((yy >= lo1) & (yy < hi1))
        counts[0] = m0
        counts[1] = m1
        return j1 - j0
    for b in range(nb):
        counts[b] = 0
    for i in range(j0, j1):
        yy = np.int64(y[i])
        r = np.int32(i - i0)
        for b in range(nb):
            out[b, counts[b]] = r
            counts[b] += np.int64((yy >= row_lo[b]) & (yy < row_hi[b]))
    return j1 - j0


@njit(cache=True, nogil=True)
def band_split_lut(y, i0, j0, j1, band_of_row, edge_of_row, out, counts):
    """:func:`band_split` by table look-up, for many bands: the same lists in the same order.

    ``band_of_row[r]`` is the band owning row ``r``; ``edge_of_row[r]`` has bit 1 when row ``r``
    is also the ghost row of the band before (its ``hi``) and bit 2 when it is the ghost row of
    the band after (its ``lo - 1``). Each event is appended to its band's list and, in the rare
    edge rows, to its neighbour's: a few operations per event whatever the number of bands,
    where :func:`band_split` tests every band (a worker's share of the split then stops
    shrinking as workers are added: ``nb`` tests for each of its ``1/nb`` of the events).
    """
    nb = counts.shape[0]
    for b in range(nb):
        counts[b] = 0
    for i in range(j0, j1):
        yy = np.int64(y[i])
        b = np.int64(band_of_row[yy])
        r = np.int32(i - i0)
        e = edge_of_row[yy]
        if e & 1:  # the band before reads this row as its ghost row hi
            out[b - 1, counts[b - 1]] = r
            counts[b - 1] += 1
        out[b, counts[b]] = r
        counts[b] += 1
        if e & 2:
            out[b + 1, counts[b + 1]] = r
            counts[b + 1] += 1
    return j1 - j0


@njit(cache=True, nogil=True)
def row_histogram(y, i0, i1, step, hist):
    """Count the rows of every ``step``-th event of ``[i0, i1)`` into ``hist`` (zeroed first).

    Rows at or past ``hist``'s length are not counted. Used to balance the row bands.
    """
    hist[:] = 0
    h = np.uint64(hist.shape[0])
    for i in range(i0, i1, step):
        yy = np.uint64(y[i])
        if yy < h:
            hist[yy] += 1
    return hist


@njit(cache=True, nogil=True, inline="always")
def _akf_event(S, te, te_base, pix, tp, wp, ti, positive, has_la_step, seg_t0, seg_inv_t,
               c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, has_px):
    """One AKF event at pixel ``pix`` (padded index ``tp``, padded width ``wp``), time ``ti`` µs:
    :func:`akf_event_step` with t* from the 3×3 window of ``te``. See :func:`akf_events`.

    Indices are unsigned (no negative-index wraparound code) and ``te`` is padded by one pixel on
    every side, so the 3×3 window needs no border branch. ``te`` holds times relative to
    ``te_base`` µs; every use is a difference of two times, taken in int64, so an int32 ``te``
    gives the int64 one's bits wherever its values fit.
    """
    tr = ti - te_base  # relative to te's origin
    te0 = np.int64(te[tp])
    b = tp - wp
    c = tp + wp
    tstar = max(max(max(te[b - ONE], te[b]), max(te[b + ONE], te[tp - ONE])),
                max(max(te0, te[tp + ONE]), max(max(te[c - ONE], te[c]), te[c + ONE])))
    jump_on = con_px[pix] if has_px else c_on
    jump_off = -(coff_px[pix] if has_px else c_off)
    lh, pp, la = akf_event_step(S[pix, A_L], S[pix, A_P], S[pix, A_LA], S[pix, A_TU], ti, tr - te0, tr - tstar,
                                positive, S[pix, A_RINV], S[pix, A_BETA], S[pix, A_KLOG], S[pix, A_LASTEP],
                                has_la_step, seg_t0, seg_inv_t, jump_on, jump_off, s_proc, s_iso, s_ref, rho_us,
                                noise_form)
    S[pix, A_L] = lh
    S[pix, A_P] = pp
    if has_la_step:
        S[pix, A_LA] = la
    S[pix, A_TU] = np.float64(ti)
    te[tp] = tr


@njit(cache=True, nogil=True)
def akf_start(S, p0, p_cens, log_off, has_off, t_init, pix_lo, pix_hi):
    """Initialise pixels ``[pix_lo, pix_hi)`` from the loaded first frame (``AKFEngine.start``):
    L̂ = L^A, P = ``p0``, tu = ``t_init``; a pixel clipped in that frame (β = 0, ``A_KLOG`` ≠ 0)
    P = ``p_cens``, and a clipped dark one (``A_KLOG`` < 0, ``has_off``) P = max(w², ``p0``)
    with w = L^A - ``log_off`` (the interval ln I0 <= L <= L^A as one standard deviation).
    The numpy column operations it replaces, in one pass per row band: the same bits."""
    for pix in range(pix_lo, pix_hi):
        S[pix, A_L] = S[pix, A_LA]
        S[pix, A_P] = akf_initial_covariance(S[pix, A_LA], S[pix, A_BETA], S[pix, A_KLOG], p0, p_cens, has_off,
                                             log_off)
        S[pix, A_TU] = t_init
    return pix_hi - pix_lo


@njit(cache=True, nogil=True)
def reverse_columns(t, x, y, p, m1, i0, i1, rt, rx, ry, rp):
    """Events ``[i0, i1)`` reversed into ``rt, rx, ry, rp`` at ``n - 1 - i``: time ``m1 - t``,
    polarity negated (the two-sided filter's backward pass, :func:`..smoother.reverse_events`)."""
    n = t.shape[0]
    for i in range(i0, i1):
        j = n - 1 - i
        rt[j] = m1 - t[i]
        rx[j] = x[i]
        ry[j] = y[i]
        rp[j] = -p[i]
    return i1 - i0


def padded_te(height: int, width: int, t_init: int, dtype=np.int64) -> np.ndarray:
    """Last-event times for the AKF kernels: ``(height + 2) * (width + 2)``, all ``t_init``.

    ``dtype`` int64 (times as they are, ``te_base = 0``) or int32 (times relative to a
    ``te_base`` the caller keeps within int32 range of every value: half the bytes, so the 3×3
    windows of a 1280x720 sensor miss the caches less; see ``AKFEngine._te_fit``).

    Pixel (y, x) lives at ``(y + 1) * (width + 2) + x + 1`` (see :func:`te_view`). The one-pixel
    border is never written and holds the start time, which no in-sensor time is below, so the
    3×3 maximum over the padded window equals the maximum over the window clipped at the border.
    """
    if t_init == 0:  # pages mapped on first touch: by the worker that zeroes or fills its own array
        return np.zeros((height + 2) * (width + 2), dtype=dtype)
    return np.full((height + 2) * (width + 2), t_init, dtype=dtype)


def te_view(te: np.ndarray, height: int, width: int) -> np.ndarray:
    """The in-sensor (height, width) view of a :func:`padded_te` array."""
    return te.reshape(height + 2, width + 2)[1:-1, 1:-1]


@njit(cache=True, nogil=True, inline="always")
def _akf_prefetch(S, te, y, x, w, wp, con_px, coff_px, has_px):
    """Prefetch what :func:`_akf_event` will touch for the event at (``y``, ``x``): the pixel's
    record and the three rows of its padded 3×3 ``te`` window (and its thresholds)."""
    yy = np.uint64(y)
    xx = np.uint64(x)
    pix = yy * w + xx
    prefetch(S, pix * np.uint64(AKF_FIELDS))
    tq = (yy + ONE) * wp + xx + ONE
    prefetch(te, tq - wp)
    prefetch(te, tq)
    prefetch(te, tq + wp)
    if has_px:
        prefetch(con_px, pix)
        prefetch(coff_px, pix)


@njit(cache=True, nogil=True, inline="always")
def _akf_scan(t, x, y, p, i0, i1, row_lo, row_hi, width, S, te, te_base, has_la_step, seg_t0, seg_inv_t, c_on,
              c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, has_px):
    n = 0
    w = np.uint64(width)
    wp = w + ONE + ONE
    lo = np.uint64(max(row_lo, 0))
    hi = np.uint64(max(row_hi, 0))
    for i in range(i0, i1):
        if i + PREFETCH_AHEAD < i1:
            _akf_prefetch(S, te, y[i + PREFETCH_AHEAD], x[i + PREFETCH_AHEAD], w, wp, con_px, coff_px, has_px)
        yy = np.uint64(y[i])
        xx = np.uint64(x[i])
        tp = (yy + ONE) * wp + xx + ONE
        if yy < lo or yy >= hi:
            if yy + ONE == lo or yy == hi:  # ghost row: neighbour time only
                te[tp] = t[i] - te_base
            continue
        _akf_event(S, te, te_base, yy * w + xx, tp, wp, t[i], p[i] > 0, has_la_step, seg_t0,
                   seg_inv_t, c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, has_px)
        n += 1
    return n


@njit(cache=True, nogil=True)
def akf_events(t, x, y, p, i0, i1, row_lo, row_hi, width, height, S, te, te_base, has_la_step,
               seg_t0, seg_inv_t, c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px):
    """AKF update at each event (eqs. 15, 17, 20, 21 with the Q of eq. 2 and §3.1.1).

    For the event at pixel p and time t_i, in order: propagate L̂ and P from the last update
    ``tu`` with the stable closed forms of eqs. 17 and 20 (g = P ∫R⁻¹; P ← P/(1+g);
    L̂ ← L^A + (L̂ - L^A)/(1+g)); add Q = Q_proc + Q_iso + Q_ref to P (eq. 21); jump L̂ by
    +c_on or -c_off (eq. 15); set ``tu = te = t_i``; when the measurement is event-driven
    (``has_la_step``, frame augmentation), move L^A by +``la_step`` (ON) or by
    -``la_step`` c_off/c_on (OFF: ``la_step`` is the calibrated ON step, the OFF step keeps the
    thresholds' ratio).

    Q (``noise_form`` 0, paper §3.1.1): σ²_proc (t_i - t_{i-1}) + σ²_iso (t_i - t*) + σ²_ref·[t_i -
    t_{i-1} ≤ ρ]; ``noise_form`` 1 (reference code): σ_p (t_i - tu) + σ_i (t_i - t*) +
    σ_r (t_i - t_{i-1})·[t_i - t_{i-1} ≤ ρ]. t* is the latest event time in the 3×3 window
    including p (clipped at the border); t_{i-1} starts at the filter's start time. ``te`` is
    the padded last-event-time array of :func:`padded_te`, its times relative to ``te_base`` µs
    (0 for absolute int64 times; the kernel stores ``t_i - te_base``, which must fit ``te``).
    ``con_px``/``coff_px`` (flattened, or empty for the scalars ``c_on``/``c_off``) are per-pixel
    ON and OFF thresholds. A negative ``la_step`` makes L^A follow each event's own jump.

    Processes the events ``[i0, i1)``; events in the ghost rows ``row_lo - 1`` and ``row_hi``
    only set ``te`` and all other rows outside ``[row_lo, row_hi)`` are skipped (``0, height``
    is the serial filter). Returns the number of events applied to pixels of the band.
    """
    if con_px.shape[0] > 0:  # two inlined copies, each with has_px a constant LLVM folds away
        return _akf_scan(t, x, y, p, i0, i1, row_lo, row_hi, width, S, te, te_base, has_la_step, seg_t0, seg_inv_t,
                         c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, True)
    return _akf_scan(t, x, y, p, i0, i1, row_lo, row_hi, width, S, te, te_base, has_la_step, seg_t0, seg_inv_t,
                     c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, False)


@njit(cache=True, nogil=True, inline="always")
def _akf_indexed(t, x, y, p, i0, idx, m, row_lo, row_hi, width, S, te, te_base, has_la_step, seg_t0, seg_inv_t, c_on,
                 c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, has_px):
    n = 0
    w = np.uint64(width)
    wp = w + ONE + ONE
    lo = np.uint64(max(row_lo, 0))
    hi = np.uint64(max(row_hi, 0))
    for k in range(m):
        if k + PREFETCH_AHEAD < m:
            j = i0 + np.int64(idx[k + PREFETCH_AHEAD])
            _akf_prefetch(S, te, y[j], x[j], w, wp, con_px, coff_px, has_px)
        i = i0 + np.int64(idx[k])
        yy = np.uint64(y[i])
        xx = np.uint64(x[i])
        tp = (yy + ONE) * wp + xx + ONE
        if yy < lo or yy >= hi:  # ghost row
            te[tp] = t[i] - te_base
            continue
        _akf_event(S, te, te_base, yy * w + xx, tp, wp, t[i], p[i] > 0, has_la_step, seg_t0,
                   seg_inv_t, c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, has_px)
        n += 1
    return n


@njit(cache=True, nogil=True)
def akf_events_indexed(t, x, y, p, i0, idx, m, row_lo, row_hi, width, height, S, te, te_base, has_la_step,
                       seg_t0, seg_inv_t, c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px,
                       coff_px):
    """:func:`akf_events` over the events ``i0 + idx[:m]`` (from :func:`band_select`).

    ``idx`` selects the band's rows ``[row_lo - 1, row_hi + 1)``: the ghost rows ``row_lo - 1``
    and ``row_hi`` only set ``te``. The arithmetic per event is that of the serial kernel, so
    disjoint bands with private ``te`` arrays reproduce it bit for bit.
    """
    if con_px.shape[0] > 0:
        return _akf_indexed(t, x, y, p, i0, idx, m, row_lo, row_hi, width, S, te, te_base, has_la_step, seg_t0,
                            seg_inv_t, c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, True)
    return _akf_indexed(t, x, y, p, i0, idx, m, row_lo, row_hi, width, S, te, te_base, has_la_step, seg_t0, seg_inv_t,
                        c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, False)


@njit(cache=True, nogil=True)
def akf_switch(S, propagate, seg_t0, seg_inv_t, t_to, log_frame, rinv, beta, la_step, censor, seg_t_s,
               discrete, s_proc, update_frame, pix_lo, pix_hi):
    """Frame switch of pixels ``[pix_lo, pix_hi)`` in one pass: propagate, then load the new segment.

    When ``propagate``, each pixel is first carried to ``t_to`` µs under the current segment
    (eqs. 17, 20; ``seg_t0``/``seg_inv_t`` are the current segment's) and ``tu = t_to``; this is
    done only where L^A or R changes, never at output times. Then the new segment is loaded:
    L^A = ``log_frame``, 1/R = ``rinv``, β = ``beta`` and ``klog = rinv T / β`` (β ≠ 0; 0
    otherwise) of :func:`rinv_integral`, with ``T = seg_t_s`` the new segment's length in s.
    Pass ``seg_t_s = 0`` for an open-ended segment (β is then stored as 0: R held), and empty
    ``beta`` / ``la_step`` / ``censor`` arrays for zeros. ``censor`` is +1 where ``log_frame`` is
    a lower bound (clipped bright), -1 where it is an upper bound (clipped dark), 0 otherwise;
    a censored pixel holds R (β = 0) and keeps the direction in ``klog`` (:func:`pull_integral`).
    A propagating switch adds ``s_proc`` (log²/s) times the time since the pixel's last update
    to P (0: the paper's model, process noise at events only). With ``discrete``, the loaded
    frame is then applied as one discrete measurement (:func:`frame_update`, R = 1/``rinv``):
    the log frame ``update_frame`` when not empty (the plain frame under an augmented L^A),
    else ``log_frame``.
    """
    has_beta = beta.shape[0] > 0 and seg_t_s > 0.0
    has_step = la_step.shape[0] > 0
    has_cens = censor.shape[0] > 0
    has_uf = update_frame.shape[0] > 0
    for pix in range(pix_lo, pix_hi):
        akf_switch_arrays_pixel(S, pix, propagate, seg_t0, seg_inv_t, t_to, s_proc, log_frame, rinv, beta, la_step,
                                censor, update_frame, seg_t_s, discrete, has_beta, has_step, has_cens, has_uf)
    return pix_hi - pix_lo


@njit(cache=True, nogil=True)
def akf_switch_lut(S, propagate, seg_t0, seg_inv_t, t_to, code, code_next, max_code, rbar_l, logf_l,
                   rinv_l, cens_l, la_step, seg_t_s, discrete, s_proc, pix_lo, pix_hi):
    """:func:`akf_switch` with the new segment built from pixel codes and per-code tables.

    Loads exactly what :func:`lut_segment` followed by :func:`akf_switch` would (L^F of eq. 8,
    1/R of eq. 9, β of eq. 7 from ``code_next``, or 0 when it is empty or ``seg_t_s = 0``; no
    L^A step), without the intermediate per-pixel arrays, so a row band builds its own part of
    the measurement in the same pass as its propagation. ``cens_l`` is the per-code censoring
    direction (+1, -1 or 0, see :func:`akf_switch`; empty: none); β is 0 where frame k or k+1
    is censored (R̄ is not interpolated towards or away from a bound). ``la_step`` is one L^A
    step per event for every pixel (0: zero-order hold; the nominal threshold: the causal
    forward interpolation of eq. 10 from the frame itself).
    """
    has_beta = code_next.shape[0] > 0 and seg_t_s > 0.0
    has_cens = cens_l.shape[0] > 0
    for pix in range(pix_lo, pix_hi):
        akf_switch_codes_pixel(S, pix, propagate, seg_t0, seg_inv_t, t_to, s_proc, code, code_next, max_code, rbar_l,
                               logf_l, rinv_l, cens_l, la_step, seg_t_s, discrete, has_beta, has_cens)
    return pix_hi - pix_lo


@njit(cache=True, nogil=True, inline="always")
def _output_pixel(S, pix, seg_t0, seg_inv_t, t_out):
    """:func:`output_pixel` of record ``pix`` of ``S``."""
    return output_pixel(S[pix, A_L], S[pix, A_P], S[pix, A_LA], S[pix, A_RINV], S[pix, A_BETA], S[pix, A_KLOG],
                        S[pix, A_TU], t_out, seg_t0, seg_inv_t)


@njit(cache=True, nogil=True)
def akf_output(S, seg_t0, seg_inv_t, t_out, out_l32, out_log, out_var, pix_lo, pix_hi):
    """State at ``t_out`` µs in closed form (eqs. 17, 20) without changing it.

    Writes L̂ rounded to float32 into ``out_l32`` (the caller turns it into linear intensity
    with one vectorised single-precision ``exp(L̂) - offset`` pass, :func:`log_to_linear`: a
    scalar ``exp`` call per pixel cost more than the rest of this loop) and, when they have the
    full size, L̂ into ``out_log`` and P into ``out_var`` (float64; pass empty arrays to skip).
    """
    want_log = out_log.shape[0] > 0
    want_var = out_var.shape[0] > 0
    for pix in range(pix_lo, pix_hi):
        akf_output_store(S, pix, seg_t0, seg_inv_t, t_out, out_l32, out_log, out_var, want_log, want_var)
    return pix_hi - pix_lo


#: Floor of every linear output, in frame-linear units (1 = the frame camera's clip level): a
#: millionth of the clip level, 120 dB below it, under any sensor's noise floor. Estimates
#: below it (or NaN) are clamped to it and counted (``Video.info["n_clamped"]``), so no method
#: writes a non-positive or NaN intensity and the clamp never hides a defect.
MIN_INTENSITY = 1e-6


def clamp_linear(a: np.ndarray, floor: float = MIN_INTENSITY) -> int:
    """In place: raise values below ``floor`` (default :data:`MIN_INTENSITY`) and NaN to it;
    return how many."""
    bad = ~(a >= np.float32(floor))
    n = int(np.count_nonzero(bad))
    if n:
        a[bad] = np.float32(floor)
    return n


@njit(cache=True, nogil=True)
def akf_output_state32(S, seg_t0, seg_inv_t, t_out, out_l, out_p, pix_lo, pix_hi):
    """L̂ and P at ``t_out`` µs in closed form (eqs. 17, 20), rounded to float32, without changing
    the state: the two-sided filter's per-pass estimates (:mod:`..smoother`). P of a censored
    pixel is its held P, as :func:`akf_output`."""
    for pix in range(pix_lo, pix_hi):
        lhat, pv = _output_pixel(S, pix, seg_t0, seg_inv_t, t_out)
        out_l[pix] = np.float32(lhat)
        out_p[pix] = np.float32(pv)
    return pix_hi - pix_lo


@njit(cache=True, nogil=True, error_model="numpy")
def fuse_log32(l_f, p_f, l_b, p_b, out):
    """Two-filter fusion per pixel into float32 ``out``: ``L̂ = (L_f P_b + L_b P_f)/(P_f + P_b)``.

    Computed in float64 from the float32 pass estimates (exactly symmetric in the two passes),
    then rounded to float32, as the forward filter rounds L̂ before its exp
    (:func:`akf_output`): a pixel both passes give the same (L, P) fuses to that L's bits. The
    division has no per-pixel zero check (``error_model="numpy"``: a branch out of the loop would
    stop LLVM vectorising it); a zero ``P_f + P_b`` is counted in the loop and raises
    ZeroDivisionError after it, as a checked division would.
    """
    n_zero = 0
    for i in range(out.shape[0]):
        pf = np.float64(p_f[i])
        pb = np.float64(p_b[i])
        den = pf + pb
        n_zero += den == 0.0
        out[i] = np.float32((np.float64(l_f[i]) * pb + np.float64(l_b[i]) * pf) / den)
    if n_zero:
        raise ZeroDivisionError("fuse_log32: P_f + P_b is 0")
    return out.shape[0]


def fuse_to_linear(l_f, p_f, l_b, p_b, offset, floor, out) -> int:
    """Two-filter fusion, then ``exp(L̂) - offset`` clamped at ``floor``, into float32 ``out``;
    returns the number of clamped pixels.

    :func:`fuse_log32` (the weighting, vectorised by LLVM), then the forward filter's own
    :func:`log_to_linear` (numpy's vectorised float32 ``exp``) and :func:`clamp_linear`, so a
    fused output and a forward output of the same L̂ have the same bits. A scalar float64 ``exp`` per pixel took 3.6x as long at 346x260
    (0.64 vs 0.2 ms per image); the float32 exp's relative error, a few 1e-7, is the output's
    own precision.
    """
    fuse_log32(l_f, p_f, l_b, p_b, out)
    log_to_linear(out, offset)
    return clamp_linear(out, floor)


def log_to_linear(a: np.ndarray, offset: float) -> np.ndarray:
    """In place: float32 log intensity ``a`` -> ``exp(a) - offset``, in single precision (the
    driver then clamps every method's output with :func:`clamp_linear`).

    numpy's float32 ``exp`` is vectorised (a relative error of a few 1e-7, the output's own
    precision); L̂ was rounded to float32 first, a relative error below 1e-6 for |L̂| < 8.
    """
    np.exp(a, out=a)
    a -= np.float32(offset)
    return a


@njit(cache=True, nogil=True)
def lut_segment(code, code_next, max_code, inten_l, rbar_l, logf_l, rinv_l, cens_l, log_frame, intensity, rinv,
                beta):
    """A frame's measurement from per-code tables, in one pass (see ``FrameMeasurements.segment``).

    Codes are clipped to ``[0, max_code]``. Writes L^F (eq. 8), I (eq. 3), 1/R (eq. 9) and, when
    ``code_next`` is not empty, β = R̄(code_next)/R̄(code) - 1 of eq. 7 (zeros otherwise, and
    where either code is censored by ``cens_l``; empty ``cens_l``: none is).
    """
    n = code.shape[0]
    has_next = code_next.shape[0] > 0
    has_cens = cens_l.shape[0] > 0
    for i in range(n):
        c = min(max(np.int64(code[i]), 0), max_code)
        log_frame[i] = logf_l[c]
        intensity[i] = inten_l[c]
        rinv[i] = rinv_l[c]
        beta[i] = 0.0
        if has_next:
            c1 = min(max(np.int64(code_next[i]), 0), max_code)
            if not (has_cens and (cens_l[c] != 0.0 or cens_l[c1] != 0.0)):
                beta[i] = rbar_l[c1] / rbar_l[c] - 1.0
    return n


@njit(cache=True, nogil=True, inline="always")
def _cf_update(C, pix, tif, pol, c_on, c_off, event_decay, con_px, coff_px, has_px):
    """One CF event at pixel ``pix``, time ``tif`` µs: exact decay towards L^F, then the jump."""
    C[pix, C_L] = cf_event_step(C[pix, C_L], C[pix, C_LF], C[pix, C_ALPHA], C[pix, C_TU], tif, pol > 0,
                                con_px[pix] if has_px else c_on, coff_px[pix] if has_px else c_off, event_decay)
    C[pix, C_TU] = tif


@njit(cache=True, nogil=True)
def cf_events(t, x, y, p, i0, i1, row_lo, row_hi, width, C, c_on, c_off, event_decay, con_px, coff_px):
    """Complementary filter per event (Scheerlinck et al. 2018): dL̂/dt = e - α(L̂ - L^F).

    Between events L̂ = L^F + (L̂_u - L^F) exp(-α Δt) (exact for a held L^F); at an event the
    deviation is further scaled by exp(-event_decay) (the per-event decay of the high-pass
    variant; 0 for CF) and L̂ jumps by +c_on or -c_off.
    """
    if con_px.shape[0] > 0:  # two inlined copies, each with has_px a constant
        return _cf_scan(t, x, y, p, i0, i1, row_lo, row_hi, width, C, c_on, c_off, event_decay, con_px, coff_px,
                        True)
    return _cf_scan(t, x, y, p, i0, i1, row_lo, row_hi, width, C, c_on, c_off, event_decay, con_px, coff_px, False)


@njit(cache=True, nogil=True, inline="always")
def _cf_scan(t, x, y, p, i0, i1, row_lo, row_hi, width, C, c_on, c_off, event_decay, con_px, coff_px, has_px):
    n = 0
    for i in range(i0, i1):
        if i + PREFETCH_AHEAD < i1:
            prefetch(C, (np.int64(y[i + PREFETCH_AHEAD]) * width + np.int64(x[i + PREFETCH_AHEAD])) * CF_FIELDS)
        yy = np.int64(y[i])
        if yy < row_lo or yy >= row_hi:
            continue
        tif = np.float64(t[i])
        pix = yy * width + np.int64(x[i])
        _cf_update(C, pix, tif, p[i], c_on, c_off, event_decay, con_px, coff_px, has_px)
        n += 1
    return n


@njit(cache=True, nogil=True)
def cf_events_indexed(t, x, y, p, i0, idx, m, width, C, c_on, c_off, event_decay, con_px, coff_px):
    """:func:`cf_events` over the events ``i0 + idx[:m]`` (one row band, from :func:`band_select`)."""
    if con_px.shape[0] > 0:
        return _cf_indexed(t, x, y, p, i0, idx, m, width, C, c_on, c_off, event_decay, con_px, coff_px, True)
    return _cf_indexed(t, x, y, p, i0, idx, m, width, C, c_on, c_off, event_decay, con_px, coff_px, False)


@njit(cache=True, nogil=True, inline="always")
def _cf_indexed(t, x, y, p, i0, idx, m, width, C, c_on, c_off, event_decay, con_px, coff_px, has_px):
    n = 0
    for k in range(m):
        if k + PREFETCH_AHEAD < m:
            j = i0 + np.int64(idx[k + PREFETCH_AHEAD])
            prefetch(C, (np.int64(y[j]) * width + np.int64(x[j])) * CF_FIELDS)
        i = i0 + np.int64(idx[k])
        tif = np.float64(t[i])
        pix = np.int64(y[i]) * width + np.int64(x[i])
        _cf_update(C, pix, tif, p[i], c_on, c_off, event_decay, con_px, coff_px, has_px)
        n += 1
    return n


@njit(cache=True, nogil=True)
def cf_propagate(C, t_to, pix_lo, pix_hi):
    """Propagate the CF state of pixels ``[pix_lo, pix_hi)`` to ``t_to`` µs (exact exponential)."""
    for pix in range(pix_lo, pix_hi):
        C[pix, C_L] = cf_decayed(C[pix, C_L], C[pix, C_LF], C[pix, C_ALPHA], C[pix, C_TU], t_to, 0.0)
        C[pix, C_TU] = t_to
    return pix_hi - pix_lo


@njit(cache=True, nogil=True)
def cf_output(C, t_out, offset, out_lin, pix_lo, pix_hi):
    """Write ``exp(L̂(t_out)) - offset`` (float32) without changing the CF state."""
    for pix in range(pix_lo, pix_hi):
        lhat = cf_decayed(C[pix, C_L], C[pix, C_LF], C[pix, C_ALPHA], C[pix, C_TU], t_out, 0.0)
        out_lin[pix] = math.exp(lhat) - offset
    return pix_hi - pix_lo


def aligned_state(n_pixels: int, n_fields: int) -> np.ndarray:
    """Zeroed C-contiguous float64 array (n_pixels, n_fields) whose rows start on 64-byte lines."""
    raw = np.zeros(n_pixels * n_fields + 8, dtype=np.float64)
    off = (-raw.ctypes.data % 64) // 8
    return raw[off:off + n_pixels * n_fields].reshape(n_pixels, n_fields)


@njit(cache=True, nogil=True)
def count_pixel_events_indexed(y, x, i0, idx, m, width, cnt):
    """``cnt[y·width + x] += 1`` for the events ``i0 + idx[:m]`` (one row band, :func:`band_select`)."""
    for k in range(m):
        i = i0 + np.int64(idx[k])
        cnt[np.int64(y[i]) * width + np.int64(x[i])] += np.float32(1.0)


@njit(cache=True, nogil=True)
def count_pixel_events(y, x, i0, i1, width, cnt):
    """``cnt[y·width + x] += 1`` for the events ``[i0, i1)`` (float32 counts, exact below 2²⁴)."""
    for i in range(i0, i1):
        cnt[np.int64(y[i]) * width + np.int64(x[i])] += np.float32(1.0)


@njit(cache=True, nogil=True)
def add_carried_variance(var, cnt, q, s_age):
    """In place, float32: ``var += q·cnt + s_age`` (the two-sided fusion's carried variance,
    :class:`hybridhdr.reconstruct.smoother._CarriedVariance`), in one pass."""
    qq = np.float32(q)
    sa = np.float32(s_age)
    for i in range(var.shape[0]):
        var[i] = var[i] + (qq * cnt[i] + sa)



@njit(cache=True, nogil=True)
def add_carried_variance_since(var, cnt, q, s, t_us, tau_ref):
    """In place, float32: ``var += q·cnt + s·(t_us − tau_ref)·1e-6`` per pixel, the two-sided
    fusion's carried variance with each pixel's own reference frame time ``tau_ref`` (µs; int64)
    (:class:`hybridhdr.reconstruct.smoother._CarriedVariance`). With one ``tau_ref`` for every
    pixel the same float32 values as :func:`add_carried_variance`."""
    qq = np.float32(q)
    for i in range(var.shape[0]):
        sa = np.float32(s * ((t_us - tau_ref[i]) * 1e-6))
        var[i] = var[i] + (qq * cnt[i] + sa)
