"""ROS bag reader (format ``rosbag``): ROS1 ``.bag`` files and ROS2 bags, without ROS.

Detected by magic, never by the file name: ``#ROSBAG V2.0`` (ROS 1), a ROS 2 SQLite storage file
(``SQLite format 3\0`` with rosbag2's ``topics`` and ``messages`` tables, usually ``.db3``), an MCAP
file (``\x89MCAP0\r\n``), or a ROS 2 bag folder (``metadata.yaml``; one whose
``storage_identifier`` is empty is read by the storage its files' magic names). A lone storage file
is read without its ``metadata.yaml``.

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

Frames: one ``sensor_msgs/msg/Image`` topic is read by :meth:`RosbagReader.read_frames`
(decoded by :mod:`hybridhdr.formats._ros_image`: ``mono8/16``, ``rgb/bgr/rgba/bgra 8/16`` and
``bayer_{rggb,bggr,gbrg,grbg}{8,16}``; ``step * height`` must equal the data length). The option
``image_topic=`` chooses it; by default it is the bag's only Image topic, else ``<ns>/image_raw``
next to the event topic ``<ns>/events`` (the topic names of the ``rpg_dvs_ros`` DAVIS driver),
else the bag's only ``*/image_raw`` topic; otherwise no frames are read and
``metadata.provenance["image_topic_note"]`` says why. An image topic chosen by default whose
encoding is not supported is skipped the same way; one named by ``image_topic=`` is an error
naming the encoding and the supported ones.

Exposure: a ``sensor_msgs/Image`` has only ``header.stamp``. Without more, a frame is taken as a
zero-length exposure at its stamp (``t_start_us = t_end_us``). When the image topic
``<ns>/image_raw`` has a ``std_msgs/msg/Int32`` topic ``<ns>/exposure`` beside it (or one is named
by ``exposure_topic=``; ``exposure_topic=""`` ignores it), its k-th value is taken as the k-th
image's exposure E in µs: the ``rpg_dvs_ros`` DAVIS driver publishes libcaer's
``caerFrameEventGetExposureLength`` there and stamps the image with
``caerFrameEventGetTimestamp64``, which libcaer defines as start of exposure + E/2 (integer
division), so ``t_start_us = stamp - E // 2`` and ``t_end_us = t_start_us + E``. If the two topics
have different message counts the pairing is unknown and every frame is zero-length at its
stamp. ``metadata.provenance["frame_exposure"]`` records which rule applies.

Colour filter (``metadata.*_camera.cfa``): a ``bayer_*`` image encoding declares the frame
camera's pattern (``bayer_rggb8`` -> ``RGGB``; the frames are its raw mosaic, (K, H, W)). When
those Bayer frames have the event sensor's size, the event camera is declared with the same
pattern: this assumes a colour DAVIS, whose events and frames come from one pixel array under one
filter (``metadata.provenance["event_cfa_source"]`` says so); frames of another size declare
nothing for the events. ``rgb8``/``bgr8``/... frames are demosaicked colour (K, H, W, 3): they
do not tell the sensor's pattern, and neither do ``mono`` frames (a colour DAVIS driver may
publish its mosaic as ``mono8``), so nothing is declared; pass ``--cfa`` for those.

Limits (:mod:`hybridhdr._util.limits`, lifted by ``--allow-huge``), the same for ROS 1 and ROS 2: the
sensor height/width of the messages (``max_side``) and the size of every message
(``max_packet_bytes``), checked before it is decoded; for ROS 2 storage also before the bag is
opened, from what the file declares (SQLite: the largest stored message; MCAP: every record's
length and every chunk's uncompressed size, which must also lie within the file).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator

import numpy as np

from .._util.limits import check_frame_bytes, check_packet_size, check_sensor_size
from ..errors import FormatError
from ..events import EVENT_DTYPE, SensorSize, empty_events, empty_triggers
from .base import EventChunk, EventFileReader, register_formats
from ..model import CameraInfo, Frames, Metadata
from ._ros_image import ENCODINGS, IMAGE, INT32, decode_image, image_kind

__all__ = ["RosbagReader", "READERS", "WRITERS", "sniff", "MSG_DEFINITIONS", "make_typestore",
           "EVENT_ARRAY", "EVENT_PACKET", "storage_kind", "check_mcap", "check_sqlite"]

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


ROS1_MAGIC = b"#ROSBAG V2.0"
SQLITE_MAGIC = b"SQLite format 3\x00"
MCAP_MAGIC = b"\x89MCAP0\r\n"
#: storage id (rosbag2's ``storage_identifier``) -> the suffix ``rosbags`` opens it by
STORAGE_SUFFIX = {"sqlite3": ".db3", "mcap": ".mcap"}


def _is_rosbag2_sqlite(path: Path) -> bool:
    """True for an SQLite file with rosbag2's ``topics`` and ``messages`` tables (opened read-only)."""
    import sqlite3
    try:
        con = sqlite3.connect(Path(path).resolve().as_uri() + "?mode=ro", uri=True)
    except (sqlite3.Error, ValueError):
        return False
    try:
        names = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        return {"topics", "messages"} <= names
    except sqlite3.Error:
        return False
    finally:
        con.close()


