"""The pixel-parallel CPU engine of the AKF (private): each window's events split once by row band.

The row-band engine (:class:`._engine.AKFEngine` with several workers) keeps its bands from batch
to batch, each with its own last-event-time array, and pipelines each batch's split into the
bands' filtering. This engine cuts new bands for every window of events (between two breakpoints
of the driver: frame switches, output times, chunk ends) from that window's events per row, so
the workers' shares are equal whatever the events' layout, and shares one last-event-time array
``te`` between the bands: each band copies its two *ghost rows* (the rows just above and below
it, whose times its pixels' t* read and which their owners move meanwhile) at the start of the
window, and the ghost rows' events move only the copies. Every pixel then sees its events in
stream order with the serial filter's Δt and t* (eq. 2, §3.1.1: the latest event time in the 3×3
window before the event) and the per-event step :func:`._kernels.akf_event_step`, the function
the serial kernel and the CUDA kernels compile: the outputs are bit-identical to
:class:`._engine.AKFEngine` for any window split and any number of workers.

How a worker gets its band's events (``w`` workers, ``n`` events in the window):

- up to :data:`SELECT_MAX_WORKERS` workers: the calling thread cuts the bands from a 1-in-8
  sample of the rows and copies the ghost rows; each worker selects its band's events (ghost
  rows included) from the whole window, branch-free (:func:`._kernels.band_select`), and filters
  them (:meth:`PixelAKFEngine._process_selected`). No barrier; each worker reads all ``n`` rows;
- more workers: each counts the rows of its ``1/w`` of the window (:func:`._kernels.row_histogram`),
  the calling thread cuts the bands (:func:`plan_bands`), each worker scatters its part's event
  indices into the bands' lists, in stream order (:func:`block_scatter`) and copies its band's
  ghost rows, then filters its band's list. Three barriers; each worker reads ``n / w`` rows.

A worker filters its band in stream order (:func:`block_stream`, :data:`BLOCK_ORDER` "stream"),
one pass with the serial kernel's prefetching; or, with :data:`BLOCK_ORDER` "pixel", as the
CUDA kernels do: it groups the band's events by pixel (:func:`group_block`, a stable counting
sort with t* and the Δt computed on the way) and walks each pixel's events with the state record
in registers (:func:`walk_block`). The grouping pass cost more than the walk saved: at 346x260,
1 M events, on one core, the grouping took 50 ns per event and the walk 18, where the stream
order takes 15-20 (the serial kernel's cost; ``te`` int32 as the row-band engine's). The GPU
reads t* from the neighbours' groups instead (a merge per pair of pixels); on a CPU core that
merge is bound by the latency of its compare-and-advance chain (about 100 ns per event at 346x260).

A pending frame switch (one pass over the pixels, :meth:`._engine.AKFEngine._load`) is applied
by the workers at the start of the window, each its band's pixels: one hand-off per window, not
two. Windows of fewer than :data:`PARALLEL_MIN_EVENTS` events, and every window with one worker,
are filtered by the calling thread with the serial kernel itself (:func:`._kernels.akf_events`,
on the same ``te``). ``te`` is padded by one pixel (:func:`._kernels.padded_te`), int32 relative
to the start, int64 absolute past int32's reach (:meth:`PixelAKFEngine._te_fit`). Outputs are the
row-band engine's (one pass over the pixels, split by rows).
"""

from __future__ import annotations

import threading

import numpy as np
from numba import njit

from .._util import phases as PH
from .._util.nbprefetch import prefetch
from . import _kernels as K
from . import _engine
from ._engine import AKFEngine

#: how a worker filters its band's events: "stream" (:func:`block_stream`, in stream order, one
#: pass) or "pixel" (:func:`group_block` then :func:`walk_block`, the CUDA kernels' grouping by
#: pixel; the window is then split by rows whatever the workers, never selected). Both give the
#: serial filter's bits; "stream" is the default: the grouping pass cost more than the walk saved
#: (module docstring)
BLOCK_ORDER = "stream"
BLOCK_ORDERS = ("stream", "pixel")
#: windows of fewer events are filtered by the calling thread alone (as one band: the same bits);
#: the row-band engine's threshold (``_engine.PARALLEL_MIN_WORK``)
PARALLEL_MIN_EVENTS = 20_000
#: up to this many workers each selects its band's events from the whole window (one pass over
#: the window per worker, no barrier: :meth:`PixelAKFEngine._process_selected`); with more, the
#: window is split once by rows (a histogram, then a scatter, between barriers), whose cost per
#: worker shrinks as workers are added where a whole pass per worker does not
SELECT_MAX_WORKERS = 4
#: :func:`group_block` lists a block's pixels with events by scanning its pixels when they are at
#: most this many per event of the window (then the walk reads the state in address order)
SCAN_PIXELS_PER_EVENT = 1
ONE = K.ONE


