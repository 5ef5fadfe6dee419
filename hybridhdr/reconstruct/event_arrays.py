"""Events held in memory as contiguous arrays with half-open time windows (:class:`EventArrays`),
and the streaming variant that reads a source chunk by chunk (:class:`StreamingEventArrays`).

Used by EDI (:mod:`.edi`), frame augmentation (:mod:`.augment`) and the two-sided smoother
(:mod:`.smoother`). Time windows are ``[t0, t1)`` selected with ``searchsorted``
(``docs/conventions.md``).
"""

from __future__ import annotations

import numpy as np

from .._util.checks import check_shape
from ..events import EVENT_DTYPE
from . import _augment_kernels as AK

#: events per thread below which the whole-array passes (split, reversal) stay in one thread
PARALLEL_MIN_EVENTS = 1 << 18


def split_range(ev, i0: int, i1: int, t, x, y, p, shape=None) -> bool:
    """Copy the columns of structured events ``ev[i0:i1]`` into ``t, x, y, p`` at ``[i0, i1)``
    (numpy's strided copies, which release the GIL: ranges in threads fill a recording's columns
    in parallel); with ``shape`` (H, W) also return True when the range is out of time order
    (against the event before ``i0`` too) or off the sensor, else False."""
    for dst, name in ((t, "t"), (x, "x"), (y, "y"), (p, "p")):
        dst[i0:i1] = ev[name][i0:i1]
    if shape is None or i1 <= i0:
        return False
    tt = t[max(i0 - 1, 0):i1]
    return bool(np.any(tt[1:] < tt[:-1])) or int(x[i0:i1].max()) >= shape[1] or int(y[i0:i1].max()) >= shape[0]


