"""ROS bag reader (format ``rosbag``): ROS1 ``.bag`` files and ROS2 bag folders, without ROS.

Reads, through the ``rosbags`` package (``rosbags.highlevel.AnyReader``), one topic of

* ``dvs_msgs/msg/EventArray`` (``uzh-rpg/rpg_dvs_ros``): ``{header, height, width, events[]}``
  with each event ``{uint16 x, uint16 y, time ts, bool polarity}``;
* ``event_camera_msgs/msg/EventPacket``: ``{header, height, width, seq, time_base, encoding,
  is_bigendian, uint8[] events}``. With ``encoding == "evt3"`` the payloads of all packets are
  concatenated and decoded as one Prophesee EVT 3.0 stream (``time_base`` is undefined for evt3)
  by :class:`hybridhdr.formats.prophesee.Evt3Decoder`, which also yields the external
  triggers. Other encodings (``mono``, ``trigger`` ...) raise a clear :class:`FormatError`.

The custom message types are registered with the ``rosbags`` typestore from the definitions in
this module (:data:`MSG_DEFINITIONS`); ROS1 bags embed their own definitions, ROS2 bags may not.

Conversions: a ROS ``time`` ``(sec, nsec)`` becomes int64 µs rounded to the nearest µs (half up),
``(sec * 10**9 + nsec + 500) // 1000``; ``polarity`` True -> +1, False -> -1.
ROS1 ``EventArray`` messages are decoded straight from their serialized bytes with NumPy (13 bytes
per event); ROS2 ones go through ``rosbags`` deserialization (slower, one Python object per event).

Options: ``topic=`` chooses the topic (default: the first topic, by name, of a supported type).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import FormatError
from ..events import EVENT_DTYPE, SensorSize, empty_events, empty_triggers
from .base import EventChunk, EventFileReader, register_formats
from ..model import CameraInfo, Metadata

__all__ = ["RosbagReader", "READERS", "WRITERS", "sniff", "MSG_DEFINITIONS", "make_typestore",
           "EVENT_ARRAY", "EVENT_PACKET"]

EVENT_ARRAY = "dvs_msgs/msg/EventArray"
EVENT_PACKET = "event_camera_msgs/msg/EventPacket"

#: ROS .msg definitions of the supported message types (field lists of the upstream packages).
MSG_DEFINITIONS: dict[str, str] = {
    "dvs_msgs/msg/Event": "uint16 x\nuint16 y\ntime ts\nbool polarity\n",
    EVENT_ARRAY: "std_msgs/Header header\nuint32 height\nuint32 width\ndvs_msgs/Event[] events\n",
    EVENT_PACKET: ("std_msgs/Header header\nuint32 height\nuint32 width\nuint64 seq\nuint64 time_base\n"
                   "string encoding\nbool is_bigendian\nuint8[] events\n"),
}
SUPPORTED_TYPES = (EVENT_ARRAY, EVENT_PACKET)

#: One serialized ROS1 dvs_msgs/Event: packed, little-endian, 13 bytes.
_ROS1_EVENT = np.dtype([("x", "<u2"), ("y", "<u2"), ("sec", "<u4"), ("nsec", "<u4"), ("polarity", "u1")])


def make_typestore(ros2: bool = True):
    """A ``rosbags`` typestore (ROS2 Humble or ROS1 Noetic) with the event message types registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    types = {}
    for name, text in MSG_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def sniff(path: Path, head: bytes) -> str | None:
    """``"rosbag"`` for a ROS1 bag (``#ROSBAG V2.0`` magic) or a ROS2 bag folder (``metadata.yaml``)."""
    try:
        path = Path(path)
        if head.startswith(b"#ROSBAG V2.0"):
            return "rosbag"
        if path.is_dir():
            meta = path / "metadata.yaml"
            if meta.is_file():
                with open(meta, "rb") as f:
                    if b"rosbag2_bagfile_information" in f.read(4096):
                        return "rosbag"
        return None
    except OSError:
        return None


def _ns_to_us(sec, nsec) -> np.ndarray:
    ns = np.asarray(sec, dtype=np.int64) * 1_000_000_000 + np.asarray(nsec, dtype=np.int64)
    return (ns + 500) // 1000