@njit(cache=True, nogil=True)
def block_scatter(y, a, j0, j1, block_of_row, edge_of_row, pos, out):
    """Event indices (relative to the window start ``a``) of ``[j0, j1)`` into ``out`` at the write
    position ``pos[b]`` (advanced) of every block that reads them, in stream order."""
    for i in range(j0, j1):
        r = y[i]
        b = block_of_row[r]
        v = np.int32(i - a)
        e = edge_of_row[r]
        if e & 1:
            out[pos[b - 1]] = v
            pos[b - 1] += 1
        out[pos[b]] = v
        pos[b] += 1
        if e & 2:
            out[pos[b + 1]] = v
            pos[b + 1] += 1
    return j1 - j0


@njit(cache=True, nogil=True, inline="always")
def _rows_around(te, tp, wpu, c, first_row, last_row, top, bot):
    """The last event times of the three pixels above and the three below te index ``tp`` (column
    ``c``): from the band's ghost-row copies ``top``/``bot`` on its first/last row, else from ``te``."""
    if first_row:
        u0, u1, u2 = top[c], top[c + ONE], top[c + ONE + ONE]
    else:
        u0, u1, u2 = te[tp - wpu - ONE], te[tp - wpu], te[tp - wpu + ONE]
    if last_row:
        d0, d1, d2 = bot[c], bot[c + ONE], bot[c + ONE + ONE]
    else:
        d0, d1, d2 = te[tp + wpu - ONE], te[tp + wpu], te[tp + wpu + ONE]
    return u0, u1, u2, d0, d1, d2


@njit(cache=True, nogil=True, inline="always")
def _window_max(te, tp, te0, u0, u1, u2, d0, d1, d2):
    """The latest event time of the 3x3 window, in the serial kernel's order (K._akf_event)."""
    return max(max(max(u0, u1), max(u2, te[tp - ONE])),
               max(max(te0, te[tp + ONE]), max(max(d0, d1), d2)))


