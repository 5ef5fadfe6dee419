"""Recorder: live sources -> bounded queue -> writer thread -> crash-safe journal -> container.

Design (see ``docs/capture.md``):

* One producer thread per source moves chunks/frames into a bounded :class:`queue.Queue` of
  ``queue_chunks`` items (memory bound: ``queue_chunks`` × chunk size).
* When the queue is full the policy ``on_full`` applies: ``"block"`` makes the producer wait (only
  for sources that can be back-pressured: file replay, generators); ``"drop"`` drops the item and
  counts it; ``"auto"`` (default) blocks for back-pressurable sources and drops for live devices,
  whose driver buffers would overflow anyway. Drops are never silent: they are counted (events,
  triggers, frames and chunks), logged with ``logging.warning``, written into every flush record,
  stored in the recording metadata (``metadata.provenance["recorder"]``) and returned in
  :class:`RecorderStats`.
* The writer thread appends length-prefixed, CRC-32-checked records to an append-only journal
  ``REC.h5.journal`` and writes a FLUSH record (with cumulative counts) every ``flush_interval_s``,
  handing the bytes to the OS (``fsync=True`` also forces them to the disk, for power loss).
  HDF5 files killed mid-write are often unreadable, so the HDF5 container is not written while
  recording; :meth:`Recorder.finish` replays the journal into a container ``REC.h5.partial`` with
  :class:`~hybridhdr.formats.container.RecordingWriter`, renames it to ``REC.h5`` and deletes the journal.
* After ``kill -9`` (or a power cut with ``fsync=True``) :func:`recover` performs the same replay
  on whatever the journal holds: every record whose length and checksum are intact, which includes
  everything up to the last flush. ``hybridhdr capture recover REC.h5`` runs it.

Journal layout (little endian): an 8-byte magic ``b"HHDRJNL1"``, then records, each a 32-byte
header ``<I B B H Q Q I I>`` (sync word 0x4A524543, type, flags (bit 0: payload is an LZ4 block),
reserved, stored payload length, raw payload length, CRC-32 of the stored payload, CRC-32 of the
first 28 header bytes) followed by the payload. Types: 1 HEADER (JSON), 2 EVENTS (u64 n, columns
t i8, x u2, y u2, p i1), 3 TRIGGERS (u64 n, columns t i8, channel u2, edge i1), 4 FRAME (u32 JSON
length, JSON, pixel bytes), 5 FLUSH (JSON cumulative counts), 6 END (JSON final stats), 7 IMU (u64
n, columns t i8 then the ``IMU_FIELDS`` as f4, in that order). IMU samples come in the event
source's chunks (:attr:`~hybridhdr.formats.EventChunk.imu`), are journaled, recovered and
counted (``imu_written``, ``imu_dropped``) like triggers.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import queue
import struct
import sys
import threading
import time
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import FormatError
from ..events import EVENT_DTYPE, IMU_DTYPE, TRIGGER_DTYPE, SensorSize
from ..formats.container import RecordingWriter
from ..model import Frames, Metadata
from .sources import FrameItem

__all__ = ["Recorder", "RecorderStats", "recover", "journal_path", "JournalWriter", "read_journal",
           "ON_FULL_POLICIES", "warm_up"]

log = logging.getLogger(__name__)

ON_FULL_POLICIES = ("auto", "block", "drop")
_MAGIC = b"HHDRJNL1"
_SYNC = 0x4A524543
_HDR = struct.Struct("<IBBHQQII")
T_HEADER, T_EVENTS, T_TRIGGERS, T_FRAME, T_FLUSH, T_END, T_IMU = 1, 2, 3, 4, 5, 6, 7
_IMU_COLUMNS = tuple((name, IMU_DTYPE[name]) for name in IMU_DTYPE.names)  # t, then the IMU_FIELDS
_IMU_RECORD_BYTES = sum(dt.itemsize for _, dt in _IMU_COLUMNS)
_F_LZ4 = 1


def journal_path(path) -> Path:
    """The journal next to a recording: ``REC.h5`` -> ``REC.h5.journal``."""
    p = Path(path)
    return p if p.name.endswith(".journal") else p.with_name(p.name + ".journal")


def _lz4():
    try:
        import lz4.block
    except ImportError:
        return None
    return lz4.block


# -- journal ----------------------------------------------------------------------------------
class JournalWriter:
    """Append-only journal of checksummed records (see the module docstring for the layout)."""

    def __init__(self, path, header: dict, *, compression: str | None = "lz4", fsync: bool = False):
        if compression not in (None, "none", "lz4"):
            raise ValueError(f"journal compression must be 'lz4' or None, got {compression!r}")
        self._lz4 = _lz4() if compression == "lz4" else None
        if compression == "lz4" and self._lz4 is None:
            raise ImportError("journal compression 'lz4' needs the lz4 package: pip install lz4 "
                              "(or pass journal_compression=None)")
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"{self.path}: a journal already exists (an interrupted recording?); "
                                  f"run 'hybridhdr capture recover' on it or delete it first")
        self.fsync = bool(fsync)
        self._f = open(self.path, "xb", buffering=1 << 20)
        # an exclusive lock held until the journal is converted and deleted (release_lock): a
        # 'capture recover' meanwhile would convert, and then lose, a recording still being written
        self._lock_fd = os.open(self.path, os.O_RDWR | os.O_CLOEXEC)
        from .._util.atomic import try_lock
        try_lock(self._lock_fd)
        self._f.write(_MAGIC)
        self.bytes_written = len(_MAGIC)
        self._record(T_HEADER, json.dumps(header).encode(), compress=False)
        self.flush()

    def _record(self, rtype: int, payload, compress: bool = True) -> None:
        raw_len = len(payload)
        flags = 0
        if compress and self._lz4 is not None and raw_len > 256:
            payload = self._lz4.compress(payload, store_size=False)
            flags |= _F_LZ4
        head = struct.pack("<IBBHQQI", _SYNC, rtype, flags, 0, len(payload), raw_len, zlib.crc32(payload))
        self._f.write(head + struct.pack("<I", zlib.crc32(head)))
        self._f.write(payload)
        self.bytes_written += _HDR.size + len(payload)

    def write_events(self, ev: np.ndarray) -> None:
        from ._kernels import pack_columns
        n = len(ev)
        buf = bytearray(8 + 13 * n)
        struct.pack_into("<Q", buf, 0, n)
        cols = []
        o = 8
        for name, size in (("t", 8), ("x", 2), ("y", 2), ("p", 1)):
            cols.append(np.frombuffer(buf, dtype=EVENT_DTYPE[name], count=n, offset=o))
            o += size * n
        pack_columns(ev["t"], ev["x"], ev["y"], ev["p"], *cols)
        self._record(T_EVENTS, buf)

    def write_triggers(self, tr: np.ndarray) -> None:
        n = len(tr)
        parts = [struct.pack("<Q", n)] + [np.ascontiguousarray(tr[k]).tobytes() for k in ("t", "channel", "edge")]
        self._record(T_TRIGGERS, b"".join(parts))

    def write_imu(self, imu: np.ndarray) -> None:
        parts = [struct.pack("<Q", len(imu))] + [np.ascontiguousarray(imu[k]).tobytes() for k, _ in _IMU_COLUMNS]
        self._record(T_IMU, b"".join(parts))

    def write_frame(self, item) -> None:
        im = np.ascontiguousarray(item.image)
        meta = {"t_start_us": item.t_start_us, "t_end_us": item.t_end_us, "exposure_us": item.exposure_us,
                "iso": item.iso, "gain": item.gain, "sequence": item.sequence, "shape": list(im.shape),
                "dtype": im.dtype.str}
        mj = json.dumps(meta).encode()
        self._record(T_FRAME, struct.pack("<I", len(mj)) + mj + im.tobytes())

    def write_json(self, rtype: int, obj: dict) -> None:
        self._record(rtype, json.dumps(obj).encode(), compress=False)

    def flush(self) -> None:
        self._f.flush()
        if self.fsync:
            os.fsync(self._f.fileno())

    def close(self, keep_lock: bool = False) -> None:
        """Close the file; with ``keep_lock`` the lock stays until :meth:`release_lock` (the
        recorder converts the journal before it lets anyone else at it)."""
        try:
            if not self._f.closed:
                try:
                    self.flush()
                finally:
                    self._f.close()
        finally:
            if not keep_lock:
                self.release_lock()

    def release_lock(self) -> None:
        fd, self._lock_fd = getattr(self, "_lock_fd", None), None
        if fd is not None:
            os.close(fd)


def journal_in_use(path) -> bool:
    """True when a live recorder holds the journal's lock (it is still being written)."""
    from .._util.atomic import try_lock
    try:
        fd = os.open(path, os.O_RDWR | os.O_CLOEXEC | os.O_NOFOLLOW)
    except OSError:
        return False
    try:
        return not try_lock(fd)
    finally:
        os.close(fd)  # closing the open file description drops the probe's own lock


