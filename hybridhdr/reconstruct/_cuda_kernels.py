"""CUDA kernels of the AKF and CF (private; imported only by :mod:`.cuda` when the GPU path runs).

Numba's CUDA target (``numba.cuda``; with ``NUMBA_ENABLE_CUDASIM=1`` its simulator, which is how
the tests run them without a GPU). The arithmetic per pixel is not written here: it is the
plain per-pixel functions of :mod:`._kernels` (``PIXEL_FUNCTIONS``) compiled as device
functions, the same source the CPU kernels inline; only the schedule differs:

* **Grouped by pixel.** The events of one time window (between two breakpoints of the driver:
  frame switches and output times) are grouped by pixel on the device: a count per pixel
  (:func:`k_count`, atomic, which also gives each event a slot in its pixel's group), an
  exclusive scan of the counts (:func:`scan_block` / :func:`k_add_offsets`), a scatter of event
  indices into the groups (:func:`k_scatter`) and a sort of each group by event index
  (:func:`k_sort_groups`): the groups are then in stream order, which is time order.
* **One thread per pixel** (:func:`k_akf_walk`) walks its group in order and applies the event
  step (:func:`._kernels.akf_event_step`) to its state record (:func:`._kernels.akf_walk_pixel`).
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
from numba import config as _nb_config
from numba import cuda

from . import _kernels as K
from ._kernels import A_BETA, A_KLOG, A_L, A_LA, A_P, A_RINV, A_TU, C_ALPHA, C_L, C_LF, C_TU

#: scan tile: threads per block and items per thread; the simulator runs each thread as a Python
#: thread, so it gets a small block (same algorithm)
SCAN_BLOCK = 32 if getattr(_nb_config, "ENABLE_CUDASIM", 0) else 512
SCAN_ITEMS = 4
SCAN_TILE = SCAN_BLOCK * SCAN_ITEMS
#: a window bound above every event index (the streamed walk takes all of a pixel's group)
NO_BOUND = np.int64(np.iinfo(np.int32).max)

# -- device functions: the per-pixel arithmetic of _kernels, compiled for the device -------------

_D = K.compile_pixel_functions(cuda.jit(device=True))
d_akf_walk_pixel = _D["akf_walk_pixel"]
d_window_neighbours = _D["window_neighbours"]
d_akf_switch_arrays_pixel = _D["akf_switch_arrays_pixel"]
d_akf_switch_codes_pixel = _D["akf_switch_codes_pixel"]
d_akf_initial_covariance = _D["akf_initial_covariance"]
d_output_pixel_values = _D["output_pixel"]
d_akf_output_store = _D["akf_output_store"]
d_cf_decayed = _D["cf_decayed"]
d_cf_event_step = _D["cf_event_step"]


@cuda.jit(device=True)
def d_output_pixel(S, pix, seg_t0, seg_inv_t, t_out):
    """:func:`._kernels.output_pixel` of record ``pix``: (L̂, P) at ``t_out``, the state unchanged."""
    return d_output_pixel_values(S[pix, A_L], S[pix, A_P], S[pix, A_LA], S[pix, A_RINV], S[pix, A_BETA],
                                 S[pix, A_KLOG], S[pix, A_TU], t_out, seg_t0, seg_inv_t)


@cuda.jit(device=True)
def d_jumps(pix, c_on, c_off, con_px, coff_px, has_px):
    """The ON jump and the (negative) OFF jump of pixel ``pix`` (eq. 15)."""
    return (con_px[pix] if has_px else c_on), -(coff_px[pix] if has_px else c_off)


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
    """One thread per pixel: its window events in stream order, each by :func:`._kernels.akf_walk_pixel`.

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
        nb_pos = cuda.local.array(8, np.int32)
        nb_hi = cuda.local.array(8, np.int32)
        nb_te = cuda.local.array(8, np.int64)
        n_nb, t_quiet = d_window_neighbours(pix, height, width, start, start[1:], te_in, nb_pos, nb_hi, nb_te)
        jump_on, jump_off = d_jumps(pix, c_on, c_off, con_px, coff_px, has_px)
        g, te_last = d_akf_walk_pixel(S, pix, t, p, a, grp, lo, hi, NO_BOUND, te_in[pix], t_quiet, nb_pos, nb_hi,
                                      nb_te, n_nb, has_la_step, seg_t0, seg_inv_t, jump_on, jump_off, s_proc,
                                      s_iso, s_ref, rho_us, noise_form)
        te_out[pix] = te_last
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
        d_akf_switch_arrays_pixel(S, pix, propagate, seg_t0, seg_inv_t, t_to, s_proc, log_frame, rinv, beta,
                                  la_step, censor, update_frame, seg_t_s, discrete, has_beta, has_step, has_cens,
                                  has_uf)


