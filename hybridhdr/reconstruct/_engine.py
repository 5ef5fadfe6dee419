"""Filter engines and the event/frame/output scheduler shared by all methods (private)."""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator

import numpy as np

from .._util import phases as PH
from .._util.checks import check_shape
from .._util.procs import raise_if_signalled
from .._util.prefetch import Prefetcher
from . import _kernels as K

T_EXACT_LIMIT_US = 1 << 53  # float64 holds every integer µs below this
PARALLEL_MIN_WORK = 20_000  # events or pixels per call below which bands run in the caller
TE32_MAX = int(np.iinfo(np.int32).max)  # the int32 last-event times' reach, µs (about 35 minutes)
#: above this many bands, the threaded AKF splits batches by row look-up (band_split_lut), whose
#: cost per event does not grow with the bands, instead of testing every band (band_split)
SPLIT_LUT_MIN_BANDS = 4


def check_time_range(t: np.ndarray, what: str = "event timestamps") -> None:
    if t.size and (int(t[-1]) >= T_EXACT_LIMIT_US or int(t[0]) <= -T_EXACT_LIMIT_US):
        raise ValueError(f"{what} must lie within ±2**53 µs (float64-exact), got {int(t[0])}..{int(t[-1])}")


def row_bands(height: int, n_workers: int) -> list[tuple[int, int]]:
    """Split rows 0..height into ``n_workers`` contiguous bands of (nearly) equal size."""
    n = max(1, min(int(n_workers), height))
    edges = [round(i * height / n) for i in range(n + 1)]
    return [(edges[i], edges[i + 1]) for i in range(n) if edges[i + 1] > edges[i]]


def segment_span(m, k: int, segment):
    """``(codes or None, segment or None, t0_us, 1/T_us, T in s)`` of frame segment k of the
    measurement provider ``m``: its per-code tables when it has them (``m.segment_codes``), else
    ``segment(k)`` (the provider's segment, fetched as the caller does); T is the segment's length
    (0 for the last, open one). Shared by the CPU and GPU frame switches."""
    times = m.times_us
    t0_us = int(times[k])
    t1_us = int(times[k + 1]) if k + 1 < len(m) else None
    codes_fn = getattr(m, "segment_codes", None)
    sc = codes_fn(k) if codes_fn is not None else None
    seg = None
    if sc is None:
        seg = segment(k)
        t0_us, t1_us = seg.t0_us, seg.t1_us
    if t1_us is None:
        return sc, seg, t0_us, 0.0, 0.0
    T_us = t1_us - t0_us
    return sc, seg, t0_us, 1.0 / T_us, T_us * K.US


class Engine:
    """Base of the per-method engines driven by :func:`drive`.

    The driver calls :meth:`start` once, then interleaves :meth:`process` (events in time
    order), :meth:`switch` (at :meth:`next_switch_us`) and :meth:`output` (never changes state).
    """

    uses_events = True

    def __init__(self, shape, n_workers: int = 1):
        self.shape = (int(shape[0]), int(shape[1]))
        self.n = self.shape[0] * self.shape[1]
        self.n_workers = max(1, int(n_workers))
        self.bands = row_bands(self.shape[0], self.n_workers)
        self._pool = ThreadPoolExecutor(len(self.bands) - 1) if len(self.bands) > 1 else None
        self._bufs: dict = {}  # reused int32 index buffers, see _index_buffer
        self.n_events = 0
        self.con_px = np.empty(0)  # per-pixel ON / OFF thresholds (flattened); empty: the params' scalars
        self.coff_px = np.empty(0)

    def set_thresholds(self, c_on, c_off) -> None:
        """Per-pixel ON and OFF thresholds (log units, arrays of the sensor's shape), or None for
        the parameters' scalars; non-finite or non-positive entries take the scalar."""
        if c_on is None and c_off is None:
            self.con_px = np.empty(0)
            self.coff_px = np.empty(0)
            return
        pr = self.params
        out = []
        for a, scalar, name in ((c_on, pr.c_on, "c_on"), (c_off, pr.c_off, "c_off")):
            a = np.asarray(a, dtype=np.float64)
            check_shape(a, "H W", f"threshold map {name} (the sensor's)", sizes=dict(zip("HW", self.shape)))
            a = np.where(np.isfinite(a) & (a > 0), a, scalar)
            out.append(np.ascontiguousarray(a.reshape(-1)))
        self.con_px, self.coff_px = out

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _map_bands(self, fn, min_work: int) -> list:
        """Run ``fn(band_index, row_lo, row_hi)`` per band, in threads when worth it.

        The last band runs in the calling thread (one hand-off fewer per call).
        """
        if self._pool is None or min_work < PARALLEL_MIN_WORK:
            return [fn(b, lo, hi) for b, (lo, hi) in enumerate(self.bands)]
        futs = [self._pool.submit(fn, b, lo, hi) for b, (lo, hi) in enumerate(self.bands[:-1])]
        b = len(self.bands) - 1
        errors = []
        try:
            last = fn(b, *self.bands[b])
        except BaseException as e:  # noqa: BLE001 - re-raised below, once every worker has stopped
            errors.append(e)
        out = []
        for f in futs:  # wait for every worker, even after an error: none may outlive the call
            try:
                out.append(f.result())
            except BaseException as e:  # noqa: BLE001
                errors.append(e)
        if errors:
            # the cause, not the BrokenBarrierError it gave the workers waiting for it
            raise next((e for e in errors if not isinstance(e, threading.BrokenBarrierError)), errors[0])
        return out + [last]

    def _index_buffer(self, key, n: int, rows: int = 1) -> np.ndarray:
        """A reused int32 index buffer (``rows``, >= ``n``) for the band-selection kernels.

        ``key`` names the owner: ``("band", b)`` for :func:`_kernels.band_select`,
        ``("split", w)`` for worker ``w``'s :func:`_kernels.band_split`; threads never share one.
        """
        if n >= 1 << 31:
            raise ValueError(f"a batch of {n} events is too large for the parallel kernels (< 2**31)")
        buf = self._bufs.get(key)
        if buf is None or buf.shape[0] != rows or buf.shape[1] < n:
            buf = np.empty((rows, max(n, 2 * (buf.shape[1] if buf is not None else 0))), np.int32)
            self._bufs[key] = buf
        return buf

    # -- interface ----------------------------------------------------------------------------
    def start(self, t_start_us: int | None) -> int:
        raise NotImplementedError

    def next_switch_us(self) -> int | None:
        return None

    def switch(self) -> None:
        raise NotImplementedError

    def process(self, t, x, y, p, i0: int, i1: int) -> None:
        raise NotImplementedError

    def output(self, t_us: int) -> np.ndarray:
        raise NotImplementedError

    def output_clamped(self, t_us: int) -> tuple[np.ndarray, int]:
        """``(image, n)``: :meth:`output` with every value below ``K.MIN_INTENSITY`` (or NaN) raised
        to it, ``n`` of them (:func:`clamped_output`). The row-band engines clamp each band in its
        worker; this default clamps the whole image in the caller."""
        img = self.output(t_us)
        return img, K.clamp_linear(img)