@njit(cache=True, nogil=True)
def group_block(t, x, y, p, a, ev, e0, e1, identity, width, row_lo, row_hi, te, te_base, top, bot, gcnt, glo, ghi, rec,
                act):
    """Group a block's events by pixel with each event's Δt and t*; returns the pixels with events.

    The block's events are ``ev[e0:e1]`` (indices relative to ``a``, stream order, its ghost rows'
    included), or ``e0 .. e1 - 1`` themselves when ``identity``; its rows are ``[row_lo, row_hi)``.
    Pixel ``q``'s group becomes rows ``[glo[q], ghi[q])`` of ``rec``, one record of three int64 per
    event (one cache line for most, where four arrays would touch four): t_i, 2 (t_i - the
    pixel's previous event time) + (1 if ON), and t_i - t*; in the block's range ``[e0, e1)``; the
    pixels with events are listed in ``act[e0:e0 + k]``, and ``k`` is returned. ``te`` is the
    padded last-event-time array (:func:`._kernels.padded_te`, times relative to ``te_base`` µs:
    int32 or int64, every use a difference taken in int64), updated in place for the block's
    rows; ``top`` and ``bot`` are the block's copies of its padded ghost rows ``row_lo - 1`` and
    ``row_hi`` (``te``'s type), which their events move. ``gcnt``, ``glo`` and ``ghi`` are 0 for
    every pixel without events (:func:`walk_block` restores that).
    """
    wp = width + 2
    # the pixels with events in pixel order (a scan of the block's pixels) when the events are
    # many enough to pay for it, else in the order of their first event (no pass over the pixels:
    # a 1280x720 window of 300 k events has 3x as many pixels as events); the bits are the same
    scan = (row_hi - row_lo) * width <= SCAN_PIXELS_PER_EVENT * (e1 - e0)
    k = 0
    wu = np.uint64(width)
    for j in range(e0, e1):
        if j + 2 * K.PREFETCH_AHEAD < e1:  # the counts of a large sensor do not stay in cache
            jn = np.int64(a) + (np.int64(j + 2 * K.PREFETCH_AHEAD) if identity else
                                np.int64(ev[j + 2 * K.PREFETCH_AHEAD]))
            prefetch(gcnt, np.uint64(y[jn]) * wu + np.uint64(x[jn]))
        i = j if identity else np.int64(ev[j])
        r = np.int64(y[a + i])
        if r >= row_lo and r < row_hi:
            q = r * width + np.int64(x[a + i])
            if not scan and gcnt[q] == 0:
                act[e0 + k] = q
                k += 1
            gcnt[q] += 1
    pos = np.int32(e0)
    if scan:
        for q in range(row_lo * width, row_hi * width):
            c = gcnt[q]
            if c != 0:
                act[e0 + k] = q
                k += 1
                glo[q] = pos
                ghi[q] = pos
                pos += c
    else:
        for m in range(e0, e0 + k):
            if m + K.PREFETCH_AHEAD < e0 + k:
                qn = np.uint64(act[m + K.PREFETCH_AHEAD])
                prefetch(glo, qn)
                prefetch(ghi, qn)
            q = act[m]
            glo[q] = pos
            ghi[q] = pos
            pos += gcnt[q]
    # unsigned index arithmetic (no negative-index wraparound code), no slices, and the serial
    # kernel's prefetch of the 3x3 te window a few events ahead (and of the pixel's write position)
    w = np.uint64(width)
    wpu = np.uint64(wp)
    lo = np.uint64(row_lo)
    hi = np.uint64(row_hi)
    au = np.int64(a)
    for j in range(e0, e1):
        if j + 2 * K.PREFETCH_AHEAD < e1:
            jn = au + (np.int64(j + 2 * K.PREFETCH_AHEAD) if identity else np.int64(ev[j + 2 * K.PREFETCH_AHEAD]))
            yn = np.uint64(y[jn])
            xn = np.uint64(x[jn])
            tn = (yn + ONE) * wpu + xn + ONE
            prefetch(te, tn - wpu)
            prefetch(te, tn)
            prefetch(te, tn + wpu)
            prefetch(ghi, yn * w + xn)
        if j + K.PREFETCH_AHEAD < e1:
            # the record the event K.PREFETCH_AHEAD on will write (its pixel's write position now:
            # the same or the next record then); these scattered writes were the grouping's cost
            jn = au + (np.int64(j + K.PREFETCH_AHEAD) if identity else np.int64(ev[j + K.PREFETCH_AHEAD]))
            yn = np.uint64(y[jn])
            if yn >= lo and yn < hi:
                gn = np.uint64(ghi[yn * w + np.uint64(x[jn])]) * np.uint64(3)
                prefetch(rec, gn)
                prefetch(rec, gn + np.uint64(2))
        i = au + (np.int64(j) if identity else np.int64(ev[j]))
        r = np.uint64(y[i])
        c = np.uint64(x[i])
        ti = t[i]
        tr = ti - te_base  # relative to te's origin (int32 te: see AKFEngine._te_fit)
        if r < lo:
            top[c + ONE] = tr
            continue
        if r >= hi:
            bot[c + ONE] = tr
            continue
        tp = (r + ONE) * wpu + c + ONE
        u0, u1, u2, d0, d1, d2 = _rows_around(te, tp, wpu, c, r == lo, r + ONE == hi, top, bot)
        te0 = te[tp]
        tstar = _window_max(te, tp, te0, u0, u1, u2, d0, d1, d2)
        q = r * w + c
        g = ghi[q]
        rec[g, 0] = ti
        rec[g, 1] = 2 * (tr - te0) + np.int64(p[i] > 0)
        rec[g, 2] = tr - tstar
        ghi[q] = g + 1
        te[tp] = tr
    return k


