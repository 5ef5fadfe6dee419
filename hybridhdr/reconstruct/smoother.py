"""Two-sided offline AKF: a forward and a backward filter fused per pixel (a two-filter smoother).

The AKF of Wang et al. (ICCV 2021) is a forward filter: at time t it knows the frames and
events before t. Offline the future is known too. The backward filter is the *same* AKF run on
the time-reversed recording: every time t maps to ``t' = T0 - 1 - t``, event order is reversed
and polarity negated (a rise of log I forward is a fall backward), each frame keeps its
exposure length with its mid-exposure time reversed, and the noise models (eq. 2, §3.1.1) and
the frame model (eqs. 3-9, eq. 7 between frames) apply unchanged in reverse time. At each
output time t the two estimates (L̂_f, P_f) and (L̂_b, P_b) are independent given the state
(the forward one uses the data before t, the backward one the data from t on) and are fused by
inverse-covariance weighting,

    P = 1 / (1/P_f + 1/P_b),    L̂ = P (L̂_f/P_f + L̂_b/P_b),

the two-filter smoother of Fraser & Potter ("The optimum linear smoother as a combination of two
optimum linear filters", IEEE TAC 14(4), 1969), exact for the AKF's scalar per-pixel state with
Gaussian noise. Assumptions and their limits (docs/reconstruct.md, "Two-sided offline AKF"):

* Half-open windows: the forward output at t holds the events with timestamps < t; the backward
  output at t' = T0 - t holds the reversed events with t'_e < t', i.e. the forward events with
  timestamps >= t. Every event is used by exactly one of the two.
* A frame whose mid-exposure time equals an output time is used by both passes (at equal
  times the frame switch precedes the output), so at frame times P is about half what it
  should be; the mean is unaffected where both passes agree with the frame.
* A censored (clipped) frame is a bound in both passes; a convex combination of two estimates
  that satisfy a bound satisfies it.
* Outputs before the first frame or after the last have only one pass (the other cannot start
  there): the single filter's estimate is used.

Both passes run the row-band parallel kernels, so the result is bit-identical for any
``n_workers``. With one worker the backward pass runs first and keeps its estimates (float32 L̂
and P, 8 bytes per pixel per output; beyond ``MEMORY_LIMIT_BYTES`` in an unlinked temporary
file through pwritev/preadv, so memory stays bounded); the forward pass then streams, fusing as
it goes. With two or more the passes run at the same time, one thread each with half the
workers, and whichever reaches an output second fuses it (about the same memory, spilled the
same way); the frames are the same bit for bit.
"""

from __future__ import annotations

import math
import os
import tempfile
from typing import Callable, Iterator

import numpy as np

from .._util import phases as PH
from ..model import Frames
from . import _engine as E
from . import _kernels as K
from .event_arrays import EventArrays, map_ranges

__all__ = ["reverse_events", "reverse_frames", "fuse", "frames_measure", "output_times", "two_sided_iter", "MEMORY_LIMIT_BYTES"]

#: Backward estimates beyond this size go to an unlinked temporary file, written and read with
#: pwrite/pread (the page cache, not the process, holds them: memory stays bounded).
MEMORY_LIMIT_BYTES = 256 << 20


