"""iniVation AEDAT 4.0 reader (events, triggers, frames and IMU) with a bounds-checked decoder.

Layout (iniVation "AEDAT 4.0" documentation and the dv FlatBuffers schemas ``IOHeader.fbs``,
``events.fbs``, ``frame.fbs``, ``trigger.fbs``, ``FileDataTable.fbs``):

* ``#!AER-DAT4.0\\r\\n`` (14 bytes), an int32 header length, then the ``IOHE`` FlatBuffer
  ``IOHeader {compression: int32 enum (0 none, 1 LZ4, 2 LZ4 high, 3 ZSTD, 4 ZSTD high),
  dataTablePosition: int64 = -1, infoNode: string (XML)}``; the XML lists the streams (id, type
  identifier ``EVTS``/``FRME``/``TRIG``/``IMUS``, ``sizeX``/``sizeY``, ``source``);
* packets up to ``dataTablePosition`` (or the end of the file): ``{int32 stream_id, int32 size}``
  and ``size`` bytes, compressed as the header says (LZ4 frame / Zstandard frame), holding a
  size-prefixed FlatBuffer with its 4-byte identifier;
* ``EVTS``: ``elements: [Event]``, ``Event = {int64 timestamp, int16 x, int16 y, bool polarity}``
  (16-byte structs); ``TRIG``: ``elements: [Trigger]``, ``Trigger`` a table
  ``{timestamp: int64, type: int8}``; ``FRME``: one ``Frame`` table (timestamps, OpenCV-style format, size,
  position, ``pixels``, ``exposure``); ``IMUS``: ``elements: [IMU]``, ``IMU`` a table ``{timestamp:
  int64, temperature, accelerometerX..Z, gyroscopeX..Z, magnetometerX..Z: float}`` (°C, g, °/s, µT:
  dv's ``imu.fbs``);
* the file data table (``FTAB``) after ``dataTablePosition`` is not needed and not read.

The packets are parsed here in Python/NumPy with every offset and length checked, because the
``aedat`` and ``dv-processing`` libraries abort or crash the interpreter on some corrupt files
(found by fuzzing). Decompression uses the ``lz4`` and ``zstandard`` packages, imported only when
a file is compressed. Reading streams packet by packet: memory is bounded by the chunk size plus
one packet.

Conversions (see ``docs/conventions.md``):

* event ``timestamp`` (µs, as recorded; usually Unix-epoch µs) -> int64 ``t`` unchanged;
  ``polarity`` -> ``p`` = +1 (ON) / -1 (OFF);
* triggers -> ``TRIGGER_DTYPE`` with the channel/edge mapping of :data:`TRIGGER_TYPE_MAP`
  (``TIMESTAMP_RESET`` markers are skipped);
* frames -> :class:`hybridhdr.Frames` with ``t_start_us``/``t_end_us`` the recorded start/end of
  exposure (if those are unset: ``timestamp`` - ``exposure``/2 and + ``exposure``/2 rounded down
  when ``exposure`` is known, else ``timestamp`` for both); grey frames are (H, W), colour frames
  (H, W, 3) converted from the stored BGR to RGB (alpha dropped); 8- and 16-bit depths are kept.
  Frames smaller than the stream resolution (an ROI) are pasted at their position into a zero
  image of the stream size.
* IMU samples -> ``IMU_DTYPE`` (:meth:`Aedat4Reader.read_imu`, ``Recording.imu``): ``timestamp``
  -> ``t`` unchanged, the float32 quantities copied bit for bit into the fields of the same
  quantity (:data:`hybridhdr.events.IMU_FIELDS`), sorted by time (stable) if a packet is not.

Only the first event, frame, trigger and IMU stream are read (options ``event_stream``,
``frame_stream``, ``trigger_stream``, ``imu_stream`` take a stream id to choose another).
"""

from __future__ import annotations

import re
import struct
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Iterator

import numpy as np

from .._util.limits import (LIMITS, OVERRIDE_HINT, LimitExceeded, check_frame_bytes, check_sensor_size,
                        huge_allowed)
from ..errors import FormatError
from ..events import (EVENT_DTYPE, IMU_DTYPE, IMU_FIELDS, TRIGGER_DTYPE, SensorSize, empty_events, empty_imu,
                      empty_triggers)
