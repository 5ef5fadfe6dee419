"""Format detection and the one way in and out: :func:`read`, :func:`write`, :func:`open_reader`,
:func:`open_writer`.

The format modules are imported by :func:`_format_modules` (explicitly, on first use, so that
``import hybridhdr`` loads neither h5py nor numba); each registers its readers and writers with
:func:`hybridhdr.formats.base.register_formats` as it is imported. A new format is a module in
``hybridhdr/formats/`` that registers itself, plus one line in :func:`_format_modules`.
"""

from __future__ import annotations

import warnings
from pathlib import Path

from ..errors import UnknownFormatError
from ..model import Metadata, Recording
from .base import REGISTERED, DataDropWarning, EventFileReader, EventFileWriter, FormatSpec, unsupported_parts

__all__ = ["formats", "detect_format", "open_reader", "open_writer", "read", "write", "format_for_output"]

#: extension -> default output format for writers.
_OUTPUT_EXTENSIONS = {".h5": "hybridhdr", ".hdf5": "hybridhdr", ".raw": "evt2", ".dat": "dat",
                      ".mat": "akf_mat", ".aedat4": "aedat4"}

_ALIASES = {"evt20": "evt2", "evt30": "evt3", "evt2_1": "evt21", "h5": "hybridhdr", "hdf5": "hybridhdr",
            "mat": "akf_mat", "akf": "akf_mat", "bag": "rosbag", "txt": "e2vid"}


def _format_modules() -> tuple:
    """Every format module, in sniffing order (more specific sniffers first)."""
    from . import aedat4, akf_mat, container, hdf5_layouts, prophesee, rosbag, text
    return (container, akf_mat, hdf5_layouts, prophesee, aedat4, rosbag, text)


# the order formats are listed in (``formats()``, the demo's round trip)
_LISTING_ORDER = ("hybridhdr", "evt2", "evt21", "evt3", "dat", "aedat4", "ecd", "e2vid", "dsec", "monash",
                  "akf_mat", "rosbag")


def formats() -> dict[str, FormatSpec]:
    """Every registered format: name -> :class:`~hybridhdr.formats.base.FormatSpec`."""
    _format_modules()
    rank = {name: i for i, name in enumerate(_LISTING_ORDER)}
    return dict(sorted(REGISTERED.items(), key=lambda kv: (rank.get(kv[0], len(rank)), kv[0])))


def _check_format(fmt: str) -> str:
    key = fmt.lower().replace(".", "").replace("-", "_")
    key = _ALIASES.get(key, key)
    known = formats()
    if key not in known:
        raise UnknownFormatError(None, f"unknown format {fmt!r}; expected one of {sorted(known)}")
    return key