def storage_kind(path, head: bytes | None = None) -> str | None:
    """What a bag file is by its magic: ``"ros1"``, ``"sqlite3"`` (a rosbag2 SQLite file), ``"mcap"``
    or None (also for folders)."""
    path = Path(path)
    if not path.is_file():
        return None
    if head is None:
        with open(path, "rb") as f:
            head = f.read(64)
    if head.startswith(ROS1_MAGIC):
        return "ros1"
    if head.startswith(MCAP_MAGIC):
        return "mcap"
    if head.startswith(SQLITE_MAGIC) and _is_rosbag2_sqlite(path):
        return "sqlite3"
    return None


def _folder_storage_files(folder: Path) -> list[tuple[Path, str]]:
    """The ROS 2 storage files of a folder, by magic: ``[(path, "sqlite3" | "mcap"), ...]`` sorted."""
    out = []
    for q in sorted(folder.iterdir()):
        if q.name == "metadata.yaml" or not q.is_file():
            continue
        try:
            kind = storage_kind(q)
        except OSError:
            continue
        if kind in STORAGE_SUFFIX:
            out.append((q, kind))
    return out


def sniff(path: Path, head: bytes) -> str | None:
    """``"rosbag"`` for a ROS1 bag (``#ROSBAG V2.0``), a ROS 2 SQLite or MCAP storage file (by magic),
    a ROS2 bag folder (``metadata.yaml``) or a folder holding exactly one ROS 2 storage file."""
    try:
        path = Path(path)
        if head.startswith((ROS1_MAGIC, MCAP_MAGIC)):
            return "rosbag"
        if path.is_file():
            return "rosbag" if storage_kind(path, head) else None
        if path.is_dir():
            meta = path / "metadata.yaml"
            if meta.is_file():
                with open(meta, "rb") as f:
                    if b"rosbag2_bagfile_information" in f.read(4096):
                        return "rosbag"
                return None
            if len(_folder_storage_files(path)) == 1:
                return "rosbag"
        return None
    except OSError:
        return None