class _Store:
    """Per-output records of ``fields`` float32 arrays of ``n_pix``: in memory, or in a temporary file.

    In memory a record is the caller's own arrays, kept by reference (no copy: the passes hand
    over arrays they allocated for that output and never touch again); with ``block`` the
    records are rows of one array allocated up front, and a pass writes its estimates straight
    into the row :meth:`slot` gives it (no copy, and no allocation per output). In a file
    (``spill``, by default when the records would exceed :data:`MEMORY_LIMIT_BYTES`) they are
    written straight from the arrays with ``pwritev`` and read into fresh writable arrays with
    ``preadv``.
    """

    def __init__(self, n_out: int, n_pix: int, fields: int = 2, spill: bool | None = None, block: bool = False):
        self.n_pix = n_pix
        self.fields = fields
        self.rec = 4 * fields * n_pix
        if spill is None:
            spill = self.rec * n_out > MEMORY_LIMIT_BYTES
        self.file = tempfile.TemporaryFile(prefix="hybridhdr-backward-") if spill else None
        self.mem = None if spill else [None] * n_out
        self.block = np.empty((n_out, fields, n_pix), np.float32) if block and not spill else None

    def slot(self, i: int) -> tuple[np.ndarray, ...]:
        """Arrays to compute record ``i`` into, then :meth:`put`: its rows of the block, or new arrays."""
        if self.block is not None:
            return tuple(self.block[i])
        return tuple(np.empty(self.n_pix, np.float32) for _ in range(self.fields))

    def put(self, i: int, *arrays: np.ndarray) -> None:
        if len(arrays) != self.fields or any(a.dtype != np.float32 or a.shape != (self.n_pix,) for a in arrays):
            raise ValueError(f"a record is {self.fields} float32 arrays of shape ({self.n_pix},)")
        if self.file is None:
            if self.block is not None:
                for k, a in enumerate(arrays):
                    if a.ctypes.data != self.block[i, k].ctypes.data:  # not computed in place: copy
                        self.block[i, k] = a
                arrays = tuple(self.block[i])
            self.mem[i] = arrays
            return
        n = os.pwritev(self.file.fileno(), [np.ascontiguousarray(a) for a in arrays], i * self.rec)
        if n != self.rec:
            raise OSError(f"short write of the two-sided filter's estimates ({n} of {self.rec} bytes)")

    def get(self, i: int) -> tuple[np.ndarray, ...]:
        if self.file is None:
            return self.mem[i]
        buf = np.empty((self.fields, self.n_pix), np.float32)
        n = os.preadv(self.file.fileno(), [buf], i * self.rec)
        if n != self.rec:
            raise OSError(f"short read of the two-sided filter's estimates ({n} of {self.rec} bytes)")
        return tuple(buf)

    def drop(self, i: int) -> None:
        """Forget record ``i`` (in memory: its arrays can be freed)."""
        if self.file is None:
            self.mem[i] = None

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
        self.mem = None
        self.block = None


def reverse_events(ev: EventArrays, t_mirror_us: int, n_workers: int = 1) -> EventArrays:
    """Events in reversed time ``t' = t_mirror_us - 1 - t``, reversed order, negated polarity
    (``n_workers`` threads, each a contiguous part: :func:`_kernels.reverse_columns`)."""
    n = len(ev)
    m1 = int(t_mirror_us) - 1
    if n and (ev.t[0] < m1 - (1 << 62) or ev.t[-1] > m1 + (1 << 62)):  # keep m1 - t inside int64
        raise ValueError(f"cannot reverse event times {int(ev.t[0])}..{int(ev.t[-1])} about {m1} µs")
    rt = np.empty(n, np.int64)
    rx = np.empty(n, np.uint16)
    ry = np.empty(n, np.uint16)
    rp = np.empty(n, np.int8)
    map_ranges(n, n_workers, lambda i0, i1: K.reverse_columns(ev.t, ev.x, ev.y, ev.p, np.int64(m1), i0, i1,
                                                                rt, rx, ry, rp))
    return EventArrays._trusted(rt, rx, ry, rp, ev.shape)  # a reversed sorted stream is sorted


def reverse_frames(frames: Frames, t_mirror_us: int) -> Frames:
    """Frames in reversed time: each mid-exposure time ``τ' = t_mirror_us - 1 - τ`` exactly, the
    exposure length kept, ordered by the reversed exposure start. Exposure starts in order do not
    make mid-exposure times in order (a long exposure, then a short one inside it): reversing the
    index order alone then gave starts out of order, and an error about the input that was false
    of it; the filter orders frames by their mid-exposure time itself."""
    T = frames.exposure_us[::-1]
    mid = (np.int64(t_mirror_us) - 1) - frames.t_mid_us[::-1]
    start = mid - T // 2
    order = np.argsort(start, kind="stable")
    sel = lambda a: None if a is None else a[::-1][order]  # noqa: E731
    return Frames(np.ascontiguousarray(frames.images[::-1][order]), start[order], (start + T)[order],
                  sel(frames.gain), sel(frames.iso), frames.encoding)


def fuse(l_f, p_f, l_b, p_b):
    """Inverse-covariance fusion of two independent estimates: ``(L̂, P)`` (float64).

    >>> fuse(np.array([1.0]), np.array([1.0]), np.array([3.0]), np.array([1.0]))
    (array([2.]), array([0.5]))
    """
    l_f, p_f, l_b, p_b = (np.asarray(a, dtype=np.float64) for a in (l_f, p_f, l_b, p_b))
    p = p_f * p_b / (p_f + p_b)
    return (l_f * p_b + l_b * p_f) / (p_f + p_b), p