@njit(cache=True, nogil=True)
def walk_block(rec, act, m0, m1, gcnt, glo, ghi, S, has_la_step, seg_t0, seg_inv_t, c_on, c_off, s_proc, s_iso,
               s_ref, rho_us, noise_form, con_px, coff_px):
    """Walk the pixels ``act[m0:m1]`` (:func:`group_block`'s groups): each pixel's events in stream
    order, each by :func:`._kernels.akf_event_step`, the state record in registers; then the
    pixel's group bounds cleared. Returns the events walked."""
    has_px = con_px.shape[0] > 0
    n = 0
    for m in range(m0, m1):
        if m + K.PREFETCH_AHEAD < m1:
            # the pixels come in first-event order on a large sensor (no scan): a cache miss each
            qn = np.uint64(act[m + K.PREFETCH_AHEAD])
            prefetch(S, qn * np.uint64(K.AKF_FIELDS))
            prefetch(glo, qn)
            prefetch(ghi, qn)
            prefetch(gcnt, qn)
        q = act[m]
        lo = glo[q]
        hi = ghi[q]
        jump_on = con_px[q] if has_px else c_on
        jump_off = -(coff_px[q] if has_px else c_off)
        sl = S[q, K.A_L]
        sp = S[q, K.A_P]
        sla = S[q, K.A_LA]
        stu = S[q, K.A_TU]
        rinv = S[q, K.A_RINV]
        beta = S[q, K.A_BETA]
        klog = S[q, K.A_KLOG]
        lastep = S[q, K.A_LASTEP]
        for e in range(lo, hi):
            ti = rec[e, 0]
            v = rec[e, 1]
            sl, sp, sla = K.akf_event_step(sl, sp, sla, stu, ti, v >> 1, rec[e, 2], (v & 1) != 0, rinv, beta, klog,
                                           lastep, has_la_step, seg_t0, seg_inv_t, jump_on, jump_off, s_proc, s_iso,
                                           s_ref, rho_us, noise_form)
            stu = np.float64(ti)
        S[q, K.A_L] = sl
        S[q, K.A_P] = sp
        S[q, K.A_LA] = sla
        S[q, K.A_TU] = stu
        gcnt[q] = 0
        glo[q] = 0
        ghi[q] = 0
        n += hi - lo
    return n


@njit(cache=True, nogil=True, inline="always")
def _block_stream(t, x, y, p, a, ev, e0, e1, identity, width, row_lo, row_hi, S, te, te_base, top, bot, has_la_step,
                  seg_t0, seg_inv_t, c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px, has_px):
    n = 0
    w = np.uint64(width)
    wpu = w + ONE + ONE
    lo = np.uint64(row_lo)
    hi = np.uint64(row_hi)
    au = np.int64(a)
    inner_hi = np.int64(row_hi) - np.int64(row_lo) - 1  # rows lo + 1 .. hi - 2 (relative 1 .. inner_hi - 1)
    for j in range(e0, e1):
        if j + K.PREFETCH_AHEAD < e1:  # the serial kernel's prefetch: the record and the 3x3 te window
            jn = au + (np.int64(j + K.PREFETCH_AHEAD) if identity else np.int64(ev[j + K.PREFETCH_AHEAD]))
            yn = np.uint64(y[jn])
            xn = np.uint64(x[jn])
            prefetch(S, (yn * w + xn) * np.uint64(K.AKF_FIELDS))
            tn = (yn + ONE) * wpu + xn + ONE
            prefetch(te, tn - wpu)
            prefetch(te, tn)
            prefetch(te, tn + wpu)
            if has_px:
                prefetch(con_px, yn * w + xn)
                prefetch(coff_px, yn * w + xn)
        i = au + (np.int64(j) if identity else np.int64(ev[j]))
        r = np.uint64(y[i])
        c = np.uint64(x[i])
        ti = t[i]
        tr = ti - te_base  # relative to te's origin (int32 te: see AKFEngine._te_fit)
        tp = (r + ONE) * wpu + c + ONE
        rr = np.int64(r) - np.int64(row_lo)
        if rr > 0 and rr < inner_hi:  # an inner row (most events; one test): its 3x3 window is in te
            u0 = te[tp - wpu - ONE]
            u1 = te[tp - wpu]
            u2 = te[tp - wpu + ONE]
            d0 = te[tp + wpu - ONE]
            d1 = te[tp + wpu]
            d2 = te[tp + wpu + ONE]
        else:
            if r < lo:  # a ghost row: its owner moves te, this band only its copy
                top[c + ONE] = tr
                continue
            if r >= hi:
                bot[c + ONE] = tr
                continue
            # the band's first or last row: the row above or below is the ghost row's copy
            u0, u1, u2, d0, d1, d2 = _rows_around(te, tp, wpu, c, r == lo, r + ONE == hi, top, bot)
        te0 = te[tp]
        tstar = _window_max(te, tp, te0, u0, u1, u2, d0, d1, d2)
        q = r * w + c
        jump_on = con_px[q] if has_px else c_on
        jump_off = -(coff_px[q] if has_px else c_off)
        lh, pp, la = K.akf_event_step(S[q, K.A_L], S[q, K.A_P], S[q, K.A_LA], S[q, K.A_TU], ti, tr - te0, tr - tstar,
                                      p[i] > 0, S[q, K.A_RINV], S[q, K.A_BETA], S[q, K.A_KLOG], S[q, K.A_LASTEP],
                                      has_la_step, seg_t0, seg_inv_t, jump_on, jump_off, s_proc, s_iso, s_ref,
                                      rho_us, noise_form)
        S[q, K.A_L] = lh
        S[q, K.A_P] = pp
        if has_la_step:
            S[q, K.A_LA] = la
        S[q, K.A_TU] = np.float64(ti)
        te[tp] = tr
        n += 1
    return n


