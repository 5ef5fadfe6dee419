"""iniVation AEDAT 4.0 reader (events, triggers and frames), built on the ``aedat`` package.

An AEDAT 4.0 file starts with the magic ``#!AER-DAT4.0\\r\\n``, an XML description of its
streams (events, frames, IMU, triggers ...) and then a sequence of FlatBuffer packets, each
belonging to one stream and optionally LZ4/ZSTD compressed. The ``aedat`` package (a Rust
extension) decodes the packets one at a time, so reading streams with memory bounded by the
chunk size plus one packet.

Conversions (see ``docs/conventions.md``):

* event ``t`` (uint64 µs, as recorded; usually Unix-epoch µs) -> int64 µs unchanged;
  ``on`` (bool) -> ``p`` = +1 (ON) / -1 (OFF);
* trigger packets -> ``TRIGGER_DTYPE`` with the channel/edge mapping of
  :data:`TRIGGER_TYPE_MAP` (``TIMESTAMP_RESET`` markers are skipped);
* frames -> :class:`hybridhdr.Frames` with ``t_start_us``/``t_end_us`` the recorded exposure
  begin/end; grey frames are (H, W), colour frames (H, W, 3) in RGB order (``aedat`` converts the
  stored BGR), RGBA drops alpha. Frames smaller than the stream resolution (an ROI) are pasted at
  their offset into a zero image of the stream size.

Only the first event, frame and trigger stream are read (options ``event_stream``,
``frame_stream``, ``trigger_stream`` take a stream id to choose another).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Iterator

import numpy as np

from ...errors import FormatError
from ...events import EVENT_DTYPE, TRIGGER_DTYPE, SensorSize, empty_events, empty_triggers
from ...io import EventChunk, EventFileReader
from ...model import CameraInfo, Frames, Metadata

__all__ = ["Aedat4Reader", "READERS", "WRITERS", "sniff", "MAGIC", "TRIGGER_TYPE_MAP"]

MAGIC = b"#!AER-DAT4.0"

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

_INT64_MAX = np.iinfo(np.int64).max


def sniff(path: Path, head: bytes) -> str | None:
    """Return ``"aedat4"`` when ``head`` starts with the AEDAT 4.0 magic, else None."""
    return "aedat4" if head.startswith(MAGIC) else None


def _is_library_error(exc: BaseException) -> bool:
    # The Rust extension raises RuntimeError/OSError for malformed data and, on some malformed
    # FlatBuffers, a pyo3 PanicException (a BaseException subclass, not an Exception).
    return isinstance(exc, Exception) or type(exc).__name__ == "PanicException"


def _header_xml(path: Path) -> str:
    """The XML stream description of the file header (best effort, for camera name only)."""
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    start, end = head.find(b"<dv"), head.find(b"</dv>")
    if start < 0 or end < 0:
        return ""
    return head[start:end + 5].decode("utf-8", "replace")


class Aedat4Reader(EventFileReader):
    """Streaming reader of iniVation AEDAT 4.0 files.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.aedat4`` file.
    sensor_size : SensorSize or (height, width), optional
        Overrides the event stream's ``sizeX``/``sizeY``.
    event_stream, frame_stream, trigger_stream : int, optional
        Stream ids to read; default the first stream of each type.

    Notes
    -----
    Timestamps are kept exactly as recorded (int64 µs, usually Unix-epoch based). Events must be
    non-decreasing in time within the event stream and lie inside the sensor; otherwise
    :class:`~hybridhdr.errors.FormatError` is raised naming the packet and event index.
    """

    format_name = "aedat4"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        with open(self.path, "rb") as f:
            magic = f.read(len(MAGIC))
        if magic != MAGIC:
            raise FormatError(self.path, f"not an AEDAT 4.0 file: expected magic {MAGIC!r}, got {magic!r}",
                              offset=0)
        try:
            import aedat
        except ImportError as exc:  # pragma: no cover - dependency missing
            raise ImportError("reading AEDAT4 needs the 'aedat' package: pip install aedat") from exc
        self._aedat = aedat
        try:
            streams = self._decoder().id_to_stream()
        except BaseException as exc:
            if not _is_library_error(exc):
                raise
            raise FormatError(self.path, f"cannot parse the AEDAT4 header: {exc}", offset=len(MAGIC)) from None
        self.streams = {int(k): dict(v) for k, v in streams.items()}

        def pick(kind, opt):
            ids = sorted(k for k, v in self.streams.items() if v.get("type") == kind)
            want = options.get(opt)
            if want is not None:
                if int(want) not in ids:
                    raise FormatError(self.path, f"{opt}={want} is not a {kind} stream; {kind} streams: {ids}")
                return int(want)
            return ids[0] if ids else None

        self.event_stream = pick("events", "event_stream")
        self.frame_stream = pick("frame", "frame_stream")
        self.trigger_stream = pick("triggers", "trigger_stream")
        if self.event_stream is None:
            raise FormatError(self.path, "the AEDAT4 file has no event stream; streams: "
                                         f"{ {k: v.get('type') for k, v in self.streams.items()} }")
        ev_info = self.streams[self.event_stream]
        stored = None
        if ev_info.get("width") and ev_info.get("height"):
            try:
                stored = SensorSize(int(ev_info["height"]), int(ev_info["width"]))
            except (TypeError, ValueError) as exc:
                raise FormatError(self.path, f"invalid event stream resolution: {exc}") from None
        if self.sensor_size is None:
            self.sensor_size = stored
        if self.sensor_size is None:
            raise FormatError(self.path, "the event stream stores no resolution; pass sensor_size=(height, width)")
        self.frame_size = None
        if self.frame_stream is not None:
            fi = self.streams[self.frame_stream]
            if fi.get("width") and fi.get("height"):
                try:
                    self.frame_size = SensorSize(int(fi["height"]), int(fi["width"]))
                except (TypeError, ValueError):
                    self.frame_size = None
        xml = _header_xml(self.path)
        m = re.search(r'<attr key="source" type="string">([^<]*)</attr>', xml)
        model = m.group(1) if m else ""
        serial = model.rsplit("_", 1)[1] if "_" in model else ""
        self.metadata = Metadata(
            event_camera=CameraInfo(self.sensor_size, model, serial),
            frame_camera=CameraInfo(self.frame_size, model if self.frame_stream is not None else "",
                                    serial if self.frame_stream is not None else ""),
            provenance={
                "source_file": str(self.path), "format": "aedat4", "reader": "aedat",
                "streams": {str(k): dict(v) for k, v in self.streams.items()},
                "event_stream": self.event_stream, "frame_stream": self.frame_stream,
                "trigger_stream": self.trigger_stream,
                "sensor_size_source": "option" if options.get("sensor_size") is not None else "file",
                "trigger_mapping": "channel 0 external signal, 1 generator, 2 APS frame, 3 APS "
                                   "exposure; rising/start +1, falling/end -1; TIMESTAMP_RESET skipped",
            })

    def _decoder(self):
        return self._aedat.Decoder(str(self.path))

    def _packets(self) -> Iterator[tuple[int, dict]]:
        """Yield ``(packet_index, packet)``; wrap library errors into FormatError."""
        try:
            dec = self._decoder()
        except BaseException as exc:
            if not _is_library_error(exc):
                raise
            raise FormatError(self.path, f"cannot open AEDAT4 file: {exc}") from None
        i = 0
        while True:
            try:
                pkt = next(dec)
            except StopIteration:
                return
            except BaseException as exc:
                if not _is_library_error(exc):
                    raise
                raise FormatError(self.path, f"corrupt or truncated AEDAT4 packet: {exc}", record=i) from None
            yield i, pkt
            i += 1

    def _convert_events(self, raw: np.ndarray, pkt_index: int, n_before: int, last_t: int | None) -> np.ndarray:
        if not isinstance(raw, np.ndarray) or raw.ndim != 1 or raw.dtype.names is None or not {
                "t", "x", "y", "on"} <= set(raw.dtype.names):
            raise FormatError(self.path, f"unexpected event packet layout {getattr(raw, 'dtype', type(raw))}",
                              record=pkt_index)
        ev = np.empty(raw.shape[0], dtype=EVENT_DTYPE)
        if ev.size == 0:
            return ev
        t = raw["t"]
        big = t > _INT64_MAX
        if big.any():
            i = int(np.flatnonzero(big)[0])
            raise FormatError(self.path, f"event timestamp {int(t[i])} µs overflows int64 (packet {pkt_index}, "
                                         f"event {n_before + i})", record=pkt_index)
        ev["t"] = t.astype(np.int64)
        ev["x"] = raw["x"]
        ev["y"] = raw["y"]
        ev["p"] = np.where(raw["on"], 1, -1)
        tt = ev["t"]
        dec = np.flatnonzero(tt[1:] < tt[:-1])
        if dec.size:
            i = int(dec[0]) + 1
            raise FormatError(self.path, f"event timestamps decrease: event {n_before + i} has {int(tt[i])} µs after "
                                         f"{int(tt[i - 1])} µs (packet {pkt_index})", record=pkt_index)
        if last_t is not None and tt[0] < last_t:
            raise FormatError(self.path, f"event timestamps decrease across packets: event {n_before} has "
                                         f"{int(tt[0])} µs after {last_t} µs (packet {pkt_index})", record=pkt_index)
        ss = self.sensor_size
        for field, lim, dim in (("x", ss.width, "width"), ("y", ss.height, "height")):
            bad = np.flatnonzero(ev[field] >= lim)
            if bad.size:
                i = int(bad[0])
                raise FormatError(self.path, f"event {n_before + i} has {field}={int(ev[field][i])} outside the "
                                             f"sensor {dim} {lim} (packet {pkt_index})", record=pkt_index)
        return ev

    def _convert_triggers(self, raw: np.ndarray, pkt_index: int) -> np.ndarray:
        if not isinstance(raw, np.ndarray) or raw.dtype.names is None or not {"t", "source"} <= set(raw.dtype.names):
            raise FormatError(self.path, f"unexpected trigger packet layout {getattr(raw, 'dtype', type(raw))}",
                              record=pkt_index)
        codes = raw["source"].astype(np.int64)
        keep = np.isin(codes, list(TRIGGER_TYPE_MAP))
        unknown = (codes != 0) & ~keep
        if unknown.any():
            raise FormatError(self.path, f"unknown AEDAT4 trigger type {int(codes[unknown][0])} "
                                         f"(expected 0..9)", record=pkt_index)
        t = raw["t"][keep]
        if (t > _INT64_MAX).any():
            raise FormatError(self.path, "trigger timestamp overflows int64", record=pkt_index)
        codes = codes[keep]
        tr = np.empty(codes.size, dtype=TRIGGER_DTYPE)
        tr["t"] = t.astype(np.int64)
        lut_ch = np.zeros(10, np.uint16)
        lut_edge = np.zeros(10, np.int8)
        for code, (ch, edge) in TRIGGER_TYPE_MAP.items():
            lut_ch[code], lut_edge[code] = ch, edge
        tr["channel"] = lut_ch[codes]
        tr["edge"] = lut_edge[codes]
        if tr.size > 1 and np.any(np.diff(tr["t"]) < 0):
            tr = tr[np.argsort(tr["t"], kind="stable")]
        return tr

    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        pending: list[np.ndarray] = []
        n_pending = 0
        triggers: list[np.ndarray] = []
        n_total = 0
        last_t = None
        for i, pkt in self._packets():
            sid = pkt.get("stream_id")
            if sid == self.event_stream and "events" in pkt:
                ev = self._convert_events(pkt["events"], i, n_total, last_t)
                if ev.size:
                    last_t = int(ev["t"][-1])
                    n_total += ev.size
                    pending.append(ev)
                    n_pending += ev.size
            elif sid == self.trigger_stream and "triggers" in pkt:
                tr = self._convert_triggers(pkt["triggers"], i)
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

    def read_frames(self) -> Frames | None:
        """All frames of the frame stream (None when the file has no frame stream).

        Returns
        -------
        Frames or None
            ``images`` (K, H, W) for grey frames or (K, H, W, 3) RGB, dtype as stored (uint8 or
            uint16); ``t_start_us``/``t_end_us`` the recorded exposure begin/end (µs). When a frame
            has no valid exposure interval (end before start), its timestamp ``t`` is used for
            both. ``encoding`` is ``"raw"``.
        """
        if self.frame_stream is None:
            return None
        imgs, ts, te = [], [], []
        size = self.frame_size
        for i, pkt in self._packets():
            if pkt.get("stream_id") != self.frame_stream or "frame" not in pkt:
                continue
            fr = pkt["frame"]
            try:
                px = np.asarray(fr["pixels"])
                fmt = str(fr.get("format", ""))
                b, e = int(fr.get("exposure_begin_t", 0)), int(fr.get("exposure_end_t", 0))
                t = int(fr["t"])
                ox, oy = int(fr.get("offset_x", 0)), int(fr.get("offset_y", 0))
            except (KeyError, TypeError, ValueError) as exc:
                raise FormatError(self.path, f"malformed frame packet: {exc}", record=i) from None
            if px.ndim == 3 and px.shape[2] == 4:
                px = px[..., :3]
            if not (px.ndim == 2 or (px.ndim == 3 and px.shape[2] == 3)):
                raise FormatError(self.path, f"unsupported frame pixel layout {px.shape} (format {fmt!r})", record=i)
            if size is None:
                size = SensorSize(px.shape[0], px.shape[1])
            if px.shape[:2] != size.shape or ox or oy:
                if ox < 0 or oy < 0 or oy + px.shape[0] > size.height or ox + px.shape[1] > size.width:
                    raise FormatError(self.path, f"frame of shape {px.shape[:2]} at offset ({ox}, {oy}) does not "
                                                 f"fit the {size} frame stream", record=i)
                full = np.zeros(size.shape + px.shape[2:], px.dtype)
                full[oy:oy + px.shape[0], ox:ox + px.shape[1]] = px
                px = full
            if imgs and (px.shape != imgs[0].shape or px.dtype != imgs[0].dtype):
                raise FormatError(self.path, f"frame {len(imgs)} has shape {px.shape} dtype {px.dtype}, unlike "
                                             f"the first frame's {imgs[0].shape} {imgs[0].dtype}", record=i)
            if e < b or b <= 0:
                b = e = t
            imgs.append(px)
            ts.append(b)
            te.append(e)
        if not imgs:
            h, w = size.shape if size is not None else self.sensor_size.shape
            return Frames.empty(h, w)
        ts_a, te_a = np.asarray(ts, np.int64), np.asarray(te, np.int64)
        order = np.argsort(ts_a, kind="stable")
        try:
            return Frames(np.stack(imgs)[order], ts_a[order], te_a[order], encoding="raw")
        except ValueError as exc:
            raise FormatError(self.path, f"invalid frames: {exc}") from None


READERS = {"aedat4": Aedat4Reader}
WRITERS: dict = {}