def frames_measure(frames: Frames, censored_codes: tuple | None) -> Callable[[int], np.ndarray] | None:
    """``measured(j)``: the flat bool mask of the pixels that the frame(s) at the j-th distinct
    mid-exposure time of ``frames`` measure, i.e. whose code (:func:`hybridhdr.camera.encoding.
    frames_to_codes`, as the frame measurements read it) lies strictly between the censored codes
    ``(lo, hi)`` (frames sharing a mid-exposure time: any of them); None when ``censored_codes``
    is None (every frame then measures every pixel)."""
    if censored_codes is None or frames is None or len(frames) == 0:
        return None
    from ..camera.encoding import frames_to_codes
    lo, hi = (float(v) for v in censored_codes)
    mids = np.asarray(frames.t_mid_us, dtype=np.int64)
    taus = np.unique(mids)
    H, W = frames.images.shape[1:3]

    def measured(j: int) -> np.ndarray:
        m = np.zeros(H * W, bool)
        for k in np.flatnonzero(mids == taus[j]):
            c = np.asarray(frames_to_codes(frames.select([int(k)]), (H, W))[0]).reshape(-1)
            m |= (c > lo) & (c < hi)
        return m
    return measured


def output_times(frame_times_us, t_last_us: int, *, times_us=None, fps=None, t_start_us=None,
                 t_end_us=None) -> np.ndarray:
    """The output times the forward driver would produce, as an explicit array.

    ``times_us`` as given (windowed); ``fps``: ``t0 + round(k 1e6 / fps)`` from the first frame
    (or ``t_start_us``) up to the last event or frame; neither: the frame times.
    """
    ft = np.unique(np.asarray(frame_times_us, dtype=np.int64))
    t0 = int(ft[0])
    if times_us is not None and fps is not None:
        E.OutputClock(times_us=times_us, fps=fps)  # raises: exactly one of the two
    if times_us is not None:
        t = np.asarray(E.OutputClock(times_us=times_us).times, dtype=np.int64)
        E.OutputClock(times_us=t).set_origin(t0)  # the same check as the forward driver's
    elif fps is not None:
        clk = E.OutputClock(fps=fps)
        start = t0 if t_start_us is None else max(t0, int(t_start_us))
        stop = int(t_last_us) + 1 if t_end_us is None else int(t_end_us)
        n = max(0, math.ceil((stop - start) * clk.fps / 1e6) + 1)
        t = start + np.round(np.arange(n) * (1e6 / clk.fps)).astype(np.int64)
        t = np.unique(t[t < stop])
    else:
        t = ft
    if t_start_us is not None:
        t = t[t >= int(t_start_us)]
    if t_end_us is not None:
        t = t[t < int(t_end_us)]
    return t


class _StateEngine:
    """Wraps an :class:`~._engine.AKFEngine` so that each output also keeps L̂ and P."""

    def __init__(self, engine, dest: Callable[[int], tuple] | None = None):
        self._e = engine
        self.dest = dest  # t_us -> the (L̂, P) arrays to write that output into; None: new arrays
        self.last = None

    def __getattr__(self, name):
        return getattr(self._e, name)

    def output(self, t_us: int):
        """L̂ and P at ``t_us`` as float32 (no linear image: the fused one is made later)."""
        e = self._e
        W = e.shape[1]
        if self.dest is None:
            lg = np.empty(e.n, np.float32)
            var = np.empty(e.n, np.float32)
        else:
            lg, var = self.dest(int(t_us))
        with PH.phase("output", "parallel"):
            e._map_bands(lambda b, lo, hi: K.akf_output_state32(e._S, e.seg_t0, e.seg_inv_t, float(t_us), lg, var,
                                                                  lo * W, hi * W), e.n)
        self.last = (lg, var)
        return lg