@njit(cache=True, nogil=True)
def block_stream(t, x, y, p, a, ev, e0, e1, identity, width, row_lo, row_hi, S, te, te_base, top, bot, has_la_step,
                 seg_t0, seg_inv_t, c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px):
    """Filter a block's events in stream order: each by :func:`._kernels.akf_event_step`, as the
    serial kernel does, with t* from the 3x3 window of ``te`` and the block's ghost-row copies.

    The block's events are ``ev[e0:e1]`` (indices relative to ``a``, stream order, its ghost rows'
    included), or ``e0 .. e1 - 1`` themselves when ``identity``; its rows are ``[row_lo, row_hi)``;
    ``te``, ``te_base``, ``top`` and ``bot`` as in :func:`group_block` (an event of a ghost row
    moves only the copy); the other arguments those of :func:`._kernels.akf_events`. Each pixel
    sees its events in stream order with the serial filter's t* and Δt, so the state is the serial
    filter's bit for bit. Returns the events applied to the block's pixels.
    """
    if con_px.shape[0] > 0:  # two inlined copies, each with has_px a constant LLVM folds away
        return _block_stream(t, x, y, p, a, ev, e0, e1, identity, width, row_lo, row_hi, S, te, te_base, top, bot,
                             has_la_step, seg_t0, seg_inv_t, c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form,
                             con_px, coff_px, True)
    return _block_stream(t, x, y, p, a, ev, e0, e1, identity, width, row_lo, row_hi, S, te, te_base, top, bot,
                         has_la_step, seg_t0, seg_inv_t, c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form,
                         con_px, coff_px, False)


def cut_bands(row_counts: np.ndarray, n_bands: int) -> np.ndarray:
    """Edges of ``min(n_bands, rows)`` bands of contiguous rows with about equal ``row_counts``
    (the greedy cut of the running sum; at least one row each): band ``v`` is rows
    ``[edges[v], edges[v + 1])``."""
    H = row_counts.shape[0]
    nb = max(1, min(int(n_bands), H))
    cum = np.cumsum(row_counts)
    edges = np.empty(nb + 1, np.int64)
    edges[0], edges[nb] = 0, H
    total = int(cum[-1]) if H else 0
    cuts = np.searchsorted(cum, total * np.arange(1, nb) / nb, side="left") + 1
    for k in range(1, nb):
        r = int(cuts[k - 1]) if total > 0 else (H * k) // nb
        edges[k] = min(max(r, edges[k - 1] + 1), H - (nb - k))
    return edges


def plan_bands(row_hist: np.ndarray, n_bands: int):
    """The row bands of one window and where each worker's part of it goes, from ``row_hist``
    (``(workers, height)``: the events per row of each worker's part of the window).

    The bands are contiguous rows of about equal events (:func:`cut_bands`); a band's list holds
    the events of its rows and of its two ghost rows (the rows just above and below it), each
    worker's part in stream order after the parts before it. Returns ``(edges, band_of_row,
    edge_of_row, start, pos)``: band ``v`` has rows
    ``[edges[v], edges[v + 1])`` and the list ``[start[v], start[v + 1])``; ``band_of_row`` and
    ``edge_of_row`` (bit 1: the row is also the ghost row below the band above, bit 2: the ghost
    row above the band below) are :func:`block_scatter`'s tables, ``pos[w, v]`` worker ``w``'s
    first write position in band ``v``'s list.
    """
    nw, H = row_hist.shape
    edges = cut_bands(row_hist.sum(axis=0), n_bands)
    nb = edges.shape[0] - 1
    band_of_row = np.repeat(np.arange(nb, dtype=np.int32), np.diff(edges))
    edge_of_row = np.zeros(H, np.uint8)
    edge_of_row[edges[1:nb]] |= 1
    edge_of_row[edges[1:nb] - 1] |= 2
    # events of worker w in band v's list: rows [edges[v] - 1, edges[v + 1] + 1) clipped
    csum = np.zeros((nw, H + 1), np.int64)
    np.cumsum(row_hist, axis=1, out=csum[:, 1:])
    lo = np.maximum(edges[:-1] - 1, 0)
    hi = np.minimum(edges[1:] + 1, H)
    cnt = csum[:, hi] - csum[:, lo]  # (workers, bands)
    start = np.zeros(nb + 1, np.int64)
    np.cumsum(cnt.sum(axis=0), out=start[1:])
    pos = np.ascontiguousarray(start[:-1][None, :] + np.cumsum(cnt, axis=0) - cnt)
    return edges, band_of_row, edge_of_row, start, pos


