"""Live and replayed data sources: iterators of timestamped event chunks and frames.

An :class:`EventSource` yields :class:`~hybridhdr.formats.EventChunk` objects (sorted events plus the
trigger edges and, from a live DAVIS, the IMU samples that arrived with them); a :class:`FrameSource` yields :class:`FrameItem` objects (one
image with its exposure interval, exposure, ISO/gain and the camera's sequence number). Both are
context managers (``open``/``close``), describe their device with :meth:`device_info`, and stop
early when :meth:`stop` is called from another thread (the recorder does this).

``can_backpressure`` tells the recorder what to do when its queue is full: a file replay or a
generator can simply be made to wait (the producer blocks), a live camera cannot (its driver
buffer would overflow), so the recorder drops and counts instead. See ``docs/capture.md``.

Times are int64 µs (``docs/conventions.md``). Replay pacing uses :func:`time.perf_counter`.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from .._util.checks import check_shape
from ..events import EVENT_DTYPE, SensorSize, empty_triggers
from ..formats import EventChunk
from ..formats import open_reader
from ..model import Frames

__all__ = ["FrameItem", "EventSource", "FrameSource", "ReplayEventSource", "ReplayFrameSource",
           "SyntheticEventSource", "PACES", "frames_from_items"]

#: Replay pacing modes: ``realtime`` follows the recorded clock (scaled by ``speed``); ``fast``
#: delivers as fast as the consumer takes the data.
PACES = ("realtime", "fast")


@dataclass(frozen=True, eq=False)
class FrameItem:
    """One frame from a :class:`FrameSource`.

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, 3)
        Pixel values, dtype kept.
    t_start_us, t_end_us : int
        Exposure interval on the frame camera's clock, µs.
    exposure_us : int
        Exposure time reported by the camera for THIS frame (µs).
    iso, gain : float or None
        Sensitivity reported for this frame.
    sequence : int
        The camera's frame counter (gaps mean frames lost before they reached us).
    """

    image: np.ndarray
    t_start_us: int
    t_end_us: int
    exposure_us: int
    iso: float | None = None
    gain: float | None = None
    sequence: int = 0

    def __post_init__(self):
        im = np.asarray(self.image)
        check_shape(im, "H W | H W 3", "FrameItem.image")
        if int(self.t_end_us) < int(self.t_start_us):
            raise ValueError(f"FrameItem: exposure end {self.t_end_us} µs is before its start {self.t_start_us} µs")
        if int(self.exposure_us) < 0:
            raise ValueError(f"FrameItem.exposure_us must be >= 0, got {self.exposure_us}")
        object.__setattr__(self, "image", im)
        for name in ("t_start_us", "t_end_us", "exposure_us", "sequence"):
            object.__setattr__(self, name, int(getattr(self, name)))


def frames_from_items(items, encoding: str = "unknown") -> Frames:
    """Stack :class:`FrameItem` objects into :class:`~hybridhdr.model.Frames` (ISO/gain NaN if absent)."""
    items = list(items)
    if not items:
        raise ValueError("frames_from_items needs at least one FrameItem, got none")
    imgs = np.stack([it.image for it in items])
    kw = {}
    for name in ("iso", "gain"):
        vals = [getattr(it, name) for it in items]
        if any(v is not None for v in vals):
            kw[name] = np.array([np.nan if v is None else float(v) for v in vals])
    return Frames(imgs, np.array([it.t_start_us for it in items], np.int64),
                  np.array([it.t_end_us for it in items], np.int64), encoding=encoding, **kw)


class _Source:
    """Shared open/close/stop plumbing."""

    #: True when the producer may be made to wait (file replay, generator); False for live devices.
    can_backpressure: bool = False

    def __init__(self):
        self._stop_event = threading.Event()
        self._opened = False

    def open(self):
        self._stop_event.clear()
        self._opened = True
        return self

    def close(self) -> None:
        self._opened = False

    def stop(self) -> None:
        """Ask the iterator to end after the current item (thread-safe)."""
        self._stop_event.set()

    @property
    def stopped(self) -> bool:
        return self._stop_event.is_set()

    def device_info(self) -> dict:
        return {"kind": type(self).__name__}

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()

    def _sleep_until(self, deadline: float) -> None:
        """Sleep until ``perf_counter() >= deadline`` or stop() (checks every 50 ms)."""
        while not self._stop_event.is_set():
            d = deadline - time.perf_counter()
            if d <= 0:
                return
            self._stop_event.wait(min(d, 0.05))


class EventSource(_Source):
    """Interface: iterate to get :class:`~hybridhdr.formats.EventChunk` objects in time order.

    Subclasses set :attr:`sensor_size` and implement :meth:`_iter`.
    """

    sensor_size: SensorSize | None = None

    def _iter(self) -> Iterator[EventChunk]:
        raise NotImplementedError(f"{type(self).__name__} must implement _iter")

    def __iter__(self) -> Iterator[EventChunk]:
        if not self._opened:
            self.open()
        for chunk in self._iter():
            yield chunk
            if self._stop_event.is_set():
                return


class FrameSource(_Source):
    """Interface: iterate to get :class:`FrameItem` objects in order of exposure start."""

    encoding: str = "unknown"

    def _iter(self) -> Iterator[FrameItem]:
        raise NotImplementedError(f"{type(self).__name__} must implement _iter")

    def __iter__(self) -> Iterator[FrameItem]:
        if not self._opened:
            self.open()
        for item in self._iter():
            yield item
            if self._stop_event.is_set():
                return


def _check_pace(pace, speed):
    if pace not in PACES:
        raise ValueError(f"pace must be one of {PACES}, got {pace!r}")
    if not (float(speed) > 0):
        raise ValueError(f"speed must be > 0 (1.0 = recorded rate), got {speed}")
    return float(speed)


class ReplayEventSource(EventSource):
    """Replay an event file of any readable format as a live stream.

    Parameters
    ----------
    path : path-like
        Any file :func:`hybridhdr.open_reader` reads.
    pace : {"realtime", "fast"}
        ``realtime`` delivers each window when the wall clock reaches its end (scaled by ``speed``);
        ``fast`` as fast as the consumer takes it.
    speed : float
        Replay speed factor for ``realtime`` (2.0 = twice as fast as recorded).
    chunk_us : int
        Length of each delivered window in µs (half-open ``[t0, t0 + chunk_us)``).
    format : str, optional
        Reader format override.
    t_origin_us : int, optional
        Recorded time that corresponds to the wall-clock start (default: the first event); pass the
        same value to a :class:`ReplayFrameSource` to replay both in step.
    """

    can_backpressure = True

    def __init__(self, path, pace: str = "realtime", speed: float = 1.0, chunk_us: int = 10_000, *,
                 format: str | None = None, t_origin_us: int | None = None, read_chunk_events: int = 1 << 20,
                 **reader_options):
        super().__init__()
        self.path = Path(path)
        self.pace = pace
        self.speed = _check_pace(pace, speed)
        if int(chunk_us) < 1:
            raise ValueError(f"chunk_us must be >= 1 µs, got {chunk_us}")
        self.chunk_us = int(chunk_us)
        self.format = format
        self.t_origin_us = t_origin_us
        self.read_chunk_events = int(read_chunk_events)
        self._reader_options = reader_options
        self._reader = None

    def open(self):
        if self._reader is None:
            self._reader = open_reader(self.path, self.format, **self._reader_options)
            self.sensor_size = self._reader.sensor_size
        return super().open()

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        super().close()

    def device_info(self) -> dict:
        r = self._reader
        return {"kind": "replay", "path": str(self.path), "format": None if r is None else r.format_name,
                "sensor": None if self.sensor_size is None else str(self.sensor_size),
                "model": "" if r is None else r.metadata.event_camera.model,
                "pace": self.pace, "speed": self.speed}

    def _windows(self) -> Iterator[tuple[int, EventChunk]]:
        """Cut the reader's chunks into ``chunk_us`` windows; yields (window end µs, chunk)."""
        pend_ev: list[np.ndarray] = []
        pend_tr: list[np.ndarray] = []
        t0 = None
        for c in self._reader.iter_chunks(self.read_chunk_events):
            if len(c.triggers):
                pend_tr.append(c.triggers)
            if len(c.events):
                pend_ev.append(c.events)
            if t0 is None:
                ts = [a["t"][0] for a in pend_ev + pend_tr if len(a)]
                if not ts:
                    continue
                t0 = int(min(ts)) if self.t_origin_us is None else int(self.t_origin_us)
                if self.t_origin_us is None:
                    self.t_origin_us = t0
            if not pend_ev:
                continue
            last = int(pend_ev[-1]["t"][-1])
            if last < t0 + self.chunk_us:
                continue
            ev = np.concatenate(pend_ev) if len(pend_ev) > 1 else pend_ev[0]
            tr = np.concatenate(pend_tr) if len(pend_tr) > 1 else (pend_tr[0] if pend_tr else empty_triggers())
            # emit every complete window; the last (possibly incomplete) one waits for more data
            n_full = (last - t0) // self.chunk_us
            bounds = t0 + self.chunk_us * np.arange(1, n_full + 1, dtype=np.int64)
            ie = np.searchsorted(ev["t"], bounds, side="left")
            it = np.searchsorted(tr["t"], bounds, side="left")
            a = b = 0
            for k in range(n_full):
                yield int(bounds[k]), EventChunk(ev[a:ie[k]], tr[b:it[k]])
                a, b = int(ie[k]), int(it[k])
            t0 = int(bounds[-1])
            pend_ev = [ev[a:]] if a < len(ev) else []
            pend_tr = [tr[b:]] if b < len(tr) else []
        ev = np.concatenate(pend_ev) if pend_ev else np.zeros(0, EVENT_DTYPE)
        tr = np.concatenate(pend_tr) if pend_tr else empty_triggers()
        if len(ev) or len(tr):
            t_end = max(int(ev["t"][-1]) if len(ev) else 0, int(tr["t"][-1]) if len(tr) else 0) + 1
            yield t_end, EventChunk(ev, tr)

    def _iter(self) -> Iterator[EventChunk]:
        wall0 = time.perf_counter()
        for t_end, chunk in self._windows():
            if self.pace == "realtime":
                self._sleep_until(wall0 + (t_end - self.t_origin_us) / (1e6 * self.speed))
                if self.stopped:
                    return
            yield chunk