class _Ros1Buf:
    """Bounds-checked cursor over one ROS1-serialized message."""

    def __init__(self, path, data: bytes, record: int):
        self.path, self.data, self.pos, self.record = path, memoryview(data), 0, record

    def take(self, n: int) -> memoryview:
        if n < 0 or self.pos + n > len(self.data):
            raise FormatError(self.path, f"message {self.record} is truncated: needs {n} bytes at {self.pos}, "
                                         f"has {len(self.data)}", record=self.record)
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def u32(self) -> int:
        return int.from_bytes(self.take(4), "little")

    def u64(self) -> int:
        return int.from_bytes(self.take(8), "little")

    def string(self) -> bytes:
        return bytes(self.take(self.u32()))

    def header(self):
        self.u32()  # seq
        sec, nsec = self.u32(), self.u32()
        frame = self.string()
        return sec, nsec, frame


class RosbagReader(EventFileReader):
    """Streaming reader of event topics in ROS1/ROS2 bags (see the module notes).

    Parameters
    ----------
    path : str or os.PathLike
        A ROS1 ``.bag`` file or a ROS2 bag folder.
    topic : str, optional
        The event topic; default the first (by name) of type ``dvs_msgs/msg/EventArray`` or
        ``event_camera_msgs/msg/EventPacket``.
    sensor_size : SensorSize or (height, width), optional
        Overrides the ``height``/``width`` of the first message (inferred as max coordinate + 1,
        with a provenance note, when those are 0).
    """

    format_name = "rosbag"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        try:
            from rosbags.highlevel import AnyReader  # noqa: F401
        except ImportError as exc:  # pragma: no cover - dependency missing
            raise ImportError("reading ROS bags needs the 'rosbags' package: pip install rosbags") from exc
        self._typestore = make_typestore(ros2=True)
        with self._reader() as r:
            try:
                topics = {name: info.msgtype for name, info in r.topics.items()}
            except Exception as exc:
                raise FormatError(self.path, f"cannot list the bag's topics: {type(exc).__name__}: {exc}") from None
            self.is_ros2 = bool(getattr(r, "is2", False))
            want = options.get("topic")
            if want is not None:
                if want not in topics:
                    raise FormatError(self.path, f"topic {want!r} is not in the bag; topics: {topics}")
                if topics[want] not in SUPPORTED_TYPES:
                    raise FormatError(self.path, f"topic {want!r} has type {topics[want]}; supported: "
                                                 f"{list(SUPPORTED_TYPES)}")
                self.topic = want
            else:
                cands = sorted(t for t, ty in topics.items() if ty in SUPPORTED_TYPES)
                if not cands:
                    raise FormatError(self.path, f"no event topic of a supported type {list(SUPPORTED_TYPES)}; "
                                                 f"topics: {topics}")
                self.topic = cands[0]
            self.msgtype = topics[self.topic]
            first = None
            for rec, (conn, ts, raw) in self._messages(r):
                first = self._head(r, rec, raw)
                break
        self.encoding = first["encoding"] if first else None
        stored = None
        if first and first["height"] and first["width"]:
            try:
                stored = SensorSize(first["height"], first["width"])
            except ValueError as exc:
                raise FormatError(self.path, f"invalid height/width in the first message: {exc}", record=0) from None
        src, note = "option", None
        if self.sensor_size is None:
            if stored is not None:
                self.sensor_size, src = stored, "message height/width"
            else:
                self.sensor_size = self._infer_size()
                src = "inferred"
                note = "messages carry height = width = 0: inferred as max coordinate + 1"
        prov = {"source_file": str(self.path), "format": "rosbag", "ros_version": 2 if self.is_ros2 else 1,
                "topic": self.topic, "msgtype": self.msgtype, "encoding": self.encoding,
                "sensor_size_source": src, "topics": topics,
                "time_conversion": "t_us = (sec*1e9 + nsec + 500) // 1000 (nearest µs)"}
        if note:
            prov["sensor_size_note"] = note
        self.metadata = Metadata(event_camera=CameraInfo(self.sensor_size), provenance=prov)

    # -- access -------------------------------------------------------------------------------
    @contextlib.contextmanager
    def _reader(self):
        from rosbags.highlevel import AnyReader
        tmpdir = None
        bag = self.path
        if bag.is_file() and bag.suffix != ".bag":
            # rosbags tells ROS 1 from ROS 2 by the '.bag' suffix; we detected the ROS 1 magic, so
            # hand it the file under a '.bag' name (a symlink, nothing copied)
            import tempfile
            tmpdir = tempfile.mkdtemp(prefix="hybridhdr-bag-")
            bag = Path(tmpdir) / "recording.bag"
            os.symlink(self.path.resolve(), bag)
        try:
            try:
                reader = AnyReader([bag], default_typestore=self._typestore)
                reader.open()
            except Exception as exc:
                raise FormatError(self.path, f"cannot open the bag (corrupt, truncated or unsupported?): "
                                             f"{type(exc).__name__}: {exc}") from None
            try:
                yield reader
            finally:
                try:
                    reader.close()
                except Exception:
                    pass
        finally:
            if tmpdir is not None:
                import shutil
                shutil.rmtree(tmpdir, ignore_errors=True)

    def _messages(self, r) -> Iterator[tuple[int, tuple]]:
        conns = [c for c in r.connections if c.topic == self.topic]
        it = r.messages(connections=conns)
        i = 0
        while True:
            try:
                item = next(it)
            except StopIteration:
                return
            except FormatError:
                raise
            except Exception as exc:
                raise FormatError(self.path, f"cannot read message {i} of {self.topic}: {type(exc).__name__}: {exc}",
                                  record=i) from None
            yield i, item
            i += 1

    def _deserialize(self, r, raw: bytes, rec: int):
        try:
            return r.deserialize(raw, self.msgtype)
        except Exception as exc:
            raise FormatError(self.path, f"cannot deserialize message {rec} of {self.topic} ({self.msgtype}): "
                                         f"{type(exc).__name__}: {exc}", record=rec) from None

    def _head(self, r, rec: int, raw: bytes) -> dict:
        """height, width (and encoding for packets) of one raw message."""
        if self.is_ros2:
            msg = self._deserialize(r, raw, rec)
            return {"height": int(msg.height), "width": int(msg.width),
                    "encoding": str(getattr(msg, "encoding", "")) if self.msgtype == EVENT_PACKET else None}
        b = _Ros1Buf(self.path, raw, rec)
        b.header()
        h, w = b.u32(), b.u32()
        enc = None
        if self.msgtype == EVENT_PACKET:
            b.u64()
            b.u64()
            try:
                enc = b.string().decode("ascii")
            except UnicodeDecodeError:
                raise FormatError(self.path, f"message {rec}: encoding is not ASCII", record=rec) from None
        return {"height": h, "width": w, "encoding": enc}

    # -- decoding -----------------------------------------------------------------------------
    def _decode_event_array(self, r, raw: bytes, rec: int) -> np.ndarray:
        if not self.is_ros2:
            b = _Ros1Buf(self.path, raw, rec)
            b.header()
            b.u32()
            b.u32()
            n = b.u32()
            rest = len(raw) - b.pos
            if n * _ROS1_EVENT.itemsize != rest:
                raise FormatError(self.path, f"message {rec}: {n} events need {n * _ROS1_EVENT.itemsize} bytes, "
                                             f"{rest} present", record=rec)
            a = np.frombuffer(raw, dtype=_ROS1_EVENT, count=n, offset=b.pos)
            sec, nsec, x, y, pol = a["sec"], a["nsec"], a["x"], a["y"], a["polarity"] != 0
        else:
            msg = self._deserialize(r, raw, rec)
            evs = msg.events
            x = np.fromiter((e.x for e in evs), np.uint16, len(evs))
            y = np.fromiter((e.y for e in evs), np.uint16, len(evs))
            sec = np.fromiter((e.ts.sec for e in evs), np.int64, len(evs))
            nsec = np.fromiter((e.ts.nanosec for e in evs), np.int64, len(evs))
            pol = np.fromiter((bool(e.polarity) for e in evs), bool, len(evs))
        ev = np.empty(len(x), EVENT_DTYPE)
        ev["t"] = _ns_to_us(sec, nsec)
        ev["x"] = x
        ev["y"] = y
        ev["p"] = np.where(pol, 1, -1)
        return ev

    def _packet_payload(self, r, raw: bytes, rec: int) -> tuple[str, bytes]:
        if self.is_ros2:
            msg = self._deserialize(r, raw, rec)
            return str(msg.encoding), np.asarray(msg.events, dtype=np.uint8).tobytes()
        b = _Ros1Buf(self.path, raw, rec)
        b.header()
        b.u32()
        b.u32()
        b.u64()
        b.u64()
        enc = bytes(b.string()).decode("ascii", "replace")
        b.take(1)
        payload = bytes(b.take(b.u32()))
        return enc, payload

    def _evt3_decoder(self):
        from .prophesee import Evt3Decoder  # numba: loaded for EVT 3 packets only
        return Evt3Decoder(self.sensor_size)

    def _check(self, ev: np.ndarray, rec: int, n_before: int, last_t: int | None) -> None:
        if ev.size == 0:
            return
        t = ev["t"]
        dec = np.flatnonzero(t[1:] < t[:-1])
        if dec.size:
            i = int(dec[0]) + 1
            raise FormatError(self.path, f"message {rec}: event {n_before + i} has {int(t[i])} µs after "
                                         f"{int(t[i - 1])} µs (timestamps must be non-decreasing)", record=rec)
        if last_t is not None and t[0] < last_t:
            raise FormatError(self.path, f"message {rec}: event {n_before} has {int(t[0])} µs after {last_t} µs "
                                         f"(timestamps must be non-decreasing)", record=rec)
        ss = self.sensor_size
        if ss is None:
            return
        for name, lim, dim in (("x", ss.width, "width"), ("y", ss.height, "height")):
            bad = np.flatnonzero(ev[name] >= lim)
            if bad.size:
                i = int(bad[0])
                raise FormatError(self.path, f"message {rec}: event {n_before + i} has {name} = {int(ev[name][i])} "
                                             f"outside the sensor {dim} {lim}", record=rec)

    def _iter_decoded(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Yield ``(events, triggers)`` per message, validated (EVT 3.0 decoded as one stream)."""
        last_t = None
        n = 0
        rec = -1
        dec = None
        with self._reader() as r:
            for rec, (conn, ts, raw) in self._messages(r):
                trig = empty_triggers()
                if self.msgtype == EVENT_ARRAY:
                    ev = self._decode_event_array(r, raw, rec)
                else:
                    enc, payload = self._packet_payload(r, raw, rec)
                    if enc != "evt3":
                        raise FormatError(self.path, f"message {rec}: EventPacket encoding {enc!r} is not supported "
                                                     f"(supported: 'evt3')", record=rec)
                    if dec is None:
                        dec = self._evt3_decoder()
                    try:
                        ev, trig = dec.decode(payload)
                    except FormatError as exc:
                        raise FormatError(self.path, f"message {rec}: invalid EVT 3.0 payload at stream byte "
                                                     f"{exc.offset}: {exc.message}", record=rec) from None
                self._check(ev, rec, n, last_t)
                if ev.size:
                    last_t = int(ev["t"][-1])
                    n += ev.size
                yield ev, trig
        if dec is not None:
            try:
                ev, trig = dec.flush()
            except FormatError as exc:
                raise FormatError(self.path, f"the concatenated EVT 3.0 payload is incomplete: {exc.message}",
                                  record=rec) from None
            self._check(ev, rec, n, last_t)
            yield ev, trig

    def _infer_size(self) -> SensorSize:
        saved, self.sensor_size = self.sensor_size, None
        mx = my = -1
        try:
            for ev, _ in self._iter_decoded():
                if ev.size:
                    mx, my = max(mx, int(ev["x"].max())), max(my, int(ev["y"].max()))
        finally:
            self.sensor_size = saved
        if mx < 0:
            raise FormatError(self.path, f"topic {self.topic} has no size and no events: pass sensor_size")
        return SensorSize(my + 1, mx + 1)

    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        pending, trigs, n = [], [], 0
        for ev, tr in self._iter_decoded():
            if ev.size:
                pending.append(ev)
                n += ev.size
            if tr.size:
                trigs.append(tr)
            while n >= chunk_events:
                buf = np.concatenate(pending)
                yield EventChunk(buf[:chunk_events], np.concatenate(trigs) if trigs else empty_triggers())
                rest = buf[chunk_events:]
                pending, trigs, n = ([rest] if rest.size else []), [], rest.size
        if n or trigs:
            yield EventChunk(np.concatenate(pending) if pending else empty_events(),
                             np.concatenate(trigs) if trigs else empty_triggers())


READERS = {"rosbag": RosbagReader}
WRITERS: dict = {}

register_formats(__name__, {
    "rosbag": "ROS bag with dvs_msgs/EventArray or event_camera_msgs/EventPacket",
}, READERS, WRITERS)