class AKFEngine(Engine):
    """Asynchronous Kalman filter state (eqs. 14-21) over a measurement provider."""

    kind = "row-band"  # the events of each batch split by row band (see _pixel_engine for the other)

    lookahead = True  # compute a generic provider's next segment in the background

    def __init__(self, shape, measurements, params, n_workers: int = 1):
        super().__init__(shape, n_workers)
        self.m = measurements
        self.params = params
        self._S = K.aligned_state(self.n, K.AKF_FIELDS)
        # last-event times, int32 relative to te_base (half the bytes of int64: the 3x3 windows of
        # a 1280x720 sensor, which no cache holds, cost 20-25 % less; benchmarks/akf.py), int64
        # absolute once a recording outgrows int32 (_te_fit): the same bits either way
        self.te = self._int32_te()
        self.te_base = 0
        self._pending = None  # a frame switch not yet applied: fn(band, row_lo, row_hi)
        self._ahead = None  # (k, Future of segment k) computed in the background
        self._ahead_pool = None
        self._hist = np.zeros(self.shape[0], np.int64)
        self.k = -1
        self.seg_t0 = 0.0
        self.seg_inv_t = 0.0
        self.has_la_step = False
        self.noise_form = K.NOISE_PAPER if params.noise_model == "paper" else K.NOISE_REFERENCE

    def set_thresholds(self, c_on, c_off) -> None:
        """:meth:`Engine.set_thresholds`, also given to a measurement provider that takes them
        (frame augmentation: eq. 12 and the interpolation step ON and OFF events by their own
        thresholds)."""
        super().set_thresholds(c_on, c_off)
        fn = getattr(self.m, "set_thresholds", None)
        if fn is not None:
            fn(*((None, None) if self.con_px.size == 0 else (self.con_px, self.coff_px)))

    @property
    def S(self) -> np.ndarray:
        """The per-pixel state (n_pixels, 8) with any pending frame switch applied."""
        self._flush()
        return self._S

    def _flush(self) -> None:
        if self._pending is not None:
            self._map_bands(lambda b, lo, hi: None, self.n)

    def _map_bands(self, fn, min_work: int) -> list:
        """As :meth:`Engine._map_bands`, each band first applying its rows of a pending switch."""
        pend = self._pending
        if pend is None:
            return super()._map_bands(fn, min_work)
        self._pending = None

        def both(b, lo, hi):
            pend(b, lo, hi)
            return fn(b, lo, hi)
        return super()._map_bands(both, max(min_work, self.n))

    def _load(self, k: int, t_to: float | None = None) -> None:
        """Load segment ``k``; first propagate the current one to ``t_to`` µs (a frame switch).

        Both happen in one pass per row band (:func:`_kernels.akf_switch`); when the provider
        exposes the segment's codes and tables (``segment_codes``), each band also builds its
        own part of the measurement in that pass (:func:`_kernels.akf_switch_lut`). The pass is
        deferred into the next parallel call (events, output, or a state read), where each
        worker first switches its own rows: one hand-off per segment instead of two. The switch
        is pixel-wise, so it commutes with the band edges moving in between.
        """
        self._flush()
        n = self.n
        W = self.shape[1]
        sc, seg, t0_us, seg_inv_t, seg_t_s = segment_span(self.m, k, self._segment)
        prop = t_to is not None
        disc = prop and self.params.frame_update == "discrete"  # the first frame initialises instead
        # process noise accrues at switches too in our model (0: the paper's, at events only)
        s_proc = float(self.params.process_noise_per_s) if self.params.frame_update == "discrete" else 0.0
        args = (self._S, prop, self.seg_t0, self.seg_inv_t, float(t_to) if prop else 0.0)
        if sc is not None:
            for a, name in ((sc.code, "code"), (sc.code_next, "code_next")):
                if a.ndim != 1 or a.shape[0] not in ((n,) if name == "code" else (0, n)):
                    raise ValueError(f"measurement segment {k}: {name} has shape {a.shape}, expected ({n},) (H*W)")
            self._pending = lambda b, lo, hi: K.akf_switch_lut(*args, sc.code, sc.code_next, sc.max_code, sc.rbar,
                                                               sc.log_frame, sc.rinv, sc.censor, sc.la_step,
                                                               seg_t_s, disc, s_proc, lo * W, hi * W)
            self.has_la_step = sc.la_step != 0.0
        else:
            def col(a, name, required):
                if a is None:
                    if required:
                        raise ValueError(f"measurement segment {k} has no {name}; the AKF needs it")
                    return np.empty(0)
                a = np.ascontiguousarray(a, dtype=np.float64).reshape(-1)
                if a.shape[0] != n:
                    raise ValueError(f"measurement segment {k}: {name} has {a.shape[0]} values, expected {n} (H*W)")
                return a

            lf = col(seg.log_frame, "log_frame", True)
            rinv = col(seg.rinv, "rinv", True)
            beta = col(seg.beta, "beta", False)
            step = col(seg.la_step, "la_step", False)
            cens = col(getattr(seg, "censor", None), "censor", False)
            disc = disc and bool(getattr(seg, "frame_update", True))
            uf = col(getattr(seg, "update_log_frame", None), "update_log_frame", False)
            self._pending = lambda b, lo, hi: K.akf_switch(*args, lf, rinv, beta, step, cens, seg_t_s, disc,
                                                           s_proc, uf, lo * W, hi * W)
            self.has_la_step = seg.la_step is not None
        self.seg_t0 = float(t0_us)
        self.seg_inv_t = seg_inv_t
        self.k = k

    def _segment(self, k: int):
        """``m.segment(k)``; then segment k+1 is computed in a background thread.

        A provider's own work (frame augmentation: deblurring, threshold calibration) then
        overlaps the filtering of segment k instead of stalling it. Calls stay sequential, in
        the same order, so the result does not change; only one runs at a time.
        """
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead[0] == k:
            seg = ahead[1].result()
        else:
            if ahead is not None:
                ahead[1].exception()  # wait for the stale one (providers are not re-entrant)
            seg = self.m.segment(k)
        if self.lookahead and k + 1 < len(self.m):
            if self._ahead_pool is None:
                self._ahead_pool = ThreadPoolExecutor(1, thread_name_prefix="hybridhdr-measure")
            self._ahead = (k + 1, self._ahead_pool.submit(self.m.segment, k + 1))
        return seg

    def close(self):
        """Stop the worker threads; wait for a measurement being computed ahead (idempotent)."""
        if self._ahead_pool is not None:
            self._ahead_pool.shutdown(wait=True)
            self._ahead_pool = None
            self._ahead = None
        super().close()

    def start(self, t_start_us=None) -> int:
        times = self.m.times_us
        k0 = 0 if t_start_us is None else max(int(np.searchsorted(times, t_start_us, side="right")) - 1, 0)
        t_init = int(times[k0])
        check_time_range(times, "frame timestamps")
        self._load(k0)
        # initialise from the frame, never from t = 0 (K.akf_start, each band its rows, after its
        # part of the load): L̂ = L^A, P = the initial covariance; a pixel clipped in the first
        # frame is known only to lie beyond its bound (the censored initial P) ... except that a
        # clipped dark code bounds it on both sides: the state is ln(I + I0) with I >= 0, so
        # ln I0 <= L <= L_dark, an interval of width w = L_dark - ln I0 (1e-3 at code 0 of a
        # gamma-2.2 8-bit camera with I0 = 1e-3; 4.9 for AHDR's codes < 100): its P is w² (the
        # interval as one standard deviation), at least the unclipped initial P
        p0 = float(self.params.initial_covariance)
        p_cens = float(getattr(self.params, "censored_initial_covariance", p0))
        off = getattr(self.params, "intensity_offset", None)
        log_off = math.log(off) if off is not None else 0.0
        if self.te and self.te[0].dtype != np.int32:  # a restart after the int64 fallback
            self.te = self._int32_te()
        W = self.shape[1]

        def band(b, lo, hi):
            K.akf_start(self._S, p0, p_cens, log_off, off is not None, float(t_init), lo * W, hi * W)
            self._start_band_te(b)
        with PH.phase("start", "parallel"):
            self._map_bands(band, self.n)
        self.te_base = t_init
        return t_init

    def _start_band_te(self, b: int) -> None:
        """Zero band ``b``'s last-event times (relative to the start: each worker first touches
        its own pages)."""
        self.te[b][:] = 0

    def _int32_te(self) -> list:
        """One zeroed int32 last-event-time array per band (times relative to ``te_base``)."""
        return [K.padded_te(self.shape[0], self.shape[1], 0, np.int32) for _ in self.bands]

    def _te_fit(self, t_first: int, t_last: int) -> None:
        """Make the events' times ``[t_first, t_last]`` µs fit the last-event times.

        The kernels store ``t - te_base`` (``te_base``: the start time) in int32, which reaches
        about 35 minutes from the start. Past that the arrays become int64 absolute times
        (``te_base = 0``) for the rest of the run. Every use is a difference of two times, so the
        filter's bits never depend on which. (Moving the base instead would rarely help: a pixel
        that never fires, and the padding, keep the start time.)"""
        if self.te[0].dtype == np.int32 and not (-TE32_MAX - 1 <= t_first - self.te_base
                                                 and t_last - self.te_base <= TE32_MAX):
            self.te = [te.astype(np.int64) + self.te_base for te in self.te]
            self.te_base = 0

    def next_switch_us(self):
        return int(self.m.times_us[self.k + 1]) if self.k + 1 < len(self.m) else None

    def switch(self) -> None:
        if PH.ACTIVE is not None and self._pending is not None:  # two switches with no call in between
            with PH.phase("switch", "parallel"):
                self._flush()
        with PH.phase("load_segment"):
            self._load(self.k + 1, t_to=float(self.m.times_us[self.k + 1]))

    def process(self, t, x, y, p, i0, i1) -> None:
        if i1 <= i0:
            return
        pr = self.params
        H, W = self.shape
        self._te_fit(int(t[i0]), int(t[i1 - 1]))
        tb = np.int64(self.te_base)
        rho = np.int64(pr.refractory_period_us)
        args = (self.has_la_step, self.seg_t0, self.seg_inv_t, pr.c_on, pr.c_off, pr.process_noise_per_s,
                pr.isolated_noise_per_s, pr.refractory_noise, rho, self.noise_form, self.con_px, self.coff_px)
        if len(self.bands) == 1:
            if PH.ACTIVE is not None and self._pending is not None:
                with PH.phase("switch", "parallel"):
                    self._flush()
            with PH.phase("filter", "parallel"):
                self.n_events += K.akf_events(t, x, y, p, i0, i1, 0, H, W, H, self.S, self.te[0], tb, *args)
            return
        if i1 - i0 >= PARALLEL_MIN_WORK:
            # a 1-in-8 sample of the rows balances as well, 8x cheaper
            with PH.phase("plan_bands"):
                self._rebalance(K.row_histogram(y, i0, i1, 8, self._hist))

        if i1 - i0 < PARALLEL_MIN_WORK:
            def band(b, lo, hi):
                # select the band's rows plus the two ghost rows, then filter only those events
                idx = self._index_buffer(("band", b), i1 - i0)[0]
                m = K.band_select(y, i0, i1, lo - 1, hi + 1, idx)
                return K.akf_events_indexed(t, x, y, p, i0, idx, m, lo, hi, W, H, self._S, self.te[b], tb, *args)
            with PH.phase("filter_small", "parallel"):
                self.n_events += int(sum(self._map_bands(band, i1 - i0)))
            return
        # threaded (every band has its own thread): worker w splits part w of the batch for all
        # bands (own rows plus the two ghost rows), then each band filters its events part by
        # part, in time order, waiting only for the part it reaches next to be split (no barrier
        # for all the parts: a band filters part 0 while part 1 is still being split)
        with PH.phase("plan_bands"):
            nb = len(self.bands)
            parts = np.linspace(i0, i1, nb + 1).astype(np.int64)
            los = np.array([lo - 1 for lo, _ in self.bands], np.int64)
            his = np.array([hi + 1 for _, hi in self.bands], np.int64)
            bufs = [self._index_buffer(("split", w), int(parts[w + 1] - parts[w]), nb) for w in range(nb)]
            counts = np.zeros((nb, nb), np.int64)
            ready = [threading.Event() for _ in range(nb)]
            failed: list = []
            lut = self._band_lut() if nb > SPLIT_LUT_MIN_BANDS else None

        def band_threaded(b, lo, hi):
            with PH.phase("worker_split", "worker"):
                try:
                    if lut is None:
                        K.band_split(y, i0, parts[b], parts[b + 1], los, his, bufs[b], counts[b])
                    else:
                        K.band_split_lut(y, i0, parts[b], parts[b + 1], lut[0], lut[1], bufs[b], counts[b])
                except BaseException:
                    failed.append(b)
                    for e in ready:  # release the other workers (they raise BrokenBarrierError)
                        e.set()
                    raise
                ready[b].set()
            n = 0
            for w in range(nb):
                if not ready[w].is_set():
                    with PH.phase("worker_wait_split", "worker"):
                        ready[w].wait()
                if failed:
                    raise threading.BrokenBarrierError(f"worker {failed[0]} failed")
                with PH.phase("worker_filter", "worker"):
                    n += K.akf_events_indexed(t, x, y, p, i0, bufs[w][b], counts[w, b], lo, hi, W, H, self._S,
                                              self.te[b], tb, *args)
            return n
        with PH.phase("filter", "parallel"):
            self.n_events += int(sum(self._map_bands(band_threaded, i1 - i0)))

    def _band_lut(self):
        """(band of each row, edge flags of each row) for :func:`_kernels.band_split_lut`,
        rebuilt when the bands move."""
        if getattr(self, "_lut_bands", None) != self.bands:
            H = self.shape[0]
            bor = np.empty(H, np.int32)
            edge = np.zeros(H, np.uint8)
            for b, (lo, hi) in enumerate(self.bands):
                bor[lo:hi] = b
                if b > 0:
                    edge[lo] |= 1  # ghost row hi of band b - 1
                if b + 1 < len(self.bands):
                    edge[hi - 1] |= 2  # ghost row lo - 1 of band b + 1
            self._lut = (bor, edge)
            self._lut_bands = list(self.bands)
        return self._lut

    def _rebalance(self, hist) -> None:
        """Move the band edges so each band gets about the same number of this batch's events
        (``hist``: the events per row, of the batch or of a sample of it).

        Events cluster (a moving edge, a bright object), so equal row counts leave one worker
        idle. Each band's private last-event-time array is exact for its own rows and its two
        ghost rows; when an edge moves, the rows a band newly reads (own or ghost) are copied
        from the band that owned them, whose values are exact, so the filter stays bit-identical
        to the serial one. The state ``S`` is shared and pixel-wise, so it needs nothing.
        """
        H, W = self.shape
        nb = len(self.bands)
        cum = np.cumsum(hist)
        edges = [0]
        for k in range(1, nb):
            r = int(np.searchsorted(cum, cum[-1] * k / nb, side="left")) + 1
            edges.append(min(max(r, edges[-1] + 1), H - (nb - k)))
        edges.append(H)
        new = [(edges[k], edges[k + 1]) for k in range(nb)]
        if new == self.bands:
            return
        owner = np.empty(H, np.int64)
        for b, (lo, hi) in enumerate(self.bands):
            owner[lo:hi] = b
        views = [K.te_view(te, H, W) for te in self.te]
        for b, (lo, hi) in enumerate(new):
            # rows b now reads that it did not keep exact (its old rows and two ghost rows are):
            # copied from their old owner; at most the few rows an edge moved by, not every row
            olo, ohi = self.bands[b]
            n0, n1 = max(lo - 1, 0), min(hi + 1, H)
            h0, h1 = max(olo - 1, 0), min(ohi + 1, H)
            for r in (*range(n0, min(n1, h0)), *range(max(n0, h1), n1)):
                views[b][r] = views[owner[r]][r]  # owner[r] != b: b's own rows stay intact
        self.bands = new

    def output(self, t_us: int, with_state: bool = False):
        return self._output(t_us, with_state)[0]

    def output_clamped(self, t_us: int) -> tuple[np.ndarray, int]:
        return self._output(t_us, False, clamp=True)

    def _output(self, t_us: int, with_state: bool, clamp: bool = False):
        """(image or (image, L̂, P), clamped count); each band clamps its own rows when ``clamp``."""
        W = self.shape[1]
        out = np.empty(self.n, np.float32)
        lg = np.empty(self.n if with_state else 0)
        var = np.empty(self.n if with_state else 0)
        off = self.params.intensity_offset

        def band(b, lo, hi):
            K.akf_output(self._S, self.seg_t0, self.seg_inv_t, float(t_us), out, lg, var, lo * W, hi * W)
            K.log_to_linear(out[lo * W:hi * W], off)  # numpy's ufunc loop releases the GIL
            return K.clamp_linear(out[lo * W:hi * W]) if clamp else 0
        with PH.phase("output", "parallel"):
            n_clamped = int(sum(self._map_bands(band, self.n)))
        if with_state:
            return (out.reshape(self.shape), lg.reshape(self.shape), var.reshape(self.shape)), n_clamped
        return out.reshape(self.shape), n_clamped