@dataclass
class JournalContents:
    """What :func:`read_journal` found (records are streamed, this is the summary)."""

    header: dict
    records: int = 0
    flushes: int = 0
    last_flush: dict | None = None
    end: dict | None = None
    events_after_last_flush: int = 0
    truncated_bytes: int = 0
    stop_reason: str = "end of file"


def _decode(rtype: int, payload: bytes):
    if rtype == T_EVENTS:
        n = struct.unpack_from("<Q", payload, 0)[0]
        if len(payload) != 8 + 13 * n:
            raise ValueError(f"EVENTS record holds {len(payload)} bytes, expected {8 + 13 * n} for {n} events")
        ev = np.empty(n, EVENT_DTYPE)
        o = 8
        for name, size in (("t", 8), ("x", 2), ("y", 2), ("p", 1)):
            ev[name] = np.frombuffer(payload, dtype=EVENT_DTYPE[name], count=n, offset=o)
            o += size * n
        return ev
    if rtype == T_TRIGGERS:
        n = struct.unpack_from("<Q", payload, 0)[0]
        if len(payload) != 8 + 11 * n:
            raise ValueError(f"TRIGGERS record holds {len(payload)} bytes, expected {8 + 11 * n}")
        tr = np.empty(n, TRIGGER_DTYPE)
        o = 8
        for name, size in (("t", 8), ("channel", 2), ("edge", 1)):
            tr[name] = np.frombuffer(payload, dtype=TRIGGER_DTYPE[name], count=n, offset=o)
            o += size * n
        return tr
    if rtype == T_IMU:
        n = struct.unpack_from("<Q", payload, 0)[0]
        if len(payload) != 8 + _IMU_RECORD_BYTES * n:
            raise ValueError(f"IMU record holds {len(payload)} bytes, expected {8 + _IMU_RECORD_BYTES * n}")
        imu = np.empty(n, IMU_DTYPE)
        o = 8
        for name, dt in _IMU_COLUMNS:
            imu[name] = np.frombuffer(payload, dtype=dt, count=n, offset=o)
            o += dt.itemsize * n
        return imu
    if rtype == T_FRAME:
        ml = struct.unpack_from("<I", payload, 0)[0]
        if 4 + ml > len(payload):
            raise ValueError(f"FRAME record metadata length {ml} exceeds the record")
        meta = json.loads(payload[4:4 + ml])
        if not isinstance(meta, dict):
            raise ValueError("FRAME record metadata is not a JSON object")
        dt = np.dtype(str(meta["dtype"]))
        if dt.kind not in "uif" or dt.itemsize > 8:
            raise ValueError(f"FRAME record pixel dtype {dt} is not numeric")
        shape = meta["shape"]
        if (not isinstance(shape, list) or len(shape) not in (2, 3)
                or not all(isinstance(v, int) and 0 < v <= 1 << 16 for v in shape)):
            raise ValueError(f"FRAME record shape {shape!r} is not a valid image shape")
        from .._util.limits import check_finite, check_sensor_size
        check_sensor_size(shape[0], shape[1], None, "journal frame")
        for k in ("t_start_us", "t_end_us", "exposure_us", "sequence"):
            v = meta.get(k)
            if v is not None and (not isinstance(v, int) or not -(1 << 63) <= v < (1 << 63)):
                raise ValueError(f"FRAME record {k} = {v!r} is not an int64")
        if meta.get("t_start_us") is None or meta.get("t_end_us") is None:
            raise ValueError("FRAME record has no exposure interval")
        for k in ("iso", "gain"):
            v = meta.get(k)
            if v is not None and (not isinstance(v, (int, float)) or not np.isfinite(float(v))):
                raise ValueError(f"FRAME record {k} = {v!r} is not a finite number")
        n = int(np.prod(shape)) * dt.itemsize
        if len(payload) - 4 - ml != n:
            raise ValueError(f"FRAME record holds {len(payload) - 4 - ml} pixel bytes, expected {n}")
        im = np.frombuffer(payload, dtype=dt, offset=4 + ml).reshape(shape)
        check_finite(im, None, "journal frame")
        return meta, im
    return json.loads(payload)