def detect_format(path) -> str:
    """Detect the format of ``path`` from its header/magic bytes (not its extension)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    from .._util.limits import check_input_file
    check_input_file(path)  # a FIFO, a device or a socket would hang the sniffing read
    head = b""
    if path.is_file():
        with open(path, "rb") as f:
            head = f.read(4096)
    for mod in _format_modules():
        name = mod.sniff(path, head)
        if name:
            return name
    what = "directory" if path.is_dir() else f"{path.stat().st_size}-byte file starting with {head[:16]!r}"
    from . import hdf5_layouts
    hint = hdf5_layouts.undetected_hint(path, head) if path.is_file() else None
    if hint:
        what = f"{path.stat().st_size}-byte file, {hint}"
    raise UnknownFormatError(path, f"could not detect the event format of this {what}; expected one of "
                                   f"{sorted(formats())} (give the format explicitly to override: --format NAME "
                                   f"on the command line, hybridhdr.read(path, format='NAME') in Python)")


def open_reader(path, format: str | None = None, **options) -> EventFileReader:
    """Open a streaming reader; ``format`` overrides detection."""
    if format is not None and Path(path).exists():
        from .._util.limits import check_input_file
        check_input_file(path)  # a FIFO, a device or a socket would hang the reader
    fmt = detect_format(path) if format is None else _check_format(format)
    cls = formats()[fmt].reader
    if cls is None:
        raise UnknownFormatError(path, f"no reader for format {fmt!r}")
    return cls(path, **options)


def _raw_format_in_name(stem: str) -> str | None:
    """The Prophesee encoding a ``.raw`` file's name asks for (``x_evt3.raw``, ``rec.evt21.raw``),
    or None when it names none, or several."""
    import re
    found = {{"21": "evt21", "2.1": "evt21", "2_1": "evt21", "3": "evt3", "2": "evt2"}[m.group(1)]
             for m in re.finditer(r"(?<![a-z0-9])evt(2\.1|2_1|21|3|2)(?![0-9])", stem.lower())}
    return found.pop() if len(found) == 1 else None


def format_for_output(path, format: str | None = None) -> str:
    """The format a writer uses for ``path``: ``format`` when given, else the extension's
    (``.h5`` hybridhdr container, ``.dat``, ``.mat``, ``.aedat4``, no extension: an ECD folder).
    A ``.raw`` file is EVT 2.0 unless its name says ``evt3`` or ``evt21`` (``x_evt3.raw`` is
    EVT 3.0); give ``format`` to choose otherwise."""
    if format is not None:
        return _check_format(format)
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".raw":
        return _raw_format_in_name(p.stem) or _OUTPUT_EXTENSIONS[ext]
    if ext in _OUTPUT_EXTENSIONS:
        return _OUTPUT_EXTENSIONS[ext]
    if ext == "" or p.is_dir():
        return "ecd"
    raise UnknownFormatError(p, f"cannot choose an output format from extension {ext!r}; give one of "
                                f"{sorted(_writable_formats())}")


def _writable_formats() -> list[str]:
    return [name for name, spec in formats().items() if spec.writer is not None]


def open_writer(path, format: str | None = None, *, sensor_size=None, metadata: Metadata | None = None,
                **options) -> EventFileWriter:
    """Open an atomic writer; the format comes from ``format`` or the extension."""
    fmt = format_for_output(path, format)
    cls = formats()[fmt].writer
    if cls is None:
        raise UnknownFormatError(path, f"format {fmt!r} can be read but not written; writable formats: "
                                       f"{sorted(_writable_formats())}")
    return cls(path, sensor_size=sensor_size, metadata=metadata, **options)


def read(path, format: str | None = None, *, t_start_us=None, t_end_us=None, absolute: bool = True,
         **options) -> Recording:
    """Read a file of any supported format into a :class:`~hybridhdr.Recording`.

    ``t_start_us``/``t_end_us``: the half-open window to read, µs sensor time (``absolute=True``,
    the default, as timestamps are stored) or µs from the recording's start (``absolute=False``:
    its first event or frame exposure start, as the command line's ``--start``/``--end``). A
    window wholly outside the data raises :class:`~hybridhdr.errors.WindowOutsideDataError`
    naming the recording's span."""
    from ..events import api_window
    if t_start_us is None and t_end_us is None:
        with open_reader(path, format, **options) as r:
            return r.read()
    api_window(t_start_us, t_end_us, absolute=True, span=None, what=str(path))  # types
    if not absolute:  # the origin: the first chunk and the frames suffice
        span = _data_span(path, format, options, full=False)
        api_window(t_start_us, t_end_us, absolute=span is not None, span=None, what=str(path))  # no data: error
        t_start_us = None if t_start_us is None else int(t_start_us) + span[0]
        t_end_us = None if t_end_us is None else int(t_end_us) + span[0]
    with open_reader(path, format, **options) as r:
        rec = r.read(t_start_us, t_end_us)
    if not (rec.events.size or (rec.frames is not None and len(rec.frames)) or rec.triggers.size):
        # nothing in the window: is it outside the data?
        api_window(t_start_us, t_end_us, absolute=True, span=_data_span(path, format, options), what=str(path))
    return rec


def _data_span(path, format, options, *, full: bool = True):
    """``(start, last)`` µs of a file's data (first event or frame exposure start; last event or
    frame exposure end), as the command line's origin; ``full=False``
    reads one chunk of events (``last`` is then only a lower bound). None without data."""
    firsts, lasts = [], []
    with open_reader(path, format, **options) as r:
        for c in r.iter_chunks(1 << 20):
            if len(c.events):
                if not firsts:
                    firsts.append(int(c.events["t"][0]))
                lasts = [int(c.events["t"][-1])]
                if not full:
                    break
        fr = r.read_frames()
        if fr is not None and len(fr):
            firsts.append(int(fr.t_start_us.min()))
            lasts.append(int(fr.t_end_us.max()))
    return (min(firsts), max(lasts)) if firsts else None


def write(recording: Recording, path, format: str | None = None, *, on_unsupported: str = "warn",
          **options) -> Path:
    """Write a :class:`~hybridhdr.Recording` atomically; returns the path written.

    Parameters
    ----------
    on_unsupported : {"warn", "error", "ignore"}
        What to do when the format cannot hold the recording's frames, triggers, HDR references or
        IMU samples:
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
            warnings.warn(msg + "; they are not written", DataDropWarning, stacklevel=2)
        w.write_events(recording.events)
        if "triggers" in w.supports:
            w.write_triggers(recording.triggers)
        if "frames" in w.supports:
            w.write_frames(recording.frames)
        if recording.hdr is not None and len(recording.hdr) and "hdr" in w.supports:
            w.write_hdr(recording.hdr)
        if "imu" in w.supports:
            w.write_imu(recording.imu)
    return Path(path)