class CFEngine(Engine):
    """Complementary filter, direct integration and high-pass filter (exact exponential kernels).

    ``mode``: "cf" (L^F from frames, gain α), "direct" (α = 0, reset to the frame at each frame)
    or "highpass" (L^F = 0, no frames, output exp(L̂)).
    """

    def __init__(self, shape, measurements, params, mode: str, n_workers: int = 1):
        super().__init__(shape, n_workers)
        if mode not in ("cf", "direct", "highpass"):
            raise ValueError(f"mode must be 'cf', 'direct' or 'highpass', got {mode!r}")
        self.mode = mode
        self.m = measurements
        self.params = params
        self.C = K.aligned_state(self.n, K.CF_FIELDS)
        self.k = -1
        self.event_decay = float(getattr(params, "event_decay", 0.0))
        self.offset = 0.0 if mode == "highpass" else float(params.intensity_offset)
        self._ahead = None  # (k, Future of segment k) computed in the background
        self._ahead_pool = None

    def _alpha(self, seg) -> np.ndarray:
        pr = self.params
        if self.mode == "direct":
            return np.zeros(self.n)
        a = np.full(self.n, pr.alpha_rad_per_s)
        if self.mode == "cf" and pr.adaptive_gain:
            bad = (seg.intensity < pr.adaptive_low) | (seg.intensity > pr.adaptive_high)
            a[bad] *= pr.adaptive_gain_scale
        return a

    def _load(self, k: int) -> None:
        """Load segment ``k``: each row band its pixels' L^F = ln(I + offset) and gain (the same
        elementwise numpy operations, on slices); segment ``k + 1`` is then computed in the
        background (as :meth:`AKFEngine._segment`), off the critical path."""
        with PH.phase("load_segment"):
            codes_fn = getattr(self.m, "segment_codes", None)
            sc = codes_fn(k) if codes_fn is not None else None
            if sc is None or sc.intensity is None:
                seg = self._segment_ahead(k)
        if sc is not None and sc.intensity is not None:  # per-code tables: each band looks its pixels up
            self._load_codes(sc)
            self.k = k
            return
        pr = self.params
        W = self.shape[1]
        inten = seg.intensity
        off = self.offset
        C = self.C

        def band(b, lo, hi):
            a, z = lo * W, hi * W
            C[a:z, K.C_LF] = np.log(inten[a:z] + off)
            if self.mode == "direct":
                C[a:z, K.C_ALPHA] = 0.0
                return
            al = np.full(z - a, pr.alpha_rad_per_s)
            if self.mode == "cf" and pr.adaptive_gain:
                bad = (inten[a:z] < pr.adaptive_low) | (inten[a:z] > pr.adaptive_high)
                al[bad] *= pr.adaptive_gain_scale
            C[a:z, K.C_ALPHA] = al
        with PH.phase("load_bands", "parallel"):
            self._map_bands(band, self.n)
        self.k = k

    def _segment_ahead(self, k: int):
        """``m.segment(k)`` (computed ahead when it was asked for); then segment ``k + 1`` in the background."""
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead[0] == k:
            seg = ahead[1].result()
        else:
            if ahead is not None:
                ahead[1].exception()  # wait for the stale one (providers are not re-entrant)
            seg = self.m.segment(k)
        if k + 1 < len(self.m):
            if self._ahead_pool is None:
                self._ahead_pool = ThreadPoolExecutor(1, thread_name_prefix="hybridhdr-measure")
            self._ahead = (k + 1, self._ahead_pool.submit(self.m.segment, k + 1))
        return seg

    def _load_codes(self, sc) -> None:
        """:meth:`_load` from a segment's codes: I = the per-code intensity of each pixel's
        clipped code, exactly what ``FrameMeasurements.segment`` holds, then the same operations."""
        pr = self.params
        W = self.shape[1]
        C = self.C
        code, table, mx = sc.code, sc.intensity, int(sc.max_code)
        if code.shape[0] != self.n:
            raise ValueError(f"measurement codes have {code.shape[0]} values, expected {self.n} (H*W)")

        def band(b, lo, hi):
            a, z = lo * W, hi * W
            inten = table[np.clip(code[a:z].astype(np.int64), 0, mx)]
            C[a:z, K.C_LF] = np.log(inten + self.offset)
            if self.mode == "direct":
                C[a:z, K.C_ALPHA] = 0.0
                return
            al = np.full(z - a, pr.alpha_rad_per_s)
            if self.mode == "cf" and pr.adaptive_gain:
                al[(inten < pr.adaptive_low) | (inten > pr.adaptive_high)] *= pr.adaptive_gain_scale
            C[a:z, K.C_ALPHA] = al
        with PH.phase("load_bands", "parallel"):
            self._map_bands(band, self.n)

    def close(self):
        """Stop the worker threads; wait for a measurement being computed ahead (idempotent)."""
        if self._ahead_pool is not None:
            self._ahead_pool.shutdown(wait=True)
            self._ahead_pool = None
            self._ahead = None
        super().close()

    def start(self, t_start_us=None) -> int:
        if self.mode == "highpass":
            self.C[:, K.C_L] = 0.0
            self.C[:, K.C_LF] = 0.0
            self.C[:, K.C_ALPHA] = self._alpha(None)
            t_init = int(t_start_us)
        else:
            times = self.m.times_us
            k0 = 0 if t_start_us is None else max(int(np.searchsorted(times, t_start_us, side="right")) - 1, 0)
            check_time_range(times, "frame timestamps")
            self._load(k0)
            t_init = int(times[k0])
            self.C[:, K.C_L] = self.C[:, K.C_LF]
        self.C[:, K.C_TU] = float(t_init)
        return t_init

    def next_switch_us(self):
        if self.m is None or self.mode == "highpass":
            return None
        return int(self.m.times_us[self.k + 1]) if self.k + 1 < len(self.m) else None

    def switch(self) -> None:
        t_to = float(self.m.times_us[self.k + 1])
        W = self.shape[1]
        if self.mode == "direct":
            self._load(self.k + 1)
            self.C[:, K.C_L] = self.C[:, K.C_LF]
            self.C[:, K.C_TU] = t_to
            return
        with PH.phase("switch", "parallel"):
            self._map_bands(lambda b, lo, hi: K.cf_propagate(self.C, t_to, lo * W, hi * W), self.n)
        self._load(self.k + 1)

    def process(self, t, x, y, p, i0, i1) -> None:
        if i1 <= i0:
            return
        pr = self.params
        W = self.shape[1]
        if len(self.bands) == 1:
            with PH.phase("filter", "parallel"):
                self.n_events += K.cf_events(t, x, y, p, i0, i1, 0, self.shape[0], W, self.C, pr.c_on, pr.c_off,
                                             self.event_decay, self.con_px, self.coff_px)
            return

        def band(b, lo, hi):
            idx = self._index_buffer(("band", b), i1 - i0)[0]
            m = K.band_select(y, i0, i1, lo, hi, idx)
            return K.cf_events_indexed(t, x, y, p, i0, idx, m, W, self.C, pr.c_on, pr.c_off, self.event_decay,
                                       self.con_px, self.coff_px)
        with PH.phase("filter", "parallel"):
            self.n_events += int(sum(self._map_bands(band, i1 - i0)))

    def output(self, t_us: int) -> np.ndarray:
        return self._output(t_us)[0]

    def output_clamped(self, t_us: int) -> tuple[np.ndarray, int]:
        return self._output(t_us, clamp=True)

    def _output(self, t_us: int, clamp: bool = False):
        """(image, clamped count); each band clamps its own rows when ``clamp``."""
        W = self.shape[1]
        out = np.empty(self.n, np.float32)

        def band(b, lo, hi):
            K.cf_output(self.C, float(t_us), self.offset, out, lo * W, hi * W)
            return K.clamp_linear(out[lo * W:hi * W]) if clamp else 0
        with PH.phase("output", "parallel"):
            n_clamped = int(sum(self._map_bands(band, self.n)))
        return out.reshape(self.shape), n_clamped