def read_journal(path, on_record=None) -> JournalContents:
    """Stream a journal; call ``on_record(rtype, decoded)`` for every intact record.

    Reading stops at the first record whose header or payload is truncated or fails its CRC (the
    tail a ``kill -9`` leaves behind); :attr:`JournalContents.stop_reason` says why.
    """
    path = Path(path)
    lz4 = _lz4()
    size = path.stat().st_size
    with open(path, "rb") as f:
        magic = f.read(8)
        if magic != _MAGIC:
            raise FormatError(path, f"not a hybridhdr journal (magic {magic!r}, expected {_MAGIC!r})")
        pos = 8
        contents = None
        while True:
            head = f.read(_HDR.size)
            if len(head) < _HDR.size:
                reason = "end of file" if not head else f"truncated record header at byte {pos}"
                break
            sync, rtype, flags, _, stored, raw_len, crc, hcrc = _HDR.unpack(head)
            if sync != _SYNC or zlib.crc32(head[:28]) != hcrc:
                reason = f"corrupt record header at byte {pos}"
                break
            if stored > size - pos - _HDR.size:
                reason = (f"truncated record at byte {pos} ({size - pos - _HDR.size} of {stored} payload "
                          f"bytes)")
                break
            payload = f.read(stored)
            if len(payload) < stored:
                reason = f"truncated record at byte {pos} ({len(payload)} of {stored} payload bytes)"
                break
            if zlib.crc32(payload) != crc:
                reason = f"checksum mismatch in record at byte {pos}"
                break
            try:
                if flags & _F_LZ4:
                    if lz4 is None:
                        raise ImportError("this journal is LZ4-compressed; install lz4 to recover it")
                    # LZ4 expands at most ~255x; a larger declared size is a forged header
                    if raw_len > 255 * stored + 64:
                        raise ValueError(f"declared raw length {raw_len} is impossible for {stored} LZ4 bytes")
                    from .._util.limits import check_packet_size
                    check_packet_size(raw_len, path, "journal record", offset=pos)
                    payload = lz4.decompress(payload, uncompressed_size=raw_len)
                elif raw_len != stored:
                    raise ValueError(f"raw length {raw_len} differs from the stored {stored} bytes")
                obj = _decode(rtype, payload)
            except ImportError:
                raise
            except (ValueError, KeyError, TypeError, OverflowError, IndexError, struct.error, MemoryError,
                    json.JSONDecodeError, UnicodeDecodeError) as e:
                reason = f"undecodable record at byte {pos} ({type(e).__name__}: {e})"
                break
            except Exception as e:  # lz4.block.LZ4BlockError and the like
                reason = f"undecodable record at byte {pos} ({type(e).__name__}: {e})"
                break
            if contents is None:
                if rtype != T_HEADER or not isinstance(obj, dict):
                    raise FormatError(path, "journal does not start with a HEADER record", offset=pos)
                from .._util.limits import check_sensor_size
                try:
                    check_sensor_size(obj.get("sensor_height"), obj.get("sensor_width"), path, "journal sensor")
                except FormatError as e:
                    raise FormatError(path, f"journal HEADER: {e.message}", offset=pos) from None
                contents = JournalContents(header=obj)
            else:
                contents.records += 1
                if rtype == T_FLUSH:
                    contents.flushes += 1
                    contents.last_flush = obj
                    contents.events_after_last_flush = 0
                elif rtype == T_END:
                    contents.end = obj
                elif rtype == T_EVENTS:
                    contents.events_after_last_flush += len(obj)
                if on_record is not None:
                    on_record(rtype, obj)
            pos += _HDR.size + stored
        if contents is None:
            raise FormatError(path, f"journal has no intact HEADER record ({reason})")
        contents.stop_reason = reason
        contents.truncated_bytes = size - pos
        return contents


