"""The AKF and CF on an NVIDIA GPU (Numba's CUDA target), optional.

``reconstruct(..., device="cuda"|"cpu"|"auto")`` and ``hybridhdr reconstruct --device``.
"auto" runs here when :func:`cuda_unavailable_reason` returns None (Numba's CUDA target imports
and sees a device), else on the CPU; :meth:`.request.Device.resolve` gives the one line that says which.
Nothing in this module imports ``numba.cuda`` until a GPU engine is built, so CPU-only
installations never need a CUDA package.

Schedule (kernels in :mod:`._cuda_kernels`): the driver's time windows (between frame switches
and output times, as the CPU engines see them) are grouped by pixel on the device and filtered
by one thread per pixel; frame switches, outputs, the isolated-pixel term, the two-sided
filter's reversal, carried variance and fusion all run on the device. Only the output images
come back (linear float32, the exp of the float32-rounded L̂ taken on the device, within an
ulp of the CPU's numpy float32 exp), plus the backward pass's estimates when they outgrow the
device budget :data:`DEVICE_STORE_BYTES`. Events stream through a bounded staging buffer, or stay
resident on the device for the two-sided filter when they fit.

Agreement with the CPU path (``tests/reconstruct/test_cuda.py``, in Numba's CUDA simulator): the
same equations in the same order, so L̂ and P agree to rounding (1e-9 relative, float64); the
GPU may contract a*b+c into one fused multiply-add, which is why they are not bit-identical.
"""

from __future__ import annotations

import math
import os

import numpy as np

from .._util import phases as PH
from . import _kernels as K

__all__ = ["cuda_unavailable_reason", "CudaAKFEngine", "CudaCFEngine", "DeviceEvents", "cuda_two_sided_iter"]

#: the two-sided filter keeps the backward pass's estimates on the device up to this many bytes;
#: beyond, they go to host memory (smoother's store, which spills to a temporary file)
DEVICE_STORE_BYTES = 2 << 30
#: events resident on the device (13 bytes each, twice for the reversed copy) up to this
DEVICE_EVENTS_BYTES = 4 << 30
#: the longest window the grouping kernels take at once (int32 indices); longer ones are split,
#: which leaves the result unchanged (the per-pixel walk of two consecutive windows is the walk of
#: their union)
MAX_WINDOW = 1 << 24
#: resident events (:class:`DeviceEvents`) are grouped by pixel once per chunk of this many events
#: and each window of the chunk walked from per-pixel cursors (one launch per window instead of a
#: grouping per window; :func:`._cuda_kernels.k_akf_walk_res`); 0: grouped per window as streamed
#: events are. Either way the same per-pixel event sequences and t*, so the same results.
RESIDENT_CHUNK = 1 << 25
_STAGE_MIN = 1 << 16
#: events per pinned staging buffer when the whole recording is uploaded (:meth:`DeviceEvents.upload`)
UPLOAD_CHUNK = 1 << 22


def numpy_compat() -> None:
    """numba-cuda 0.30 (the GPU host's) registers an overload of ``np.row_stack`` when its typing
    context first loads, and NumPy 2.5 removed that alias (it was ``np.vstack``): every kernel
    compile then failed with AttributeError on an H200 with numpy 2.5.2. Restore the alias, only
    when it is missing, before anything compiles."""
    if not hasattr(np, "row_stack"):
        np.row_stack = np.vstack


def _cuda():
    numpy_compat()
    from numba import config, cuda
    # small images launch few blocks on purpose (the grid-stride loops are correct for any size):
    # no NumbaPerformanceWarning per launch (which a warnings-as-errors test run would raise)
    config.CUDA_LOW_OCCUPANCY_WARNINGS = 0
    return cuda


def _driver_present() -> bool:
    """An NVIDIA driver is visible (device nodes or libcuda): checked before importing numba.cuda,
    so that a CPU-only machine answers "auto" at no import cost."""
    if os.path.exists("/dev/nvidiactl") or os.path.exists("/dev/nvidia0"):
        return True
    import ctypes.util
    return ctypes.util.find_library("cuda") is not None


def cuda_unavailable_reason() -> str | None:
    """None when the CUDA path can run here, else why not (one line)."""
    if os.environ.get("NUMBA_ENABLE_CUDASIM") != "1" and not _driver_present():
        return "no NVIDIA driver here (no /dev/nvidiactl, no libcuda)"
    try:
        cuda = _cuda()
    except Exception as e:  # noqa: BLE001 - any import failure means no CUDA path
        return f"numba.cuda cannot be imported ({type(e).__name__}: {e})"
    try:
        if not cuda.is_available():
            return "numba.cuda sees no usable CUDA device (driver, GPU or CUDA runtime missing)"
    except Exception as e:  # noqa: BLE001
        return f"numba.cuda failed to query the CUDA driver ({type(e).__name__}: {e})"
    return None


def device_name() -> str:
    cuda = _cuda()
    if _simulated():
        return "Numba CUDA simulator (NUMBA_ENABLE_CUDASIM=1)"
    try:
        d = cuda.get_current_device()
        name = d.name.decode() if isinstance(d.name, bytes) else str(d.name)
        return f"{name} (compute capability {d.compute_capability[0]}.{d.compute_capability[1]})"
    except Exception as e:  # noqa: BLE001
        return f"CUDA device ({type(e).__name__}: {e})"


def _simulated() -> bool:
    from numba import config
    return bool(getattr(config, "ENABLE_CUDASIM", 0))