class ReplayFrameSource(FrameSource):
    """Replay the frames of a file (or a :class:`~hybridhdr.model.Frames`) as a live frame stream.

    Each frame is delivered when the (scaled) wall clock reaches its exposure end. Sequence numbers
    count from 0; exposure is ``t_end_us - t_start_us``.
    """

    can_backpressure = True

    def __init__(self, source, pace: str = "realtime", speed: float = 1.0, *, format: str | None = None,
                 t_origin_us: int | None = None):
        super().__init__()
        self.pace = pace
        self.speed = _check_pace(pace, speed)
        self.t_origin_us = t_origin_us
        if isinstance(source, Frames):
            self.path, self._frames = None, source
        else:
            self.path, self._frames = Path(source), None
            self.format = format

    def open(self):
        if self._frames is None:
            with open_reader(self.path, self.format) as r:
                fr = r.read_frames()
            if fr is None or not len(fr):
                raise ValueError(f"{self.path}: the file holds no frames (expected a frame-carrying format "
                                 f"such as a hybridhdr container, AEDAT4 or an ECD folder)")
            self._frames = fr
        self.encoding = self._frames.encoding
        return super().open()

    def device_info(self) -> dict:
        fr = self._frames
        return {"kind": "replay", "path": None if self.path is None else str(self.path),
                "frames": None if fr is None else len(fr),
                "frame_size": None if fr is None else f"{fr.shape[1]}x{fr.shape[0]}", "pace": self.pace}

    def _iter(self) -> Iterator[FrameItem]:
        fr = self._frames
        if not len(fr):
            return
        t0 = int(fr.t_start_us[0]) if self.t_origin_us is None else int(self.t_origin_us)
        wall0 = time.perf_counter()
        for k in range(len(fr)):
            if self.pace == "realtime":
                self._sleep_until(wall0 + (int(fr.t_end_us[k]) - t0) / (1e6 * self.speed))
                if self.stopped:
                    return
            yield FrameItem(fr.images[k], int(fr.t_start_us[k]), int(fr.t_end_us[k]),
                            int(fr.t_end_us[k] - fr.t_start_us[k]),
                            None if fr.iso is None else float(fr.iso[k]),
                            None if fr.gain is None else float(fr.gain[k]), k)