class FramesEngine(Engine):
    """Frames only: zero-order hold or linear interpolation (in linear intensity) between τ_k."""

    uses_events = False

    def __init__(self, shape, measurements, params):
        super().__init__(shape, 1)
        self.m = measurements
        self.linear = params.interpolation == "linear"
        self.k = -1

    def start(self, t_start_us=None) -> int:
        times = self.m.times_us
        self.k = 0 if t_start_us is None else max(int(np.searchsorted(times, t_start_us, side="right")) - 1, 0)
        self._cur = self.m.segment(self.k)
        self._nxt = self.m.segment(self.k + 1) if self.linear and self.k + 1 < len(self.m) else None
        return int(times[self.k])

    def next_switch_us(self):
        return int(self.m.times_us[self.k + 1]) if self.k + 1 < len(self.m) else None

    def switch(self) -> None:
        self.k += 1
        self._cur = self._nxt if self._nxt is not None else self.m.segment(self.k)
        self._nxt = self.m.segment(self.k + 1) if self.linear and self.k + 1 < len(self.m) else None

    def process(self, t, x, y, p, i0, i1) -> None:
        return None

    def output(self, t_us: int) -> np.ndarray:
        cur = self._cur
        if self._nxt is None:
            img = cur.intensity
        else:
            u = (t_us - cur.t0_us) / (self._nxt.t0_us - cur.t0_us)
            img = (1.0 - u) * cur.intensity + u * self._nxt.intensity
        return img.astype(np.float32).reshape(self.shape)