from ..model import CameraInfo, Frames, Metadata
from .base import EventChunk, EventFileReader, register_formats

__all__ = ["Aedat4Reader", "Aedat4Writer", "READERS", "WRITERS", "sniff", "MAGIC", "TRIGGER_TYPE_MAP"]

MAGIC = b"#!AER-DAT4.0\r\n"

#: AEDAT4 trigger ``type`` code (dv::TriggerType) -> (channel, edge) in TRIGGER_DTYPE.
#: Channel 0: external input signal; 1: external generator output; 2: APS frame readout;
#: 3: APS exposure. Rising/start is +1, falling/end is -1. A detected ``EXTERNAL_SIGNAL_PULSE``
#: (code 3) is stored as a rising edge on channel 0. ``TIMESTAMP_RESET`` (0) is not an edge and
#: is skipped.
TRIGGER_TYPE_MAP: dict[int, tuple[int, int]] = {
    1: (0, 1),   # EXTERNAL_SIGNAL_RISING_EDGE
    2: (0, -1),  # EXTERNAL_SIGNAL_FALLING_EDGE
    3: (0, 1),   # EXTERNAL_SIGNAL_PULSE
    4: (1, 1),   # EXTERNAL_GENERATOR_RISING_EDGE
    5: (1, -1),  # EXTERNAL_GENERATOR_FALLING_EDGE
    6: (2, 1),   # APS_FRAME_START
    7: (2, -1),  # APS_FRAME_END
    8: (3, 1),   # APS_EXPOSURE_START
    9: (3, -1),  # APS_EXPOSURE_END
}

_COMPRESSION = {0: "NONE", 1: "LZ4", 2: "LZ4_HIGH", 3: "ZSTD", 4: "ZSTD_HIGH"}

#: field index of each quantity in dv's ``IMU`` FlatBuffer table (``imu.fbs``; 0 is ``timestamp``)
_IMU_TABLE_INDEX = {"temperature": 1, "accelerometerX": 2, "accelerometerY": 3, "accelerometerZ": 4,
                    "gyroscopeX": 5, "gyroscopeY": 6, "gyroscopeZ": 7, "magnetometerX": 8, "magnetometerY": 9,
                    "magnetometerZ": 10}
#: Largest header / (decompressed) packet accepted, bytes: corrupt sizes cannot exhaust memory.
_MAX_HEADER = 16 << 20
_MAX_PACKET = 1 << 30
_EVENT_STRUCT = np.dtype({"names": ["t", "x", "y", "p"], "formats": ["<i8", "<i2", "<i2", "u1"],
                          "offsets": [0, 8, 10, 12], "itemsize": 16})
_TRIG_CH = np.zeros(256, np.uint16)
_TRIG_EDGE = np.zeros(256, np.int8)
for _code, (_ch, _edge) in TRIGGER_TYPE_MAP.items():
    _TRIG_CH[_code], _TRIG_EDGE[_code] = _ch, _edge


def sniff(path: Path, head: bytes) -> str | None:
    """Return ``"aedat4"`` when ``head`` starts with the AEDAT 4.0 magic, else None."""
    return "aedat4" if head.startswith(MAGIC[:12]) else None


class _Corrupt(Exception):
    """Internal: a FlatBuffer offset or length is out of bounds."""