def check_mcap(path) -> None:
    """Walk an MCAP file's records before ``rosbags`` reads it: every record's length within the
    file, every message within ``max_packet_bytes`` and every chunk's declared uncompressed size
    too (a chunk that inflates to gigabytes is refused, not allocated)."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        if f.read(8) != MCAP_MAGIC:
            raise FormatError(path, "not an MCAP file (no \\x89MCAP0\\r\\n magic)", offset=0)
        pos = 8
        while pos < size:
            f.seek(pos)
            if size - pos == 8:
                if f.read(8) != MCAP_MAGIC:
                    raise FormatError(path, "the MCAP file does not end with its magic", offset=pos)
                return
            hdr = f.read(9)
            if len(hdr) < 9:
                raise FormatError(path, f"MCAP record header at byte {pos} is truncated", offset=pos)
            op, n = hdr[0], int.from_bytes(hdr[1:], "little")
            if n > size - pos - 9:
                raise FormatError(path, f"MCAP record 0x{op:02x} at byte {pos} declares {n:,} bytes, past the end "
                                        f"of the {size:,}-byte file (truncated?)", offset=pos)
            if op == 0x06:  # Chunk: start u64, end u64, uncompressed_size u64, crc u32, compression ...
                body = f.read(min(n, 24))
                if len(body) < 24:
                    raise FormatError(path, f"MCAP chunk at byte {pos} is too short ({n} bytes)", offset=pos)
                check_packet_size(int.from_bytes(body[16:24], "little"), path,
                                  what=f"MCAP chunk at byte {pos} (uncompressed)", offset=pos)
            elif op == 0x05:  # Message outside a chunk
                check_packet_size(n, path, what=f"MCAP message at byte {pos}", offset=pos)
            elif op == 0x02:  # Footer: the end
                return
            pos += 9 + n
        raise FormatError(path, "the MCAP file ends without a footer (truncated?)", offset=size)


def check_sqlite(path) -> None:
    """The largest message a rosbag2 SQLite file stores, within ``max_packet_bytes`` (read-only)."""
    import sqlite3
    path = Path(path)
    try:
        con = sqlite3.connect(path.resolve().as_uri() + "?mode=ro", uri=True)
        try:
            (big,) = con.execute("SELECT max(length(data)) FROM messages").fetchone()
        finally:
            con.close()
    except sqlite3.Error as exc:
        raise FormatError(path, f"cannot read the SQLite bag: {type(exc).__name__}: {exc}") from None
    if big is not None:
        check_packet_size(int(big), path, what="the largest message in the bag")


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
        A ROS1 ``.bag`` file, a ROS2 bag folder or a lone ROS2 storage file (SQLite ``.db3`` or ``.mcap``, found by magic).
    topic : str, optional
        The event topic; default the first (by name) of type ``dvs_msgs/msg/EventArray`` or
        ``event_camera_msgs/msg/EventPacket``.
    sensor_size : SensorSize or (height, width), optional
        Overrides the ``height``/``width`` of the first message (inferred as max coordinate + 1,
        with a provenance note, when those are 0).
    image_topic : str, optional
        The ``sensor_msgs/msg/Image`` topic of the frames; default chosen as the module notes say.
    exposure_topic : str, optional
        A ``std_msgs/msg/Int32`` topic of exposure times in µs, one per image; default
        ``<ns>/exposure`` beside ``<ns>/image_raw`` when the bag has it, ``""`` for none.
    frame_encoding : str, optional
        The frames' transfer function (ROS images state none: ``"unknown"`` by default).
    """

    format_name = "rosbag"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        try:
            from rosbags.highlevel import AnyReader  # noqa: F401
        except ImportError as exc:  # pragma: no cover - dependency missing
            raise ImportError("reading ROS bags needs the 'rosbags' package: pip install rosbags") from exc
        self._typestore = make_typestore(ros2=True)
        if storage_kind(self.path) == "ros1":  # every chunk's decompressed size bounded, once, before rosbags
            from ._ros1_chunks import check_ros1_chunks
            check_ros1_chunks(self.path)
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
            img = self._open_images(r, topics, options)
        self.encoding = first["encoding"] if first else None
        stored = None
        if first and first["height"] and first["width"]:
            # the limit first (its own error, naming the override); then the type's own checks
            hw = check_sensor_size(first["height"], first["width"], self.path,
                                   what=f"sensor size of the messages on {self.topic}")
            try:
                stored = SensorSize(*hw)
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
        frame_cam, event_cfa = CameraInfo(), None
        prov.update(img["provenance"])
        if self.image_topic is not None:
            frame_cam = CameraInfo(self.frame_size, cfa=img["cfa"])
            if img["cfa"] is not None:
                if self.frame_size == self.sensor_size:
                    event_cfa = img["cfa"]
                    prov["event_cfa_source"] = (f"assumed the frames' ({img['encoding']} on {self.image_topic}): "
                                                f"Bayer frames of the event sensor's size, as on a colour DAVIS "
                                                f"whose events and frames share one pixel array")
                else:
                    prov["event_cfa_source"] = (f"not declared: the Bayer frames are {self.frame_size}, the events "
                                                f"{self.sensor_size} (not one pixel array); pass --cfa")
        self.metadata = Metadata(event_camera=CameraInfo(self.sensor_size, cfa=event_cfa), frame_camera=frame_cam,
                                 provenance=prov)

    # -- image topics -------------------------------------------------------------------------
    def _open_images(self, r, topics: dict, options: dict) -> dict:
        """Choose the image topic (and the exposure topic) and read the first image's head; sets
        ``image_topic``, ``exposure_topic``, ``frame_size``, ``image_encoding``."""
        self.image_topic = self.exposure_topic = self.frame_size = self.image_encoding = None
        images = sorted(t for t, ty in topics.items() if ty == IMAGE)
        want = options.get("image_topic")
        prov: dict = {}
        if want is not None:
            if want not in topics:
                raise FormatError(self.path, f"image topic {want!r} is not in the bag; topics: {topics}")
            if topics[want] != IMAGE:
                raise FormatError(self.path, f"image topic {want!r} has type {topics[want]}; supported: {IMAGE}")
            chosen, how = want, "option"
        else:
            chosen, how = None, None
            ns = self.topic.rsplit("/", 1)[0]
            raw_named = [t for t in images if t.rsplit("/", 1)[-1] == "image_raw"]
            if len(images) == 1:
                chosen, how = images[0], "the bag's only sensor_msgs/Image topic"
            elif f"{ns}/image_raw" in images:
                chosen, how = f"{ns}/image_raw", "the image_raw topic next to the event topic"
            elif len(raw_named) == 1:
                chosen, how = raw_named[0], "the bag's only */image_raw topic"
            elif images:
                prov["image_topic_note"] = (f"no frames read: several image topics {images} and none is the "
                                            f"image_raw next to {self.topic}; pass image_topic=")
        out = {"cfa": None, "encoding": None, "provenance": prov}
        if chosen is None:
            return out
        head = None
        for rec, (conn, ts, raw) in self._messages(r, chosen):
            head = self._image_fields(r, raw, rec, chosen)
            break
        if head is None:
            prov["image_topic_note"] = f"image topic {chosen} has no messages: no frames"
            return out
        enc = head["encoding"]
        if enc not in ENCODINGS:
            if want is not None:
                image_kind(enc, self.path, f"message 0 of {chosen}: ")
            prov["image_topic_note"] = (f"no frames read: {chosen} ({how}) has encoding {enc!r}, not one of "
                                        f"{', '.join(ENCODINGS)}")
            return out
        hw = check_sensor_size(head["height"], head["width"], self.path, what=f"images on {chosen}")
        try:
            self.frame_size = SensorSize(*hw)
        except ValueError as exc:
            raise FormatError(self.path, f"message 0 of {chosen}: invalid height/width: {exc}", record=0) from None
        self.image_topic, self.image_encoding = chosen, enc
        _, _, kind, cfa = ENCODINGS[enc]
        out.update(cfa=cfa, encoding=enc)
        if cfa is not None:
            cfa_src = f"image encoding {enc}: the raw Bayer mosaic, pattern {cfa}"
        elif kind in ("rgb", "bgr"):
            cfa_src = (f"not declared: image encoding {enc} holds demosaicked RGB frames and does not state the "
                       f"sensor's pattern (pass --cfa)")
        else:
            cfa_src = f"not declared: image encoding {enc} is grey (a Bayer mosaic stored as {enc} needs --cfa)"
        prov.update({"image_topic": chosen, "image_topic_source": how, "image_encoding": enc,
                     "frame_cfa_source": cfa_src})
        exp = options.get("exposure_topic")
        parent = chosen.rsplit("/", 1)[0]
        if exp is None:
            exp = f"{parent}/exposure" if topics.get(f"{parent}/exposure") == INT32 else None
        elif exp == "" or exp is False:
            exp = None
        elif topics.get(exp) != INT32:
            raise FormatError(self.path, f"exposure topic {exp!r} is not a {INT32} topic of the bag; topics: {topics}")
        self.exposure_topic = exp
        if exp is None:
            prov["frame_exposure"] = ("zero-length exposure at header.stamp (a sensor_msgs/Image carries no "
                                      "exposure time): t_start_us = t_end_us = stamp")
        else:
            prov["exposure_topic"] = exp
            prov["frame_exposure"] = (f"exposure E µs from {exp} (std_msgs/Int32, the k-th message for the k-th "
                                      f"image; the rpg_dvs_ros DAVIS driver publishes caerFrameEventGetExposureLength "
                                      f"there) around header.stamp, which that driver sets to libcaer's "
                                      f"start of exposure + E/2: t_start_us = stamp - E//2, t_end_us = t_start_us + "
                                      f"E; when the counts differ: zero-length exposure at the stamp")
        return out

    def _image_fields(self, r, raw: bytes, rec: int, topic: str) -> dict:
        """The fields of one sensor_msgs/Image message (``data`` not copied for ROS 1)."""
        if self.is_ros2:
            m = self._deserialize(r, raw, rec, IMAGE, topic)
            return {"sec": int(m.header.stamp.sec), "nsec": int(m.header.stamp.nanosec), "height": int(m.height),
                    "width": int(m.width), "encoding": str(m.encoding), "is_bigendian": int(m.is_bigendian),
                    "step": int(m.step), "data": np.asarray(m.data, dtype=np.uint8)}
        b = _Ros1Buf(self.path, raw, rec)
        sec, nsec, _ = b.header()
        h, w = b.u32(), b.u32()
        try:
            enc = b.string().decode("ascii")
        except UnicodeDecodeError:
            raise FormatError(self.path, f"message {rec} of {topic}: encoding is not ASCII", record=rec) from None
        big = b.take(1)[0]
        step = b.u32()
        data = b.take(b.u32())
        if b.pos != len(raw):
            raise FormatError(self.path, f"message {rec} of {topic}: {len(raw) - b.pos} bytes after the image data "
                                         f"(not a sensor_msgs/Image?)", record=rec)
        return {"sec": sec, "nsec": nsec, "height": h, "width": w, "encoding": enc, "is_bigendian": big,
                "step": step, "data": data}

    def read_frames(self) -> Frames | None:
        """The frames of the image topic, or None when no image topic was chosen (module notes).

        Returns
        -------
        Frames or None
            ``images`` (K, H, W) for grey and Bayer encodings (the raw mosaic), (K, H, W, 3) RGB for
            colour ones; uint8 or uint16 as stored. ``t_start_us``/``t_end_us``: zero-length at
            ``header.stamp``, or around it with the exposure topic's values (module notes); sorted
            by start. ``encoding`` is the declared ``frame_encoding``, else ``"unknown"`` (ROS
            images state no transfer function).
        """
        if self.image_topic is None:
            return None
        topic, enc0 = self.image_topic, self.image_encoding
        ch, nb, _, _ = ENCODINGS[enc0]
        imgs, stamps, exposures = [], [], []
        total = 0
        with self._reader() as r:
            for rec, (conn, ts, raw) in self._messages(r, topic):
                where = f"message {rec} of {topic}: "
                f = self._image_fields(r, raw, rec, topic)
                if f["encoding"] != enc0 or (f["height"], f["width"]) != self.frame_size.shape:
                    raise FormatError(self.path, f"{where}{f['encoding']} {f['height']}x{f['width']} image, unlike the "
                                                 f"first one's {enc0} {self.frame_size.height}x{self.frame_size.width}",
                                      record=rec)
                total += self.frame_size.height * self.frame_size.width * min(ch, 3) * nb
                check_frame_bytes(total, self.path, f"the frames of {topic}")
                imgs.append(decode_image(f["height"], f["width"], f["encoding"], f["is_bigendian"], f["step"],
                                         f["data"], self.path, where, rec))
                stamps.append(int(_ns_to_us(f["sec"], f["nsec"])))
            if self.exposure_topic is not None:
                for rec, (conn, ts, raw) in self._messages(r, self.exposure_topic):
                    if self.is_ros2:
                        v = int(self._deserialize(r, raw, rec, INT32, self.exposure_topic).data)
                    else:
                        if len(raw) != 4:
                            raise FormatError(self.path, f"message {rec} of {self.exposure_topic}: {len(raw)} bytes, "
                                                         f"a std_msgs/Int32 has 4", record=rec)
                        v = int.from_bytes(raw, "little", signed=True)
                    if v < 0:
                        raise FormatError(self.path, f"message {rec} of {self.exposure_topic}: negative exposure "
                                                     f"{v} µs", record=rec)
                    exposures.append(v)
        if not imgs:
            return Frames(np.zeros((0,) + self.frame_size.shape + ((3,) if ch >= 3 else ()),
                                   np.uint8 if nb == 1 else np.uint16), np.zeros(0, np.int64), np.zeros(0, np.int64),
                          encoding=self._frame_encoding("unknown"))
        t = np.asarray(stamps, np.int64)
        if exposures and len(exposures) == len(t):
            e = np.asarray(exposures, np.int64)
            ts = t - e // 2
            te = ts + e
        else:
            ts, te = t, t.copy()
        order = np.argsort(ts, kind="stable")
        try:
            return Frames(np.stack([imgs[i] for i in order]), ts[order], te[order],
                          encoding=self._frame_encoding("unknown"))
        except ValueError as exc:
            raise FormatError(self.path, f"invalid frames: {exc}") from None

    # -- access -------------------------------------------------------------------------------
    @contextlib.contextmanager
    def _reader(self):
        from rosbags.highlevel import AnyReader
        tmpdir = None
        try:
            bag, tmpdir = self._bag_for_rosbags()
        except OSError as exc:
            raise FormatError(self.path, f"cannot open the bag: {type(exc).__name__}: {exc}") from None
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

    def _bag_for_rosbags(self) -> tuple[Path, str | None]:
        """The path to hand ``rosbags`` (which tells storages apart by suffix: '.bag', '.db3',
        '.mcap', a folder) and the temporary folder holding symlinks under those names, if any.

        Files are checked against the limits first (module notes); nothing is copied."""
        import tempfile
        path = self.path
        if path.is_dir():
            meta = path / "metadata.yaml"
            if not meta.is_file():
                files = _folder_storage_files(path)
                if len(files) != 1:
                    raise FormatError(path, f"a ROS 2 bag folder needs metadata.yaml or exactly one storage file "
                                            f"(.db3/.mcap), found {len(files)}")
                path = files[0][0]
            else:
                files = _folder_storage_files(path)
                for q, kind in files:
                    (check_mcap if kind == "mcap" else check_sqlite)(q)
                text = meta.read_text(encoding="utf-8", errors="replace")
                import re
                empty = re.compile(r"^(\s*storage_identifier:)[ \t]*(''|\"\")?[ \t]*$", re.M)
                if not empty.search(text):
                    return path, None
                kinds = {k for _, k in files}
                if len(kinds) != 1:
                    raise FormatError(path, f"metadata.yaml names no storage and the folder's files are "
                                            f"{sorted(kinds) or 'none'} (need one kind: sqlite3 or mcap)")
                kind = kinds.pop()
                # rosbags refuses an empty storage id: the same folder, by symlinks, with the id filled in
                tmpdir = tempfile.mkdtemp(prefix="hybridhdr-bag-")
                for q in path.iterdir():
                    if q.name != "metadata.yaml":
                        os.symlink(q.resolve(), Path(tmpdir) / q.name)
                (Path(tmpdir) / "metadata.yaml").write_text(empty.sub(rf"\1 {kind}", text), encoding="utf-8")
                return Path(tmpdir), tmpdir
        kind = storage_kind(path)
        if kind is None:
            raise FormatError(path, "not a ROS bag: no ROS 1, SQLite (rosbag2) or MCAP magic")
        if kind == "mcap":
            check_mcap(path)
        elif kind == "sqlite3":
            check_sqlite(path)
        suffix = ".bag" if kind == "ros1" else STORAGE_SUFFIX[kind]
        if path.suffix == suffix:
            return path, None
        # detected by magic under another name: hand rosbags a symlink with the suffix it expects
        tmpdir = tempfile.mkdtemp(prefix="hybridhdr-bag-")
        link = Path(tmpdir) / ("recording" + suffix)
        os.symlink(path.resolve(), link)
        return link, tmpdir

    def _messages(self, r, topic: str | None = None) -> Iterator[tuple[int, tuple]]:
        topic = self.topic if topic is None else topic
        conns = [c for c in r.connections if c.topic == topic]
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
                raise FormatError(self.path, f"cannot read message {i} of {topic}: {type(exc).__name__}: {exc}",
                                  record=i) from None
            check_packet_size(len(item[2]), self.path, what=f"message {i} of {topic}")
            yield i, item
            i += 1

    def _deserialize(self, r, raw: bytes, rec: int, msgtype: str | None = None, topic: str | None = None):
        msgtype = self.msgtype if msgtype is None else msgtype
        topic = self.topic if topic is None else topic
        try:
            return r.deserialize(raw, msgtype)
        except Exception as exc:
            raise FormatError(self.path, f"cannot deserialize message {rec} of {topic} ({msgtype}): "
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
    "rosbag": "ROS bag with dvs_msgs/EventArray or event_camera_msgs/EventPacket (+ sensor_msgs/Image frames)",
}, READERS, WRITERS)
