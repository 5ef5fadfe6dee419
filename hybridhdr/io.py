"""Format registry, detection, and the reader/writer base classes every format implements.

Readers stream: :meth:`EventFileReader.iter_chunks` yields :class:`EventChunk` objects of roughly
``chunk_events`` events with the triggers decoded from the same stretch of the file, so memory does
not grow with file size. Writers are atomic: they write ``NAME.partial`` and rename it to ``NAME``
on :meth:`EventFileWriter.close`; on error (or :meth:`abort`) the partial file is removed.

Format modules are imported lazily, so ``import hybridhdr`` does not import h5py or numba.
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import FormatError, UnknownFormatError
from .events import (EVENT_DTYPE, TRIGGER_DTYPE, SensorSize, concatenate_events, empty_events,
                     empty_triggers, slice_time)
from .model import Frames, Metadata, Recording

__all__ = [
    "EventChunk", "EventFileReader", "EventFileWriter", "FORMAT_MODULES", "FORMAT_DESCRIPTIONS",
    "detect_format", "open_reader", "open_writer", "read", "write", "format_for_output",
    "DEFAULT_CHUNK_EVENTS", "DataDropWarning", "unsupported_parts",
]

DEFAULT_CHUNK_EVENTS = 1 << 20

#: format name -> module that implements it (module attributes READERS, WRITERS, sniff).
FORMAT_MODULES: dict[str, str] = {
    "hybridhdr": "hybridhdr.container",
    "evt2": "hybridhdr.capture.formats.prophesee",
    "evt21": "hybridhdr.capture.formats.prophesee",
    "evt3": "hybridhdr.capture.formats.prophesee",
    "dat": "hybridhdr.capture.formats.prophesee",
    "aedat4": "hybridhdr.capture.formats.aedat4",
    "ecd": "hybridhdr.capture.formats.text",
    "e2vid": "hybridhdr.capture.formats.text",
    "dsec": "hybridhdr.capture.formats.hdf5_layouts",
    "monash": "hybridhdr.capture.formats.hdf5_layouts",
    "akf_mat": "hybridhdr.capture.formats.akf_mat",
    "rosbag": "hybridhdr.capture.formats.rosbag",
}

FORMAT_DESCRIPTIONS: dict[str, str] = {
    "hybridhdr": "hybridhdr HDF5 recording container (.h5)",
    "evt2": "Prophesee RAW EVT 2.0 (.raw)",
    "evt21": "Prophesee RAW EVT 2.1, standard or legacy byte order (.raw)",
    "evt3": "Prophesee RAW EVT 3.0 (.raw)",
    "dat": "Prophesee DAT CD events (.dat)",
    "aedat4": "iniVation AEDAT 4 (.aedat4)",
    "ecd": "Event Camera Dataset text folder (events.txt, images.txt, images/)",
    "e2vid": "E2VID text (.txt or .zip, first line 'width height')",
    "dsec": "DSEC events HDF5 (/events/{x,y,t,p}, /ms_to_idx, /t_offset)",
    "monash": "Monash / event_cnn HDF5 (events/xs, ys, ts, ps; images/)",
    "akf_mat": "AKF MATLAB .mat (v7.3 HDF5 or v5)",
    "rosbag": "ROS bag with dvs_msgs/EventArray or event_camera_msgs/EventPacket",
}

#: extension -> default output format for writers.
_OUTPUT_EXTENSIONS = {".h5": "hybridhdr", ".hdf5": "hybridhdr", ".raw": "evt2", ".dat": "dat",
                      ".mat": "akf_mat", ".aedat4": "aedat4"}

# Order matters: more specific sniffers first.
_SNIFF_ORDER = ("hybridhdr.container", "hybridhdr.capture.formats.akf_mat",
                "hybridhdr.capture.formats.hdf5_layouts", "hybridhdr.capture.formats.prophesee",
                "hybridhdr.capture.formats.aedat4", "hybridhdr.capture.formats.rosbag",
                "hybridhdr.capture.formats.text")


@dataclass
class EventChunk:
    """A stretch of a file: events (sorted) and the triggers decoded alongside them."""

    events: np.ndarray = field(default_factory=empty_events)
    triggers: np.ndarray = field(default_factory=empty_triggers)


class EventFileReader:
    """Base class of every reader.

    Subclasses set :attr:`format_name`, fill :attr:`sensor_size` and :attr:`metadata` in
    ``__init__`` (reading only the header), and implement :meth:`_iter_chunks`. Frame-carrying
    formats override :meth:`read_frames` and give their frames the encoding
    :meth:`_frame_encoding` returns.

    Options common to every reader: ``sensor_size`` (height, width) and ``frame_encoding``, the
    declared encoding of the frames (``linear``, ``gamma2.2``, ``srgb`` or a ``Frames.encoding``
    value; see :func:`hybridhdr.camera.encoding.parse_frame_encoding`), which replaces what the
    format states or the reader assumes.
    """

    format_name: str = ""

    def __init__(self, path, **options):
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"{self.path}: no such file or directory")
        self.options = options
        self.sensor_size: SensorSize | None = SensorSize.from_any(options.get("sensor_size"))
        self.metadata: Metadata = Metadata()
        enc = options.get("frame_encoding")
        if enc is not None:
            from .camera.encoding import parse_frame_encoding
            enc = parse_frame_encoding(enc)
        #: The declared frame encoding (a ``Frames.encoding`` value), or None.
        self.frame_encoding: str | None = enc

    def _frame_encoding(self, default: str) -> str:
        """The encoding to give the frames read: the declared one, else the reader's ``default``."""
        return default if self.frame_encoding is None else self.frame_encoding

    # -- to implement -------------------------------------------------------------------------
    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        raise NotImplementedError(f"{type(self).__name__} must implement _iter_chunks")

    def read_frames(self) -> Frames | None:
        """Frames stored in the file, or None when the format has none."""
        return None

    # -- provided -----------------------------------------------------------------------------
    def iter_chunks(self, chunk_events: int = DEFAULT_CHUNK_EVENTS) -> Iterator[EventChunk]:
        """Yield :class:`EventChunk` objects of roughly ``chunk_events`` events each, in time order."""
        if int(chunk_events) < 1:
            raise ValueError(f"chunk_events must be >= 1, got {chunk_events}")
        yield from self._iter_chunks(int(chunk_events))

    def iter_events(self, chunk_events: int = DEFAULT_CHUNK_EVENTS) -> Iterator[np.ndarray]:
        for c in self.iter_chunks(chunk_events):
            if len(c.events):
                yield c.events

    def iter_time_windows(self, window_us: int, chunk_events: int = DEFAULT_CHUNK_EVENTS):
        """Yield ``(t0, events)`` for consecutive half-open windows ``[t0, t0 + window_us)``."""
        window_us = int(window_us)
        if window_us < 1:
            raise ValueError(f"window_us must be >= 1 µs, got {window_us}")
        pending: list[np.ndarray] = []
        t0 = None
        for ev in self.iter_events(chunk_events):
            if t0 is None:
                t0 = int(ev["t"][0])
            pending.append(ev)
            while True:
                last = int(pending[-1]["t"][-1])
                if last < t0 + window_us:
                    break
                buf = concatenate_events(pending)
                i = int(np.searchsorted(buf["t"], t0 + window_us, side="left"))
                yield t0, buf[:i]
                pending = [buf[i:]]
                t0 += window_us
        if t0 is not None:
            buf = concatenate_events(pending)
            while len(buf):
                i = int(np.searchsorted(buf["t"], t0 + window_us, side="left"))
                yield t0, buf[:i]
                buf = buf[i:]
                t0 += window_us

    def read(self, t_start_us=None, t_end_us=None) -> Recording:
        """Read the whole file (or the window ``[t_start_us, t_end_us)``) into a :class:`Recording`."""
        evs, trs = [], []
        for c in self.iter_chunks():
            e, tr = c.events, c.triggers
            if t_start_us is not None or t_end_us is not None:
                e, tr = slice_time(e, t_start_us, t_end_us), slice_time(tr, t_start_us, t_end_us)
            evs.append(e)
            trs.append(tr)
            if t_end_us is not None and len(c.events) and c.events["t"][-1] >= t_end_us:
                break
        frames = self.read_frames()
        if frames is not None and (t_start_us is not None or t_end_us is not None):
            frames = frames.slice_time(t_start_us, t_end_us)
        trig = np.concatenate(trs) if trs else empty_triggers()
        if trig.size and np.any(np.diff(trig["t"]) < 0):
            trig = trig[np.argsort(trig["t"], kind="stable")]
        return Recording(concatenate_events(evs), self.sensor_size, frames, trig, None, self.metadata)

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.format_name} {self.path} sensor={self.sensor_size}>"