class SyntheticEventSource(EventSource):
    """A cheap event generator for soak tests, with loss detectable end to end.

    One chunk of ``rate_ev_per_s * chunk_us / 1e6`` events (sorted random times in
    ``[0, chunk_us)``, random pixels and polarities from ``seed``) is built once; chunk ``k`` is that
    chunk with ``k * chunk_us`` added to every timestamp. So event ``i`` of the stream is fully
    determined by ``i`` — :meth:`check_events` verifies a read-back stream event by event (a lost,
    duplicated or reordered chunk changes the timestamps of everything after it).

    Parameters
    ----------
    rate_ev_per_s : float
        Event rate (events per second of the event clock).
    sensor_size : SensorSize or (height, width)
    chunk_us : int
        Chunk length in µs (the sequence unit).
    duration_s : float, optional
        Stop after this much event time (default: until :meth:`stop`).
    pace : {"realtime", "fast"}
        ``realtime`` releases chunk ``k`` when the wall clock reaches ``(k + 1) * chunk_us``
        (never waits to catch up if the consumer was late); ``fast`` as fast as consumed.
    seed : int
    """

    can_backpressure = True

    def __init__(self, rate_ev_per_s: float, sensor_size=(720, 1280), chunk_us: int = 10_000, *,
                 duration_s: float | None = None, pace: str = "realtime", seed: int = 0,
                 t0_us: int = 0):
        super().__init__()
        if not (float(rate_ev_per_s) > 0):
            raise ValueError(f"rate_ev_per_s must be > 0, got {rate_ev_per_s}")
        if int(chunk_us) < 1:
            raise ValueError(f"chunk_us must be >= 1 µs, got {chunk_us}")
        self.pace = pace
        _check_pace(pace, 1.0)
        self.rate_ev_per_s = float(rate_ev_per_s)
        self.sensor_size = SensorSize.from_any(sensor_size)
        self.chunk_us = int(chunk_us)
        self.chunk_events = max(1, int(round(self.rate_ev_per_s * self.chunk_us / 1e6)))
        self.n_chunks = None if duration_s is None else max(1, int(round(float(duration_s) * 1e6 / self.chunk_us)))
        self.seed = seed
        self.t0_us = int(t0_us)
        self.base = self.make_base_chunk(self.chunk_events, self.chunk_us, self.sensor_size, seed, self.t0_us)
        # fast chunk construction: copy the 16-byte records as int64 pairs, add the offset to t
        self._base_t = np.ascontiguousarray(self.base["t"])
        self._base_rest = np.ascontiguousarray(self.base.view(np.int64).reshape(-1, 2)[:, 1])
        self.chunks_emitted = 0
        self.events_emitted = 0

    @staticmethod
    def make_base_chunk(n: int, chunk_us: int, sensor_size: SensorSize, seed, t0_us: int = 0) -> np.ndarray:
        rng = np.random.default_rng(seed)
        ev = np.empty(n, EVENT_DTYPE)
        ev["t"] = t0_us + np.sort(rng.integers(0, chunk_us, n))
        ev["x"] = rng.integers(0, sensor_size.width, n)
        ev["y"] = rng.integers(0, sensor_size.height, n)
        ev["p"] = np.where(rng.random(n) < 0.5, 1, -1)
        return ev

    def device_info(self) -> dict:
        return {"kind": "synthetic", "rate_ev_per_s": self.rate_ev_per_s, "chunk_us": self.chunk_us,
                "chunk_events": self.chunk_events, "seed": self.seed, "sensor": str(self.sensor_size),
                "pace": self.pace}

    def _iter(self) -> Iterator[EventChunk]:
        wall0 = time.perf_counter()
        k = 0
        empty = empty_triggers()
        while self.n_chunks is None or k < self.n_chunks:
            if self.pace == "realtime":
                self._sleep_until(wall0 + (k + 1) * self.chunk_us / 1e6)
                if self.stopped:
                    return
            buf = np.empty((self.chunk_events, 2), np.int64)
            buf[:, 1] = self._base_rest
            np.add(self._base_t, k * self.chunk_us, out=buf[:, 0])
            ev = buf.view(EVENT_DTYPE).reshape(-1)
            self.chunks_emitted = k + 1
            self.events_emitted += len(ev)
            yield EventChunk(ev, empty)
            k += 1

    def check_events(self, events: np.ndarray, start_index: int = 0) -> int:
        """Compare events ``start_index ..`` of a read-back stream with what this source generated.

        Returns the number of matching events; raises ``ValueError`` naming the first mismatch.
        """
        n = len(events)
        if n == 0:
            return 0
        i = np.arange(start_index, start_index + n, dtype=np.int64)
        k, j = np.divmod(i, self.chunk_events)
        b = self.base
        bad = ((events["t"] != b["t"][j] + k * self.chunk_us) | (events["x"] != b["x"][j])
               | (events["y"] != b["y"][j]) | (events["p"] != b["p"][j]))
        if bad.any():
            q = int(np.flatnonzero(bad)[0])
            raise ValueError(f"event {start_index + q} differs from the generated stream: expected t="
                             f"{int(b['t'][j[q]] + k[q] * self.chunk_us)} x={int(b['x'][j[q]])}, got "
                             f"t={int(events['t'][q])} x={int(events['x'][q])} (chunk {int(k[q])} lost or "
                             f"reordered?)")
        return n

    def check_stream(self, blocks) -> dict:
        """Verify a read-back stream that may miss whole chunks (dropped by a recorder).

        ``blocks`` is an iterable of event arrays in file order. Every chunk present must be complete,
        bit-exact and in increasing chunk order (no duplicates); missing chunks are counted.

        Returns
        -------
        dict
            ``events`` read, ``chunks_present``, ``chunks_missing`` (before the last chunk present),
            ``first_missing`` (up to 10 chunk indices).
        """
        b = self.base
        cu, ce = self.chunk_us, self.chunk_events
        carry = None
        n = present = missing = 0
        first_missing: list[int] = []
        last_k = -1

        def check_group(g, k):
            nonlocal present, missing, last_k
            if k <= last_k:
                raise ValueError(f"chunk {k} appears after chunk {last_k} (duplicated or reordered)")
            if len(g) != ce:
                raise ValueError(f"chunk {k} holds {len(g)} events, expected {ce} (partially lost)")
            if not (np.array_equal(g["t"] - k * cu, b["t"]) and np.array_equal(g["x"], b["x"])
                    and np.array_equal(g["y"], b["y"]) and np.array_equal(g["p"], b["p"])):
                raise ValueError(f"chunk {k} differs from the generated chunk")
            if k > last_k + 1:
                missing += k - last_k - 1
                first_missing.extend(range(last_k + 1, min(k, last_k + 11 - len(first_missing))))
                del first_missing[10:]
            present += 1
            last_k = k

        for ev in blocks:
            n += len(ev)
            buf = ev if carry is None or not len(carry) else np.concatenate([carry, ev])
            if not len(buf):
                continue
            k = (buf["t"] - self.t0_us) // cu
            cut = np.flatnonzero(np.diff(k)) + 1
            starts = np.concatenate([[0], cut])
            for a, e in zip(starts[:-1], cut):
                check_group(buf[a:e], int(k[a]))
            carry = buf[starts[-1]:]
        if carry is not None and len(carry):
            check_group(carry, int((carry["t"][0] - self.t0_us) // cu))
        return {"events": n, "chunks_present": present, "chunks_missing": missing,
                "first_missing": first_missing}