def _grid(n: int, stream=0):
    """(blocks, threads, stream) for a grid-stride loop over ``n`` items launched on ``stream``
    (0: the default stream)."""
    if _simulated():
        return 1, 8, stream  # the simulator runs each thread as a Python thread
    return max(1, min((n + 255) // 256, 1 << 20)), 256, stream


def _engine_stream(cuda):
    """The stream an engine launches its kernels on: its own, so that the copies of the next
    window (:class:`PinnedUploader`, on the uploader's stream) overlap them. Both are ordinary
    (blocking) streams, so the legacy default stream, on which host copies, uploads of tables
    and the two-sided filter's fusion run, still orders itself against both. With Numba's
    per-thread default stream that implicit ordering is gone: the engine then launches on the
    default stream (0), as everything else there does, and only the events order the copies."""
    from numba import config
    return 0 if getattr(config, "CUDA_PER_THREAD_DEFAULT_STREAM", 0) else cuda.stream()


class _Grouper:
    """Groups a window's events by pixel on the device (count, scan, scatter, sort per group)."""

    def __init__(self, n_pix: int, stream=0):
        cuda = _cuda()
        from . import _cuda_kernels as CK
        self.ck = CK
        self.n_pix = n_pix
        self.stream = stream  # the stream of its kernels (the engine's)
        self.cnt = cuda.to_device(np.zeros(n_pix + 1, np.int32))  # cnt[n_pix] stays 0: start[n_pix] = total
        self.start = cuda.device_array(n_pix + 1, np.int32)
        self.slot = cuda.device_array(_STAGE_MIN, np.int32)
        self.grp = cuda.device_array(_STAGE_MIN, np.int32)
        self._scan_bufs: dict = {}

    def _ensure(self, n: int) -> None:
        if self.slot.shape[0] < n:
            cuda = _cuda()
            cap = max(n, 2 * self.slot.shape[0])
            self.slot = cuda.device_array(cap, np.int32)
            self.grp = cuda.device_array(cap, np.int32)

    def _scan(self, src, n: int, dst, level: int = 0) -> None:
        CK = self.ck
        nb = (n + CK.SCAN_TILE - 1) // CK.SCAN_TILE
        key = (level, nb)
        bufs = self._scan_bufs.get(key)
        if bufs is None:
            cuda = _cuda()
            bufs = (cuda.device_array(nb, np.int32), cuda.device_array(nb, np.int32))
            self._scan_bufs[key] = bufs
        sums, offs = bufs
        CK.scan_block[nb, CK.SCAN_BLOCK, self.stream](src, n, dst, sums)
        if nb > 1:
            self._scan(sums, nb, offs, level + 1)
            CK.k_add_offsets[_grid(n, self.stream)](dst, n, offs)

    def group(self, dx, dy, a: int, n: int, width: int) -> None:
        """Group events ``a + [0, n)`` of the device arrays: ``start`` (n_pix + 1) and ``grp``."""
        CK = self.ck
        self._ensure(n)
        g = _grid(n, self.stream)
        with PH.phase("group_count", "parallel"):
            CK.k_count[g](dx, dy, a, n, width, self.cnt, self.slot)
        with PH.phase("group_scan", "parallel"):
            self._scan(self.cnt, self.n_pix + 1, self.start)
        with PH.phase("group_scatter", "parallel"):
            CK.k_scatter[g](dx, dy, a, n, width, self.start, self.slot, self.grp, self.cnt)
        with PH.phase("group_sort", "parallel"):
            CK.k_sort_groups[_grid(self.n_pix, self.stream)](self.start, self.n_pix, self.grp)


class PinnedUploader:
    """Host event columns to the device through two page-locked (pinned) staging buffers.

    :meth:`copy` packs a range of the columns into one buffer (a host copy) and queues its
    asynchronous DMA to the device on the uploader's own stream, ordered by CUDA events: the DMA
    waits for ``after`` (recorded on the consumer's stream once the kernels that last read the
    destination have been queued), and the kernels queued next on ``consumer`` (the engine's
    stream) wait for the DMA. It returns at once, so the host packs (and the driver reads and
    decodes) the next range while the device copies it and filters the previous one: copies
    overlap kernels. A pinned buffer is reused only once its previous DMA has completed (an event
    per buffer, waited on by the host). Pinned memory is what lets the DMA run asynchronously and
    at the bus's full speed (a pageable copy is staged by the driver through its own pinned
    buffer and blocks the host).
    """

    DTYPES = (np.int64, np.uint16, np.uint16, np.int8)

    def __init__(self, capacity: int, consumer=None):
        cuda = _cuda()
        self.cuda = cuda
        self.consumer = consumer  # the stream whose kernels read the copies (None: the host waits)
        self.cap = int(capacity)
        self.bufs = [[cuda.pinned_array(self.cap, dt) for dt in self.DTYPES] for _ in range(2)]
        self.done = [None, None]
        self.k = 0
        self.stream = cuda.stream()

    def copy(self, cols, a: int, b: int, dst, after=None) -> None:
        """Columns ``cols`` (t, x, y, p) ``[a, b)`` (at most the capacity) into the device arrays
        ``dst`` (each ``b - a`` long), asynchronously, once the event ``after`` (if any) has
        completed; the consumer's stream waits for the copy."""
        n = b - a
        if n > self.cap:
            raise ValueError(f"a range of {n} events exceeds the pinned staging capacity {self.cap}")
        k = self.k
        self.k ^= 1
        if self.done[k] is not None:
            self.done[k].synchronize()  # this buffer's previous DMA has finished
        buf = self.bufs[k]
        if after is not None:
            after.wait(self.stream)  # the kernels that read ``dst`` before have run
        for src, pb, d in zip(cols, buf, dst):
            np.copyto(pb[:n], src[a:b], casting="unsafe")  # as np.asarray(src, dtype) did
            d.copy_to_device(pb[:n], stream=self.stream)
        ev = self.cuda.event()
        ev.record(stream=self.stream)
        self.done[k] = ev
        if self.consumer is not None:
            ev.wait(self.consumer)  # the consumer's next kernels read the copy

    def wait(self) -> None:
        for ev in self.done:
            if ev is not None:
                ev.synchronize()


class DeviceEvents:
    """Event columns on the device (t int64, x, y uint16, p int8), with the host times for the
    window bounds (``lower(t)``: the number of events with timestamps < t)."""

    def __init__(self, t, x, y, p, host_t=None, reversed_of=None):
        self.t, self.x, self.y, self.p = t, x, y, p
        self.n = int(t.shape[0])
        self._host_t = host_t
        self._rev = reversed_of  # (forward host t, mirror): this copy is reversed

    @classmethod
    def upload(cls, events, pinned: bool = True, chunk_events: int = UPLOAD_CHUNK) -> "DeviceEvents":
        """The event columns on the device. ``pinned`` (default): through page-locked staging
        buffers, ``chunk_events`` at a time (:class:`PinnedUploader`: the copy into one buffer
        overlaps the DMA from the other, at the bus's speed); else one pageable copy per column."""
        cuda = _cuda()
        cols = [np.ascontiguousarray(a) for a in (events.t, events.x, events.y, events.p)]
        if not pinned:
            return cls(*(cuda.to_device(a) for a in cols), host_t=events.t)
        dev = [cuda.device_array(a.shape[0], a.dtype) for a in cols]
        up = PinnedUploader(chunk_events)
        with PH.phase("upload_pinned", "parallel"):
            for a in range(0, cols[0].shape[0], chunk_events):
                b = min(cols[0].shape[0], a + chunk_events)
                up.copy(cols, a, b, [d[a:b] for d in dev])
            up.wait()
        return cls(*dev, host_t=events.t)

    def reversed(self, t_mirror_us: int) -> "DeviceEvents":
        """:func:`.smoother.reverse_events` on the device."""
        cuda = _cuda()
        from . import _cuda_kernels as CK
        rt = cuda.device_array(self.n, np.int64)
        rx = cuda.device_array(self.n, np.uint16)
        ry = cuda.device_array(self.n, np.uint16)
        rp = cuda.device_array(self.n, np.int8)
        if self.n:
            with PH.phase("reverse_events", "parallel"):
                CK.k_reverse_events[_grid(self.n)](self.t, self.x, self.y, self.p, self.n, np.int64(t_mirror_us) - 1,
                                               rt, rx, ry, rp)
        return DeviceEvents(rt, rx, ry, rp, reversed_of=(self._host_t, int(t_mirror_us)))

    def lower(self, t_us: int) -> int:
        if self._rev is None:
            return int(np.searchsorted(self._host_t, t_us, side="left"))
        # reversed event j is forward event n-1-j with t' = mirror - 1 - t: t' < t_us <=> t > mirror - 1 - t_us
        ht, mirror = self._rev
        return self.n - int(np.searchsorted(ht, mirror - 1 - int(t_us), side="right"))

    def nbytes(self) -> int:
        return 13 * self.n


class _CudaEngine:
    """Shared by the GPU engines: thresholds, staging of host events, windows."""

    uses_events = True

    def __init__(self, shape, measurements, params):
        cuda = _cuda()
        from . import _cuda_kernels as CK
        self.cuda, self.ck = cuda, CK
        self.shape = (int(shape[0]), int(shape[1]))
        self.n = self.shape[0] * self.shape[1]
        self.m = measurements
        self.params = params
        self.k = -1
        self.stream = _engine_stream(cuda)  # every kernel of the engine (:func:`_engine_stream`)
        self.grouper = _Grouper(self.n, self.stream)
        self.n_events = 0  # every event of a window is applied (the serial filter's count)
        self._stage = None
        self._stage_k = 0
        self._stage_free = [None, None]  # per staging set: its readers' kernels, queued (an event)
        self._uploader = None
        self.con_px = self.coff_px = self._empty(np.float64)
        self.device_line = f"device: cuda ({device_name()})"
        self._cache: dict = {}
        self._rc = None  # resident chunk: [events, chunk start, chunk end, processed up to]
        self._cur = None

    def _dev(self, a, dtype=None):
        """A host array on the device, cached by its buffer (codes and tables come back)."""
        a = np.ascontiguousarray(a, dtype=dtype)
        key = (a.__array_interface__["data"][0], a.shape, a.dtype.str)
        hit = self._cache.get(key)
        if hit is not None:  # the same buffer (the cache keeps the array alive: no address reuse)
            return hit[1]
        d = self.cuda.to_device(a)
        if len(self._cache) > 8:
            self._cache.clear()
        self._cache[key] = (a, d)
        return d

    def _empty(self, dtype):
        return self.cuda.device_array(0, dtype)

    def set_thresholds(self, c_on, c_off) -> None:
        """Per-pixel ON and OFF thresholds, as :meth:`._engine.Engine.set_thresholds` (host
        arrays are checked and filled there, then uploaded)."""
        from ._engine import Engine
        host = Engine.__new__(Engine)
        host.params, host.shape = self.params, self.shape
        Engine.set_thresholds(host, c_on, c_off)
        self.host_con_px, self.host_coff_px = host.con_px, host.coff_px
        if host.con_px.size == 0:
            self.con_px = self.coff_px = self._empty(np.float64)
        else:
            self.con_px = self.cuda.to_device(host.con_px)
            self.coff_px = self.cuda.to_device(host.coff_px)

    def process(self, t, x, y, p, i0, i1) -> None:
        """Host events ``[i0, i1)``: uploaded through pinned staging buffers
        (:class:`PinnedUploader`, asynchronous), then :meth:`process_device` on the same stream.
        Two device staging sets alternate, so a window's copy runs while the previous window's
        kernels read the other set; a set is refilled once the kernels that read it have run
        (events, :class:`PinnedUploader`)."""
        for a in range(i0, i1, MAX_WINDOW):
            b = min(i1, a + MAX_WINDOW)
            n = b - a
            if self._stage is None or self._stage[0][0].shape[0] < n:
                cap = max(n, _STAGE_MIN, 0 if self._stage is None else 2 * self._stage[0][0].shape[0])
                cap = min(cap, MAX_WINDOW)
                self._stage = [tuple(self.cuda.device_array(cap, dt) for dt in PinnedUploader.DTYPES)
                               for _ in range(2)]
                if self._uploader is not None:
                    self._uploader.wait()
                self._uploader = PinnedUploader(cap, consumer=self.stream)
                self._stage_free = [None, None]
            k = self._stage_k
            self._stage_k ^= 1
            st = self._stage[k]
            with PH.phase("stage_upload", "parallel"):
                self._uploader.copy((t, x, y, p), a, b, [d[:n] for d in st], after=self._stage_free[k])
            self.process_device(*st, 0, n)
            ev = self.cuda.event()
            ev.record(stream=self.stream)
            self._stage_free[k] = ev

    def process_resident(self, dev: "DeviceEvents", i: int, j: int) -> None:
        """Events ``[i, j)`` of resident ``dev``: windows of a chunk grouped once
        (:data:`RESIDENT_CHUNK`), walked from per-pixel cursors. Consecutive calls continue the
        chunk; anything else (another range, :meth:`process_device`) closes it first."""
        if RESIDENT_CHUNK <= 0:
            self.process_device(dev.t, dev.x, dev.y, dev.p, i, j - i)
            return
        while i < j:
            rc = self._rc
            if rc is None or rc[0] is not dev or i != rc[3] or i >= rc[2]:
                self._flush_resident()
                c1 = min(dev.n, i + RESIDENT_CHUNK)
                self.grouper.group(dev.x, dev.y, i, c1 - i, self.shape[1])
                if self._cur is None:
                    self._cur = [self.cuda.device_array(self.n, np.int32), self.cuda.device_array(self.n, np.int32)]
                with PH.phase("chunk_cursors", "parallel"):
                    self.ck.k_copy_i32[_grid(self.n, self.stream)](self.grouper.start, self._cur[0], self.n)
                rc = self._rc = [dev, i, c1, i]
            e = min(j, rc[2])
            with PH.phase("walk", "parallel"):
                self._walk_res(dev, rc[1], e - rc[1])
            self._cur.reverse()
            rc[3] = e
            self.n_events += e - i
            i = e

    def _flush_resident(self) -> None:
        """Close the resident chunk (the AKF carries its last-event times over)."""
        rc, self._rc = self._rc, None
        if rc is not None:
            self._close_chunk(rc[0], rc[1])

    def _close_chunk(self, dev, c0: int) -> None:
        return None

    def process_device(self, dt, dx, dy, dp, a: int, n: int) -> None:
        self._flush_resident()
        for s in range(a, a + n, MAX_WINDOW):
            m = min(a + n, s + MAX_WINDOW) - s
            if m > 0:
                self.grouper.group(dx, dy, s, m, self.shape[1])
                with PH.phase("walk", "parallel"):
                    self._walk(dt, dx, dy, dp, s)
                self.n_events += m

    def close(self) -> None:
        """End of the pass: the resident chunk is closed (its events no longer referenced here)."""
        self._flush_resident()


class CudaAKFEngine(_CudaEngine):
    """:class:`._engine.AKFEngine` on the GPU: the same interface (``start``, ``next_switch_us``,
    ``switch``, ``process``, ``output``), driven by :func:`._engine.drive` or
    :func:`cuda_two_sided_iter`."""

    def __init__(self, shape, measurements, params):
        super().__init__(shape, measurements, params)
        cuda = self.cuda
        self.S = cuda.to_device(np.zeros((self.n, K.AKF_FIELDS)))
        self.te = [cuda.device_array(self.n, np.int64), cuda.device_array(self.n, np.int64)]
        self.seg_t0 = 0.0
        self.seg_inv_t = 0.0
        self.has_la_step = False
        self.noise_form = K.NOISE_PAPER if params.noise_model == "paper" else K.NOISE_REFERENCE
        self.ccount = self._empty(np.float32)
        self._out = None

    def set_thresholds(self, c_on, c_off) -> None:
        super().set_thresholds(c_on, c_off)
        fn = getattr(self.m, "set_thresholds", None)
        if fn is not None:
            fn(*((None, None) if self.con_px.shape[0] == 0 else (self.host_con_px, self.host_coff_px)))

    def _load(self, k: int, t_to: float | None = None) -> None:
        """:meth:`._engine.AKFEngine._load`, applied at once by a device kernel."""
        n = self.n
        from ._engine import segment_span
        sc, seg, t0_us, seg_inv_t, seg_t_s = segment_span(self.m, k, self.m.segment)
        prop = t_to is not None
        disc = prop and self.params.frame_update == "discrete"
        s_proc = float(self.params.process_noise_per_s) if self.params.frame_update == "discrete" else 0.0
        args = (self.S, prop, self.seg_t0, self.seg_inv_t, float(t_to) if prop else 0.0)
        g = _grid(n, self.stream)
        if sc is not None:
            for a, name in ((sc.code, "code"), (sc.code_next, "code_next")):
                if a.ndim != 1 or a.shape[0] not in ((n,) if name == "code" else (0, n)):
                    raise ValueError(f"measurement segment {k}: {name} has shape {a.shape}, expected ({n},) (H*W)")
            code = self._dev(sc.code)
            nxt = self._dev(sc.code_next) if sc.code_next.shape[0] else self._empty(code.dtype)
            tabs = [self._dev(a, np.float64) if np.asarray(a).shape[0] else self._empty(np.float64)
                    for a in (sc.rbar, sc.log_frame, sc.rinv, sc.censor)]
            self.ck.k_akf_switch_lut[g](*args, code, nxt, int(sc.max_code), *tabs, float(sc.la_step), seg_t_s,
                                        disc, s_proc, n)
            self.has_la_step = sc.la_step != 0.0
        else:
            def col(a, name, required):
                if a is None:
                    if required:
                        raise ValueError(f"measurement segment {k} has no {name}; the AKF needs it")
                    return self._empty(np.float64)
                a = np.ascontiguousarray(a, dtype=np.float64).reshape(-1)
                if a.shape[0] != n:
                    raise ValueError(f"measurement segment {k}: {name} has {a.shape[0]} values, expected {n} (H*W)")
                return self.cuda.to_device(a)
            lf = col(seg.log_frame, "log_frame", True)
            rinv = col(seg.rinv, "rinv", True)
            beta = col(seg.beta, "beta", False)
            step = col(seg.la_step, "la_step", False)
            cens = col(getattr(seg, "censor", None), "censor", False)
            disc = disc and bool(getattr(seg, "frame_update", True))
            uf = col(getattr(seg, "update_log_frame", None), "update_log_frame", False)
            self.ck.k_akf_switch[g](*args, lf, rinv, beta, step, cens, seg_t_s, disc, s_proc, uf, n)
            self.has_la_step = seg.la_step is not None
        self.seg_t0 = float(t0_us)
        self.seg_inv_t = seg_inv_t
        self.k = k

    def start(self, t_start_us=None) -> int:
        """:meth:`._engine.AKFEngine.start`: the first frame loaded and the state initialised
        from it, on the device (:func:`._cuda_kernels.k_akf_init`)."""
        times = self.m.times_us
        k0 = 0 if t_start_us is None else max(int(np.searchsorted(times, t_start_us, side="right")) - 1, 0)
        t_init = int(times[k0])
        from ._engine import check_time_range
        check_time_range(times, "frame timestamps")
        self._load(k0)
        pr = self.params
        off = getattr(pr, "intensity_offset", None)
        self.ck.k_akf_init[_grid(self.n, self.stream)](self.S, float(pr.initial_covariance),
                                          float(getattr(pr, "censored_initial_covariance", pr.initial_covariance)),
                                          off is not None, math.log(off) if off is not None else 0.0,
                                          float(t_init), self.n)
        g = _grid(self.n, self.stream)
        for te in self.te:
            self.ck.k_fill_i64[g](te, np.int64(t_init), self.n)
        return t_init

    def next_switch_us(self):
        return int(self.m.times_us[self.k + 1]) if self.k + 1 < len(self.m) else None

    def switch(self) -> None:
        with PH.phase("switch", "parallel"):
            self._load(self.k + 1, t_to=float(self.m.times_us[self.k + 1]))

    def _walk(self, dt, dx, dy, dp, a: int) -> None:
        pr = self.params
        H, W = self.shape
        gr = self.grouper
        self.ck.k_akf_walk[_grid(self.n, self.stream)](
            dt, dx, dy, dp, a, H, W, gr.start, gr.grp, self.te[0], self.te[1], self.S, self.has_la_step,
            self.seg_t0, self.seg_inv_t, pr.c_on, pr.c_off, pr.process_noise_per_s, pr.isolated_noise_per_s,
            pr.refractory_noise, np.int64(pr.refractory_period_us), self.noise_form, self.con_px, self.coff_px,
            self.ccount)
        self.te.reverse()

    def _walk_res(self, dev, c0: int, wb: int) -> None:
        pr = self.params
        H, W = self.shape
        gr = self.grouper
        self.ck.k_akf_walk_res[_grid(self.n, self.stream)](
            dev.t, dev.p, c0, wb, H, W, gr.start, gr.grp, self._cur[0], self._cur[1], self.te[0], self.S,
            self.has_la_step, self.seg_t0, self.seg_inv_t, pr.c_on, pr.c_off, pr.process_noise_per_s,
            pr.isolated_noise_per_s, pr.refractory_noise, np.int64(pr.refractory_period_us), self.noise_form,
            self.con_px, self.coff_px, self.ccount)

    def _close_chunk(self, dev, c0: int) -> None:
        gr = self.grouper
        with PH.phase("chunk_close", "parallel"):
            self.ck.k_chunk_te[_grid(self.n, self.stream)](dev.t, c0, gr.start, gr.grp, self._cur[0], self.te[0], self.te[1],
                                              self.n)
        self.te.reverse()

    # -- outputs ---------------------------------------------------------------------------
    def output_device(self, t_us: int, with_state: bool = False):
        """Device arrays (float32 L̂[, float64 L̂, P]) at ``t_us``."""
        cuda = self.cuda
        if self._out is None:
            self._out = cuda.device_array(self.n, np.float32)
        lg = cuda.device_array(self.n, np.float64) if with_state else self._empty(np.float64)
        var = cuda.device_array(self.n, np.float64) if with_state else self._empty(np.float64)
        self.ck.k_akf_output[_grid(self.n, self.stream)](self.S, self.seg_t0, self.seg_inv_t, float(t_us), self._out, lg, var,
                                            self.n)
        return self._out, lg, var

    def output(self, t_us: int, with_state: bool = False):
        """As :meth:`._engine.AKFEngine.output`: linear float32 image (H, W) [, float64 L̂, P],
        computed on the device (:func:`._cuda_kernels.k_akf_output_linear`); one copy back."""
        if with_state:
            d32, lg, var = self.output_device(t_us, True)
            out = d32.copy_to_host()
            K.log_to_linear(out, self.params.intensity_offset)
        else:
            if self._out is None:
                self._out = self.cuda.device_array(self.n, np.float32)
            with PH.phase("output_kernel", "parallel"):
                self.ck.k_akf_output_linear[_grid(self.n, self.stream)](self.S, self.seg_t0, self.seg_inv_t, float(t_us),
                                                           np.float32(self.params.intensity_offset), self._out,
                                                           self.n)
            with PH.phase("output_copy", "parallel"):
                out = self._out.copy_to_host()
        if with_state:
            return out.reshape(self.shape), lg.copy_to_host().reshape(self.shape), var.copy_to_host().reshape(self.shape)
        return out.reshape(self.shape)

    def output_state32(self, t_us: int, out_l, out_p, carried: tuple | None) -> None:
        """Float32 L̂ and P at ``t_us`` into device arrays; ``carried = (q, s)`` adds the carried
        variance ``q·n + s·(t_us − τ_ref)`` from :attr:`ccount` and :attr:`ctau` (see
        :class:`.smoother._CarriedVariance`)."""
        if carried is not None:
            cc, ct, q, s = self.ccount, self.ctau, carried[0], carried[1]
        else:
            cc, ct, q, s = self._empty(np.float32), self._empty(np.int64), 0.0, 0.0
        self.ck.k_akf_output_state32[_grid(self.n, self.stream)](self.S, self.seg_t0, self.seg_inv_t, float(t_us), out_l,
                                                    out_p, cc, q, s, np.int64(t_us), ct, self.n)

    def enable_count(self) -> None:
        """Count each pixel's events into :attr:`ccount` (for the carried variance), from the time
        :attr:`ctau` per pixel."""
        self.ccount = self.cuda.to_device(np.zeros(self.n, np.float32))
        self.ctau = self.cuda.to_device(np.zeros(self.n, np.int64))

    def reset_count(self, tau: int = 0, mask=None) -> None:
        """Restart the counts at a frame at ``tau`` µs for the pixels it measures (``mask``, a
        flat bool array; None: every pixel)."""
        m = self._empty(np.uint8) if mask is None else self.cuda.to_device(np.ascontiguousarray(mask, np.uint8))
        self.ck.k_reset_count[_grid(self.n, self.stream)](self.ccount, self.ctau, m, np.int64(tau), self.n)


class CudaCFEngine(_CudaEngine):
    """:class:`._engine.CFEngine` on the GPU ("cf", "direct", "highpass")."""

    def __init__(self, shape, measurements, params, mode: str):
        if mode not in ("cf", "direct", "highpass"):
            raise ValueError(f"mode must be 'cf', 'direct' or 'highpass', got {mode!r}")
        super().__init__(shape, measurements, params)
        self.mode = mode
        self.C = self.cuda.to_device(np.zeros((self.n, K.CF_FIELDS)))
        self.event_decay = float(getattr(params, "event_decay", 0.0))
        self.offset = 0.0 if mode == "highpass" else float(params.intensity_offset)
        self._lg = None

    def _columns(self, k: int | None, reset_l: bool, t_tu: float | None) -> None:
        """Load L^F and α of segment ``k`` (the CPU engine's host arithmetic, then uploaded),
        optionally L̂ = L^F and tu (:func:`._cuda_kernels.k_cf_load`). Frames of integer codes
        (``segment_codes`` with an intensity table) take the per-code path of
        :meth:`._engine.CFEngine._load_codes`: L^F and α are computed once per code on the host
        (the same numpy operations on the same intensities) and looked up per pixel on the device
        (:func:`._cuda_kernels.k_cf_load_lut`): no per-pixel host work, no full-image upload but
        the codes (cached by buffer)."""
        from ._engine import CFEngine
        host = CFEngine.__new__(CFEngine)
        host.mode, host.params, host.n = self.mode, self.params, self.n
        set_tu = t_tu is not None
        tu = float(t_tu) if set_tu else 0.0
        if k is not None:
            codes_fn = getattr(self.m, "segment_codes", None)
            sc = codes_fn(k) if codes_fn is not None else None
            if sc is not None and sc.intensity is not None:
                if sc.code.shape[0] != self.n:
                    raise ValueError(f"measurement codes have {sc.code.shape[0]} values, expected {self.n} (H*W)")
                table = np.asarray(sc.intensity, dtype=np.float64)
                pr = self.params
                lf_l = np.ascontiguousarray(np.log(table + self.offset))
                if self.mode == "direct":
                    al_l = np.zeros(table.shape[0])
                else:
                    al_l = np.full(table.shape[0], pr.alpha_rad_per_s)
                    if self.mode == "cf" and pr.adaptive_gain:
                        al_l[(table < pr.adaptive_low) | (table > pr.adaptive_high)] *= pr.adaptive_gain_scale
                key = ("cf_lut", table.__array_interface__["data"][0], table.shape, self.offset)
                hit = self._cache.get(key)
                if hit is None:
                    hit = (table, self.cuda.to_device(lf_l), self.cuda.to_device(al_l))
                    self._cache[key] = hit
                self.ck.k_cf_load_lut[_grid(self.n, self.stream)](self.C, self._dev(sc.code), int(sc.max_code), hit[1], hit[2],
                                                     bool(reset_l), set_tu, tu, self.n)
                self.k = k
                return
        if k is None:
            lf = np.zeros(self.n)
            alpha = np.ascontiguousarray(host._alpha(None), dtype=np.float64)
        else:
            seg = self.m.segment(k)
            lf = np.ascontiguousarray(np.log(seg.intensity + self.offset), dtype=np.float64).reshape(-1)
            alpha = np.ascontiguousarray(host._alpha(seg), dtype=np.float64).reshape(-1)
            self.k = k
        cuda = self.cuda
        self.ck.k_cf_load[_grid(self.n, self.stream)](self.C, cuda.to_device(lf), cuda.to_device(alpha), bool(reset_l),
                                         set_tu, tu, self.n)

    def start(self, t_start_us=None) -> int:
        if self.mode == "highpass":
            t_init = int(t_start_us)
            self._columns(None, True, float(t_init))
            return t_init
        from ._engine import check_time_range
        times = self.m.times_us
        k0 = 0 if t_start_us is None else max(int(np.searchsorted(times, t_start_us, side="right")) - 1, 0)
        check_time_range(times, "frame timestamps")
        t_init = int(times[k0])
        self._columns(k0, True, float(t_init))
        return t_init

    def next_switch_us(self):
        if self.m is None or self.mode == "highpass":
            return None
        return int(self.m.times_us[self.k + 1]) if self.k + 1 < len(self.m) else None

    def switch(self) -> None:
        t_to = float(self.m.times_us[self.k + 1])
        with PH.phase("switch", "parallel"):
            if self.mode == "direct":
                self._columns(self.k + 1, True, t_to)
                return
            self.ck.k_cf_propagate[_grid(self.n, self.stream)](self.C, t_to, self.n)
            self._columns(self.k + 1, False, None)

    def _walk(self, dt, dx, dy, dp, a: int) -> None:
        pr = self.params
        gr = self.grouper
        self.ck.k_cf_walk[_grid(self.n, self.stream)](dt, dp, a, self.n, gr.start, gr.grp, self.C, pr.c_on, pr.c_off,
                                         self.event_decay, self.con_px, self.coff_px)

    def _walk_res(self, dev, c0: int, wb: int) -> None:
        pr = self.params
        gr = self.grouper
        self.ck.k_cf_walk_res[_grid(self.n, self.stream)](dev.t, dev.p, c0, wb, self.n, gr.start, gr.grp, self._cur[0],
                                             self._cur[1], self.C, pr.c_on, pr.c_off, self.event_decay,
                                             self.con_px, self.coff_px)

    def output(self, t_us: int, with_state: bool = False):
        if self._lg is None:
            self._lg = self.cuda.device_array(self.n, np.float64)
        with PH.phase("output_kernel", "parallel"):
            self.ck.k_cf_output[_grid(self.n, self.stream)](self.C, float(t_us), self._lg, self.n)
        with PH.phase("output_copy", "parallel"):
            lg = self._lg.copy_to_host()
        with PH.phase("output_host_exp", "parallel"):
            out = (np.exp(lg) - self.offset).astype(np.float32)
        if with_state:
            return out.reshape(self.shape), lg.reshape(self.shape)
        return out.reshape(self.shape)


# -- two-sided -----------------------------------------------------------------------------------

class _HostWindows:
    """:class:`DeviceEvents`'s window interface over host events: each window is uploaded
    through the engine's staging buffer (bounded device memory)."""

    def __init__(self, ev):
        self.ev = ev
        self.n = len(ev)

    def lower(self, t_us: int) -> int:
        return int(np.searchsorted(self.ev.t, t_us, side="left"))

    def process(self, eng, i: int, j: int) -> None:
        eng.process(self.ev.t, self.ev.x, self.ev.y, self.ev.p, i, j)


def _device_process(dev: DeviceEvents, eng, i: int, j: int) -> None:
    eng.process_resident(dev, i, j)


def _run_pass_device(eng: CudaAKFEngine, dev, times: np.ndarray, taus: np.ndarray | None, progress=None,
                     measured=None):
    """Drive one pass as :func:`._engine.drive` would with explicit output ``times``; yield
    ``(t, j)`` at each output (the state then at t; ``j`` the index of the last frame time τ_j <= t
    in ``taus``, -1 before the first). At equal times: frame switch, then (carried variance) the
    per-pixel event count reset at τ_j (``measured(j)``: only the pixels frame j measures, after
    the first frame; None: every pixel), then the output; an output at t holds the events with
    timestamps < t, so the counts cover [τ_ref, t) as :class:`.smoother._CarriedVariance` does."""
    process = dev.process if isinstance(dev, _HostWindows) else (lambda e, i, j: _device_process(dev, e, i, j))
    t_init = eng.start(None)
    times = times[times >= t_init]
    INF = np.iinfo(np.int64).max
    i = dev.lower(t_init)  # events before the start are skipped
    io = it = 0
    j_tau = -1
    while io < times.size:
        ts = eng.next_switch_us()
        ts = INF if ts is None else ts
        to = int(times[io])
        tt = int(taus[it]) if taus is not None and it < taus.size else INF
        bp = min(ts, to, tt)
        j = max(dev.lower(bp), i)
        if j > i:
            process(eng, i, j)
            if progress is not None:
                progress(j - i)
            i = j
        if ts == bp:
            eng.switch()
        elif tt == bp:
            eng.reset_count(tt, None if (measured is None or j_tau < 0) else measured(it))
            j_tau = it
            it += 1
        else:
            yield to, j_tau
            io += 1


def cuda_two_sided_iter(events, frames, make_engine, times: np.ndarray, *, offset: float, progress=None,
                        info: dict | None = None, carried_variance: tuple | None = None, device_events=None,
                        censored_codes: tuple | None = None):
    """:func:`.smoother.two_sided_iter` on the GPU, in its serial order: the backward pass (on the
    reversed recording) keeps its float32 (L̂, P) per output on the device (host memory beyond
    :data:`DEVICE_STORE_BYTES`), then the forward pass streams, each output fused on the device
    (:func:`._cuda_kernels.k_fuse_linear`) and only the fused linear image copied back.

    ``make_engine(frames, events, backward)`` builds a :class:`CudaAKFEngine`; ``events`` is the
    host :class:`.event_arrays.EventArrays` of the pass (reversed for the backward pass) when
    ``make_engine.needs_events`` is true (frame augmentation), else None. ``device_events``: the
    events already on the device (:meth:`DeviceEvents.upload`); else they are uploaded when the
    forward and reversed copies fit :data:`DEVICE_EVENTS_BYTES`, otherwise each window streams
    through the engines' staging buffers. Yields ``(t_us, linear image)``.
    """
    from .smoother import _Store, frames_measure, reverse_events, reverse_frames
    cuda = _cuda()
    from . import _cuda_kernels as CK
    shape = events.shape
    n_pix = shape[0] * shape[1]
    t_lo = min(int(events.t[0]) if len(events) else int(frames.t_start_us[0]), int(frames.t_start_us[0]))
    t_hi = max(int(events.t[-1]) if len(events) else int(frames.t_end_us[-1]), int(frames.t_end_us[-1]))
    mirror = t_lo + t_hi + 1  # as smoother.two_sided_iter
    rev_fr = reverse_frames(frames, mirror)
    times = np.asarray(times, dtype=np.int64)
    rev_times = (np.int64(mirror) - times)[::-1]
    needs_host = bool(getattr(make_engine, "needs_events", False))
    dev = device_events
    if dev is None and 26 * len(events) <= DEVICE_EVENTS_BYTES:
        dev = DeviceEvents.upload(events)
    stats = {"outputs_fused": 0, "outputs_one_pass": 0, "backward_outputs": 0, "spilled_to_host": False,
             "n_clamped": 0, "n_output_pixels": 0}
    index = {int(t): i for i, t in enumerate(times)}
    n_out = times.size
    on_device = 8 * n_pix * n_out <= DEVICE_STORE_BYTES
    stats["spilled_to_host"] = not on_device
    dstore: list = [None] * n_out
    hstore = None if on_device else _Store(n_out, n_pix, 2)
    have_b = np.zeros(n_out, bool)
    g = _grid(n_pix)

    def taus_of(fr):
        return np.unique(np.asarray(fr.t_mid_us, dtype=np.int64)) if carried_variance is not None else None

    def carried_at(taus, j, t):
        if taus is None or j < 0:
            return None
        q, s = carried_variance
        return float(q), float(s)  # the age per pixel: as _CarriedVariance.add_to

    def passes(fr, ev_host, ev_dev, backward, tms):
        eng = make_engine(fr, ev_host if needs_host else None, backward)
        taus = taus_of(fr)
        if taus is not None:
            eng.enable_count()
        src = ev_dev if ev_dev is not None else _HostWindows(ev_host)
        measured = frames_measure(fr, censored_codes) if taus is not None else None
        try:
            for t, j in _run_pass_device(eng, src, tms, taus, progress, measured):
                yield eng, t, carried_at(taus, j, t)
        finally:
            eng.close()

    out = cuda.device_array(n_pix, np.float32)
    counts = cuda.to_device(np.zeros(2, np.int64))

    def fuse_one(l1, p1, l2, p2):
        """Fused linear image on the device (fusion, exp, clamp: _kernels.fuse_to_linear's steps)."""
        with PH.phase("fuse_kernel", "parallel"):
            CK.k_fill_i64[1, 32](counts, np.int64(0), 2)  # on the device: no host copy per output
            CK.k_fuse_linear[g](l1, p1, l2, p2, np.float32(offset), np.float32(K.MIN_INTENSITY), out, n_pix, counts)
        with PH.phase("output_copy", "parallel"):
            img = out.copy_to_host()
            nz, ncl = (int(v) for v in counts.copy_to_host())
        if nz:
            raise ZeroDivisionError("fuse_log32: P_f + P_b is 0")
        stats["n_clamped"] += ncl
        stats["n_output_pixels"] += img.size
        return img.reshape(shape)

    def backward_of(i):
        if on_device:
            return dstore[i]
        lb, pb = hstore.get(i)
        return cuda.to_device(lb), cuda.to_device(pb)

    try:
        # -- backward pass (reversed on the device when the events are resident)
        rev_dev = dev.reversed(mirror) if dev is not None else None
        rev_host = reverse_events(events, mirror) if (needs_host or rev_dev is None) else None
        for eng, tr, carried in passes(rev_fr, rev_host, rev_dev, True, rev_times):
            i = index[int(mirror - tr)]
            with PH.phase("backward_store", "parallel"):
                lb = cuda.device_array(n_pix, np.float32)
                pb = cuda.device_array(n_pix, np.float32)
                eng.output_state32(tr, lb, pb, carried)
            if on_device:
                dstore[i] = (lb, pb)
            else:
                hstore.put(i, lb.copy_to_host(), pb.copy_to_host())
            have_b[i] = True
            stats["backward_outputs"] += 1
        del rev_dev, rev_host
        # -- forward pass, fused as it goes, in time order
        lf = cuda.device_array(n_pix, np.float32)
        pf = cuda.device_array(n_pix, np.float32)
        fwd = passes(frames, events, dev, False, times)
        nxt = next(fwd, None)
        for i, t in enumerate(times):
            t = int(t)
            if nxt is not None and nxt[1] == t:
                eng, _, carried = nxt
                with PH.phase("forward_state32", "parallel"):
                    eng.output_state32(t, lf, pf, carried)
                if have_b[i]:
                    lb, pb = backward_of(i)
                    img = fuse_one(lf, pf, lb, pb)
                    stats["outputs_fused"] += 1
                else:  # one pass only: fusing it with itself is the identity
                    img = fuse_one(lf, pf, lf, pf)
                    stats["outputs_one_pass"] += 1
                nxt = next(fwd, None)
            elif have_b[i]:
                lb, pb = backward_of(i)
                img = fuse_one(lb, pb, lb, pb)
                stats["outputs_one_pass"] += 1
            else:
                continue
            dstore[i] = None
            yield t, img
    finally:
        if hstore is not None:
            hstore.close()
    if info is not None:
        info["two_sided"] = {k: stats[k] for k in ("outputs_fused", "outputs_one_pass", "backward_outputs",
                                                   "spilled_to_host")}
        info["n_clamped"] = stats["n_clamped"]
        info["n_output_pixels"] = stats["n_output_pixels"]