class EventFileWriter:
    """Base class of every writer: atomic ``.partial`` file renamed on close.

    Subclasses implement :meth:`_open` (create ``self.tmp_path``), :meth:`_write_events`,
    optionally :meth:`_write_triggers` / :meth:`_write_frames`, and :meth:`_finish`.
    ``supports`` names what the format can hold besides events.
    """

    format_name: str = ""
    supports: frozenset = frozenset()
    requires_sensor_size: bool = True

    def __init__(self, path, sensor_size=None, metadata: Metadata | None = None, **options):
        self.path = Path(path)
        self.sensor_size = SensorSize.from_any(sensor_size)
        if self.sensor_size is None and self.requires_sensor_size:
            raise ValueError(f"{self.format_name} writer for {self.path} needs sensor_size (height, width)")
        self.metadata = metadata or Metadata()
        self.options = options
        self.tmp_path = self.path.with_name(self.path.name + ".partial")
        self._last_t = None
        self._closed = False
        self.n_events = 0
        try:
            self._open()
        except BaseException:
            # a writer failing while creating its file (full disk, bad option) leaves nothing behind
            try:
                self.abort()
            except Exception:
                pass
            raise

    def _open(self) -> None:
        raise NotImplementedError

    def _write_events(self, events: np.ndarray) -> None:
        raise NotImplementedError

    def _write_triggers(self, triggers: np.ndarray) -> None:
        raise ValueError(f"the {self.format_name} format cannot hold triggers")

    def _write_frames(self, frames: Frames) -> None:
        raise ValueError(f"the {self.format_name} format cannot hold frames")

    def _finish(self) -> None:
        pass

    def _cleanup(self) -> None:
        """Release file handles without finishing (called by abort)."""

    def write_events(self, events: np.ndarray) -> None:
        """Append events; they must continue the time order of everything written so far."""
        if self._closed:
            raise ValueError(f"{self.path}: writer is closed")
        if not isinstance(events, np.ndarray) or events.dtype != EVENT_DTYPE:
            raise TypeError(f"events must be an ndarray of dtype EVENT_DTYPE, got {getattr(events, 'dtype', type(events))}")
        if len(events) == 0:
            return
        from .events import validate_events
        if events.flags.c_contiguous and events.ndim == 1:
            # one fused pass (time order, polarity, coordinates); the full check names the error
            from ._write_kernels import events_ok
            ss = self.sensor_size
            w, h = (0, 0) if ss is None else (ss.width, ss.height)
            if events_ok(events.view(np.uint8).reshape(len(events), events.dtype.itemsize), events["t"], w, h) >= 0:
                validate_events(events, self.sensor_size)
        else:
            validate_events(events, self.sensor_size)
        if self._last_t is not None and events["t"][0] < self._last_t:
            raise ValueError(f"{self.path}: events must be appended in time order; chunk starts at "
                             f"{int(events['t'][0])} µs after {self._last_t} µs")
        self._write_events(events)
        self._last_t = int(events["t"][-1])
        self.n_events += len(events)

    def write_triggers(self, triggers: np.ndarray) -> None:
        if triggers is None or len(triggers) == 0:
            return
        if triggers.dtype != TRIGGER_DTYPE:
            raise TypeError(f"triggers must have dtype TRIGGER_DTYPE, got {triggers.dtype}")
        self._write_triggers(triggers)

    def write_frames(self, frames: Frames | None) -> None:
        if frames is None or len(frames) == 0:
            return
        self._write_frames(frames)

    def write_chunk(self, chunk: EventChunk) -> None:
        self.write_events(chunk.events)
        self.write_triggers(chunk.triggers)

    def close(self) -> None:
        """Finish the file and rename ``.partial`` to the final name."""
        if self._closed:
            return
        try:
            self._finish()
            self._closed = True
            os.replace(self.tmp_path, self.path)
        except BaseException:
            self.abort()
            raise

    def abort(self) -> None:
        """Drop the partial output."""
        self._closed = True
        try:
            self._cleanup()
        finally:
            if self.tmp_path.is_dir():
                import shutil
                shutil.rmtree(self.tmp_path, ignore_errors=True)
            elif self.tmp_path.exists():
                self.tmp_path.unlink()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _module(name: str):
    return importlib.import_module(name)