class PixelAKFEngine(AKFEngine):
    """:class:`._engine.AKFEngine` whose events are filtered pixel by pixel (module docstring): the
    same interface, the same state and the same bits; frame switches and outputs are inherited."""

    kind = "pixel-parallel"

    def __init__(self, shape, measurements, params, n_workers: int = 1):
        super().__init__(shape, measurements, params, n_workers)
        H, W = self.shape
        n = self.n
        # last event times, int32 relative to te_base as the row-band engine's (half the bytes: the
        # 3x3 windows miss the caches less), int64 absolute past int32's reach (_te_fit); same bits
        self.te_px = K.padded_te(H, W, 0, np.int32)
        self.gcnt = np.zeros(n, np.int32)
        self.glo = np.zeros(n, np.int32)
        self.ghi = np.zeros(n, np.int32)
        # one worker per row band of the base engine (its pool: fewer than n_workers on a sensor
        # with fewer rows than workers)
        self._nw = nw = len(self.bands)
        self.ghost = np.zeros((nw, 2, W + 2), np.int32)  # each band's copies of its ghost rows (te's type)
        self._row_hist = np.zeros((nw, H), np.int64)
        self._cap = 0
        self._bufs_px = (None, None, None)
        self._barrier = threading.Barrier(nw) if nw > 1 else None

    def _int32_te(self) -> list:
        return []  # the row-band engine's per-band arrays are not used here

    def _start_band_te(self, b: int) -> None:
        return None

    def _te_fit(self, t_first: int, t_last: int) -> None:
        """:meth:`AKFEngine._te_fit` for the one shared ``te`` (and the ghost-row copies' type)."""
        lim = _engine.TE32_MAX
        if self.te_px.dtype == np.int32 and not (-lim - 1 <= t_first - self.te_base
                                                 and t_last - self.te_base <= lim):
            self.te_px = self.te_px.astype(np.int64) + self.te_base
            self.ghost = self.ghost.astype(np.int64)
            self.te_base = 0

    def start(self, t_start_us=None) -> int:
        t_init = super().start(t_start_us)  # te_base = t_init
        if self.te_px.dtype != np.int32:  # a restart after the int64 fallback
            self.te_px = self.te_px.astype(np.int32)
            self.ghost = self.ghost.astype(np.int32)
        self.te_px[:] = 0
        return t_init

    def _buffers(self, n: int, stream: bool = False):
        """(event indices, active pixels, group records) of at least ``n`` entries, reused; in
        stream order (``stream``) only the indices are used, and the other two stay unallocated."""
        if n >= 1 << 31:
            raise ValueError(f"a window of {n} events is too large for the pixel-parallel engine (< 2**31)")
        if self._cap < n or (not stream and self._bufs_px[2] is None):
            cap = max(n, 2 * self._cap, 1 << 16)
            self._bufs_px = (np.empty(cap, np.int32), None if stream else np.empty(cap, np.int64),
                             None if stream else np.empty((cap, 3), np.int64))
            self._cap = cap
        return self._bufs_px

    def _map_workers(self, fn) -> list:
        """``fn(w)`` for each worker ``w``, the last in the calling thread (as ``_map_bands``); a
        failing worker breaks the barrier, so the others stop too."""
        nw = self._nw
        if nw == 1:
            return [fn(0)]
        bar = self._barrier

        def run(w):
            try:
                return fn(w)
            except BaseException:
                bar.abort()  # the others leave their barrier with BrokenBarrierError
                raise
        futs = [self._pool.submit(run, w) for w in range(nw - 1)]
        errors = []
        try:
            last = run(nw - 1)
        except BaseException as e:  # noqa: BLE001 - re-raised once every worker has stopped
            errors.append(e)
        out = []
        for f in futs:
            try:
                out.append(f.result())
            except BaseException as e:  # noqa: BLE001
                errors.append(e)
        if errors:
            self._barrier.reset()
            raise next((e for e in errors if not isinstance(e, threading.BrokenBarrierError)), errors[0])
        return out + [last]

    def process(self, t, x, y, p, i0, i1) -> None:
        if i1 <= i0:
            return
        pr = self.params
        H, W = self.shape
        wp = W + 2
        n = i1 - i0
        threaded = self._nw > 1 and n >= PARALLEL_MIN_EVENTS  # else a hand-off costs more than the events
        pend, bands = self._pending, self.bands
        if pend is not None and not threaded:
            with PH.phase("switch", "parallel"):
                self._flush()  # the pending frame switch, by row bands
        self._pending = None  # the workers apply it, each its row band, before they start the window
        self._te_fit(int(t[i0]), int(t[i1 - 1]))
        tb = np.int64(self.te_base)
        args = (self._S, self.has_la_step, self.seg_t0, self.seg_inv_t, pr.c_on, pr.c_off, pr.process_noise_per_s,
                pr.isolated_noise_per_s, pr.refractory_noise, np.int64(pr.refractory_period_us), self.noise_form,
                self.con_px, self.coff_px)
        te, gcnt, glo, ghi, ghost = self.te_px, self.gcnt, self.glo, self.ghi, self.ghost
        stream = BLOCK_ORDER == "stream"
        if not threaded:
            with PH.phase("filter", "parallel"):
                if stream:  # the serial kernel itself (same te layout and times)
                    self.n_events += K.akf_events(t, x, y, p, i0, i1, 0, H, W, H, self._S, te, tb, *args[1:])
                    return
                ev, act, rec = self._buffers(n)  # one block, all rows: its ghost rows are te's padding
                with PH.phase("worker_group", "worker"):
                    k = group_block(t, x, y, p, i0, ev, 0, n, True, W, 0, H, te, tb, te[0:wp], te[(H + 1) * wp:],
                                    gcnt, glo, ghi, rec, act)
                with PH.phase("worker_walk", "worker"):
                    self.n_events += walk_block(rec, act, 0, k, gcnt, glo, ghi, *args)
            return
        nw = self._nw
        if stream and nw <= SELECT_MAX_WORKERS:
            self._process_selected(t, x, y, p, i0, i1, pend, tb, args)
            return
        parts = np.linspace(i0, i1, nw + 1).astype(np.int64)
        row_hist = self._row_hist
        bar = self._barrier
        shared: dict = {}

        def worker(w):
            if pend is not None:  # the frame switch due, on the fixed row bands (pixel-wise: any split will do)
                with PH.phase("worker_switch", "worker"):
                    pend(w, *bands[w])
            with PH.phase("worker_histogram", "worker"):
                K.row_histogram(y, parts[w], parts[w + 1], 1, row_hist[w])
            with PH.phase("worker_wait", "worker"):
                bar.wait()
            if w == nw - 1:  # the calling thread: the bands of this window, the lists' offsets, buffers
                edges, bor, eor, start, pos = plan_bands(row_hist, nw)
                shared.update(edges=edges, bor=bor, eor=eor, start=start, pos=pos,
                              bufs=self._buffers(int(start[-1]), stream))
            with PH.phase("worker_wait", "worker"):
                bar.wait()
            edges, start = shared["edges"], shared["start"]
            ev, act, rec = shared["bufs"]
            lo, hi = int(edges[w]), int(edges[w + 1])
            with PH.phase("worker_scatter", "worker"):
                block_scatter(y, i0, parts[w], parts[w + 1], shared["bor"], shared["eor"], shared["pos"][w], ev)
                # the band's ghost rows as they are before any band moves its own rows
                ghost[w, 0] = te[lo * wp:(lo + 1) * wp]
                ghost[w, 1] = te[(hi + 1) * wp:(hi + 2) * wp]
            with PH.phase("worker_wait", "worker"):
                bar.wait()
            e0, e1 = int(start[w]), int(start[w + 1])
            if stream:
                with PH.phase("worker_filter", "worker"):
                    return block_stream(t, x, y, p, i0, ev, e0, e1, False, W, lo, hi, self._S, te, tb, ghost[w, 0],
                                        ghost[w, 1], *args[1:])
            with PH.phase("worker_group_walk", "worker"):
                k = group_block(t, x, y, p, i0, ev, e0, e1, False, W, lo, hi, te, tb, ghost[w, 0], ghost[w, 1], gcnt,
                                glo, ghi, rec, act)
                return walk_block(rec, act, e0, e0 + k, gcnt, glo, ghi, *args)

        with PH.phase("filter", "parallel"):
            self.n_events += int(sum(self._map_workers(worker)))


    def _process_selected(self, t, x, y, p, i0, i1, pend, tb, args) -> None:
        """A window with few workers, without a barrier: the calling thread cuts the bands (from a
        1-in-8 sample of the rows) and copies their ghost rows; each worker then switches its band's
        pixels when a frame switch is due, selects its band's events (ghost rows included) from the
        whole window (:func:`._kernels.band_select`, branch-free) and filters them in stream order."""
        H, W = self.shape
        wp = W + 2
        nw = self._nw
        n = i1 - i0
        with PH.phase("plan_bands"):
            hist = self._row_hist[0]
            K.row_histogram(y, i0, i1, 8, hist)
            edges = cut_bands(hist, nw)
            te, ghost = self.te_px, self.ghost
            for w in range(nw):  # the ghost rows as they are before any band moves its own rows
                lo, hi = int(edges[w]), int(edges[w + 1])
                ghost[w, 0] = te[lo * wp:(lo + 1) * wp]
                ghost[w, 1] = te[(hi + 1) * wp:(hi + 2) * wp]
        S = self._S

        def worker(w):
            lo, hi = int(edges[w]), int(edges[w + 1])
            if pend is not None:  # the frame switch due, on this band's pixels (pixel-wise: any split will do)
                with PH.phase("worker_switch", "worker"):
                    pend(w, lo, hi)
            with PH.phase("worker_select", "worker"):
                idx = self._index_buffer(("select", w), n)[0]
                m = K.band_select(y, i0, i1, lo - 1, hi + 1, idx)
            with PH.phase("worker_filter", "worker"):
                return block_stream(t, x, y, p, i0, idx, 0, m, False, W, lo, hi, S, te, tb, ghost[w, 0], ghost[w, 1],
                                    *args[1:])

        with PH.phase("filter", "parallel"):
            self.n_events += int(sum(self._map_workers(worker)))


