"""The pixel-parallel CPU engine of the AKF (private): the GPU's decomposition on CPU threads.

The row-band engine (:class:`._engine.AKFEngine` with several workers) splits each batch of
events by row band, and every batch hands off between the bands; at 8-16 workers those hand-offs
and the memory traffic dominate. This engine takes the CUDA path's route instead
(:mod:`._cuda_kernels`): the events of one window (between two breakpoints of the driver: frame
switches, output times, chunk ends) are grouped by pixel, and each worker walks whole pixels,
each pixel's events in stream order, with the state record in registers. The only thing a pixel
needs from its neighbours is the isolated-pixel term's t* (eq. 2, §3.1.1), the latest event time
in its 3×3 window before each of its events, and that is read from the neighbours' groups
(:func:`._kernels.akf_walk_pixel`, the same function the CUDA kernels compile). So the per-event
arithmetic is the serial filter's, in the same order for every pixel: the outputs are
bit-identical to :class:`._engine.AKFEngine` for any window split and any number of workers.

One window, ``n`` events, ``w`` workers, ``B`` row blocks (contiguous rows; more blocks than
workers, so the blocks can be dealt out by their event counts):

1. each worker counts the blocks' events in its ``1/w`` of the window (:func:`block_histogram`);
2. each worker scatters its part's event indices into per-block lists, in stream order
   (:func:`block_scatter`): a counting sort by block, stable;
3. each worker groups its blocks' events by pixel (:func:`group_block`, a stable counting sort
   over the block's pixels: the groups in pixel order, so neighbours' groups lie near each other);
4. each worker walks its blocks' pixels (:func:`walk_block`);
5. each worker moves its pixels' last event times into ``te`` and clears their group bounds.

Steps are separated by a barrier (t* reads the neighbours' groups, which another worker may be
building; ``te`` keeps every pixel's time before the window until all walks are done). With one
worker there is one block and steps 1, 2 and the barriers are skipped. Frame switches and outputs
are the row-band engine's (one pass over the pixels, split by rows).
"""

from __future__ import annotations

import threading

import numpy as np
from numba import njit

from .._util import phases as PH
from . import _kernels as K
from ._engine import AKFEngine

#: row blocks per worker: the blocks are dealt out to the workers by their events, so a few per
#: worker balance clustered events (a bright object, a moving edge) without making blocks tiny
BLOCKS_PER_WORKER = 8
#: a window bound above every event index (the walk takes each pixel's whole group)
NO_BOUND = np.int64(np.iinfo(np.int32).max)


@njit(cache=True, nogil=True)
def block_histogram(y, j0, j1, block_of_row, hist):
    """``hist[b]`` = the number of events ``[j0, j1)`` in row block ``b`` (``hist`` zeroed here)."""
    hist[:] = 0
    for i in range(j0, j1):
        hist[block_of_row[y[i]]] += 1
    return j1 - j0


@njit(cache=True, nogil=True)
def block_scatter(y, a, j0, j1, block_of_row, pos, out):
    """Event indices (relative to the window start ``a``) of ``[j0, j1)`` into ``out`` at their
    block's write position ``pos[b]`` (advanced), in stream order."""
    for i in range(j0, j1):
        b = block_of_row[y[i]]
        out[pos[b]] = np.int32(i - a)
        pos[b] += 1
    return j1 - j0


@njit(cache=True, nogil=True)
def group_block(t, x, y, p, a, ev, e0, e1, identity, width, pix_lo, pix_hi, gcnt, glo, ghi, grp, tg, pg, act):
    """Group the block's events by pixel, each pixel's in stream order.

    The block's events are ``ev[e0:e1]`` (indices relative to ``a``), or ``e0 .. e1 - 1`` themselves
    when ``identity``; its pixels are ``[pix_lo, pix_hi)``. Pixel ``q``'s group becomes
    ``grp[glo[q]:ghi[q]]``, laid out in pixel order in the block's range ``[e0, e1)`` of ``grp``,
    each event's time and polarity copied to the same position of ``tg`` and ``pg`` (the walk
    reads them in sequence, and the groups of neighbouring pixels lie near each other); the
    pixels with events are listed in ``act[e0:e0 + k]`` in pixel order, and ``k`` is returned.
    ``gcnt``, ``glo`` and ``ghi`` are 0 for every pixel without events (:func:`finish_block`
    restores that).
    """
    for j in range(e0, e1):
        i = j if identity else np.int64(ev[j])
        gcnt[np.int64(y[a + i]) * width + np.int64(x[a + i])] += 1
    k = 0
    pos = e0
    for q in range(pix_lo, pix_hi):
        c = gcnt[q]
        if c != 0:
            act[e0 + k] = q
            k += 1
            glo[q] = pos
            ghi[q] = pos
            pos += c
    for j in range(e0, e1):
        i = j if identity else np.int64(ev[j])
        q = np.int64(y[a + i]) * width + np.int64(x[a + i])
        r = ghi[q]
        grp[r] = np.int32(i)
        tg[r] = t[a + i]
        pg[r] = p[a + i]
        ghi[q] = r + 1
    return k