class _Table:
    """Bounds-checked read access to one FlatBuffer table in ``buf`` at absolute position ``pos``."""

    def __init__(self, buf: bytes, pos: int):
        n = len(buf)
        if pos < 0 or pos + 4 > n:
            raise _Corrupt(f"table offset {pos} outside the {n}-byte buffer")
        vt = pos - struct.unpack_from("<i", buf, pos)[0]
        if vt < 0 or vt + 4 > n:
            raise _Corrupt(f"vtable offset {vt} outside the {n}-byte buffer")
        vsize, tsize = struct.unpack_from("<HH", buf, vt)
        if vsize < 4 or vsize % 2 or vt + vsize > n or pos + tsize > n:
            raise _Corrupt(f"invalid vtable (size {vsize}, table size {tsize})")
        self.buf, self.pos, self.vt, self.vsize, self.tsize = buf, pos, vt, vsize, tsize

    def _field(self, index: int) -> int:
        vo = 4 + 2 * index
        if vo + 2 > self.vsize:
            return 0
        off = struct.unpack_from("<H", self.buf, self.vt + vo)[0]
        if off and off >= self.tsize:
            raise _Corrupt(f"field {index} offset {off} outside its {self.tsize}-byte table")
        return off

    def scalar(self, index: int, fmt: str, default=0):
        off = self._field(index)
        if not off:
            return default
        p = self.pos + off
        if p + struct.calcsize(fmt) > len(self.buf):
            raise _Corrupt(f"field {index} runs past the buffer")
        return struct.unpack_from(fmt, self.buf, p)[0]

    def vector(self, index: int, item_size: int) -> tuple[int, int] | None:
        """``(start, length)`` of a vector field (start of the first element), or None."""
        off = self._field(index)
        if not off:
            return None
        p = self.pos + off
        if p + 4 > len(self.buf):
            raise _Corrupt(f"field {index} runs past the buffer")
        start = p + struct.unpack_from("<I", self.buf, p)[0]
        if start + 4 > len(self.buf):
            raise _Corrupt(f"vector of field {index} at {start} outside the buffer")
        n = struct.unpack_from("<I", self.buf, start)[0]
        if start + 4 + n * item_size > len(self.buf):
            raise _Corrupt(f"vector of field {index} ({n} x {item_size} bytes) runs past the buffer")
        return start + 4, n

    def string(self, index: int) -> bytes:
        v = self.vector(index, 1)
        return b"" if v is None else bytes(self.buf[v[0]:v[0] + v[1]])


def _root(buf: bytes, size_prefixed: bool) -> tuple[_Table, bytes]:
    """Root table and 4-byte identifier of a (size-prefixed) FlatBuffer."""
    base = 4 if size_prefixed else 0
    if len(buf) < base + 8:
        raise _Corrupt(f"{len(buf)}-byte buffer is too short for a FlatBuffer")
    if size_prefixed:
        size = struct.unpack_from("<I", buf, 0)[0]
        if size + 4 > len(buf):
            raise _Corrupt(f"size prefix {size} exceeds the {len(buf) - 4} bytes present")
        buf = buf[4:4 + size]
    root = struct.unpack_from("<I", buf, 0)[0]
    return _Table(buf, root), bytes(buf[4:8])


def _decompress(data: bytes, method: int) -> bytes:
    if method == 0:
        return data
    if method in (1, 2):
        try:
            import lz4.frame
        except ImportError as exc:  # pragma: no cover - dependency missing
            raise ImportError("reading LZ4-compressed AEDAT4 files needs the 'lz4' package: pip install lz4") from exc
        limit = _packet_limit()
        d = lz4.frame.LZ4FrameDecompressor()
        out = d.decompress(data, max_length=limit + 1)
        if len(out) > limit:
            raise LimitExceeded(None, f"an LZ4 packet inflates beyond {limit:,} bytes; {OVERRIDE_HINT}")
        return out
    if method in (3, 4):
        try:
            import zstandard
        except ImportError as exc:  # pragma: no cover - dependency missing
            raise ImportError("reading ZSTD-compressed AEDAT4 files needs the 'zstandard' package: "
                              "pip install zstandard") from exc
        limit = _packet_limit()
        out = bytearray()
        for piece in zstandard.ZstdDecompressor().read_to_iter(data, read_size=1 << 16, write_size=1 << 20):
            out += piece
            if len(out) > limit:
                raise LimitExceeded(None, f"a ZSTD packet inflates beyond {limit:,} bytes; {OVERRIDE_HINT}")
        return bytes(out)
    raise _Corrupt(f"unknown compression type {method}")


def _packet_limit() -> int:
    return _MAX_PACKET if huge_allowed() else min(_MAX_PACKET, LIMITS["max_packet_bytes"])