#: the worker count from which :func:`cpu_akf_engine` picks the pixel-parallel engine: the
#: break-even of ``benchmarks/akf.py --workers`` (both engines side by side). On 2 cores, with the
#: window split by band and each band filtered in stream order, the pixel engine ran at 0.85-1.1x
#: the row-band engine's speed at 1 and 2 workers (346x260 and 1280x720, forward and two-sided,
#: interleaved on a loaded machine); the row-band engine's speed-up stops growing past 8 workers
#: (3.6x at 8, 3.8x at 16 at 1280x720 forward on a 16-core host), so the crossing is expected at
#: or below 8 workers. The 16-core run of both engines (``benchmarks/device_run.sh``) places it.
PIXEL_MIN_WORKERS = 8
ENGINES = ("auto", "row-band", "pixel-parallel")
#: the engine ``reconstruct`` uses ("auto": by the worker count; a benchmark sets one to compare)
ENGINE = "auto"


def engine_kind(n_workers: int, engine: str | None = None) -> str:
    """"row-band" or "pixel-parallel": ``engine`` (default :data:`ENGINE`), "auto" resolved by
    :data:`PIXEL_MIN_WORKERS`."""
    engine = ENGINE if engine is None else engine
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if engine == "auto":
        return "pixel-parallel" if int(n_workers) >= PIXEL_MIN_WORKERS else "row-band"
    return engine


def cpu_akf_engine(shape, measurements, params, n_workers: int = 1, engine: str | None = None) -> AKFEngine:
    """The AKF's CPU engine for ``n_workers`` (:func:`engine_kind`): :class:`._engine.AKFEngine`
    or :class:`PixelAKFEngine`. Both give the same bits; ``engine.kind`` says which ran."""
    cls = PixelAKFEngine if engine_kind(n_workers, engine) == "pixel-parallel" else AKFEngine
    return cls(shape, measurements, params, n_workers)


def engine_line(method: str, device: str, n_workers: int, mode: str = "forward") -> str:
    """``"; cpu engine: ..."``, which CPU engine runs the AKF with ``n_workers`` in ``mode`` (the
    two-sided filter's passes run at once with half the workers each), else "" (another method
    or device); appended to the device line a run reports."""
    if method != "akf" or device != "cpu":
        return ""
    nw = int(n_workers)
    passes = [(nw + 1) // 2, nw // 2] if mode == "offline" and nw >= 2 else [nw]
    text = ", ".join(f"{engine_kind(w)} ({w} worker{'s' if w != 1 else ''})" for w in passes)
    return f"; cpu engine: {text}" + (" (backward and forward pass at once)" if len(passes) == 2 else "")