@njit(cache=True, nogil=True)
def walk_block(tg, pg, height, width, act, m0, m1, glo, ghi, grp, te, tlast, S, has_la_step, seg_t0, seg_inv_t,
               c_on, c_off, s_proc, s_iso, s_ref, rho_us, noise_form, con_px, coff_px):
    """Walk the pixels ``act[m0:m1]`` (:func:`._kernels.akf_walk_pixel` on the gathered times
    ``tg`` and polarities ``pg``): each pixel's events in stream order, t* from the neighbours' groups and ``te`` (every pixel's last event time before
    the window); each pixel's last event time goes to ``tlast``. Returns the events walked."""
    has_px = con_px.shape[0] > 0
    nb_pos = np.empty(8, np.int64)
    nb_hi = np.empty(8, np.int64)
    nb_te = np.empty(8, np.int64)
    n = 0
    for m in range(m0, m1):
        q = act[m]
        lo = glo[q]
        hi = ghi[q]
        n_nb, t_quiet = K.window_neighbours(q, height, width, glo, ghi, te, nb_pos, nb_hi, nb_te)
        jump_on = con_px[q] if has_px else c_on
        jump_off = -(coff_px[q] if has_px else c_off)
        g, tl = K.akf_walk_pixel(S, q, tg, pg, 0, grp, True, lo, hi, NO_BOUND, te[q], t_quiet, nb_pos, nb_hi, nb_te, n_nb,
                                 has_la_step, seg_t0, seg_inv_t, jump_on, jump_off, s_proc, s_iso, s_ref, rho_us,
                                 noise_form)
        tlast[q] = tl
        n += hi - lo
    return n


@njit(cache=True, nogil=True)
def finish_block(act, m0, m1, te, tlast, gcnt, glo, ghi):
    """After every walk of the window: the pixels ``act[m0:m1]`` take their last event time into
    ``te`` and their group bounds are cleared for the next window."""
    for m in range(m0, m1):
        q = act[m]
        te[q] = tlast[q]
        gcnt[q] = 0
        glo[q] = 0
        ghi[q] = 0
    return m1 - m0


def deal_blocks(weights: np.ndarray, n_workers: int) -> list[tuple[int, int]]:
    """Contiguous ranges of blocks, one per worker, of about equal total ``weights`` (greedy on
    the running sum): ``[(b0, b1), ...]``, possibly empty ranges at the end."""
    nb = weights.shape[0]
    cum = np.cumsum(weights, dtype=np.float64)
    total = float(cum[-1]) if nb else 0.0
    cuts = [0]
    for w in range(1, n_workers):
        c = int(np.searchsorted(cum, total * w / n_workers, side="left")) + 1 if total > 0 else (nb * w) // n_workers
        cuts.append(min(max(c, cuts[-1]), nb))
    cuts.append(nb)
    return [(cuts[w], cuts[w + 1]) for w in range(n_workers)]