# -- scheduling -------------------------------------------------------------------------------

class OutputClock:
    """Output times: an explicit sorted array, or ``fps`` from an origin (until the data ends)."""

    def __init__(self, times_us=None, fps: float | None = None):
        if (times_us is None) == (fps is None):
            raise ValueError("give exactly one of times_us and fps")
        self.fps = None
        self.times = None
        if times_us is not None:
            t = np.asarray(times_us)
            if t.ndim != 1 or (t.size and not np.issubdtype(t.dtype, np.integer)):
                if t.ndim == 1 and t.size and np.all(np.isfinite(t)) and np.all(t == np.round(t)):
                    t = t.astype(np.int64)
                else:
                    raise ValueError(f"times_us must be a 1-D array of integer µs, got shape {t.shape} "
                                     f"dtype {t.dtype}")
            t = t.astype(np.int64)
            if t.size > 1 and np.any(np.diff(t) <= 0):
                i = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
                raise ValueError(f"times_us must be strictly increasing; index {i} has {t[i]} after {t[i - 1]}")
            check_time_range(t, "times_us")
            self.times = t
        else:
            if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
                raise ValueError(f"fps must be a positive number of frames per second, got {fps!r}")
            self.fps = float(fps)
        self.i = 0
        self.origin = None

    def set_origin(self, t0_us: int) -> None:
        self.origin = int(t0_us)
        if self.times is not None and self.times.size and self.times[0] < t0_us:
            raise ValueError(f"times_us starts at {int(self.times[0])} µs, before the filter can start "
                             f"({t0_us} µs: the first frame used); request times at or after it")

    def peek(self) -> int | None:
        if self.times is not None:
            return int(self.times[self.i]) if self.i < self.times.size else None
        return self.origin + int(round(self.i * 1e6 / self.fps))

    def pop(self) -> None:
        self.i += 1

    @property
    def bounded(self) -> bool:
        return self.times is not None