@cuda.jit
def k_akf_switch_lut(S, propagate, seg_t0, seg_inv_t, t_to, code, code_next, max_code, rbar_l, logf_l,
                     rinv_l, cens_l, la_step, seg_t_s, discrete, s_proc, n_pix):
    """:func:`._kernels.akf_switch_lut` for every pixel (one thread each)."""
    has_beta = code_next.shape[0] > 0 and seg_t_s > 0.0
    has_cens = cens_l.shape[0] > 0
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        d_akf_switch_codes_pixel(S, pix, propagate, seg_t0, seg_inv_t, t_to, s_proc, code, code_next, max_code,
                                 rbar_l, logf_l, rinv_l, cens_l, la_step, seg_t_s, discrete, has_beta, has_cens)


@cuda.jit
def k_akf_output(S, seg_t0, seg_inv_t, t_out, out_l32, out_log, out_var, n_pix):
    """:func:`._kernels.akf_output`: float32 L̂, and float64 L̂ and P when those arrays are full size."""
    want_log = out_log.shape[0] > 0
    want_var = out_var.shape[0] > 0
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        d_akf_output_store(S, pix, seg_t0, seg_inv_t, t_out, out_l32, out_log, out_var, want_log, want_var)


@cuda.jit
def k_akf_output_state32(S, seg_t0, seg_inv_t, t_out, out_l, out_p, ccount, q, s, t_us, ctau, n_pix):
    """:func:`._kernels.akf_output_state32`, then (``ccount`` not empty) the carried variance of
    :func:`._kernels.add_carried_variance_since` (float32 ``P + (q·n + s·(t_us − τ_ref)·1e-6)``,
    ``ctau`` each pixel's reference frame time, µs)."""
    has_cc = ccount.shape[0] > 0
    qq = np.float32(q)
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lhat, pv = d_output_pixel(S, pix, seg_t0, seg_inv_t, t_out)
        out_l[pix] = np.float32(lhat)
        p32 = np.float32(pv)
        if has_cc:
            sa = np.float32(s * ((t_us - ctau[pix]) * 1e-6))
            p32 = p32 + (qq * ccount[pix] + sa)
        out_p[pix] = p32


@cuda.jit
def k_reset_count(ccount, ctau, mask, tau, n_pix):
    """The carried variance's restart at a frame at ``tau`` µs: count 0 and reference time
    ``tau`` for the pixels the frame measures (``mask`` nonzero; empty ``mask``: every pixel)."""
    has_mask = mask.shape[0] > 0
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        if not has_mask or mask[pix] != 0:
            ccount[pix] = np.float32(0.0)
            ctau[pix] = tau


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
            cl = d_cf_event_step(cl, lfv, alpha, ctu, tif, p[a + i] > 0, j_on, j_off, event_decay)
            ctu = tif
        C[pix, C_L] = cl
        C[pix, C_TU] = ctu


@cuda.jit
def k_cf_propagate(C, t_to, n_pix):
    """:func:`._kernels.cf_propagate`."""
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        C[pix, C_L] = d_cf_decayed(C[pix, C_L], C[pix, C_LF], C[pix, C_ALPHA], C[pix, C_TU], t_to, 0.0)
        C[pix, C_TU] = t_to


@cuda.jit
def k_cf_output(C, t_out, out_log, n_pix):
    """L̂ of :func:`._kernels.cf_output` at ``t_out`` (float64; the host takes exp, as the CPU
    kernel's ``math.exp``)."""
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        out_log[pix] = d_cf_decayed(C[pix, C_L], C[pix, C_LF], C[pix, C_ALPHA], C[pix, C_TU], t_out, 0.0)


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
        S[pix, A_P] = d_akf_initial_covariance(S[pix, A_LA], S[pix, A_BETA], S[pix, A_KLOG], p0, p_cens, has_off,
                                               log_off)
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
        te0 = t[a + grp[g0 - 1]] if g0 > lo else te_c[pix]
        nb_pos = cuda.local.array(8, np.int32)
        nb_hi = cuda.local.array(8, np.int32)
        nb_te = cuda.local.array(8, np.int64)
        n_nb = 0
        t_quiet = te0
        for qy in range(max(yy - 1, 0), min(yy + 1, height - 1) + 1):
            for qx in range(max(xx - 1, 0), min(xx + 1, width - 1) + 1):
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
        jump_on, jump_off = d_jumps(pix, c_on, c_off, con_px, coff_px, has_px)
        g, _ = d_akf_walk_pixel(S, pix, t, p, a, grp, g0, hi, wb, te0, t_quiet, nb_pos, nb_hi, nb_te, n_nb,
                                has_la_step, seg_t0, seg_inv_t, jump_on, jump_off, s_proc, s_iso, s_ref, rho_us,
                                noise_form)
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
                cl = d_cf_event_step(cl, lfv, alpha, ctu, tif, p[a + i] > 0, j_on, j_off, event_decay)
                ctu = tif
                g += 1
            C[pix, C_L] = cl
            C[pix, C_TU] = ctu
        cur_out[pix] = g