# -- recorder ---------------------------------------------------------------------------------
@dataclass
class RecorderStats:
    """Counters of one recording (all cumulative)."""

    events_received: int = 0
    events_written: int = 0
    events_dropped: int = 0
    event_chunks_dropped: int = 0
    triggers_written: int = 0
    triggers_dropped: int = 0
    imu_written: int = 0
    imu_dropped: int = 0
    frames_received: int = 0
    frames_written: int = 0
    frames_dropped: int = 0
    frames_missing_by_sequence: int = 0
    flushes: int = 0
    journal_bytes: int = 0
    max_queue_depth: int = 0
    duration_s: float = 0.0
    finish_s: float = 0.0
    policy: str = ""
    recovered: bool = False
    errors: list = field(default_factory=list)
    #: what live sources count themselves (``counters()``: stream interruptions and restarts, data
    #: dropped because its timestamps went back, samples not stored), by source role
    source_counters: dict = field(default_factory=dict)
    #: the sources' host-clock samples (``clock_samples()``), by role, added when the recording stops
    source_clocks: dict = field(default_factory=dict)

    @property
    def dropped_anything(self) -> bool:
        return bool(self.events_dropped or self.triggers_dropped or self.imu_dropped or self.frames_dropped
                    or self.source_dropped)

    @property
    def source_dropped(self) -> int:
        """Items the sources dropped themselves: timestamps going back (a reset or a restart), or their
        own buffer full, or a reading that cannot be stored (an infinite IMU value)."""
        return sum(int(v) for c in self.source_counters.values() for k, v in c.items()
                   if k.endswith(("_out_of_order", "_dropped_in_buffer", "_not_finite")))

    @property
    def stream_interruptions(self) -> int:
        """Times a live stream stopped (whether or not it came back), over all sources."""
        return sum(int(c.get("interruptions", 0)) for c in self.source_counters.values())

    def to_dict(self) -> dict:
        d = asdict(self)
        d["stream_interruptions"] = self.stream_interruptions
        d["source_dropped"] = self.source_dropped
        return d


_SENTINEL = object()