class PixelAKFEngine(AKFEngine):
    """:class:`._engine.AKFEngine` whose events are filtered pixel by pixel (module docstring): the
    same interface, the same state and the same bits; frame switches and outputs are inherited."""

    kind = "pixel-parallel"

    def __init__(self, shape, measurements, params, n_workers: int = 1):
        super().__init__(shape, measurements, params, n_workers)
        H, W = self.shape
        n = self.n
        self.te_px = np.zeros(n, np.int64)  # every pixel's last event time before the window (µs)
        self.tlast = np.zeros(n, np.int64)
        self.gcnt = np.zeros(n, np.int32)
        self.glo = np.zeros(n, np.int64)
        self.ghi = np.zeros(n, np.int64)
        # one worker per row band of the base engine (its pool: fewer than n_workers on a sensor
        # with fewer rows than workers)
        self._nw = nw = len(self.bands)
        nb = max(1, min(H, nw * BLOCKS_PER_WORKER)) if nw > 1 else 1
        edges = np.round(np.linspace(0, H, nb + 1)).astype(np.int64)
        self.block_of_row = np.repeat(np.arange(nb, dtype=np.int32), np.diff(edges))
        self.block_rows = edges  # block b: rows [edges[b], edges[b + 1])
        self.n_blocks = nb
        self._cap = 0
        self._barrier = threading.Barrier(nw) if nw > 1 else None

    def _int32_te(self) -> list:
        return []  # the row-band engine's per-band padded arrays are not used here

    def _start_band_te(self, b: int) -> None:
        return None

    def _te_fit(self, t_first: int, t_last: int) -> None:
        return None  # int64 absolute times throughout

    def start(self, t_start_us=None) -> int:
        t_init = super().start(t_start_us)
        self.te_px[:] = t_init
        return t_init

    def _buffers(self, n: int):
        if self._cap < n:
            cap = max(n, 2 * self._cap, 1 << 16)
            if cap >= 1 << 31:
                raise ValueError(f"a window of {n} events is too large for the pixel-parallel engine (< 2**31)")
            self._grp = np.empty(cap, np.int32)
            self._ev = np.empty(cap, np.int32)
            self._act = np.empty(cap, np.int64)
            self._tg = np.empty(cap, np.int64)
            self._pg = np.empty(cap, np.int8)
            self._cap = cap
        return self._grp, self._ev, self._act, self._tg, self._pg

    def _map_workers(self, fn) -> list:
        """``fn(w)`` for each worker ``w``, the last in the calling thread (as ``_map_bands``)."""
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
        self._flush()  # a pending frame switch, by row bands
        pr = self.params
        H, W = self.shape
        n = i1 - i0
        grp, ev, act, tg, pg = self._buffers(n)
        args = (self.S, self.has_la_step, self.seg_t0, self.seg_inv_t, pr.c_on, pr.c_off, pr.process_noise_per_s,
                pr.isolated_noise_per_s, pr.refractory_noise, np.int64(pr.refractory_period_us), self.noise_form,
                self.con_px, self.coff_px)
        te, tlast, gcnt, glo, ghi = self.te_px, self.tlast, self.gcnt, self.glo, self.ghi
        if self._nw == 1:
            with PH.phase("filter", "parallel"):
                k = group_block(t, x, y, p, i0, ev, 0, n, True, W, 0, self.n, gcnt, glo, ghi, grp, tg, pg, act)
                self.n_events += walk_block(tg, pg, H, W, act, 0, k, glo, ghi, grp, te, tlast, *args)
                finish_block(act, 0, k, te, tlast, gcnt, glo, ghi)
            return
        nw, nb = self._nw, self.n_blocks
        parts = np.linspace(i0, i1, nw + 1).astype(np.int64)
        hist = np.zeros((nw, nb), np.int64)
        bor = self.block_of_row
        brow = self.block_rows
        bar = self._barrier
        shared: dict = {}

        def worker(w):
            with PH.phase("worker_histogram", "worker"):
                block_histogram(y, parts[w], parts[w + 1], bor, hist[w])
            with PH.phase("worker_wait", "worker"):
                bar.wait()
            if w == nw - 1:  # the calling thread: block offsets and the blocks dealt out by events
                tot = hist.sum(axis=0)
                bstart = np.zeros(nb + 1, np.int64)
                np.cumsum(tot, out=bstart[1:])
                pos = bstart[:-1][None, :] + np.cumsum(hist, axis=0) - hist
                shared.update(bstart=bstart, pos=np.ascontiguousarray(pos), deal=deal_blocks(tot, nw),
                              k=np.zeros(nb, np.int64))
            with PH.phase("worker_wait", "worker"):
                bar.wait()
            bstart, deal, kk = shared["bstart"], shared["deal"], shared["k"]
            with PH.phase("worker_scatter", "worker"):
                block_scatter(y, i0, parts[w], parts[w + 1], bor, shared["pos"][w], ev)
            with PH.phase("worker_wait", "worker"):
                bar.wait()
            b0, b1 = deal[w]
            with PH.phase("worker_group", "worker"):
                for b in range(b0, b1):
                    kk[b] = group_block(t, x, y, p, i0, ev, bstart[b], bstart[b + 1], False, W, brow[b] * W,
                                        brow[b + 1] * W, gcnt, glo, ghi, grp, tg, pg, act)
            with PH.phase("worker_wait", "worker"):
                bar.wait()
            m = 0
            with PH.phase("worker_walk", "worker"):
                for b in range(b0, b1):
                    m += walk_block(tg, pg, H, W, act, bstart[b], bstart[b] + kk[b], glo, ghi, grp, te, tlast, *args)
            with PH.phase("worker_wait", "worker"):
                bar.wait()
            with PH.phase("worker_finish", "worker"):
                for b in range(b0, b1):
                    finish_block(act, bstart[b], bstart[b] + kk[b], te, tlast, gcnt, glo, ghi)
            return m

        with PH.phase("filter", "parallel"):
            self.n_events += int(sum(self._map_workers(worker)))


#: the worker count from which :func:`cpu_akf_engine` picks the pixel-parallel engine. Measured by
#: ``benchmarks/akf.py --workers`` (both engines side by side): on one worker the row-band
#: engine's serial filter is the faster (its prefetching event loop, no grouping pass); from two
#: workers on the pixel-parallel engine scales further (no per-batch hand-off between bands)
PIXEL_MIN_WORKERS = 2
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
