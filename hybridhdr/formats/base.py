"""The reader/writer base classes every format implements, and the registration of formats.

Readers stream: :meth:`EventFileReader.iter_chunks` yields :class:`EventChunk` objects of roughly
``chunk_events`` events with the triggers decoded from the same stretch of the file, so memory does
not grow with file size. Writers are atomic: they write ``NAME.partial`` and rename it to ``NAME``
on :meth:`EventFileWriter.close`; on error (or :meth:`abort`) the partial file is removed.

Each format module registers its readers and writers here (:func:`register_formats`) when it is
imported; :mod:`hybridhdr.formats.registry` imports them and detects, opens, reads and writes.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from ..camera.encoding import parse_frame_encoding
from ..events import (EVENT_DTYPE, IMU_DTYPE, TRIGGER_DTYPE, SensorSize, concatenate_events, empty_events,
                      empty_imu, empty_triggers, slice_time, validate_events, validate_imu)
from ..model import Frames, Metadata, Recording

__all__ = [
    "EventChunk", "EventFileReader", "EventFileWriter", "FormatSpec", "register_formats",
    "DEFAULT_CHUNK_EVENTS", "DataDropWarning", "unsupported_parts",
]

DEFAULT_CHUNK_EVENTS = 1 << 20


@dataclass(frozen=True)
class FormatSpec:
    """One registered format: its name, a one-line description, its reader and writer classes
    (None when it cannot be read or written) and the module that implements it."""

    name: str
    description: str
    reader: type | None
    writer: type | None
    module: str


#: format name -> FormatSpec, filled by the format modules as they are imported.
REGISTERED: dict[str, FormatSpec] = {}


def register_formats(module: str, descriptions: dict[str, str], readers: dict, writers: dict) -> None:
    """Register the formats of ``module`` (its ``__name__``): each name in ``descriptions`` with
    its reader (``readers[name]``) and writer (``writers[name]``), either possibly absent."""
    for name, description in descriptions.items():
        if name not in readers and name not in writers:
            raise ValueError(f"format {name!r} of {module} has neither a reader nor a writer")
        REGISTERED[name] = FormatSpec(name, description, readers.get(name), writers.get(name), module)


@dataclass
class EventChunk:
    """A stretch of a file or a live stream: events (sorted) and the triggers decoded alongside
    them; a live source also hands over the IMU samples (``IMU_DTYPE``) that arrived meanwhile
    (file readers give theirs by :meth:`EventFileReader.read_imu`)."""

    events: np.ndarray = field(default_factory=empty_events)
    triggers: np.ndarray = field(default_factory=empty_triggers)
    imu: np.ndarray = field(default_factory=empty_imu)


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

    def read_imu(self) -> np.ndarray:
        """IMU samples stored in the file (``IMU_DTYPE``, sorted by ``t``); empty when the format
        or the file has none."""
        return empty_imu()

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
        imu = slice_time(self.read_imu(), t_start_us, t_end_us)
        return Recording(concatenate_events(evs), self.sensor_size, frames, trig, None, self.metadata, imu)

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
        self.tmp_path = self._partial_path()
        self._last_t = None
        self._closed = False
        self.n_events = 0
        self._partial_fd = None
        try:
            from .._util.atomic import claim_partial
            # created exclusively (never through a symlink, never a user's folder) and locked while
            # this writer lives: a concurrent run to the same output fails cleanly (docs/security.md)
            self.tmp_path.parent.mkdir(parents=True, exist_ok=True)
            self._partial_fd = claim_partial(self.tmp_path, directory=self.partial_is_dir)
            self._open()
        except BaseException:
            # a writer failing while creating its file (full disk, bad option) leaves nothing behind
            try:
                self.abort()
            except Exception:
                pass
            raise

    #: the partial output is a folder (ECD), not a file
    partial_is_dir: bool = False

    def _partial_path(self) -> Path:
        """Where the output is written until :meth:`close` renames it (``NAME.partial``)."""
        return self.path.with_name(self.path.name + ".partial")

    def _open(self) -> None:
        raise NotImplementedError

    def _write_events(self, events: np.ndarray) -> None:
        raise NotImplementedError

    def _write_triggers(self, triggers: np.ndarray) -> None:
        raise ValueError(f"the {self.format_name} format cannot hold triggers")

    def _write_frames(self, frames: Frames) -> None:
        raise ValueError(f"the {self.format_name} format cannot hold frames")

    def _write_imu(self, imu: np.ndarray) -> None:
        raise ValueError(f"the {self.format_name} format cannot hold IMU samples")

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
        if events.flags.c_contiguous and events.ndim == 1:
            # one fused pass (time order, polarity, coordinates); the full check names the error
            from ._write_kernels import events_ok  # numba: loaded with the first write
            ss = self.sensor_size
            w, h = (0, 0) if ss is None else (ss.width, ss.height)
            if events_ok(events.view(np.int64), w, h) >= 0:  # 2 words per 16-byte record
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

    def write_imu(self, imu: np.ndarray | None) -> None:
        """Append IMU samples (``IMU_DTYPE``), continuing the time order of those written so far."""
        if imu is None or len(imu) == 0:
            return
        if not isinstance(imu, np.ndarray) or imu.dtype != IMU_DTYPE:
            raise TypeError(f"imu must be an ndarray of dtype IMU_DTYPE, got {getattr(imu, 'dtype', type(imu))}")
        validate_imu(imu)
        self._write_imu(imu)

    def write_chunk(self, chunk: EventChunk) -> None:
        self.write_events(chunk.events)
        self.write_triggers(chunk.triggers)
        self.write_imu(chunk.imu)

    def close(self) -> None:
        """Finish the file and rename ``.partial`` to the final name."""
        if self._closed:
            return
        try:
            self._finish()
            self._closed = True
            if self.partial_is_dir:
                from .._util.atomic import PARTIAL_MARK
                (self.tmp_path / PARTIAL_MARK).unlink(missing_ok=True)
            else:
                from .._util.atomic import unmark_partial
                unmark_partial(self.tmp_path)  # the finished file no longer reads as a partial one
            os.replace(self.tmp_path, self.path)
        except BaseException:
            self.abort()
            raise
        finally:
            self._release_partial()

    def _release_partial(self) -> None:
        from .._util.atomic import release_partial
        release_partial(getattr(self, "_partial_fd", None))
        self._partial_fd = None

    def abort(self) -> None:
        """Drop the partial output."""
        self._closed = True
        if getattr(self, "_partial_fd", None) is None:
            return  # the partial name was never ours (another run holds it) or is already renamed
        try:
            self._cleanup()
        finally:
            if getattr(self, "_partial_fd", None) is not None:  # only what this writer created
                if self.tmp_path.is_dir() and not self.tmp_path.is_symlink():
                    shutil.rmtree(self.tmp_path, ignore_errors=True)
                elif self.tmp_path.exists() or self.tmp_path.is_symlink():
                    self.tmp_path.unlink()
            self._release_partial()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()


class DataDropWarning(UserWarning):
    """A writer's format cannot hold part of the recording (frames, triggers, HDR references, IMU
    samples)."""


def unsupported_parts(recording: Recording, supports) -> list[str]:
    """Names of the non-empty parts of ``recording`` that a writer supporting ``supports`` would drop."""
    parts = []
    if len(recording.triggers) and "triggers" not in supports:
        parts.append(f"{len(recording.triggers)} triggers")
    if recording.frames is not None and len(recording.frames) and "frames" not in supports:
        parts.append(f"{len(recording.frames)} frames")
    if recording.hdr is not None and len(recording.hdr) and "hdr" not in supports:
        parts.append(f"{len(recording.hdr)} HDR references")
    if len(recording.imu) and "imu" not in supports:
        parts.append(f"{len(recording.imu)} IMU samples")
    return parts