def warm_up() -> None:
    """Load/compile the journal's packing kernel (seconds on a loaded machine the first time).

    :meth:`Recorder.start` calls it before it opens the sources; a caller that opens live sources
    itself (the command line) calls it first, so that no stream waits unread meanwhile.
    """
    from ._kernels import pack_columns
    e = np.zeros(0, EVENT_DTYPE)
    pack_columns(e["t"], e["x"], e["y"], e["p"], *(np.zeros(0, EVENT_DTYPE[k]) for k in "txyp"))


class Recorder:
    """Record an event source (and optionally a frame source) into a hybridhdr container.

    Parameters
    ----------
    path : path-like
        Output container (``.h5``). While recording, data goes to ``path + '.journal'``.
    event_source : EventSource
    frame_source : FrameSource, optional
    queue_chunks : int
        Capacity of the queue between the sources and the writer thread, in items (event chunks or
        frames). Bounds memory to about ``queue_chunks`` × the largest item.
    flush_interval_s : float
        Seconds between FLUSH records; a ``kill -9`` loses at most this much data.
    on_full : {"auto", "block", "drop"}
        Queue-full policy (module docstring). ``"block"`` on a source that cannot be back-pressured
        is refused.
    compression : {"gzip", "lzf", None}
        Compression of the final container (:class:`~hybridhdr.formats.container.RecordingWriter`).
    journal_compression : {"lz4", None}
        LZ4 block compression of journal records (default when ``lz4`` is installed).
    fsync : bool
        ``os.fsync`` the journal at every flush (survives power loss, not only process death).
    metadata : Metadata, optional
        Camera descriptions and calibration to store; recorder statistics are added to
        ``provenance["recorder"]``.
    on_flush : callable, optional
        Called from the writer thread as ``on_flush(stats_dict)`` after each flush.
    """

    def __init__(self, path, event_source, frame_source=None, *, queue_chunks: int = 64,
                 flush_interval_s: float = 1.0, on_full: str = "auto", compression="gzip",
                 journal_compression: str | None = "auto", fsync: bool = False,
                 metadata: Metadata | None = None, on_flush=None, progress: bool = False):
        if on_full not in ON_FULL_POLICIES:
            raise ValueError(f"on_full must be one of {ON_FULL_POLICIES}, got {on_full!r}")
        if int(queue_chunks) < 1:
            raise ValueError(f"queue_chunks must be >= 1, got {queue_chunks}")
        if not (float(flush_interval_s) > 0):
            raise ValueError(f"flush_interval_s must be > 0 s, got {flush_interval_s}")
        self.path = Path(path)
        self.journal_path = journal_path(self.path)
        self.event_source = event_source
        self.frame_source = frame_source
        self.queue_chunks = int(queue_chunks)
        self.flush_interval_s = float(flush_interval_s)
        self.on_full = on_full
        self.compression = compression
        if journal_compression == "auto":
            journal_compression = "lz4" if _lz4() is not None else None
        self.journal_compression = journal_compression
        self.fsync = fsync
        self.metadata = metadata or Metadata()
        self.on_flush = on_flush
        self.progress = progress
        self.stats = RecorderStats()
        self._q: queue.Queue = queue.Queue(maxsize=self.queue_chunks)
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._errors: list[BaseException] = []
        self._started = False
        self._finished = False
        self._last_drop_log = 0.0
        self._last_seq = None
        self._imu_last = None

    # -- policy --------------------------------------------------------------------------------
    def _policy_for(self, source) -> str:
        can = bool(getattr(source, "can_backpressure", False))
        if self.on_full == "auto":
            return "block" if can else "drop"
        if self.on_full == "block" and not can:
            raise ValueError(f"on_full='block' needs a source that can be back-pressured; "
                             f"{type(source).__name__} is live (use 'drop' or 'auto')")
        return self.on_full

    def _put(self, item, policy: str, kind: str, n_events: int = 0, n_trig: int = 0, n_imu: int = 0) -> None:
        if policy == "block":
            while not self._stop.is_set():
                try:
                    self._q.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            else:
                # stopping while blocked: the item was never accepted -> count it, never silent
                self._count_drop(kind, n_events, n_trig, n_imu)
                return
        else:
            try:
                self._q.put_nowait(item)
            except queue.Full:
                self._count_drop(kind, n_events, n_trig, n_imu)
                return
        d = self._q.qsize()
        if d > self.stats.max_queue_depth:
            self.stats.max_queue_depth = d

    def _count_drop(self, kind, n_events, n_trig, n_imu=0):
        with self._lock:
            s = self.stats
            if kind == "events":
                s.events_dropped += n_events
                s.triggers_dropped += n_trig
                s.imu_dropped += n_imu
                s.event_chunks_dropped += 1
            else:
                s.frames_dropped += 1
            now = time.monotonic()
            if now - self._last_drop_log > 1.0:
                self._last_drop_log = now
                log.warning("recorder queue full: dropped so far %d events, %d triggers, %d IMU samples, %d "
                            "frames (writer cannot keep up; see stats)", s.events_dropped, s.triggers_dropped,
                            s.imu_dropped, s.frames_dropped)

    # -- threads -------------------------------------------------------------------------------
    def _run_events(self):
        src = self.event_source
        policy = self._policy_for(src)
        try:
            for chunk in src:
                n, m = len(chunk.events), len(chunk.triggers)
                k = len(getattr(chunk, "imu", ()))
                with self._lock:
                    self.stats.events_received += n
                if n or m or k:
                    self._put(("ev", chunk), policy, "events", n, m, k)
                if self._stop.is_set():
                    break
        except BaseException as e:  # reported by finish()
            self._errors.append(e)
            self._stop.set()

    def _run_frames(self):
        src = self.frame_source
        policy = self._frame_policy
        try:
            for item in src:
                with self._lock:
                    self.stats.frames_received += 1
                self._put(("fr", item), policy, "frames")
                if self._stop.is_set():
                    break
        except BaseException as e:
            self._errors.append(e)
            self._stop.set()

    def _sources(self):
        return (("events", self.event_source), ("frames", self.frame_source))

    def _collect_source_counters(self):
        for role, src in self._sources():
            fn = getattr(src, "counters", None)
            if callable(fn):
                self.stats.source_counters[role] = fn()

    def _flush(self, jw: JournalWriter):
        s = self.stats
        s.flushes += 1
        self._collect_source_counters()
        s.journal_bytes = jw.bytes_written
        jw.write_json(T_FLUSH, s.to_dict())
        jw.flush()
        s.journal_bytes = jw.bytes_written
        if self.on_flush is not None:
            self.on_flush(s.to_dict())

    def _run_writer(self, jw: JournalWriter):
        s = self.stats
        next_flush = time.monotonic() + self.flush_interval_s
        try:
            while True:
                try:
                    item = self._q.get(timeout=min(0.1, self.flush_interval_s))
                except queue.Empty:
                    item = None
                if item is _SENTINEL:
                    break
                if item is not None:
                    kind, obj = item
                    if kind == "ev":
                        if len(obj.events):
                            jw.write_events(obj.events)
                            s.events_written += len(obj.events)
                        if len(obj.triggers):
                            jw.write_triggers(obj.triggers)
                            s.triggers_written += len(obj.triggers)
                        imu = getattr(obj, "imu", None)
                        if imu is not None and len(imu):
                            self._check_imu(imu)
                            jw.write_imu(imu)
                            s.imu_written += len(imu)
                    else:
                        if self._last_seq is not None and obj.sequence > self._last_seq + 1:
                            s.frames_missing_by_sequence += obj.sequence - self._last_seq - 1
                        self._last_seq = obj.sequence
                        jw.write_frame(obj)
                        s.frames_written += 1
                if time.monotonic() >= next_flush:
                    self._flush(jw)
                    next_flush = time.monotonic() + self.flush_interval_s
            self._flush(jw)
        except BaseException as e:
            self._errors.append(e)
            self._stop.set()
            # keep draining so producers never block forever
            while True:
                try:
                    if self._q.get(timeout=0.5) is _SENTINEL:
                        break
                except queue.Empty:
                    break

    def _check_imu(self, imu) -> None:
        """IMU samples a source hands over must be valid and continue the time order: refused here,
        while recording (the error stops it; the journal keeps what came before), not when the
        container is written."""
        from ..events import validate_imu
        validate_imu(imu, name=f"{type(self.event_source).__name__}'s IMU samples")
        if self._imu_last is not None and imu["t"][0] < self._imu_last:
            raise ValueError(f"{type(self.event_source).__name__} handed over IMU samples out of time order: "
                             f"{int(imu['t'][0])} µs after {self._imu_last} µs")
        self._imu_last = int(imu["t"][-1])

    # -- public --------------------------------------------------------------------------------
    def start(self) -> "Recorder":
        """Open the sources and the journal and start the threads."""
        if self._started:
            raise RuntimeError("Recorder.start() called twice")
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists; choose another output name")
        self.stats.policy = self._policy_for(self.event_source)
        self._frame_policy = None if self.frame_source is None else self._policy_for(self.frame_source)
        warm_up()
        self.event_source.open()
        if self.frame_source is not None:
            self.frame_source.open()
        ss = getattr(self.event_source, "sensor_size", None)
        if ss is None:
            raise ValueError(f"{type(self.event_source).__name__} does not report its sensor size")
        header = {"format": "hybridhdr-journal", "version": 1, "sensor_height": ss.height,
                  "sensor_width": ss.width, "metadata": self.metadata.to_dict(),
                  "event_source": self.event_source.device_info(),
                  "frame_source": None if self.frame_source is None else self.frame_source.device_info(),
                  "frame_encoding": None if self.frame_source is None else self.frame_source.encoding,
                  "created_by": f"hybridhdr {__version__}", "created_unix_s": time.time(),
                  "policy": self.stats.policy, "flush_interval_s": self.flush_interval_s}
        self._jw = JournalWriter(self.journal_path, header, compression=self.journal_compression,
                                 fsync=self.fsync)
        self._t0 = time.perf_counter()
        self._writer = threading.Thread(target=self._run_writer, args=(self._jw,), name="recorder-writer",
                                        daemon=True)
        self._writer.start()
        self._threads = [threading.Thread(target=self._run_events, name="recorder-events", daemon=True)]
        if self.frame_source is not None:
            self._threads.append(threading.Thread(target=self._run_frames, name="recorder-frames", daemon=True))
        for t in self._threads:
            t.start()
        self._started = True
        return self

    def wait(self, duration_s: float | None = None) -> None:
        """Block until the sources end, ``duration_s`` passes, or an error occurs."""
        t_end = None if duration_s is None else time.perf_counter() + float(duration_s)
        while any(t.is_alive() for t in self._threads) and not self._stop.is_set():
            if t_end is not None and time.perf_counter() >= t_end:
                break
            time.sleep(0.02)

    def stop(self) -> None:
        """Stop the sources, let the writer drain the queue, write the final flush."""
        if not self._started:
            return
        for src in (self.event_source, self.frame_source):
            if src is not None:
                src.stop()
        for t in self._threads:
            t.join()
        self._q.put(_SENTINEL)
        self._writer.join()
        self.stats.duration_s = time.perf_counter() - self._t0
        self._collect_source_counters()
        for role, src in self._sources():
            fn = getattr(src, "clock_samples", None)
            if callable(fn):
                self.stats.source_clocks[role] = fn()
        for src in (self.event_source, self.frame_source):
            if src is not None:
                src.close()

    def finish(self) -> RecorderStats:
        """Stop, then convert the journal into the container atomically and delete the journal."""
        if self._finished:
            return self.stats
        self.stop()
        self._finished = True
        if not self._errors:
            try:
                self._jw.write_json(T_END, self.stats.to_dict())
                self._jw.close(keep_lock=True)
            except OSError as e:
                self._errors.append(e)
        if self._errors:
            try:
                self._jw.close(keep_lock=True)
            except OSError:
                pass  # the journal's intact records are what recover reads; a torn tail is skipped
            self._jw.release_lock()
            e = self._errors[0]
            msg = (f"recording failed ({type(e).__name__}: {e}); the journal {self.journal_path} keeps every "
                   f"record written intact so far: run 'hybridhdr capture recover {self.path}'")
            if isinstance(e, OSError):  # full disk, I/O error: one clean line from the command line
                raise OSError(e.errno, msg + " (after freeing space)") from e
            raise RuntimeError(msg) from e
        t = time.perf_counter()
        try:
            _convert(self.journal_path, self.path, compression=self.compression, progress=self.progress,
                     final_stats=self.stats)
        except OSError as e:
            self._jw.release_lock()
            kept = self.journal_path.is_file()
            fix = ("free space, then " if e.errno == errno.ENOSPC else "") + f"run 'hybridhdr capture recover {self.path}'"
            raise OSError(e.errno, f"finishing {self.path} failed ({e.strerror or e}); " +
                          (f"the journal {self.journal_path} is kept: {fix}" if kept else
                           f"the journal {self.journal_path} is gone (removed by another process)")) from e
        self.stats.finish_s = time.perf_counter() - t
        self.journal_path.unlink()
        self._jw.release_lock()
        if self.stats.dropped_anything:
            log.warning("recording %s: %d events, %d triggers, %d IMU samples and %d frames were dropped "
                        "(queue full)", self.path, self.stats.events_dropped, self.stats.triggers_dropped,
                        self.stats.imu_dropped, self.stats.frames_dropped)
        return self.stats

    def record(self, duration_s: float | None = None) -> RecorderStats:
        """``start``, ``wait(duration_s)``, ``finish``."""
        self.start()
        try:
            self.wait(duration_s)
        except KeyboardInterrupt:
            pass
        return self.finish()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.finish()