def clamped_output(engine, t_us: int) -> np.ndarray:
    """``engine.output(t_us)`` with every value below ``K.MIN_INTENSITY`` (or NaN) raised to it,
    counted in ``engine.n_clamped`` (of ``engine.n_output_pixels``): no method ever hands out a
    non-positive or NaN linear intensity, and the count shows when the clamp acted."""
    fn = getattr(engine, "output_clamped", None)  # the row-band engines clamp in their workers
    if fn is not None:
        img, n = fn(t_us)
    else:
        img = engine.output(t_us)
        n = K.clamp_linear(img)
    engine.n_clamped = getattr(engine, "n_clamped", 0) + n
    engine.n_output_pixels = getattr(engine, "n_output_pixels", 0) + img.size
    return img


def drive(engine: Engine, chunks: Iterable, clock: OutputClock, *, t_start_us=None, t_end_us=None,
          progress: Callable[[int], None] | None = None, prefetch: bool = True,
          clamp: bool = True) -> Iterator[tuple[int, np.ndarray]]:
    """Run ``engine`` over event ``chunks`` ((t, x, y, p) contiguous arrays, time-sorted), yielding
    ``(t_us, image)`` at the clock's output times as soon as all events before them are in.

    Order at equal times: frame switch, then output, then events (an output at t includes the
    events with timestamps < t). Events before the filter's start are skipped. With
    ``prefetch`` (and an engine that uses events), the next chunk is read in a background
    thread while the current one is filtered (one chunk ahead, so memory stays bounded).
    """
    pf = None
    if (prefetch and engine.uses_events and not isinstance(chunks, (list, tuple))
            and getattr(chunks, "prefetch", True)):
        chunks = pf = Prefetcher(chunks)
    try:
        yield from _drive(engine, chunks, clock, t_start_us=t_start_us, t_end_us=t_end_us, progress=progress,
                          clamp=clamp)
    finally:
        if pf is not None:
            pf.close()