class _CarriedVariance:
    """The variance a pass's carried frame has accumulated since that frame, per pixel.

    Between frames the AKF pulls L̂ continuously towards L^A, the last frame carried forward by the
    events since it (eq. 10, event interpolation), as if L^A were a fresh measurement at every
    instant with the frame's R: P then settles near R whatever the frame's age, while the error of
    L^A grows with every event it was carried by (threshold mismatch, events lost in the
    refractory period) and with the time since the frame (changes below the threshold). Fused with
    P alone, an estimate carried 45 ms from its frame weighs as much as one carried 5 ms
    (``benchmarks/accuracy.py``, AHDR between frames). Each pass therefore reports
    ``P + q·n + s·Δt`` at output time t: n the pixel's events in ``[τ_last, t)``, Δt = t − τ_last
    in s, τ_last the pass's last frame (mid-exposure) at or before t that *measured the pixel*, q
    the paper's per-event refractory-noise variance σ²_ref (§6, 0.01) and s = σ²_proc. Computed
    from the pass's own (possibly reversed) events and frames, so a reversed recording gives the
    reversed numbers.

    A frame that clips the pixel (a censored code, ``AKFParams.saturation = "bound"``) does not
    measure it: the bound moves L̂ only where L̂ violates it and leaves P as it is, so the pixel's
    L^A is still the value of its last unclipped frame carried by every event since. ``measured``
    (a callable: unique-frame index j -> bool mask of the pixels frame j measures, flat) keeps
    τ_last, n and Δt per pixel running from that frame: without it, an estimate carried 2 frames
    through clipped frames was weighed as if frame k had just measured it (each pass's clipped
    frame k at an output at τ_k set n = Δt = 0 in both passes, so the fusion weighed a backward
    estimate carried from a frame 3 periods away like the forward one carried 1 period). None:
    every frame measures every pixel (a pixel's τ_last is the pass's last frame).
    """

    def __init__(self, events: EventArrays, frame_mids_us, q_event: float, s_proc_per_s: float,
                 measured: Callable[[int], np.ndarray] | None = None):
        self.ev = events
        self.tau = np.unique(np.asarray(frame_mids_us, dtype=np.int64))
        self.q = float(q_event)
        self.s = float(s_proc_per_s)
        self.measured = measured
        self.n_pix = events.shape[0] * events.shape[1]
        self.cnt = np.zeros(self.n_pix, np.float32)  # exact up to 2**24 events per pixel and frame
        self.tau_ref = np.zeros(self.n_pix, np.int64)  # per pixel: the frame its counts run from
        self.j = -1  # the last frame the counts have passed
        self.pos = 0  # events counted up to this index
        self._bufs: dict = {}  # per band: reused int32 index buffers

    def add_to(self, t_us: int, var: np.ndarray, engine=None) -> np.ndarray:
        """``var + q·n + s·Δt`` at ``t_us``, in place (float32 ``var``, this output's own array);
        calls come in increasing time. With ``engine`` (a row-band engine: its ``_map_bands``),
        each band counts and adds its own rows (:func:`_kernels.band_select`, then
        :func:`_kernels.count_pixel_events_indexed`): the same float32 sums, as each pixel's
        count is exact and added in the same order."""
        j = int(np.searchsorted(self.tau, t_us, side="right")) - 1
        if j < 0:
            return var
        t_ev = self.ev.t
        if j != self.j:
            if self.measured is None or self.j < 0:
                # every pixel restarts at frame j (without ``measured``) or at the first frame
                j0 = j if self.measured is None else 0
                self._restart(None, int(self.tau[j0]), engine)
                self.pos = int(np.searchsorted(t_ev, self.tau[j0], side="left"))
                self.j = j0
            for jj in range(self.j + 1, j + 1):  # each later frame restarts the pixels it measures
                stop = int(np.searchsorted(t_ev, self.tau[jj], side="left"))
                self._count(self.pos, stop, engine)
                self.pos = max(stop, self.pos)
                self._restart(np.asarray(self.measured(jj), bool).reshape(-1), int(self.tau[jj]), engine)
            self.j = j
        end = int(np.searchsorted(t_ev, t_us, side="left"))
        self._count(self.pos, end, engine)
        self.pos = max(end, self.pos)
        W = self.ev.shape[1]
        cnt, q, s, tref, t = self.cnt, self.q, self.s, self.tau_ref, int(t_us)

        def add(b, lo, hi):
            a, z = lo * W, hi * W
            K.add_carried_variance_since(var[a:z], cnt[a:z], q, s, t, tref[a:z])  # in place
        if engine is None:
            add(0, 0, self.ev.shape[0])
        else:
            engine._map_bands(add, self.n_pix)
        return var

    def _restart(self, mask, tau: int, engine=None) -> None:
        """Counts 0 and reference time ``tau`` for the pixels of ``mask`` (None: every pixel);
        row bands with ``engine``."""
        W = self.ev.shape[1]
        cnt, tref = self.cnt, self.tau_ref

        def band(b, lo, hi):
            a, z = lo * W, hi * W
            if mask is None:
                cnt[a:z] = 0.0
                tref[a:z] = tau
            else:
                m = mask[a:z]
                cnt[a:z][m] = 0.0
                tref[a:z][m] = tau
        if engine is None:
            band(0, 0, self.ev.shape[0])
        else:
            engine._map_bands(band, self.n_pix)

    def _count(self, pos: int, end: int, engine=None) -> None:
        """Each pixel's events ``[pos, end)`` added to its count (row bands with ``engine``)."""
        if end <= pos:
            return
        W = self.ev.shape[1]
        ev, cnt = self.ev, self.cnt
        bufs = self._bufs

        def band(b, lo, hi):
            if lo == 0 and hi == ev.shape[0]:
                K.count_pixel_events(ev.y, ev.x, pos, end, W, cnt)
            else:
                idx = bufs.get(b)
                if idx is None or idx.shape[0] < end - pos:
                    idx = bufs[b] = np.empty(max(end - pos, 2 * (0 if idx is None else idx.shape[0])), np.int32)
                m = K.band_select(ev.y, pos, end, lo, hi, idx)
                K.count_pixel_events_indexed(ev.y, ev.x, pos, idx, m, W, cnt)
        if engine is None:
            band(0, 0, self.ev.shape[0])
            return
        if end - pos >= 1 << 31:
            raise ValueError(f"{end - pos} events between two outputs: too many for the parallel count (< 2**31)")
        threaded = (getattr(engine, "_pool", None) is not None and len(engine.bands) > 1
                    and end - pos >= E.PARALLEL_MIN_WORK)
        engine._map_bands(self._split_count(engine, pos, end) if threaded else band, self.n_pix + (end - pos))

    def _split_count(self, engine, pos: int, end: int):
        """The per-band function of :meth:`_count` for threaded bands: worker ``w`` splits part
        ``w`` of the events ``[pos, end)`` by band (own rows, :func:`_kernels.band_split_lut`),
        then each band counts its events part by part, waiting only for the part it reaches:
        every event's row is read once in all, not once per band (a band's scan of the whole
        window would not shrink as workers are added). Same counts (each is exact)."""
        import threading
        ev, cnt, W = self.ev, self.cnt, self.ev.shape[1]
        bands = list(engine.bands)
        nb = len(bands)
        bor = np.empty(ev.shape[0], np.int32)
        for b, (lo, hi) in enumerate(bands):
            bor[lo:hi] = b
        no_edges = np.zeros(ev.shape[0], np.uint8)  # own rows only: no ghost rows to count
        parts = np.linspace(pos, end, nb + 1).astype(np.int64)
        bufs = []
        for w in range(nb):
            key = ("split", w)
            buf = self._bufs.get(key)
            n = int(parts[w + 1] - parts[w])
            if buf is None or buf.shape[0] != nb or buf.shape[1] < n:
                buf = self._bufs[key] = np.empty((nb, max(n, 2 * (0 if buf is None else buf.shape[1]))), np.int32)
            bufs.append(buf)
        counts = np.zeros((nb, nb), np.int64)
        ready = [threading.Event() for _ in range(nb)]
        failed: list = []

        def band(b, lo, hi):
            if (lo, hi) != bands[b]:
                raise RuntimeError("the row bands moved during a count")
            try:
                K.band_split_lut(ev.y, pos, parts[b], parts[b + 1], bor, no_edges, bufs[b], counts[b])
            except BaseException:
                failed.append(b)
                for e in ready:
                    e.set()
                raise
            ready[b].set()
            for v in range(nb):
                ready[v].wait()
                if failed:
                    raise threading.BrokenBarrierError(f"worker {failed[0]} failed")
                K.count_pixel_events_indexed(ev.y, ev.x, pos, bufs[v][b], counts[v, b], W, cnt)
        return band