def _convert(jpath: Path, out: Path, *, compression="gzip", progress=False, final_stats=None,
             recovered=False) -> tuple[dict, JournalContents]:
    """Replay a journal into a container written atomically (``out.partial`` then rename)."""

    # the metadata needs the final stats: after a crash they come from the last intact FLUSH
    # record, found by a first pass over the journal
    if final_stats is None:
        c = read_journal(jpath)
        stats = dict(c.end or c.last_flush or {})
        stats["recovered"] = recovered
        stats["recovery"] = {"records": c.records, "flushes": c.flushes, "stop_reason": c.stop_reason,
                             "discarded_tail_bytes": c.truncated_bytes,
                             "events_after_last_flush": c.events_after_last_flush}
        header = c.header
    else:
        stats = final_stats.to_dict()
        header = None
    if header is None:
        with open(jpath, "rb") as f:
            f.read(8)
            sync, rtype, flags, _, stored, raw_len, crc, hcrc = _HDR.unpack(f.read(_HDR.size))
            header = json.loads(f.read(stored))
    ss = SensorSize(int(header["sensor_height"]), int(header["sensor_width"]))
    md = Metadata.from_dict(header.get("metadata"))
    prov = dict(md.provenance)
    prov["recorder"] = stats
    prov["sources"] = {"events": header.get("event_source"), "frames": header.get("frame_source")}
    md = Metadata(md.event_camera, md.frame_camera, md.calibration, prov)
    enc = header.get("frame_encoding") or "unknown"
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=jpath.stat().st_size, unit="B", unit_scale=True, desc=f"finish {out.name}",
                   file=sys.stderr, dynamic_ncols=True)
    state = {"has_iso": None, "has_gain": None, "events": 0, "frames": 0, "triggers": 0, "imu": 0}

    with RecordingWriter(out, ss, md, compression=compression) as w:
        def on_record(rtype, obj):
            if rtype == T_EVENTS:
                w.write_events(obj)
                state["events"] += len(obj)
                if bar is not None:
                    bar.update(13 * len(obj))
            elif rtype == T_TRIGGERS:
                w.write_triggers(obj)
                state["triggers"] += len(obj)
            elif rtype == T_IMU:
                w.write_imu(obj)
                state["imu"] += len(obj)
            elif rtype == T_FRAME:
                meta, im = obj
                if state["has_iso"] is None:
                    state["has_iso"] = meta.get("iso") is not None
                    state["has_gain"] = meta.get("gain") is not None
                it = FrameItem(im, meta["t_start_us"], meta["t_end_us"], meta["exposure_us"],
                               meta.get("iso"), meta.get("gain"), meta.get("sequence", 0))
                kw = {}
                if state["has_iso"]:
                    kw["iso"] = np.array([np.nan if it.iso is None else it.iso])
                if state["has_gain"]:
                    kw["gain"] = np.array([np.nan if it.gain is None else it.gain])
                w.write_frames(Frames(it.image[None], np.array([it.t_start_us]), np.array([it.t_end_us]),
                                      encoding=enc, **kw))
                state["frames"] += 1
        try:
            contents = read_journal(jpath, on_record)
        finally:
            if bar is not None:
                bar.close()
    return state, contents