def _check_format(fmt: str) -> str:
    key = fmt.lower().replace(".", "").replace("-", "_")
    aliases = {"evt20": "evt2", "evt30": "evt3", "evt2_1": "evt21", "h5": "hybridhdr", "hdf5": "hybridhdr",
               "mat": "akf_mat", "akf": "akf_mat", "bag": "rosbag", "txt": "e2vid"}
    key = aliases.get(key, key)
    if key not in FORMAT_MODULES:
        raise UnknownFormatError(None, f"unknown format {fmt!r}; expected one of {sorted(FORMAT_MODULES)}")
    return key


def detect_format(path) -> str:
    """Detect the format of ``path`` from its header/magic bytes (not its extension)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    head = b""
    if path.is_file():
        with open(path, "rb") as f:
            head = f.read(4096)
    for modname in _SNIFF_ORDER:
        try:
            mod = _module(modname)
        except ImportError:
            continue
        sniff = getattr(mod, "sniff", None)
        if sniff is None:
            continue
        name = sniff(path, head)
        if name:
            return name
    what = "directory" if path.is_dir() else f"{path.stat().st_size}-byte file starting with {head[:16]!r}"
    raise UnknownFormatError(path, f"could not detect the event format of this {what}; expected one of "
                                   f"{sorted(FORMAT_MODULES)} (give the format explicitly to override)")


def open_reader(path, format: str | None = None, **options) -> EventFileReader:
    """Open a streaming reader; ``format`` overrides detection."""
    fmt = detect_format(path) if format is None else _check_format(format)
    mod = _module(FORMAT_MODULES[fmt])
    cls = mod.READERS.get(fmt)
    if cls is None:
        raise UnknownFormatError(path, f"no reader for format {fmt!r}")
    return cls(path, **options)


def format_for_output(path, format: str | None = None) -> str:
    if format is not None:
        return _check_format(format)
    p = Path(path)
    ext = p.suffix.lower()
    if ext in _OUTPUT_EXTENSIONS:
        return _OUTPUT_EXTENSIONS[ext]
    if ext == "" or p.is_dir():
        return "ecd"
    raise UnknownFormatError(p, f"cannot choose an output format from extension {ext!r}; give one of "
                                f"{sorted(_writable_formats())}")


def _writable_formats():
    out = []
    for fmt, modname in FORMAT_MODULES.items():
        try:
            if fmt in _module(modname).WRITERS:
                out.append(fmt)
        except ImportError:
            pass
    return out


def open_writer(path, format: str | None = None, *, sensor_size=None, metadata: Metadata | None = None,
                **options) -> EventFileWriter:
    """Open an atomic writer; the format comes from ``format`` or the extension."""
    fmt = format_for_output(path, format)
    mod = _module(FORMAT_MODULES[fmt])
    cls = mod.WRITERS.get(fmt)
    if cls is None:
        raise UnknownFormatError(path, f"format {fmt!r} can be read but not written; writable formats: "
                                       f"{sorted(_writable_formats())}")
    return cls(path, sensor_size=sensor_size, metadata=metadata, **options)


def read(path, format: str | None = None, *, t_start_us=None, t_end_us=None, **options) -> Recording:
    """Read a file of any supported format into a :class:`~hybridhdr.Recording`."""
    with open_reader(path, format, **options) as r:
        return r.read(t_start_us, t_end_us)


class DataDropWarning(UserWarning):
    """A writer's format cannot hold part of the recording (frames, triggers, HDR references)."""


