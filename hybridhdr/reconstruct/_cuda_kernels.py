"""CUDA kernels of the AKF and CF (private; imported only by :mod:`.cuda` when the GPU path runs).

Numba's CUDA target (``numba.cuda``; with ``NUMBA_ENABLE_CUDASIM=1`` its simulator, which is how
the tests run them without a GPU). The arithmetic per pixel is that of :mod:`._kernels`, line for
line (same equations, same order of operations); only the schedule differs:

* **Grouped by pixel.** The events of one time window (between two breakpoints of the driver:
  frame switches and output times) are grouped by pixel on the device: a count per pixel
  (:func:`k_count`, atomic, which also gives each event a slot in its pixel's group), an
  exclusive scan of the counts (:func:`scan_block` / :func:`k_add_offsets`), a scatter of event
  indices into the groups (:func:`k_scatter`) and a sort of each group by event index
  (:func:`k_sort_groups`): the groups are then in stream order, which is time order.
* **One thread per pixel** (:func:`k_akf_walk`) walks its group in order and applies the serial
  kernel's event update (:func:`._kernels._akf_event`) to its state record.
* **The isolated-pixel term** needs, at each event i of pixel p, the latest event time t* in the
  3x3 window of p over the events *before i in the stream* (eq. 2, §3.1.1). For a neighbour q
  that is the last of q's events with index < i in this window (a merge of p's and q's sorted
  groups: each neighbour's position only moves forward as p's events come), or, if there is
  none, q's last-event time from before the window (``te_in``). The window's last-event times go
  to ``te_out`` (double buffering: no thread reads a time written in the same window), so the
  result equals the serial stream's for any window split.

Per-pixel state is the CPU engine's record layout ((n, 8) float64 for the AKF, (n, 4) for CF)
so the same field indices apply. Times are int64 µs (absolute: the CPU's int32 relative times
are an optimisation with the same bits, see ``_engine.AKFEngine._te_fit``). Every kernel loops
grid-stride, so any launch size is correct (the simulator runs a few threads; a GPU one per
pixel or event).
"""

from __future__ import annotations

import math

import numpy as np

if not hasattr(np, "row_stack"):  # numba-cuda 0.30 with NumPy >= 2.5 (cuda.numpy_compat, which imports us)
    np.row_stack = np.vstack
from numba import config as _nb_config  # noqa: E402
from numba import cuda  # noqa: E402

from ._kernels import (A_BETA, A_KLOG, A_L, A_LA, A_LASTEP, A_P, A_RINV, A_TU, C_ALPHA, C_L, C_LF, C_TU,
                       TOBIT_MAX_P)

US = 1e-6  # seconds per microsecond (as _kernels.US)

#: scan tile: threads per block and items per thread; the simulator runs each thread as a Python
#: thread, so it gets a small block (same algorithm)
SCAN_BLOCK = 32 if getattr(_nb_config, "ENABLE_CUDASIM", 0) else 512
SCAN_ITEMS = 4
SCAN_TILE = SCAN_BLOCK * SCAN_ITEMS


# -- device functions: the serial kernels' per-pixel arithmetic --------------------------------

@cuda.jit(device=True)
def d_rinv_integral(rinv, beta, klog, tu0, t1, seg_t0, seg_inv_t):
    """:func:`._kernels.rinv_integral`, the same operations."""
    dt = t1 - tu0
    if beta == 0.0:
        return rinv * (dt * US)
    iw0 = 1.0 / (1.0 + beta * ((tu0 - seg_t0) * seg_inv_t))
    x = beta * (dt * seg_inv_t) * iw0
    if abs(x) < 1e-2:
        s = 1.0 - x * (0.5 - x * (1.0 / 3.0 - x * (0.25 - x * (0.2 - x * (1.0 / 6.0 - x * (
            1.0 / 7.0 - x * 0.125))))))
        return rinv * (dt * US) * iw0 * s
    return klog * math.log1p(x)