def _drive(engine: Engine, chunks: Iterable, clock: OutputClock, *, t_start_us=None, t_end_us=None,
           progress: Callable[[int], None] | None = None, clamp: bool = True) -> Iterator[tuple[int, np.ndarray]]:
    t_init = engine.start(t_start_us)
    t_first_out = t_init if t_start_us is None else max(t_init, int(t_start_us))
    clock.set_origin(t_first_out)
    if clock.times is not None:  # explicit: skip nothing, but validate start
        pass
    INF = np.iinfo(np.int64).max
    end_excl = INF if t_end_us is None else int(t_end_us)
    t_last = t_init
    t_prev_chunk = None

    def limit_ok(to):
        return to is not None and to < end_excl

    it = iter(chunks)
    while True:
        # less a parallel read nested in it (in-memory records split by the workers)
        with PH.phase("read_wait", less="parallel"):
            c = next(it, None)
        if c is None:
            break
        raise_if_signalled()  # a termination signal whose exception Python dropped ends the run here
        t, x, y, p = c
        n = t.shape[0]
        if n == 0:
            continue
        if t_prev_chunk is not None and t[0] < t_prev_chunk:
            raise ValueError(f"event chunks must be time-sorted; a chunk starts at {int(t[0])} µs after "
                             f"{t_prev_chunk} µs")
        t_prev_chunk = int(t[-1])
        check_time_range(t)
        i = int(np.searchsorted(t, t_init, side="left")) if t[0] < t_init else 0
        j_end = n if t[-1] < end_excl else int(np.searchsorted(t, end_excl, side="left"))
        while True:
            ts = engine.next_switch_us()
            to = clock.peek() if limit_ok(clock.peek()) else None
            bp = min(ts if ts is not None else INF, to if to is not None else INF)
            if bp == INF or i >= j_end or t[j_end - 1] < bp:
                engine.process(t, x, y, p, i, j_end)
                if progress is not None:
                    progress(j_end - i)
                i = j_end
                break
            j = i + int(np.searchsorted(t[i:j_end], bp, side="left"))
            engine.process(t, x, y, p, i, j)
            if progress is not None:
                progress(j - i)
            i = j
            if ts is not None and ts <= bp:
                engine.switch()
            else:
                yield to, (clamped_output(engine, to) if clamp else engine.output(to))
                clock.pop()
        if j_end > 0:
            t_last = max(t_last, int(t[j_end - 1]))
        if j_end < n:
            break  # past t_end_us
    # flush: outputs after the last event
    frames_end = getattr(getattr(engine, "m", None), "times_us", None)
    if frames_end is not None and len(frames_end):
        t_last = max(t_last, int(frames_end[-1]))
    stop = end_excl if t_end_us is not None else (INF if clock.bounded else t_last + 1)
    while True:
        to = clock.peek()
        if to is None or to >= stop:
            break
        ts = engine.next_switch_us()
        if ts is not None and ts <= to:
            engine.switch()
            continue
        yield to, (clamped_output(engine, to) if clamp else engine.output(to))
        clock.pop()