def _parse_streams(path, xml: bytes) -> dict[int, dict]:
    try:
        root = ET.fromstring(xml.decode("utf-8"))
    except (ET.ParseError, UnicodeDecodeError, ValueError) as exc:
        raise FormatError(path, f"invalid XML stream description in the header: {exc}", offset=len(MAGIC)) from None
    out: dict[int, dict] = {}
    for outinfo in root.iter("node"):
        if outinfo.get("name") != "outInfo":
            continue
        for node in outinfo.findall("node"):
            try:
                sid = int(node.get("name", ""))
            except ValueError:
                continue
            info = {a.get("key"): (a.text or "") for a in node.findall("attr")}
            d = {"type_identifier": info.get("typeIdentifier", ""), "compression": info.get("compression", "")}
            sub = node.find("node[@name='info']")
            if sub is not None:
                si = {a.get("key"): (a.text or "") for a in sub.findall("attr")}
                for key, name in (("sizeX", "width"), ("sizeY", "height")):
                    if key in si:
                        try:
                            d[name] = int(si[key])
                        except ValueError:
                            raise FormatError(path, f"stream {sid}: {key} = {si[key]!r} is not an integer") from None
                if "source" in si:
                    d["source"] = si["source"]
            out[sid] = d
    return out


class Aedat4Reader(EventFileReader):
    """Streaming reader of iniVation AEDAT 4.0 files.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.aedat4`` file.
    sensor_size : SensorSize or (height, width), optional
        Overrides the event stream's ``sizeX``/``sizeY``.
    event_stream, frame_stream, trigger_stream, imu_stream : int, optional
        Stream ids to read; default the first stream of each type.

    Notes
    -----
    Timestamps are kept exactly as recorded (int64 µs). Events must be non-decreasing in time
    within the event stream and lie inside the sensor; otherwise
    :class:`~hybridhdr.errors.FormatError` is raised naming the packet (``record``) and event.
    Any malformed structure (bad offsets, truncation, failed decompression) is a FormatError with
    the byte offset of the packet.
    """

    format_name = "aedat4"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        with open(self.path, "rb") as f:
            head = f.read(len(MAGIC) + 4)
            if head[:len(MAGIC)] != MAGIC:
                raise FormatError(self.path, f"not an AEDAT 4.0 file: expected magic {MAGIC!r}, got "
                                             f"{head[:len(MAGIC)]!r}", offset=0)
            if len(head) < len(MAGIC) + 4:
                raise FormatError(self.path, "truncated header", offset=len(head))
            hsize = struct.unpack_from("<i", head, len(MAGIC))[0]
            if not 8 <= hsize <= _MAX_HEADER:
                raise FormatError(self.path, f"invalid header length {hsize}", offset=len(MAGIC))
            hbuf = f.read(hsize)
            if len(hbuf) != hsize:
                raise FormatError(self.path, f"truncated header: {len(hbuf)} of {hsize} bytes", offset=len(MAGIC) + 4)
            f.seek(0, 2)
            self._file_size = f.tell()
        try:
            tab, ident = _root(hbuf, size_prefixed=False)
            if ident != b"IOHE":
                raise _Corrupt(f"header identifier {ident!r} is not b'IOHE'")
            self.compression = int(tab.scalar(0, "<i", 0))
            self._table_pos = int(tab.scalar(1, "<q", -1))
            xml = tab.string(2)
        except (_Corrupt, struct.error) as exc:
            raise FormatError(self.path, f"corrupt AEDAT4 header: {exc}", offset=len(MAGIC) + 4) from None
        if self.compression not in _COMPRESSION:
            raise FormatError(self.path, f"unknown compression type {self.compression}", offset=len(MAGIC) + 4)
        self._data_start = len(MAGIC) + 4 + hsize
        if self._table_pos >= 0 and not self._data_start <= self._table_pos <= self._file_size:
            raise FormatError(self.path, f"data table position {self._table_pos} lies outside the packet area "
                                         f"{self._data_start}..{self._file_size} (truncated file?)")
        self._data_end = self._table_pos if self._table_pos >= 0 else self._file_size
        self.streams = _parse_streams(self.path, xml)

        def pick(ident, kind, opt):
            ids = sorted(k for k, v in self.streams.items() if v["type_identifier"] == ident)
            want = options.get(opt)
            if want is not None:
                if int(want) not in ids:
                    raise FormatError(self.path, f"{opt}={want} is not an id of a {kind} stream; {kind} streams: {ids}")
                return int(want)
            return ids[0] if ids else None

        self.event_stream = pick("EVTS", "event", "event_stream")
        self.frame_stream = pick("FRME", "frame", "frame_stream")
        self.trigger_stream = pick("TRIG", "trigger", "trigger_stream")
        self.imu_stream = pick("IMUS", "IMU", "imu_stream")
        if self.event_stream is None:
            raise FormatError(self.path, "the AEDAT4 file has no event stream; streams: "
                                         f"{ {k: v['type_identifier'] for k, v in self.streams.items()} }")

        def size_of(sid):
            info = self.streams.get(sid) if sid is not None else None
            if not info or "width" not in info or "height" not in info:
                return None
            try:
                return SensorSize(*check_sensor_size(info["height"], info["width"], self.path,
                                                     f"stream {sid} resolution"))
            except LimitExceeded:
                raise
            except (TypeError, ValueError) as exc:
                raise FormatError(self.path, f"stream {sid}: invalid resolution: {exc}") from None

        stored = size_of(self.event_stream)
        if self.sensor_size is None:
            self.sensor_size = stored
        if self.sensor_size is None:
            raise FormatError(self.path, "the event stream stores no resolution; pass sensor_size=(height, width)")
        self.frame_size = size_of(self.frame_stream)
        model = self.streams[self.event_stream].get("source", "")
        if not model:
            m = re.search(rb'<attr key="source" type="string">([^<]*)</attr>', xml)
            model = m.group(1).decode("utf-8", "replace") if m else ""
        serial = model.rsplit("_", 1)[1] if "_" in model else ""
        has_frames = self.frame_stream is not None
        self.metadata = Metadata(
            event_camera=CameraInfo(self.sensor_size, model, serial),
            frame_camera=CameraInfo(self.frame_size, model if has_frames else "", serial if has_frames else ""),
            provenance={
                "source_file": str(self.path), "format": "aedat4", "reader": "hybridhdr aedat4 (bounds-checked)",
                "compression": _COMPRESSION[self.compression],
                "streams": {str(k): dict(v) for k, v in self.streams.items()},
                "event_stream": self.event_stream, "frame_stream": self.frame_stream,
                "trigger_stream": self.trigger_stream, "imu_stream": self.imu_stream,
                "sensor_size_source": "option" if options.get("sensor_size") is not None else "file",
                "trigger_mapping": "channel 0 external signal, 1 generator, 2 APS frame, 3 APS "
                                   "exposure; rising/start +1, falling/end -1; TIMESTAMP_RESET skipped",
            })

    # -- packets ------------------------------------------------------------------------------
    def _packets(self, wanted: set) -> Iterator[tuple[int, int, int, _Table, bytes]]:
        """Yield ``(index, offset, stream_id, root_table, identifier)`` for packets of ``wanted`` streams."""
        with open(self.path, "rb") as f:
            f.seek(self._data_start)
            pos = self._data_start
            i = 0
            while pos < self._data_end:
                hdr = f.read(8)
                if len(hdr) < 8 or pos + 8 > self._data_end:
                    raise FormatError(self.path, f"truncated packet header (packet {i})", offset=pos, record=i)
                sid, size = struct.unpack("<ii", hdr)
                if size < 0 or size > _MAX_PACKET or pos + 8 + size > self._data_end:
                    raise FormatError(self.path, f"packet {i} (stream {sid}) has size {size}, beyond the "
                                                 f"{self._data_end - pos - 8} bytes left (corrupt or truncated)",
                                      offset=pos, record=i)
                if sid not in wanted:
                    f.seek(size, 1)
                else:
                    data = f.read(size)
                    if len(data) != size:
                        raise FormatError(self.path, f"truncated packet {i}", offset=pos, record=i)
                    try:
                        raw = _decompress(data, self.compression)
                        tab, ident = _root(raw, size_prefixed=True)
                    except ImportError:
                        raise
                    except LimitExceeded as exc:
                        raise LimitExceeded(self.path, f"packet {i} (stream {sid}): {exc.message}", offset=pos,
                                            record=i) from None
                    except Exception as exc:  # lz4/zstandard errors, _Corrupt, struct.error
                        raise FormatError(self.path, f"corrupt packet {i} (stream {sid}): {type(exc).__name__}: "
                                                     f"{exc}", offset=pos, record=i) from None
                    yield i, pos, sid, tab, ident
                pos += 8 + size
                i += 1

    def _check_ident(self, ident: bytes, want: bytes, i: int, pos: int) -> None:
        if ident != want:
            raise FormatError(self.path, f"packet {i} has identifier {ident!r}, expected {want!r} for its stream",
                              offset=pos, record=i)

    def _events_of(self, tab: _Table, i: int, pos: int, n_before: int, last_t: int | None) -> np.ndarray:
        try:
            v = tab.vector(0, 16)
        except _Corrupt as exc:
            raise FormatError(self.path, f"corrupt event packet {i}: {exc}", offset=pos, record=i) from None
        if v is None:
            return empty_events()
        raw = np.frombuffer(tab.buf, dtype=_EVENT_STRUCT, count=v[1], offset=v[0])
        ev = np.empty(v[1], EVENT_DTYPE)
        if ev.size == 0:
            return ev
        t, x, y = raw["t"], raw["x"], raw["y"]
        for name, a in (("x", x), ("y", y)):
            bad = np.flatnonzero(a < 0)
            if bad.size:
                j = int(bad[0])
                raise FormatError(self.path, f"event {n_before + j} has negative {name} = {int(a[j])} (packet {i})",
                                  offset=pos, record=i)
        dec = np.flatnonzero(t[1:] < t[:-1])
        if dec.size:
            j = int(dec[0]) + 1
            raise FormatError(self.path, f"event timestamps decrease: event {n_before + j} has {int(t[j])} µs after "
                                         f"{int(t[j - 1])} µs (packet {i})", offset=pos, record=i)
        if last_t is not None and t[0] < last_t:
            raise FormatError(self.path, f"event timestamps decrease across packets: event {n_before} has "
                                         f"{int(t[0])} µs after {last_t} µs (packet {i})", offset=pos, record=i)
        ss = self.sensor_size
        for name, a, lim, dim in (("x", x, ss.width, "width"), ("y", y, ss.height, "height")):
            bad = np.flatnonzero(a >= lim)
            if bad.size:
                j = int(bad[0])
                raise FormatError(self.path, f"event {n_before + j} has {name}={int(a[j])} outside the sensor {dim} "
                                             f"{lim} (packet {i})", offset=pos, record=i)
        ev["t"] = t
        ev["x"] = x
        ev["y"] = y
        ev["p"] = np.where(raw["p"] != 0, 1, -1)
        return ev

    def _triggers_of(self, tab: _Table, i: int, pos: int) -> np.ndarray:
        # TriggerPacket.elements is a vector of Trigger *tables* {timestamp: int64, type: int8}
        try:
            v = tab.vector(0, 4)
            if v is None or v[1] == 0:
                return empty_triggers()
            buf = tab.buf
            t = np.empty(v[1], np.int64)
            codes = np.empty(v[1], np.int64)
            for k in range(v[1]):
                p = v[0] + 4 * k
                el = _Table(buf, p + struct.unpack_from("<I", buf, p)[0])
                t[k] = el.scalar(0, "<q")
                codes[k] = el.scalar(1, "<b")
        except _Corrupt as exc:
            raise FormatError(self.path, f"corrupt trigger packet {i}: {exc}", offset=pos, record=i) from None
        bad = np.flatnonzero((codes < 0) | (codes > 9))
        if bad.size:
            raise FormatError(self.path, f"unknown AEDAT4 trigger type {int(codes[bad[0]])} (expected 0..9) in "
                                         f"packet {i}", offset=pos, record=i)
        keep = codes != 0
        tr = np.empty(int(keep.sum()), TRIGGER_DTYPE)
        tr["t"] = t[keep]
        tr["channel"] = _TRIG_CH[codes[keep]]
        tr["edge"] = _TRIG_EDGE[codes[keep]]
        if tr.size > 1 and np.any(tr["t"][1:] < tr["t"][:-1]):
            tr = tr[np.argsort(tr["t"], kind="stable")]
        return tr

    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        pending: list[np.ndarray] = []
        n_pending = 0
        triggers: list[np.ndarray] = []
        n_total = 0
        last_t = None
        wanted = {self.event_stream, self.trigger_stream} - {None}
        for i, pos, sid, tab, ident in self._packets(wanted):
            if sid == self.event_stream:
                self._check_ident(ident, b"EVTS", i, pos)
                ev = self._events_of(tab, i, pos, n_total, last_t)
                if ev.size:
                    last_t = int(ev["t"][-1])
                    n_total += ev.size
                    pending.append(ev)
                    n_pending += ev.size
            else:
                self._check_ident(ident, b"TRIG", i, pos)
                tr = self._triggers_of(tab, i, pos)
                if tr.size:
                    triggers.append(tr)
            while n_pending >= chunk_events:
                buf = np.concatenate(pending)
                out, rest = buf[:chunk_events], buf[chunk_events:]
                trs = np.concatenate(triggers) if triggers else empty_triggers()
                triggers = []
                yield EventChunk(out, trs)
                pending = [rest] if rest.size else []
                n_pending = rest.size
        if pending or triggers:
            yield EventChunk(np.concatenate(pending) if pending else empty_events(),
                             np.concatenate(triggers) if triggers else empty_triggers())

    # -- IMU ----------------------------------------------------------------------------------
    def _imu_of(self, tab: _Table, i: int, pos: int) -> np.ndarray:
        # IMUPacket.elements is a vector of IMU *tables* (offsets of 4 bytes each)
        try:
            v = tab.vector(0, 4)
            if v is None or v[1] == 0:
                return empty_imu()
            buf = tab.buf
            out = np.empty(v[1], IMU_DTYPE)
            t = out["t"]
            cols = [(out[name], _IMU_TABLE_INDEX[dv_name]) for name, _, dv_name in IMU_FIELDS]
            for k in range(v[1]):
                p = v[0] + 4 * k
                el = _Table(buf, p + struct.unpack_from("<I", buf, p)[0])
                t[k] = el.scalar(0, "<q")
                for col, idx in cols:
                    col[k] = el.scalar(idx, "<f", 0.0)
        except _Corrupt as exc:
            raise FormatError(self.path, f"corrupt IMU packet {i}: {exc}", offset=pos, record=i) from None
        bad = np.flatnonzero(np.any([np.isinf(out[name]) for name, _, _ in IMU_FIELDS], axis=0))
        if bad.size:
            raise FormatError(self.path, f"IMU sample {int(bad[0])} of packet {i} holds an infinite value",
                              offset=pos, record=i)
        return out

    def read_imu(self) -> np.ndarray:
        """The IMU samples of the IMU stream (``IMU_DTYPE``, sorted by ``t``); empty when the file
        has no IMU stream."""
        if self.imu_stream is None:
            return empty_imu()
        parts = []
        for i, pos, sid, tab, ident in self._packets({self.imu_stream}):
            self._check_ident(ident, b"IMUS", i, pos)
            a = self._imu_of(tab, i, pos)
            if a.size:
                parts.append(a)
        if not parts:
            return empty_imu()
        imu = np.concatenate(parts)
        if imu.size > 1 and np.any(imu["t"][1:] < imu["t"][:-1]):
            imu = imu[np.argsort(imu["t"], kind="stable")]
        return imu

    # -- frames -------------------------------------------------------------------------------
    def _frame_of(self, tab: _Table, i: int, pos: int, size: SensorSize | None):
        try:
            t = tab.scalar(0, "<q")
            soe, eoe = tab.scalar(3, "<q"), tab.scalar(4, "<q")
            fmt = tab.scalar(5, "<b")
            w, h = tab.scalar(6, "<h"), tab.scalar(7, "<h")
            ox, oy = tab.scalar(8, "<h"), tab.scalar(9, "<h")
            pv = tab.vector(10, 1)
            exposure = tab.scalar(11, "<q")
        except _Corrupt as exc:
            raise FormatError(self.path, f"corrupt frame packet {i}: {exc}", offset=pos, record=i) from None
        depth, ch = fmt & 7, (fmt >> 3) + 1
        if fmt < 0 or depth not in (0, 2) or ch not in (1, 3, 4):
            raise FormatError(self.path, f"unsupported frame format {fmt} (expected 8/16-bit grey, BGR or BGRA)",
                              offset=pos, record=i)
        dtype = np.dtype(np.uint8) if depth == 0 else np.dtype("<u2")
        if w <= 0 or h <= 0 or ox < 0 or oy < 0:
            raise FormatError(self.path, f"invalid frame geometry {w}x{h} at ({ox}, {oy})", offset=pos, record=i)
        need = w * h * ch * dtype.itemsize
        if pv is None or pv[1] != need:
            raise FormatError(self.path, f"frame {w}x{h}x{ch} ({dtype}) needs {need} pixel bytes, packet has "
                                         f"{0 if pv is None else pv[1]}", offset=pos, record=i)
        px = np.frombuffer(tab.buf, dtype=dtype, count=w * h * ch, offset=pv[0]).reshape(h, w, ch)
        px = px[..., 0] if ch == 1 else px[..., 2::-1]  # BGR(A) -> RGB
        px = np.ascontiguousarray(px, dtype=dtype.newbyteorder("="))
        if size is None:
            size = SensorSize(*check_sensor_size(h, w, self.path, "frame"))
        if (h, w) != size.shape or ox or oy:
            if oy + h > size.height or ox + w > size.width:
                raise FormatError(self.path, f"frame of shape {(h, w)} at ({ox}, {oy}) does not fit the {size} "
                                             f"frame stream", offset=pos, record=i)
            full = np.zeros(size.shape + px.shape[2:], px.dtype)
            full[oy:oy + h, ox:ox + w] = px
            px = full
        if soe and eoe and eoe >= soe:
            ts, te = soe, eoe
        elif exposure > 0:
            ts, te = t - exposure // 2, t - exposure // 2 + exposure
        else:
            ts = te = t
        return px, ts, te, size

    def read_frames(self) -> Frames | None:
        """All frames of the frame stream (None when the file has no frame stream).

        Returns
        -------
        Frames or None
            ``images`` (K, H, W) grey or (K, H, W, 3) RGB, uint8 or uint16 as stored;
            ``t_start_us``/``t_end_us`` from the recorded exposure (see the module notes), sorted by
            start. ``encoding`` is the declared ``frame_encoding`` option, else ``"raw"``.
        """
        if self.frame_stream is None:
            return None
        imgs, ts, te = [], [], []
        size = self.frame_size
        total = 0
        for i, pos, sid, tab, ident in self._packets({self.frame_stream}):
            self._check_ident(ident, b"FRME", i, pos)
            px, a, b, size = self._frame_of(tab, i, pos, size)
            total += px.nbytes
            check_frame_bytes(total, self.path, "the decoded frames")
            if imgs and (px.shape != imgs[0].shape or px.dtype != imgs[0].dtype):
                raise FormatError(self.path, f"frame {len(imgs)} has shape {px.shape} dtype {px.dtype}, unlike "
                                             f"the first frame's {imgs[0].shape} {imgs[0].dtype}", offset=pos, record=i)
            imgs.append(px)
            ts.append(a)
            te.append(b)
        if not imgs:
            h, w = size.shape if size is not None else self.sensor_size.shape
            return Frames.empty(h, w)
        ts_a, te_a = np.asarray(ts, np.int64), np.asarray(te, np.int64)
        order = np.argsort(ts_a, kind="stable")
        try:
            return Frames(np.stack(imgs)[order], ts_a[order], te_a[order], encoding=self._frame_encoding("raw"))
        except ValueError as exc:
            raise FormatError(self.path, f"invalid frames: {exc}") from None


READERS = {"aedat4": Aedat4Reader}
# the writer goes through dv-processing (imported when a file is written): aedat4_writer.py
from .aedat4_writer import Aedat4Writer  # noqa: E402

WRITERS = {"aedat4": Aedat4Writer}

register_formats(__name__, {
    "aedat4": "iniVation AEDAT 4 (.aedat4)",
}, READERS, WRITERS)