@cuda.jit(device=True)
def d_pull_integral(S, pix, t_to, seg_t0, seg_inv_t):
    """:func:`._kernels._pull_integral` (0 where a censored frame's bound holds)."""
    beta = S[pix, A_BETA]
    tu0 = S[pix, A_TU]
    if beta == 0.0:
        kl = S[pix, A_KLOG]
        if kl * (S[pix, A_L] - S[pix, A_LA]) > 0.0:
            return 0.0
        return S[pix, A_RINV] * ((t_to - tu0) * US)
    return d_rinv_integral(S[pix, A_RINV], beta, S[pix, A_KLOG], tu0, t_to, seg_t0, seg_inv_t)


@cuda.jit(device=True)
def d_propagate_pixel(S, pix, seg_t0, seg_inv_t, t_to):
    """:func:`._kernels._akf_propagate_pixel`."""
    integ = d_pull_integral(S, pix, t_to, seg_t0, seg_inv_t)
    d = 1.0 / (1.0 + S[pix, A_P] * integ)
    lav = S[pix, A_LA]
    S[pix, A_L] = lav + (S[pix, A_L] - lav) * d
    if S[pix, A_BETA] != 0.0 or S[pix, A_KLOG] == 0.0:
        S[pix, A_P] = S[pix, A_P] * d
    S[pix, A_TU] = t_to


@cuda.jit(device=True)
def d_inverse_mills(a):
    """:func:`._kernels.inverse_mills`."""
    if a > 25.0:
        return a + 1.0 / a
    return 0.7978845608028654 * math.exp(-0.5 * a * a) / math.erfc(a * 0.7071067811865476)


@cuda.jit(device=True)
def d_frame_update(S, pix, r_log, cz, lf):
    """:func:`._kernels._frame_update`."""
    lh = S[pix, A_L]
    pp = S[pix, A_P]
    if cz * (lh - lf) > 0.0:
        return
    if cz != 0.0:
        sd = math.sqrt(pp + r_log)
        if sd > 0.0 and pp < TOBIT_MAX_P:
            S[pix, A_L] = lh + cz * (pp / sd) * d_inverse_mills(cz * (lf - lh) / sd)
        else:
            S[pix, A_L] = lh + pp / (pp + r_log) * (lf - lh)
        return
    g = pp / (pp + r_log)
    S[pix, A_L] = lh + g * (lf - lh)
    S[pix, A_P] = pp - g * pp


@cuda.jit(device=True)
def d_output_pixel(S, pix, seg_t0, seg_inv_t, t_out):
    """:func:`._kernels._output_pixel`: (L̂, P) at ``t_out`` without changing the state."""
    beta = S[pix, A_BETA]
    kl = S[pix, A_KLOG]
    lh = S[pix, A_L]
    lav = S[pix, A_LA]
    pp = S[pix, A_P]
    rinv = S[pix, A_RINV]
    tu0 = S[pix, A_TU]
    held = rinv * ((t_out - tu0) * US)
    integ = 0.0 if kl * (lh - lav) > 0.0 else held
    if beta != 0.0:
        integ = d_rinv_integral(rinv, beta, kl, tu0, t_out, seg_t0, seg_inv_t)
    d = 1.0 / (1.0 + pp * integ)
    cens = (beta == 0.0) and (kl != 0.0)
    return lav + (lh - lav) * d, (pp if cens else pp * d)