def map_ranges(n: int, n_workers: int, fn, min_part: int | None = None) -> list:
    """``fn(i0, i1)`` over ``n_workers`` contiguous parts of ``range(n)``, in threads (the Numba
    kernels or numpy copies it calls release the GIL); the last part runs in the caller. Parts
    below ``min_part`` (default :data:`PARALLEL_MIN_EVENTS`) are merged, so short arrays take
    one thread."""
    min_part = PARALLEL_MIN_EVENTS if min_part is None else int(min_part)
    k = max(1, min(int(n_workers), n // max(min_part, 1)))
    edges = [round(i * n / k) for i in range(k + 1)]
    if k == 1:
        return [fn(0, n)]
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(k - 1, thread_name_prefix="hybridhdr-ranges") as ex:
        futs = [ex.submit(fn, edges[i], edges[i + 1]) for i in range(k - 1)]
        last = fn(edges[k - 1], edges[k])
        return [f.result() for f in futs] + [last]

__all__ = ["EventArrays", "StreamingEventArrays"]


class EventArrays:
    """Time-sorted events held in memory as contiguous arrays, with half-open time windows.

    Parameters
    ----------
    t : ndarray of shape (N,), int64
        Timestamps in µs, non-decreasing.
    x, y : ndarray of shape (N,), uint16
        Column and row.
    p : ndarray of shape (N,), int8
        Polarity ±1.
    shape : (int, int)
        (H, W) of the sensor.
    """

    def __init__(self, t, x, y, p, shape):
        self.t = np.ascontiguousarray(t, dtype=np.int64)
        self.x = np.ascontiguousarray(x, dtype=np.uint16)
        self.y = np.ascontiguousarray(y, dtype=np.uint16)
        self.p = np.ascontiguousarray(p, dtype=np.int8)
        n = self.t.shape[0]
        for name in ("x", "y", "p"):
            check_shape(getattr(self, name), "N", f"events: {name} (like t)", sizes={"N": n})
        self.shape = (int(shape[0]), int(shape[1]))
        _check_order_and_bounds(self.t, self.x, self.y, self.shape)

    @classmethod
    def from_structured(cls, events, shape, n_workers: int = 1) -> "EventArrays":
        """From an ``EVENT_DTYPE`` structured array, split into columns and checked by
        ``n_workers`` threads, each a contiguous part (:func:`split_range`)."""
        n = int(events.shape[0]) if getattr(events, "ndim", 0) == 1 else -1
        if n <= 0 or events.dtype != EVENT_DTYPE or not events.flags.c_contiguous:
            return cls(events["t"], events["x"], events["y"], events["p"], shape)
        h, w = int(shape[0]), int(shape[1])
        t = np.empty(n, np.int64)
        x = np.empty(n, np.uint16)
        y = np.empty(n, np.uint16)
        p = np.empty(n, np.int8)
        bad = map_ranges(n, n_workers, lambda i0, i1: split_range(events, i0, i1, t, x, y, p, (h, w)))
        if any(bad):  # the plain constructor names the fault
            return cls(events["t"], events["x"], events["y"], events["p"], shape)
        return cls._trusted(t, x, y, p, shape)

    @classmethod
    def _trusted(cls, t, x, y, p, shape) -> "EventArrays":
        """Arrays already contiguous, of the right dtypes, time-sorted and on the sensor."""
        self = cls.__new__(cls)
        self.t, self.x, self.y, self.p = t, x, y, p
        self.shape = (int(shape[0]), int(shape[1]))
        return self

    @classmethod
    def from_chunks(cls, chunks, shape) -> "EventArrays":
        """Concatenate ``(t, x, y, p)`` chunks (as produced by the readers' chunk iterators)."""
        parts = list(chunks)
        if not parts:
            z = np.zeros(0, np.int64)
            return cls(z, z.astype(np.uint16), z.astype(np.uint16), z.astype(np.int8), shape)
        return cls(*(np.concatenate([c[i] for c in parts]) for i in range(4)), shape)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def window(self, t0_us: int, t1_us: int) -> tuple[int, int]:
        """Indices ``[i0, i1)`` of the events with ``t0_us <= t < t1_us``."""
        return (int(np.searchsorted(self.t, t0_us, side="left")),
                int(np.searchsorted(self.t, t1_us, side="left")))

    def chunks(self, n: int):
        """Yield ``(t, x, y, p)`` slices of ``n`` events (for the filter driver)."""
        for i in range(0, len(self), n):
            yield self.t[i:i + n], self.x[i:i + n], self.y[i:i + n], self.p[i:i + n]

    def close(self) -> None:
        """Nothing to release (see :class:`StreamingEventArrays`)."""

    def counts(self, t0_us: int, t1_us: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel signed count Σσ and number of events in ``[t0_us, t1_us)``, int64 (H*W,)."""
        n = self.shape[0] * self.shape[1]
        s = np.zeros(n, np.int64)
        a = np.zeros(n, np.int64)
        if t1_us > t0_us:
            i0, i1 = self.window(t0_us, t1_us)
            AK.event_counts(self.x, self.y, self.p, i0, i1, self.shape[1], s, a)
        return s, a


def _check_order_and_bounds(t, x, y, shape, base: int = 0) -> None:
    """Raise ValueError unless ``t`` is non-decreasing and ``x``, ``y`` lie on the (H, W) sensor.

    ``base`` is the index of ``t[0]`` in the whole stream (for the message). No int64 diff copy
    (20 M events: 0.1 s).
    """
    if t.shape[0] > 1 and np.any(dec := t[1:] < t[:-1]):
        i = int(np.argmax(dec)) + 1
        raise ValueError(f"events t must be non-decreasing; index {base + i} has {int(t[i])} after "
                         f"{int(t[i - 1])}")
    if x.shape[0] and (int(x.max()) >= shape[1] or int(y.max()) >= shape[0]):
        raise ValueError(f"event coordinates exceed the sensor size {tuple(shape)} (H, W): max x "
                         f"{int(x.max())}, max y {int(y.max())}")


class StreamingEventArrays(EventArrays):
    """:class:`EventArrays` filled from event chunks by a background thread, read as it fills.

    For sources that declare their event count (the container, an in-memory recording), frame
    augmentation and EDI need not wait for the whole file: :meth:`window` (and so
    :meth:`counts` and the EDI functions) waits only until the events before its end time are
    in, and :meth:`chunks` yields slices as they arrive. Reading and decompressing then overlap
    the filter. Chunks are checked as they arrive (time order, coordinates); an error, or more
    events than declared, is raised in the reading thread's consumer. Fewer events than declared
    (a file that ends early) make the arrays shorter. :meth:`close` stops the thread.
    """

    def __init__(self, chunks, shape, n_total: int):
        import threading
        n_total = int(n_total)
        if n_total < 0:
            raise ValueError(f"n_total must be >= 0, got {n_total}")
        self.shape = (int(shape[0]), int(shape[1]))
        self.t = np.empty(n_total, np.int64)
        self.x = np.empty(n_total, np.uint16)
        self.y = np.empty(n_total, np.uint16)
        self.p = np.empty(n_total, np.int8)
        self._n = 0
        self._done = False
        self._error: BaseException | None = None
        self._stop = False
        self._cv = threading.Condition()
        self._src = chunks
        self._thread = threading.Thread(target=self._run, name="hybridhdr-events", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        cap = self.t.shape[0]
        n = 0
        try:
            for c in self._src:
                if self._stop:
                    return
                t, x, y, p = c
                m = len(t)
                if m == 0:
                    continue
                if n + m > cap:
                    raise ValueError(f"the source declared {cap} events but yields more ({n + m} so far)")
                if len(x) != m or len(y) != m or len(p) != m:
                    raise ValueError(f"event chunk columns differ in length: t {m}, x {len(x)}, y {len(y)}, p {len(p)}")
                self.t[n:n + m] = t
                self.x[n:n + m] = x
                self.y[n:n + m] = y
                self.p[n:n + m] = p
                b = max(n - 1, 0)  # the order check includes the previous chunk's last event
                _check_order_and_bounds(self.t[b:n + m], self.x[n:n + m], self.y[n:n + m], self.shape, base=b)
                n += m
                with self._cv:
                    self._n = n
                    self._cv.notify_all()
        except BaseException as e:  # noqa: BLE001 - handed to the reading thread
            self._error = e
        finally:
            close = getattr(self._src, "close", None)
            if close is not None:  # a generator source: release its reader (and its own thread)
                try:
                    close()
                except Exception as e:  # noqa: BLE001
                    self._error = self._error or e
            with self._cv:
                if self._error is None and n < cap:  # the source ended early: shorter arrays
                    self.t, self.x, self.y, self.p = self.t[:n], self.x[:n], self.y[:n], self.p[:n]
                self._done = True
                self._cv.notify_all()

    def _wait(self, pred) -> int:
        with self._cv:
            self._cv.wait_for(lambda: self._done or pred(self._n))
            if self._error is not None:
                raise self._error
            return self._n

    def _wait_time(self, t_us: int) -> int:
        """Wait until every event with ``t < t_us`` is in; return the number loaded."""
        return self._wait(lambda n: n > 0 and self.t[n - 1] >= t_us)

    def __len__(self) -> int:
        return self._wait(lambda n: False)

    def window(self, t0_us: int, t1_us: int) -> tuple[int, int]:
        n = self._wait_time(max(int(t0_us), int(t1_us)))
        tt = self.t[:n]
        return (int(np.searchsorted(tt, t0_us, side="left")), int(np.searchsorted(tt, t1_us, side="left")))

    def chunks(self, n: int):
        i = 0
        while True:
            m = self._wait(lambda k: k >= i + n)
            if m <= i:
                return
            j = min(m, i + n)
            yield self.t[i:j], self.x[i:j], self.y[i:j], self.p[i:j]
            i = j

    def close(self) -> None:
        """Stop the reading thread (after its current chunk) and wait for it."""
        self._stop = True
        if self._thread.is_alive():
            self._thread.join()
