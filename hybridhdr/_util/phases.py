"""Phase timer of the filters, CPU and GPU (private): where the time of a run goes, off by default.

``with phases.timing() as pt: reconstruct(...)`` makes the engines, the driver and the two-sided
filter add the wall time of each phase to ``pt`` (``time.perf_counter_ns``). The instrumented
code brackets each phase with one context manager, ``with phases.phase("filter", "parallel"):``;
off (the default) that returns a shared no-op object after testing one module attribute, once
per chunk, output or frame switch, never per event, so it costs nothing measurable.

``timing(sync=cuda.synchronize)`` times the GPU path (``benchmarks/gpu.py``): each phase is then
bracketed by ``sync()`` so that it holds the device work it queued, and its ``host_s`` says how
long the host took to queue it (launch overhead, host arithmetic and blocking copies; the rest
of its time is spent waiting for the device). This serialises host and device, so a profiled run
is slower than a plain one, whose figure is measured apart.

Each phase has a kind, which says how it scales with the row-band workers:

``parallel``
    row-band work in the driving thread's view: the wall time of a call that all workers share
    (filtering a batch, a frame switch, an output), so it shrinks as workers are added;
``serial``
    work on the critical path that one thread does whatever the number of workers (reading or
    waiting for the next chunk, planning the bands, the fusion, ...);
``worker``
    time inside the workers (summed over them): the split of a batch, waiting for the other
    workers, the filtering itself. It overlaps the ``parallel`` phase it belongs to and tells
    how the workers spend it.

``benchmarks/akf.py --workers`` turns this into the measured serial fraction of a run: with one
worker, ``1 - (parallel time) / (wall time)``, i.e. everything not inside a row-band call,
whether timed as a named ``serial`` phase or not (the remainder is reported as ``untimed``).
"""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

__all__ = ["PhaseTimer", "timing", "phase", "ACTIVE", "now"]

now = time.perf_counter_ns
KINDS = ("parallel", "serial", "worker")

#: the timer in use, or None (the default: no timing)
ACTIVE: "PhaseTimer | None" = None


class PhaseTimer:
    """Wall nanoseconds and call counts per named phase (thread-safe); ``sync``: a callable that
    waits for queued device work, called around each :func:`phase` (see the module docstring)."""

    def __init__(self, sync=None):
        self.ns: dict[str, int] = {}
        self.calls: dict[str, int] = {}
        self.kind: dict[str, str] = {}
        self.host_ns: dict[str, int] = {}
        self.sync = sync
        self._lock = threading.Lock()
        self.t0 = now()
        self.t1: int | None = None

    def add(self, name: str, t0_ns: int, kind: str = "serial") -> int:
        """Add ``now() - t0_ns`` to phase ``name`` (of ``kind``); returns now()."""
        t = now()
        if kind not in KINDS:
            raise ValueError(f"phase kind must be one of {KINDS}, got {kind!r}")
        with self._lock:
            self.ns[name] = self.ns.get(name, 0) + (t - t0_ns)
            self.calls[name] = self.calls.get(name, 0) + 1
            prev = self.kind.setdefault(name, kind)
        if prev != kind:
            raise ValueError(f"phase {name!r} was timed as {prev!r}, now as {kind!r}")
        return t

    def add_ns(self, name: str, ns: int, kind: str = "serial") -> None:
        """Add ``ns`` nanoseconds to phase ``name`` (e.g. a wait less the phases nested in it)."""
        self.add(name, now() - max(int(ns), 0), kind)

    def phase(self, name: str, kind: str = "serial") -> "_Phase":
        """A context manager adding the time of its block to phase ``name`` (of ``kind``)."""
        return _Phase(self, name, kind)

    def stop(self) -> None:
        self.t1 = now()

    @property
    def wall_ns(self) -> int:
        return (self.t1 if self.t1 is not None else now()) - self.t0

    def total(self, kind: str) -> int:
        return sum(v for k, v in self.ns.items() if self.kind[k] == kind)

    def report(self) -> dict:
        """``{"wall_s", "phases": {name: {"kind", "s", "calls"}}, "parallel_s", "serial_s",
        "untimed_s"}``: ``untimed_s`` is the wall time in neither a parallel nor a serial phase
        (Python between the calls, in the driving thread). With ``sync``, each phase also has
        ``host_s``."""
        wall = self.wall_ns
        par, ser = self.total("parallel"), self.total("serial")
        return {"wall_s": wall * 1e-9,
                "phases": {k: {"kind": self.kind[k], "s": self.ns[k] * 1e-9, "calls": self.calls[k],
                               **({"host_s": self.host_ns[k] * 1e-9} if k in self.host_ns else {})}
                           for k in sorted(self.ns)},
                "parallel_s": par * 1e-9, "serial_s": ser * 1e-9,
                "untimed_s": max(wall - par - ser, 0) * 1e-9}


class _Phase:
    __slots__ = ("tm", "name", "kind", "less", "less0", "t0")

    def __init__(self, tm: PhaseTimer, name: str, kind: str, less: str | None = None):
        self.tm, self.name, self.kind, self.less = tm, name, kind, less

    def __enter__(self):
        if self.tm.sync is not None:
            self.tm.sync()
        if self.less is not None:
            self.less0 = self.tm.total(self.less)
        self.t0 = now()
        return self

    def __exit__(self, *exc):
        tm = self.tm
        if tm.sync is not None:
            t_host = now()
            tm.sync()
            with tm._lock:
                tm.host_ns[self.name] = tm.host_ns.get(self.name, 0) + (t_host - self.t0)
        if self.less is None:
            tm.add(self.name, self.t0, self.kind)
        else:  # less the time of the phases of kind ``less`` that ran inside this one
            tm.add_ns(self.name, now() - self.t0 - (tm.total(self.less) - self.less0), self.kind)
        return False


class _NoPhase:
    __slots__ = ()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


_NO_PHASE = _NoPhase()


def phase(name: str, kind: str = "serial", less: str | None = None):
    """``with phase(name, kind):`` adds the block's wall time to phase ``name`` of the active
    timer (``kind``: see the module docstring); a shared no-op when none is active. ``less``: a
    kind whose phases nested in the block are subtracted (a wait that may hold timed work)."""
    tm = ACTIVE
    return _NO_PHASE if tm is None else _Phase(tm, name, kind, less)


@contextmanager
def timing(sync=None):
    """Time the phases of the runs inside the block; yields the :class:`PhaseTimer` (``sync``: see
    the module docstring)."""
    global ACTIVE
    prev = ACTIVE
    ACTIVE = pt = PhaseTimer(sync)
    try:
        yield pt
    finally:
        pt.stop()
        ACTIVE = prev