def recover(path, out=None, *, compression="gzip", progress: bool = False) -> dict:
    """Rebuild a container from the journal of an interrupted recording.

    Parameters
    ----------
    path : path-like
        The recording name (``REC.h5``) or its journal (``REC.h5.journal``).
    out : path-like, optional
        Output container (default: the recording name).

    Returns
    -------
    dict
        Counts recovered (``events``, ``triggers``, ``imu``, ``frames``), the number of flushes, the events
        after the last flush that were intact, the reason reading stopped and the output path.
    """
    jp = journal_path(path)
    if not jp.exists():
        raise FileNotFoundError(f"{jp}: no journal to recover (expected the '.journal' file an interrupted "
                                f"'hybridhdr capture record' leaves next to its output)")
    out = Path(out) if out is not None else jp.with_name(jp.name[: -len(".journal")])
    if journal_in_use(jp):
        raise FileExistsError(f"{jp} is being written by a running recorder (it holds the journal's lock); "
                              f"recover only a recording whose recorder has ended")
    if out.exists():
        raise FileExistsError(f"{out} already exists; pass another output name (if that recording was "
                              f"finished normally, {jp.name} is a left-over of an interrupted clean-up)")
    # a stale REC.h5.partial of an interrupted finish is removed by the writer (its lock is free);
    # one a live run holds, a symlink or a user's file there is refused (docs/security.md)
    state, contents = _convert(jp, out, compression=compression, progress=progress, recovered=True)
    return {"output": str(out), "events": state["events"], "triggers": state["triggers"], "imu": state["imu"],
            "frames": state["frames"], "flushes": contents.flushes,
            "events_after_last_flush": contents.events_after_last_flush,
            "last_flush_events": None if contents.last_flush is None else contents.last_flush.get("events_written"),
            "stop_reason": contents.stop_reason, "discarded_tail_bytes": contents.truncated_bytes,
            "clean_end": contents.end is not None}