def _run_pass(make_engine, events: EventArrays, times: np.ndarray, chunk_events: int,
              progress: Callable[[int], None] | None, carried: tuple | None = None, dest=None):
    """Drive one pass; yield ``(t, L̂, P)`` at ``times`` (those at or after the pass's start).

    ``carried = (frame_mids_us, q_event, s_proc_per_s)``: P plus the variance the carried frame
    has accumulated (:class:`_CarriedVariance`). ``dest(t)``: the float32 arrays to write the
    output at t into (default: new arrays for each output)."""
    eng = _StateEngine(make_engine(), dest)
    acc = None if carried is None else _CarriedVariance(events, *carried)
    try:
        t_init = int(eng.m.times_us[0])
        times = times[times >= t_init]
        if times.size == 0:
            return
        clock = E.OutputClock(times_us=times)
        # no prefetching thread: a chunk of events in memory is a slice, nothing to read ahead (a
        # StreamingEventArrays fills itself in its own thread)
        for t, _ in E.drive(eng, events.chunks(int(chunk_events)), clock, progress=progress, clamp=False,
                            prefetch=False):
            lg, var = eng.last
            if acc is not None:
                with PH.phase("carried_variance", "parallel"):
                    var = acc.add_to(int(t), var, eng)
            yield t, lg, var
    finally:
        eng.close()