@cuda.jit(device=True)
def d_lower_bound(grp, lo, hi, key):
    """First position in ``grp[lo:hi]`` (ascending) whose value is >= ``key`` (``hi`` if none)."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if grp[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


# -- grouping -------------------------------------------------------------------------------

@cuda.jit
def k_count(x, y, a, n, width, cnt, slot):
    """For window events ``a + [0, n)``: ``slot[i] = cnt[pix]++`` (atomic)."""
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        pix = np.int64(y[a + i]) * width + np.int64(x[a + i])
        slot[i] = cuda.atomic.add(cnt, pix, 1)


@cuda.jit
def scan_block(src, n, dst, sums):
    """Exclusive prefix sums of ``src[:n]`` within each tile of ``SCAN_TILE`` into ``dst``; the
    tile totals into ``sums`` (Hillis-Steele over the block's per-thread sums)."""
    sh = cuda.shared.array(SCAN_BLOCK, np.int64)
    tid = cuda.threadIdx.x
    b = cuda.blockIdx.x
    base = (np.int64(b) * SCAN_BLOCK + tid) * SCAN_ITEMS
    s = np.int64(0)
    for k in range(SCAN_ITEMS):
        if base + k < n:
            s += src[base + k]
    sh[tid] = s
    cuda.syncthreads()
    off = 1
    while off < SCAN_BLOCK:
        v = np.int64(0)
        if tid >= off:
            v = sh[tid - off]
        cuda.syncthreads()
        sh[tid] += v
        cuda.syncthreads()
        off *= 2
    run = sh[tid] - s
    for k in range(SCAN_ITEMS):
        if base + k < n:
            c = src[base + k]
            dst[base + k] = run
            run += c
    if tid == SCAN_BLOCK - 1:
        sums[b] = sh[tid]


@cuda.jit
def k_add_offsets(dst, n, offs):
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        dst[i] += offs[i // SCAN_TILE]


@cuda.jit
def k_scatter(x, y, a, n, width, start, slot, grp, cnt):
    """``grp[start[pix] + slot[i]] = i``, and the counts zeroed for the next window (they are not
    read again in this one: every event of a pixel writes the same 0)."""
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        pix = np.int64(y[a + i]) * width + np.int64(x[a + i])
        grp[start[pix] + slot[i]] = i
        cnt[pix] = 0


@cuda.jit
def k_sort_groups(start, n_pix, grp):
    """Sort each pixel's group by event index (insertion sort below 32, else a shell sort)."""
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lo = start[pix]
        hi = start[pix + 1]
        m = hi - lo
        if m < 2:
            continue
        # the atomic slots mostly follow the stream order already: one read pass, no sort then
        ordered = True
        for j in range(lo + 1, hi):
            if grp[j - 1] > grp[j]:
                ordered = False
                break
        if ordered:
            continue
        gap = 1
        if m >= 32:
            while gap < m // 3:
                gap = 3 * gap + 1
        while gap >= 1:
            for j in range(lo + gap, hi):
                v = grp[j]
                k = j
                while k >= lo + gap and grp[k - gap] > v:
                    grp[k] = grp[k - gap]
                    k -= gap
                grp[k] = v
            gap //= 3


# -- AKF --------------------------------------------------------------------------------------

@cuda.jit
def k_akf_walk(t, x, y, p, a, height, width, start, grp, te_in, te_out, S, has_la_step, seg_t0, seg_inv_t,
               c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, ccount):
    """One thread per pixel: its window events in stream order, each as :func:`._kernels._akf_event`.

    ``te_in`` holds every pixel's last event time before the window (absolute µs, the start
    time where none); ``te_out`` receives it after the window. ``ccount`` (float32, or empty):
    per-pixel event counts for the two-sided fusion's carried variance.
    """
    n_pix = height * width
    has_px = con_px.shape[0] > 0
    has_cc = ccount.shape[0] > 0
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lo = start[pix]
        hi = start[pix + 1]
        if lo == hi:
            te_out[pix] = te_in[pix]
            continue
        yy = pix // width
        xx = pix - yy * width
        ylo = max(yy - 1, 0)
        yhi = min(yy + 1, height - 1)
        xlo = max(xx - 1, 0)
        xhi = min(xx + 1, width - 1)
        te0 = te_in[pix]
        # neighbours without events in this window contribute their time from before it, the same
        # for every event of p: folded into one maximum; only the others are searched per event
        nb_pos = cuda.local.array(8, np.int32)
        nb_hi = cuda.local.array(8, np.int32)
        nb_te = cuda.local.array(8, np.int64)
        n_nb = 0
        t_quiet = te0
        for qy in range(ylo, yhi + 1):
            for qx in range(xlo, xhi + 1):
                q = qy * width + qx
                if q != pix:
                    q_lo = start[q]
                    q_hi = start[q + 1]
                    if q_lo == q_hi:
                        if te_in[q] > t_quiet:
                            t_quiet = te_in[q]
                    else:
                        nb_pos[n_nb] = q_lo
                        nb_hi[n_nb] = q_hi
                        nb_te[n_nb] = te_in[q]
                        n_nb += 1
        # the state record in registers for the walk (one load and one store of each field per
        # window, not per event); the fields a frame switch sets are constant here
        sl = S[pix, A_L]
        sp = S[pix, A_P]
        sla = S[pix, A_LA]
        stu = S[pix, A_TU]
        rinv = S[pix, A_RINV]
        beta = S[pix, A_BETA]
        klog = S[pix, A_KLOG]
        lastep = S[pix, A_LASTEP]
        scale_p = beta != 0.0 or klog == 0.0
        jump_on = con_px[pix] if has_px else c_on
        jump_off = -(coff_px[pix] if has_px else c_off)
        off_ratio = ((coff_px[pix] / con_px[pix]) if has_px else (c_off / c_on)) if has_la_step else 0.0
        for g in range(lo, hi):
            i = grp[g]
            ti = t[a + i]
            tif = np.float64(ti)
            tu0 = stu
            # d_pull_integral on the registers
            if beta == 0.0:
                if klog * (sl - sla) > 0.0:
                    integ = 0.0
                else:
                    integ = rinv * ((tif - tu0) * US)
            else:
                integ = d_rinv_integral(rinv, beta, klog, tu0, tif, seg_t0, seg_inv_t)
            pp = sp
            d = 1.0 / (1.0 + pp * integ)
            lav = sla
            lhat = lav + (sl - lav) * d
            if scale_p:
                pp = pp * d
            # t*: the latest event time in the 3x3 window before this event (p itself: te0)
            tstar = te0 if te0 > t_quiet else t_quiet
            for k in range(n_nb):
                # q's last event before i: p's events come in increasing i, so each neighbour's
                # position only moves forward (a merge: O(events of p and q) per window, where a
                # binary search per event costs O(events of p x log events of q))
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
            dte = ti - te0
            q_ = s_iso * ((ti - tstar) * US)
            if noise_form == 0:
                q_ += s_proc * (dte * US)
                if dte <= rho_us:
                    q_ += s_ref
            else:
                q_ += s_proc * ((tif - tu0) * US)
                if dte <= rho_us:
                    q_ += s_ref * (dte * US)
            sp = pp + q_
            positive = p[a + i] > 0
            jump = jump_on if positive else jump_off
            sl = lhat + jump
            if has_la_step:
                st = lastep
                if st < 0.0:
                    sla = lav + jump
                elif positive:
                    sla = lav + st
                else:
                    sla = lav - st * off_ratio
            stu = tif
            te0 = ti
        S[pix, A_L] = sl
        S[pix, A_P] = sp
        S[pix, A_LA] = sla
        S[pix, A_TU] = stu
        te_out[pix] = te0
        if has_cc:
            ccount[pix] += np.float32(hi - lo)


@cuda.jit
def k_akf_switch(S, propagate, seg_t0, seg_inv_t, t_to, log_frame, rinv, beta, la_step, censor, seg_t_s,
                 discrete, s_proc, update_frame, n_pix):
    """:func:`._kernels.akf_switch` for every pixel (one thread each)."""
    has_beta = beta.shape[0] > 0 and seg_t_s > 0.0
    has_step = la_step.shape[0] > 0
    has_cens = censor.shape[0] > 0
    has_uf = update_frame.shape[0] > 0
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        if propagate:
            q = s_proc * ((t_to - S[pix, A_TU]) * US)
            d_propagate_pixel(S, pix, seg_t0, seg_inv_t, t_to)
            S[pix, A_P] += q
        r = rinv[pix]
        S[pix, A_LA] = log_frame[pix]
        S[pix, A_RINV] = r
        b = beta[pix] if has_beta else 0.0
        cz = censor[pix] if has_cens else 0.0
        if cz != 0.0:
            b = 0.0
        S[pix, A_BETA] = b
        S[pix, A_KLOG] = r * seg_t_s / b if b != 0.0 else cz
        S[pix, A_LASTEP] = la_step[pix] if has_step else 0.0
        if discrete:
            d_frame_update(S, pix, 1.0 / r, cz, update_frame[pix] if has_uf else log_frame[pix])


@cuda.jit
def k_akf_switch_lut(S, propagate, seg_t0, seg_inv_t, t_to, code, code_next, max_code, rbar_l, logf_l,
                     rinv_l, cens_l, la_step, seg_t_s, discrete, s_proc, n_pix):
    """:func:`._kernels.akf_switch_lut` for every pixel (one thread each)."""
    has_beta = code_next.shape[0] > 0 and seg_t_s > 0.0
    has_cens = cens_l.shape[0] > 0
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        if propagate:
            q = s_proc * ((t_to - S[pix, A_TU]) * US)
            d_propagate_pixel(S, pix, seg_t0, seg_inv_t, t_to)
            S[pix, A_P] += q
        c = min(max(np.int64(code[pix]), 0), max_code)
        r = rinv_l[c]
        S[pix, A_LA] = logf_l[c]
        S[pix, A_RINV] = r
        cz = cens_l[c] if has_cens else 0.0
        b = 0.0
        if has_beta and cz == 0.0:
            c1 = min(max(np.int64(code_next[pix]), 0), max_code)
            if not (has_cens and cens_l[c1] != 0.0):
                b = rbar_l[c1] / rbar_l[c] - 1.0
        S[pix, A_BETA] = b
        S[pix, A_KLOG] = r * seg_t_s / b if b != 0.0 else cz
        S[pix, A_LASTEP] = la_step
        if discrete:
            d_frame_update(S, pix, 1.0 / r, cz, logf_l[c])


@cuda.jit
def k_akf_output(S, seg_t0, seg_inv_t, t_out, out_l32, out_log, out_var, n_pix):
    """:func:`._kernels.akf_output`: float32 L̂, and float64 L̂ and P when those arrays are full size."""
    want_log = out_log.shape[0] > 0
    want_var = out_var.shape[0] > 0
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lhat, pv = d_output_pixel(S, pix, seg_t0, seg_inv_t, t_out)
        out_l32[pix] = np.float32(lhat)
        if want_log:
            out_log[pix] = lhat
        if want_var:
            out_var[pix] = pv


@cuda.jit
def k_akf_output_state32(S, seg_t0, seg_inv_t, t_out, out_l, out_p, ccount, q, s_age, n_pix):
    """:func:`._kernels.akf_output_state32`, then (``ccount`` not empty) the carried variance of
    :func:`._kernels.add_carried_variance` (float32 ``P + (q·n + s_age)``)."""
    has_cc = ccount.shape[0] > 0
    qq = np.float32(q)
    sa = np.float32(s_age)
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lhat, pv = d_output_pixel(S, pix, seg_t0, seg_inv_t, t_out)
        out_l[pix] = np.float32(lhat)
        p32 = np.float32(pv)
        if has_cc:
            p32 = p32 + (qq * ccount[pix] + sa)
        out_p[pix] = p32


@cuda.jit
def k_reverse_events(t, x, y, p, n, t_mirror_m1, rt, rx, ry, rp):
    """:func:`.smoother.reverse_events` on the device: ``t' = mirror - 1 - t``, order reversed,
    polarity negated."""
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        j = n - 1 - i
        rt[i] = t_mirror_m1 - t[j]
        rx[i] = x[j]
        ry[i] = y[j]
        rp[i] = -p[j]


@cuda.jit
def k_fill_f32(a, v, n):
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        a[i] = v


@cuda.jit
def k_fill_i64(a, v, n):
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        a[i] = v


# -- CF ---------------------------------------------------------------------------------------

@cuda.jit
def k_cf_walk(t, p, a, n_pix, start, grp, C, c_on, c_off, event_decay, con_px, coff_px):
    """One thread per pixel: :func:`._kernels._cf_update` at each of its window events, in order."""
    has_px = con_px.shape[0] > 0
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lo = start[pix]
        hi = start[pix + 1]
        if lo == hi:
            continue
        # the record in registers for the walk (L^F and α are constant between frame switches)
        lfv = C[pix, C_LF]
        alpha = C[pix, C_ALPHA]
        cl = C[pix, C_L]
        ctu = C[pix, C_TU]
        j_on = con_px[pix] if has_px else c_on
        j_off = coff_px[pix] if has_px else c_off
        for g in range(lo, hi):
            i = grp[g]
            tif = np.float64(t[a + i])
            b = math.exp(-alpha * ((tif - ctu) * US) - event_decay)
            lhat = lfv + (cl - lfv) * b
            if p[a + i] > 0:
                cl = lhat + j_on
            else:
                cl = lhat - j_off
            ctu = tif
        C[pix, C_L] = cl
        C[pix, C_TU] = ctu


@cuda.jit
def k_cf_propagate(C, t_to, n_pix):
    """:func:`._kernels.cf_propagate`."""
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lfv = C[pix, C_LF]
        C[pix, C_L] = lfv + (C[pix, C_L] - lfv) * math.exp(-C[pix, C_ALPHA] * ((t_to - C[pix, C_TU]) * US))
        C[pix, C_TU] = t_to


@cuda.jit
def k_cf_output(C, t_out, out_log, n_pix):
    """L̂ of :func:`._kernels.cf_output` at ``t_out`` (float64; the host takes exp, as the CPU
    kernel's ``math.exp``)."""
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lfv = C[pix, C_LF]
        out_log[pix] = lfv + (C[pix, C_L] - lfv) * math.exp(-C[pix, C_ALPHA] * ((t_out - C[pix, C_TU]) * US))


@cuda.jit(device=True)
def d_log_to_linear(l32, offset32):
    """:func:`._kernels.log_to_linear` of one float32 L̂: exp rounded to float32, then the float32
    offset subtracted (the CPU's numpy float32 exp is within an ulp of this correctly rounded one)."""
    return np.float32(math.exp(np.float64(l32))) - offset32


@cuda.jit
def k_akf_output_linear(S, seg_t0, seg_inv_t, t_out, offset32, out_lin, n_pix):
    """:func:`._kernels.akf_output` then :func:`._kernels.log_to_linear`: the linear float32 image."""
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lhat, pv = d_output_pixel(S, pix, seg_t0, seg_inv_t, t_out)
        out_lin[pix] = d_log_to_linear(np.float32(lhat), offset32)


@cuda.jit
def k_fuse_linear(l_f, p_f, l_b, p_b, offset32, floor32, out, n, counts):
    """:func:`._kernels.fuse_to_linear` on the device: ``(L_f P_b + L_b P_f)/(P_f + P_b)`` in
    float64 from the float32 pass estimates, rounded to float32 (:func:`._kernels.fuse_log32`),
    the linear value, and the clamp at ``floor32`` (``counts[0]``: zero denominators,
    ``counts[1]``: clamped pixels, as :func:`._kernels.clamp_linear` counts them: below the floor
    or NaN)."""
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        pf = np.float64(p_f[i])
        pb = np.float64(p_b[i])
        den = pf + pb
        if den == 0.0:
            cuda.atomic.add(counts, 0, 1)
            v = np.float32(math.nan)
        else:
            v = d_log_to_linear(np.float32((np.float64(l_f[i]) * pb + np.float64(l_b[i]) * pf) / den), offset32)
        if not (v >= floor32):
            v = floor32
            cuda.atomic.add(counts, 1, 1)
        out[i] = v


@cuda.jit
def k_cf_load(C, lf, alpha, reset_l, set_tu, t_tu, n_pix):
    """Load L^F and α of a CF segment (computed on the host as :class:`._engine.CFEngine` does);
    optionally L̂ = L^F (start, direct integration) and tu."""
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        C[pix, C_LF] = lf[pix]
        C[pix, C_ALPHA] = alpha[pix]
        if reset_l:
            C[pix, C_L] = lf[pix]
        if set_tu:
            C[pix, C_TU] = t_tu


@cuda.jit
def k_cf_load_lut(C, code, max_code, lf_l, alpha_l, reset_l, set_tu, t_tu, n_pix):
    """:func:`k_cf_load` from per-code tables (:meth:`._engine.CFEngine._load_codes`): each
    pixel's clipped code looks up L^F and α."""
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        c = min(max(np.int64(code[pix]), 0), max_code)
        lf = lf_l[c]
        C[pix, C_LF] = lf
        C[pix, C_ALPHA] = alpha_l[c]
        if reset_l:
            C[pix, C_L] = lf
        if set_tu:
            C[pix, C_TU] = t_tu


@cuda.jit
def k_akf_init(S, p0, p_cens, has_off, log_off, t_init, n_pix):
    """:meth:`._engine.AKFEngine.start`'s initialisation from the loaded first frame: L̂ = L^A,
    P = ``p0``; a censored pixel ``p_cens``, a clipped dark one (bounded on both sides, with an
    offset) the square of its interval's width, at least ``p0``; tu = ``t_init``."""
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        S[pix, A_L] = S[pix, A_LA]
        p = p0
        cens = (S[pix, A_BETA] == 0.0) and (S[pix, A_KLOG] != 0.0)
        if cens:
            p = p_cens
            if has_off and S[pix, A_KLOG] < 0.0:
                w = S[pix, A_LA] - log_off
                p = max(w * w, p0)
        S[pix, A_P] = p
        S[pix, A_TU] = t_init


# -- resident events: one grouping per chunk, a cursor per pixel ------------------------------
#
# With the events resident on the device, a chunk of many windows is grouped once (the same
# count, scan, scatter and sort): each pixel's group then holds its events of every window of the
# chunk in stream order, and a window [.., wb) of the chunk is, for each pixel, the run of its group
# from its cursor up to the first index >= wb. One walk launch per window (not seven), and the
# last-event times before a window come from the groups themselves: the event before a pixel's
# cursor, or, before its first event of the chunk, ``te_c`` (the times at the chunk's start).
# Cursors are double-buffered (``cur_in`` read by every neighbour, ``cur_out`` written by the
# owner), so no thread reads a position written in the same window.

@cuda.jit
def k_copy_i32(src, dst, n):
    for i in range(cuda.grid(1), n, cuda.gridsize(1)):
        dst[i] = src[i]


@cuda.jit
def k_chunk_te(t, a, start, grp, cur, te_c, te_next, n_pix):
    """Each pixel's last event time after the chunk's processed events (its time at the chunk's
    start where it had none): the next chunk's ``te_c``."""
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        g = cur[pix]
        te_next[pix] = t[a + grp[g - 1]] if g > start[pix] else te_c[pix]


@cuda.jit
def k_akf_walk_res(t, p, a, wb, height, width, start, grp, cur_in, cur_out, te_c, S, has_la_step, seg_t0,
                   seg_inv_t, c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, ccount):
    """:func:`k_akf_walk` over the window ``[.., wb)`` (indices relative to the chunk start ``a``)
    of a chunk grouped once: the same per-event arithmetic, t* from the neighbours' groups."""
    n_pix = height * width
    has_px = con_px.shape[0] > 0
    has_cc = ccount.shape[0] > 0
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lo = start[pix]
        hi = start[pix + 1]
        g0 = cur_in[pix]
        if g0 >= hi or grp[g0] >= wb:
            cur_out[pix] = g0
            continue
        yy = pix // width
        xx = pix - yy * width
        ylo = max(yy - 1, 0)
        yhi = min(yy + 1, height - 1)
        xlo = max(xx - 1, 0)
        xhi = min(xx + 1, width - 1)
        te0 = t[a + grp[g0 - 1]] if g0 > lo else te_c[pix]
        nb_pos = cuda.local.array(8, np.int32)
        nb_hi = cuda.local.array(8, np.int32)
        nb_te = cuda.local.array(8, np.int64)
        n_nb = 0
        t_quiet = te0
        for qy in range(ylo, yhi + 1):
            for qx in range(xlo, xhi + 1):
                q = qy * width + qx
                if q != pix:
                    q_lo = start[q]
                    q_hi = start[q + 1]
                    qg = cur_in[q]
                    tq0 = t[a + grp[qg - 1]] if qg > q_lo else te_c[q]
                    if qg >= q_hi or grp[qg] >= wb:  # no event in this window: one time for all
                        if tq0 > t_quiet:
                            t_quiet = tq0
                    else:
                        nb_pos[n_nb] = qg
                        nb_hi[n_nb] = q_hi
                        nb_te[n_nb] = tq0
                        n_nb += 1
        sl = S[pix, A_L]
        sp = S[pix, A_P]
        sla = S[pix, A_LA]
        stu = S[pix, A_TU]
        rinv = S[pix, A_RINV]
        beta = S[pix, A_BETA]
        klog = S[pix, A_KLOG]
        lastep = S[pix, A_LASTEP]
        scale_p = beta != 0.0 or klog == 0.0
        jump_on = con_px[pix] if has_px else c_on
        jump_off = -(coff_px[pix] if has_px else c_off)
        off_ratio = ((coff_px[pix] / con_px[pix]) if has_px else (c_off / c_on)) if has_la_step else 0.0
        g = g0
        while g < hi:
            i = grp[g]
            if i >= wb:
                break
            ti = t[a + i]
            tif = np.float64(ti)
            tu0 = stu
            if beta == 0.0:
                if klog * (sl - sla) > 0.0:
                    integ = 0.0
                else:
                    integ = rinv * ((tif - tu0) * US)
            else:
                integ = d_rinv_integral(rinv, beta, klog, tu0, tif, seg_t0, seg_inv_t)
            pp = sp
            d = 1.0 / (1.0 + pp * integ)
            lav = sla
            lhat = lav + (sl - lav) * d
            if scale_p:
                pp = pp * d
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
            dte = ti - te0
            q_ = s_iso * ((ti - tstar) * US)
            if noise_form == 0:
                q_ += s_proc * (dte * US)
                if dte <= rho_us:
                    q_ += s_ref
            else:
                q_ += s_proc * ((tif - tu0) * US)
                if dte <= rho_us:
                    q_ += s_ref * (dte * US)
            sp = pp + q_
            positive = p[a + i] > 0
            jump = jump_on if positive else jump_off
            sl = lhat + jump
            if has_la_step:
                st = lastep
                if st < 0.0:
                    sla = lav + jump
                elif positive:
                    sla = lav + st
                else:
                    sla = lav - st * off_ratio
            stu = tif
            te0 = ti
            g += 1
        S[pix, A_L] = sl
        S[pix, A_P] = sp
        S[pix, A_LA] = sla
        S[pix, A_TU] = stu
        cur_out[pix] = g
        if has_cc:
            ccount[pix] += np.float32(g - g0)


@cuda.jit
def k_cf_walk_res(t, p, a, wb, n_pix, start, grp, cur_in, cur_out, C, c_on, c_off, event_decay, con_px, coff_px):
    """:func:`k_cf_walk` over the window ``[.., wb)`` of a chunk grouped once."""
    has_px = con_px.shape[0] > 0
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        hi = start[pix + 1]
        g = cur_in[pix]
        if g < hi and grp[g] < wb:
            lfv = C[pix, C_LF]
            alpha = C[pix, C_ALPHA]
            cl = C[pix, C_L]
            ctu = C[pix, C_TU]
            j_on = con_px[pix] if has_px else c_on
            j_off = coff_px[pix] if has_px else c_off
            while g < hi:
                i = grp[g]
                if i >= wb:
                    break
                tif = np.float64(t[a + i])
                b = math.exp(-alpha * ((tif - ctu) * US) - event_decay)
                lhat = lfv + (cl - lfv) * b
                if p[a + i] > 0:
                    cl = lhat + j_on
                else:
                    cl = lhat - j_off
                ctu = tif
                g += 1
            C[pix, C_L] = cl
            C[pix, C_TU] = ctu
        cur_out[pix] = g
