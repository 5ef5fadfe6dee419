"""Iterate a source in a background thread, a bounded number of items ahead (private).

Used by ``convert`` (the reader decodes the next chunk while the writer stores this one) and by
the reconstruction driver. Numba kernels, numpy copies, zlib and HDF5 reads release the GIL, so
the two stages overlap on two cores.
"""

from __future__ import annotations

import queue
import threading
from typing import Iterable

__all__ = ["Prefetcher"]


class Prefetcher:
    """Iterate ``items`` in a background thread, at most ``depth`` items ahead of the consumer.

    Exceptions raised by the source are re-raised in the consumer, in order. :meth:`close` stops
    the thread and waits for it (the source can then be closed safely); it also closes a
    generator source. Use as a context manager or call :meth:`close` when stopping early.
    """

    def __init__(self, items: Iterable, depth: int = 1, name: str = "hybridhdr-prefetch"):
        self._src = iter(items)
        self._q: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._q.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def _run(self):
        try:
            for c in self._src:
                if not self._put(("item", c)):
                    return
        except BaseException as e:  # noqa: BLE001 - handed to the consumer
            self._put(("error", e))
            return
        self._put(("end", None))

    def __iter__(self):
        return self

    def __next__(self):
        if self._thread is None:
            raise StopIteration
        kind, v = self._q.get()
        if kind == "item":
            return v
        self.close()
        if kind == "error":
            raise v
        raise StopIteration

    def close(self):
        if self._thread is None:
            return
        self._stop.set()
        while self._thread.is_alive():
            try:  # unblock a producer waiting on a full queue
                self._q.get_nowait()
            except queue.Empty:
                pass
            self._thread.join(0.01)
        self._thread = None
        close = getattr(self._src, "close", None)
        if close is not None:  # a generator source: let it release its reader now
            close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