def unsupported_parts(recording: Recording, supports) -> list[str]:
    """Names of the non-empty parts of ``recording`` that a writer supporting ``supports`` would drop."""
    parts = []
    if len(recording.triggers) and "triggers" not in supports:
        parts.append(f"{len(recording.triggers)} triggers")
    if recording.frames is not None and len(recording.frames) and "frames" not in supports:
        parts.append(f"{len(recording.frames)} frames")
    if recording.hdr is not None and len(recording.hdr) and "hdr" not in supports:
        parts.append(f"{len(recording.hdr)} HDR references")
    return parts


def write(recording: Recording, path, format: str | None = None, *, on_unsupported: str = "warn",
          **options) -> Path:
    """Write a :class:`~hybridhdr.Recording` atomically; returns the path written.

    Parameters
    ----------
    on_unsupported : {"warn", "error", "ignore"}
        What to do when the format cannot hold the recording's frames, triggers or HDR references:
        warn with :class:`DataDropWarning` (default), raise ``ValueError``, or drop them quietly.
    """
    if on_unsupported not in ("warn", "error", "ignore"):
        raise ValueError(f"on_unsupported must be 'warn', 'error' or 'ignore', got {on_unsupported!r}")
    with open_writer(path, format, sensor_size=recording.sensor_size, metadata=recording.metadata,
                     **options) as w:
        dropped = unsupported_parts(recording, w.supports)
        if dropped and on_unsupported != "ignore":
            msg = f"{path}: the {w.format_name} format cannot hold {', '.join(dropped)}"
            if on_unsupported == "error":
                raise ValueError(msg)
            import warnings
            warnings.warn(msg + "; they are not written", DataDropWarning, stacklevel=2)
        w.write_events(recording.events)
        if "triggers" in w.supports:
            w.write_triggers(recording.triggers)
        if "frames" in w.supports:
            w.write_frames(recording.frames)
        if recording.hdr is not None and len(recording.hdr) and "hdr" in w.supports:
            w.write_hdr(recording.hdr)
    return Path(path)