def two_sided_iter(events: EventArrays, frames: Frames, make_engine, times: np.ndarray, *, offset: float,
                   chunk_events: int = 1 << 20, progress: Callable[[int], None] | None = None,
                   info: dict | None = None, carried_variance: tuple | None = None,
                   n_workers: int | None = None, censored_codes: tuple | None = None
                   ) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(t_us, linear image)`` of the two-sided AKF at ``times`` (strictly increasing).

    ``make_engine(frames, events, backward)`` builds a forward :class:`~._engine.AKFEngine` for a
    recording; it is called once as given and once on the reversed recording (``backward``
    True), where an event's polarity is negated, so its ON and OFF thresholds must be swapped:
    a forward ON event of threshold c_on is a backward OFF event of the same size.
    ``carried_variance = (q_event, s_proc_per_s)``: fuse with each pass's P plus the variance its
    carried frame has accumulated (:class:`_CarriedVariance`); None: P alone.
    ``censored_codes = (lo, hi)``: a frame code ``<= lo`` or ``>= hi`` is a censored bound, not a
    measurement of its pixel (``AKFParams.saturation = "bound"``), so the carried variance of
    that pixel keeps running from its last frame with a code strictly between them
    (:func:`frames_measure`); None: every frame measures every pixel.

    ``n_workers`` None or 1: the passes one after the other (the backward pass first, then the
    forward pass streams, fusing as it goes), with the engines as ``make_engine`` builds them.
    ``n_workers >= 2``: the two passes run at the same time, one thread each, and
    ``make_engine(frames, events, backward, n_workers=k)`` gets each pass's share of the row-band
    workers (the backward pass ``(n_workers + 1) // 2``, the forward pass ``n_workers // 2``);
    whichever pass reaches an output second fuses it. The first output is ready only when the
    backward pass has finished, so all outputs come after both passes. Each pass's arithmetic and
    the fusion are those of the serial order: the frames are the same bit for bit.
    """
    shape = events.shape
    t_lo = min(int(events.t[0]) if len(events) else int(frames.t_start_us[0]), int(frames.t_start_us[0]))
    t_hi = max(int(events.t[-1]) if len(events) else int(frames.t_end_us[-1]), int(frames.t_end_us[-1]))
    mirror = t_lo + t_hi + 1  # reversed times stay in [t_lo, t_hi]
    with PH.phase("reverse", "parallel"):
        rev_ev = reverse_events(events, mirror, n_workers=int(n_workers or 1))
    with PH.phase("reverse_frames"):
        rev_fr = reverse_frames(frames, mirror)
    times = np.asarray(times, dtype=np.int64)
    rev_times = (np.int64(mirror) - times)[::-1]  # t' = T0 - t: the backward pass holds events >= t
    cv_b = cv_f = None
    if carried_variance is not None:
        cv_b = (rev_fr.t_mid_us,) + tuple(carried_variance) + (frames_measure(rev_fr, censored_codes),)
        cv_f = (frames.t_mid_us,) + tuple(carried_variance) + (frames_measure(frames, censored_codes),)
    passes = {True: (rev_fr, rev_ev, rev_times, cv_b), False: (frames, events, times, cv_f)}
    stats = {"outputs_fused": 0, "outputs_one_pass": 0, "backward_outputs": 0, "spilled_to_disk": False,
             "n_clamped": 0, "n_output_pixels": 0}
    if progress is not None:
        progress = _each_event_once(progress)
    if n_workers is not None and int(n_workers) >= 2:
        nw = int(n_workers)
        gen = _concurrent(shape, passes, make_engine, times, mirror, float(offset), int(chunk_events), progress,
                          {True: (nw + 1) // 2, False: nw // 2}, stats)
    else:
        gen = _serial(shape, passes, make_engine, times, mirror, float(offset), int(chunk_events), progress, stats)
    yield from gen
    if info is not None:
        info["two_sided"] = {k: stats[k] for k in ("outputs_fused", "outputs_one_pass", "backward_outputs",
                                                   "spilled_to_disk")}
        info["n_clamped"] = stats["n_clamped"]
        info["n_output_pixels"] = stats["n_output_pixels"]


def _fuse(lf, pf, lb, pb, offset: float, stats: dict | None = None, engine=None) -> np.ndarray:
    """The fused linear image (float32, flat) of two pass estimates; counts the clamped pixels.
    With ``engine`` (idle in the calling thread), each of its row bands fuses its own pixels."""
    with PH.phase("fuse", "serial" if engine is None else "parallel"):
        img = np.empty(lf.shape[0], np.float32)
        if engine is None:
            n = K.fuse_to_linear(lf, pf, lb, pb, offset, K.MIN_INTENSITY, img)
        else:
            W = engine.shape[1]
            n = sum(engine._map_bands(lambda b, lo, hi: K.fuse_to_linear(
                lf[lo * W:hi * W], pf[lo * W:hi * W], lb[lo * W:hi * W], pb[lo * W:hi * W], offset, K.MIN_INTENSITY,
                img[lo * W:hi * W]), lf.shape[0]))
        if stats is not None:
            stats["n_clamped"] += int(n)
    return img


def _each_event_once(progress: Callable[[int], None]) -> Callable[[int], None]:
    """``progress`` as the two passes should report it: each pass goes through the events, so
    half of their combined count is reported, and a progress bar counts each event once (50,000
    events: 50,000, not 100,000). Thread-safe: the concurrent passes report from two threads."""
    import threading

    lock = threading.Lock()
    counts = [0, 0]  # events counted by the passes together, events reported

    def report(k: int) -> None:
        with lock:
            counts[0] += int(k)
            half = counts[0] // 2
            step, counts[1] = half - counts[1], half
        if step:
            progress(step)

    return report


def _serial(shape, passes, make_engine, times, mirror, offset, chunk_events, progress, stats):
    """The backward pass into a :class:`_Store`, then the forward pass streaming, fused as it goes."""
    n_pix = shape[0] * shape[1]
    store = _Store(times.size, n_pix, block=True)  # the backward pass writes into its rows
    stats["spilled_to_disk"] = store.file is not None
    have_b = np.zeros(times.size, bool)
    index = {int(t): i for i, t in enumerate(times)}
    try:
        fr, ev, tms, cv = passes[True]
        for tr, lg, var in _run_pass(lambda: make_engine(fr, ev, True), ev, tms, chunk_events, progress, cv,
                                     dest=lambda tr: store.slot(index[int(mirror - tr)])):
            i = index[int(mirror - tr)]
            store.put(i, lg, var)
            have_b[i] = True
            stats["backward_outputs"] += 1
        fr, ev, tms, cv = passes[False]
        held: dict = {}  # the forward engine: its row bands fuse each output (idle between its outputs)
        fwd = _run_pass(lambda: held.setdefault("e", make_engine(fr, ev, False)), ev, tms, chunk_events, progress,
                        cv)
        nxt = next(fwd, None)
        for i, t in enumerate(times):
            t = int(t)
            if nxt is not None and nxt[0] == t:
                lf, pf = nxt[1], nxt[2]
                nxt = next(fwd, None)
            else:
                lf = pf = None
            if lf is not None and have_b[i]:
                lb, pb = store.get(i)
                img = _fuse(lf, pf, lb, pb, offset, stats, held.get("e"))
                stats["outputs_fused"] += 1
            elif lf is not None or have_b[i]:  # one pass only: fusing it with itself is the identity
                l1, p1 = (lf, pf) if lf is not None else store.get(i)
                img = _fuse(l1, p1, l1, p1, offset, stats)
                stats["outputs_one_pass"] += 1
            else:  # neither pass covers t (no frame at all around it): cannot happen with frames
                continue
            store.drop(i)
            stats["n_output_pixels"] += img.size
            yield t, img.reshape(shape)
    finally:
        store.close()


def _concurrent(shape, passes, make_engine, times, mirror, offset, chunk_events, progress, workers, stats):
    """Both passes at once, one thread each; the pass that reaches an output second fuses it.

    Per output a bit mask under one lock: 1 the forward estimate is stored, 2 the backward one, 4
    the fused image is stored. A pass that finds the other's estimate fuses at once; otherwise it
    stores its own and then marks it, and if the other marked its own in between (both stored,
    neither saw the other), the later of the two marks fuses. Outputs that one pass only covers
    are "fused" with themselves at the end, as in the serial order. Memory: the estimates waiting
    for the other pass plus the images (about the serial order's 8 bytes per pixel per output at
    most), all in temporary files beyond :data:`MEMORY_LIMIT_BYTES`.
    """
    import threading

    n_pix = shape[0] * shape[1]
    n_out = times.size
    spill = 8 * n_pix * n_out > MEMORY_LIMIT_BYTES
    stats["spilled_to_disk"] = spill
    est = {b: _Store(n_out, n_pix, 2, spill) for b in (True, False)}
    imgs = _Store(n_out, n_pix, 1, spill)
    state = np.zeros(n_out, np.uint8)
    lock = threading.Lock()
    stop = threading.Event()
    errors: list = []
    index = {int(t): i for i, t in enumerate(times)}
    sub = {True: {"n_clamped": 0, "outputs": 0}, False: {"n_clamped": 0, "outputs": 0}}
    if progress is not None:
        plock = threading.Lock()
        user_progress = progress

        def progress(k):  # noqa: F811 - the passes report from two threads
            with plock:
                user_progress(k)

    def run(backward: bool):
        me, other = (2, 1) if backward else (1, 2)
        fr, ev, tms, cv = passes[backward]
        st = sub[backward]
        eng = engines[backward]

        def fuse_store(i, lg, var, o):
            lf, pf, lb, pb = (o[0], o[1], lg, var) if backward else (lg, var, o[0], o[1])
            imgs.put(i, _fuse(lf, pf, lb, pb, offset, st, eng))  # this pass's bands
            est[not backward].drop(i)
            with lock:
                state[i] |= 4
        try:
            for tt, lg, var in _run_pass(lambda: eng, ev, tms, chunk_events, progress, cv):
                if stop.is_set():
                    return
                i = index[int(mirror - tt) if backward else int(tt)]
                st["outputs"] += 1
                with lock:
                    ready = bool(state[i] & other)
                if ready:
                    fuse_store(i, lg, var, est[not backward].get(i))
                    continue
                est[backward].put(i, lg, var)
                with lock:
                    state[i] |= me
                    late = bool(state[i] & other)
                if late:
                    fuse_store(i, lg, var, est[not backward].get(i))
                    est[backward].drop(i)
        except BaseException as e:  # noqa: BLE001 - re-raised in the caller's thread
            errors.append(e)
            stop.set()

    engines = {}  # built here, backward first as in the serial order (make_engine need not be thread-safe)
    threads = [threading.Thread(target=run, args=(b,), name=f"hybridhdr-{'backward' if b else 'forward'}-pass")
               for b in (True, False)]
    try:
        for b in (True, False):
            fr, ev, _, _ = passes[b]
            engines[b] = make_engine(fr, ev, b, n_workers=workers[b])
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        if errors:
            raise errors[0]
        stats["backward_outputs"] = sub[True]["outputs"]
        stats["n_clamped"] = sub[True]["n_clamped"] + sub[False]["n_clamped"]
        for i, t in enumerate(times):
            s = int(state[i])
            if s & 4:
                img = imgs.get(i)[0]
                imgs.drop(i)
                stats["outputs_fused"] += 1
            elif s & 3:  # one pass only: fusing it with itself is the identity
                l1, p1 = est[not (s & 1)].get(i)
                img = _fuse(l1, p1, l1, p1, offset, stats)
                est[not (s & 1)].drop(i)
                stats["outputs_one_pass"] += 1
            else:  # neither pass covers t (no frame at all around it): cannot happen with frames
                continue
            stats["n_output_pixels"] += img.size
            yield int(t), img.reshape(shape)
    finally:
        stop.set()
        for th in threads:
            if th.ident is not None:
                th.join()
        for e in engines.values():
            e.close()  # idempotent; closed already by its pass unless a pass never started
        for s in (*est.values(), imgs):
            s.close()
