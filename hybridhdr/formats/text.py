"""Text event formats: the Event Camera Dataset folder (``ecd``) and E2VID text/zip (``e2vid``).

ECD (Mueggler et al., "The Event-Camera Dataset and Simulator", IJRR 2017,
doi:10.1177/0278364917691115) is a folder holding

* ``events.txt``: one event per line, ``t x y p`` with ``t`` in seconds (float) and ``p`` in {0, 1};
* ``images.txt``: ``t images/frame_XXXXXXXX.png``, one APS frame per line;
* ``images/``: the frames (8-bit PNG for DAVIS240C);
* optional ``calib.txt`` (``fx fy cx cy k1 k2 p1 p2 k3``) and ``groundtruth.txt``
  (``t x y z qx qy qz qw``, not read);
* hybridhdr extensions, written by :class:`EcdWriter` and read back: ``frame_exposures.txt``
  (``t_start_us t_end_us`` per frame) and ``cfa.txt`` (``event_camera RGGB`` and
  ``frame_camera RGGB`` lines: the colour filter arrays, ``none`` for monochrome).

Colour: ECD states no colour filter. Colour PNGs (RGB, RGBA, palette ...) are read as (K, H, W, 3)
RGB frames, i.e. already demosaicked, which says the frame camera is a colour one but not its
pattern, nor the event sensor's; single-channel PNGs are (K, H, W) and may be grey or a raw
mosaic. So the reader declares ``metadata.*_camera.cfa`` only from ``cfa.txt``; for any other
colour ECD folder (a colour DAVIS recording exported to ECD) the pattern must be given with
``--cfa``. ``metadata.provenance["frame_colour"]`` and ``["cfa_source"]`` say what was found.

E2VID text (``uzh-rpg/rpg_e2vid``) is the same event lines preceded by one line ``width height``;
a ``.zip`` holding a single such ``.txt`` member is read by streaming the member.

Time conversion: seconds are converted to int64 µs by rounding to the nearest microsecond,
``np.rint(t * 1e6)``; digits below 1 µs (the ECD files carry 9 decimals) are therefore dropped.
For timestamps of 2^49 µs (about 17.8 years) and more, where a float64 product could be off by one,
the decimal text is converted exactly with integer arithmetic instead (rounding half up).
Polarity: ``p`` = 1 -> +1 (ON), 0 or -1 -> -1 (OFF); any other value is an error.

The text is parsed in blocks of lines with :func:`numpy.loadtxt` (its C parser), so memory stays
bounded by the block and chunk sizes. Blank lines and ``#`` comment lines are skipped.
"""

from __future__ import annotations

import io
import re
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import BinaryIO, Iterator

import numpy as np

from .._util.limits import LimitExceeded, check_frame_bytes, check_sensor_size, open_image
from ..errors import FormatError
from ..events import EVENT_DTYPE, SensorSize, empty_events
from ..model import CameraInfo, Frames, Metadata, parse_cfa
from .base import EventChunk, EventFileReader, EventFileWriter, register_formats

__all__ = ["EcdReader", "E2vidReader", "EcdWriter", "READERS", "WRITERS", "sniff", "parse_seconds_exact"]

_BLOCK_BYTES = 1 << 22
_MAX_LINE_BYTES = 1 << 20
#: Above this many µs a float64 ``t * 1e6`` may round to the wrong integer; parse exactly instead.
_EXACT_LIMIT_US = float(1 << 49)
_NUM = rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_LINE4 = re.compile(rb"^\s*" + rb"\s+".join([_NUM] * 4) + rb"\s*$")
_LINE2INT = re.compile(rb"^\s*(\d+)\s+(\d+)\s*$")


# ------------------------------------------------------------------------------------------------
# sniffing
# ------------------------------------------------------------------------------------------------

def _lines_of(head: bytes, n: int) -> list[bytes] | None:
    if not head or b"\x00" in head:
        return None
    lines = head.replace(b"\r\n", b"\n").split(b"\n")
    if len(lines) > n:
        return lines[:n]
    return None  # not enough complete lines in the head


_BOM = b"\xef\xbb\xbf"
#: errors a damaged, encrypted or exotic zip raises while it is read
_ZIP_ERRORS = (zipfile.BadZipFile, EOFError, OSError, ValueError, NotImplementedError, RuntimeError, zlib.error)


def _sniff_text(head: bytes, at_eof: bool = False) -> str | None:
    """``"e2vid"`` for a ``width height`` line followed by ``t x y p`` lines, comments or nothing
    (a UTF-8 BOM is skipped); ``"ecd"`` for a first ``t x y p`` line. ``at_eof``: ``head`` is the
    whole file, so its last line is complete."""
    if head.startswith(_BOM):
        head = head[len(_BOM):]
    if not head or b"\x00" in head:
        return None
    lines = head.replace(b"\r\n", b"\n").split(b"\n")
    if not at_eof:
        lines = lines[:-1]  # the last piece may be cut by the 4 KB head
    if not lines:
        return None
    if _LINE2INT.match(lines[0]):
        # the header, then comments / blank lines (any amount), then the first data line: t x y p
        for ln in lines[1:]:
            st = ln.strip()
            if not st or st.startswith(b"#"):
                continue
            return "e2vid" if _LINE4.match(ln) else None
        return "e2vid"  # header only, or header + comments filling the head
    if _LINE4.match(lines[0]):
        return "ecd"
    return None


def _zip_txt_member(path: Path) -> str | None:
    """Name of the single ``.txt`` member of a zip file, else None (never raises)."""
    try:
        with zipfile.ZipFile(path) as zf:
            names = [n for n in zf.namelist() if n.lower().endswith(".txt") and not n.endswith("/")]
    except _ZIP_ERRORS:
        return None
    return names[0] if len(names) == 1 else None


def sniff(path: Path, head: bytes) -> str | None:
    """Detect an ECD folder / ``events.txt`` (``"ecd"``) or an E2VID txt/zip (``"e2vid"``)."""
    try:
        path = Path(path)
        if path.is_dir():
            return "ecd" if (path / "events.txt").is_file() else None
        if head.startswith(b"PK\x03\x04"):
            name = _zip_txt_member(path)
            if name is None:
                return None
            with zipfile.ZipFile(path) as zf, zf.open(name) as f:
                inner = f.read(4096)
            return "e2vid" if _sniff_text(inner, len(inner) < 4096) == "e2vid" else None
        return _sniff_text(head, len(head) < 4096)
    except _ZIP_ERRORS:
        return None


# ------------------------------------------------------------------------------------------------
# parsing
# ------------------------------------------------------------------------------------------------

def parse_seconds_exact(tokens) -> np.ndarray:
    """Convert decimal-second strings to int64 µs exactly (halves of a µs round away from zero).

    Parameters
    ----------
    tokens : sequence of bytes or str
        Decimal numbers such as ``b"1605537493.718345001"``; exponent notation is converted
        through ``float``.

    Returns
    -------
    ndarray of shape (N,), int64
        Timestamps in µs.

    Examples
    --------
    >>> parse_seconds_exact([b"1605537493.7183455", b"-0.000001"]).tolist()
    [1605537493718346, -1]
    """
    out = np.empty(len(tokens), np.int64)
    for i, tok in enumerate(tokens):
        s = tok.decode("ascii") if isinstance(tok, (bytes, bytearray)) else str(tok)
        s = s.strip()
        if "e" in s or "E" in s:
            v = float(s) * 1e6
            if not np.isfinite(v) or abs(v) >= 9.2e18:
                raise ValueError(f"{s} s is not finite or overflows int64 µs")
            out[i] = int(round(v))
            continue
        neg = s.startswith("-")
        s = s.lstrip("+-")
        ip, _, fp = s.partition(".")
        digits = (fp + "0000000")[:7]
        us = int(ip or "0") * 1_000_000 + (int(digits) + 5) // 10
        out[i] = -us if neg else us
    return out


def _slow_locate(path, block: bytes, first_line: int, ncols: int = 4) -> FormatError:
    """Find the first malformed line of ``block`` (1-based ``first_line``) and describe it."""
    for k, raw in enumerate(block.split(b"\n")):
        line = raw.strip()
        if not line or line.startswith(b"#"):
            continue
        toks = line.split()
        if len(toks) != ncols:
            return FormatError(path, f"line {first_line + k}: expected {ncols} columns (t x y p), got "
                                     f"{len(toks)}: {raw[:80]!r}", record=first_line + k)
        for j, tok in enumerate(toks):
            try:
                float(tok)
            except ValueError:
                return FormatError(path, f"line {first_line + k}: column {j + 1} is not a number: {tok[:40]!r}",
                                   record=first_line + k)
    last = first_line + block.count(b"\n")
    return FormatError(path, f"lines {first_line}..{last}: unparsable text block",
                       record=first_line)


def _line_numbers(block: bytes, first_line: int) -> np.ndarray:
    """1-based line number of every data row (skipping blank and comment lines)."""
    nums = [first_line + k for k, raw in enumerate(block.split(b"\n"))
            if raw.strip() and not raw.strip().startswith(b"#")]
    return np.asarray(nums, np.int64)


def _iter_blocks(f: BinaryIO, first_line: int, block_bytes: int | None = None, path=None) -> Iterator[tuple[int, bytes]]:
    """Yield ``(first_line_number, block)`` with whole lines, reading ``block_bytes`` at a time."""
    block_bytes = _BLOCK_BYTES if block_bytes is None else block_bytes
    rest = b""
    line = first_line
    while True:
        data = f.read(block_bytes)
        if not data:
            break
        buf = rest + data
        cut = buf.rfind(b"\n")
        if cut < 0:
            if len(buf) > _MAX_LINE_BYTES:
                raise FormatError(path, f"line {line} is longer than {_MAX_LINE_BYTES} bytes; "
                                                            "not a text event file", record=line)
            rest = buf
            continue
        block, rest = buf[:cut + 1], buf[cut + 1:]
        yield line, block
        line += block.count(b"\n")
    if rest.strip():
        yield line, rest + b"\n"


class _TextEventParser:
    """Turns blocks of ``t x y p`` lines into validated EVENT_DTYPE arrays."""

    def __init__(self, path, sensor_size: SensorSize | None):
        self.path = path
        self.sensor_size = sensor_size
        self.last_t: int | None = None
        self.last_line: int | None = None

    def parse(self, block: bytes, first_line: int) -> np.ndarray:
        if not block.strip():
            return empty_events()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data" for comment-only blocks
            try:
                a = np.loadtxt(io.BytesIO(block), dtype=np.float64, comments="#", ndmin=2)
            except ValueError:
                raise _slow_locate(self.path, block, first_line) from None
        if a.shape[0] == 0:
            return empty_events()
        if a.shape[1] != 4:
            raise _slow_locate(self.path, block, first_line)
        nl = block.count(b"\n")
        rows = None if a.shape[0] == nl else _line_numbers(block, first_line)

        def line_of(i: int) -> int:
            return int(first_line + i) if rows is None else int(rows[i])

        bad = ~np.isfinite(a).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise FormatError(self.path, f"line {line_of(i)}: non-finite value {a[i].tolist()}", record=line_of(i))
        t_s, x, y, p = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
        for name, v in (("x", x), ("y", y)):
            bad = (v != np.floor(v)) | (v < 0) | (v > 65535)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise FormatError(self.path, f"line {line_of(i)}: {name} = {v[i].item()!r} is not a pixel index in 0..65535",
                                  record=line_of(i))
        bad = (p != 0) & (p != 1) & (p != -1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise FormatError(self.path, f"line {line_of(i)}: polarity {p[i].item()!r} is not 0, 1 or -1", record=line_of(i))
        if np.abs(t_s).max() * 1e6 >= _EXACT_LIMIT_US:
            if np.abs(t_s).max() * 1e6 >= 9.2e18:
                i = int(np.argmax(np.abs(t_s)))
                raise FormatError(self.path, f"line {line_of(i)}: timestamp {t_s[i].item()!r} s overflows int64 µs",
                                  record=line_of(i))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                toks = np.loadtxt(io.BytesIO(block), dtype="S64", comments="#", usecols=0, ndmin=1)
            t_us = parse_seconds_exact(toks.tolist())
        else:
            t_us = np.rint(t_s * 1e6).astype(np.int64)
        dec = np.flatnonzero(t_us[1:] < t_us[:-1])
        if dec.size:
            i = int(dec[0]) + 1
            raise FormatError(self.path, f"line {line_of(i)}: timestamps must be non-decreasing; "
                                         f"{int(t_us[i])} µs after {int(t_us[i - 1])} µs", record=line_of(i))
        if self.last_t is not None and t_us[0] < self.last_t:
            raise FormatError(self.path, f"line {line_of(0)}: timestamps must be non-decreasing; "
                                         f"{int(t_us[0])} µs after {self.last_t} µs (line {self.last_line})",
                              record=line_of(0))
        ss = self.sensor_size
        if ss is not None:
            for name, v, lim, dim in (("x", x, ss.width, "width"), ("y", y, ss.height, "height")):
                bad = v >= lim
                if bad.any():
                    i = int(np.flatnonzero(bad)[0])
                    raise FormatError(self.path, f"line {line_of(i)}: {name} = {int(v[i])} is outside the sensor "
                                                 f"{dim} {lim}", record=line_of(i))
        ev = np.empty(a.shape[0], EVENT_DTYPE)
        ev["t"] = t_us
        ev["x"] = x.astype(np.uint16)
        ev["y"] = y.astype(np.uint16)
        ev["p"] = np.where(p > 0, 1, -1)
        self.last_t = int(t_us[-1])
        self.last_line = line_of(a.shape[0] - 1)
        return ev


def _chunked(parsed: Iterator[np.ndarray], chunk_events: int) -> Iterator[EventChunk]:
    pending: list[np.ndarray] = []
    n = 0
    for ev in parsed:
        if ev.size:
            pending.append(ev)
            n += ev.size
        while n >= chunk_events:
            buf = np.concatenate(pending)
            yield EventChunk(buf[:chunk_events])
            rest = buf[chunk_events:]
            pending, n = ([rest] if rest.size else []), rest.size
    if n:
        yield EventChunk(np.concatenate(pending))


def _scan_max_xy(path, opener, first_line: int) -> tuple[int, int, int]:
    """Stream the events once and return ``(max_x, max_y, n_events)``."""
    parser = _TextEventParser(path, None)
    mx = my = -1
    n = 0
    with opener() as f:
        for line, block in _iter_blocks(f, first_line, path=path):
            ev = parser.parse(block, line)
            if ev.size:
                mx, my = max(mx, int(ev["x"].max())), max(my, int(ev["y"].max()))
                n += ev.size
    return mx, my, n


def _read_image(path: Path) -> np.ndarray:
    with open_image(path, "frame") as im:
        mode = im.mode
        if mode in ("1", "P", "LA", "PA", "CMYK", "YCbCr", "HSV", "LAB"):
            im = im.convert("RGB" if mode in ("P", "PA", "CMYK", "YCbCr", "HSV", "LAB") else "L")
        arr = np.asarray(im)
    if arr.ndim == 3 and arr.shape[2] == 4:
        arr = arr[..., :3]
    if arr.ndim == 3 and arr.shape[2] == 2:
        arr = arr[..., 0]
    return np.ascontiguousarray(arr)


#: PIL modes :func:`_read_image` turns into (H, W, 3) RGB frames; every other mode gives (H, W).
_COLOUR_MODES = ("RGB", "RGBA", "RGBX", "RGBa", "P", "PA", "CMYK", "YCbCr", "HSV", "LAB")


def _image_is_colour(path: Path) -> bool:
    """True when :func:`_read_image` returns (H, W, 3) for this file (from its header only)."""
    with open_image(path, "frame") as im:
        return im.mode in _COLOUR_MODES


#: ``cfa.txt`` keys: the cameras of :class:`hybridhdr.model.Metadata`.
CFA_FILE_KEYS = ("event_camera", "frame_camera")


def _parse_cfa_file(path: Path) -> dict[str, str | None]:
    """``cfa.txt`` (a hybridhdr extension written by :class:`EcdWriter`): lines
    ``event_camera RGGB`` / ``frame_camera none``; ``#`` comments and blank lines skipped."""
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise FormatError(path, f"cannot read: {exc}") from None
    if len(text) > 4096:
        raise FormatError(path, f"{len(text)} bytes; a cfa.txt holds two short lines")
    out: dict[str, str | None] = {}
    for k, raw in enumerate(text.splitlines(), 1):
        line = raw.split(b"#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        try:
            key, value = (x.decode("ascii") for x in parts) if len(parts) == 2 else (None, None)
        except UnicodeDecodeError:
            key = value = None
        if key not in CFA_FILE_KEYS:
            raise FormatError(path, f"line {k}: expected '<camera> <pattern>' with camera one of "
                                    f"{', '.join(CFA_FILE_KEYS)}, got {raw[:80]!r}", record=k)
        if key in out:
            raise FormatError(path, f"line {k}: {key} given twice", record=k)
        try:
            out[key] = parse_cfa(value)
        except ValueError as exc:
            raise FormatError(path, f"line {k}: {exc}", record=k) from None
    return out


def _image_size(path: Path) -> SensorSize:
    with open_image(path, "frame") as im:
        w, h = im.size
    return SensorSize(int(h), int(w))


def _decoded_bytes(path: Path) -> int:
    """Bytes the decoded image will take (from its header only)."""
    with open_image(path, "frame") as im:
        w, h = im.size
        bands = len(im.getbands())
        depth = 2 if im.mode.startswith("I;16") or im.mode in ("I", "F") else 1
    return int(w) * int(h) * min(bands, 3) * depth


# ------------------------------------------------------------------------------------------------
# ECD
# ------------------------------------------------------------------------------------------------

class EcdReader(EventFileReader):
    """Reader of an Event Camera Dataset folder (or of its ``events.txt``).

    Parameters
    ----------
    path : str or os.PathLike
        The folder, or its ``events.txt``. Any other text file of ``t x y p`` lines is read as
        events only.
    sensor_size : SensorSize or (height, width), optional
        ECD stores no sensor size. Without this option it is taken from the first frame listed in
        ``images.txt`` (exact for DAVIS, whose events and frames share the pixel array); with no
        frames it is inferred as max coordinate + 1 over all events (one extra pass), and
        ``metadata.provenance["sensor_size_source"]`` says which was used.
    frame_encoding : {"linear", "gamma2.2", "srgb"}, optional
        The frames' transfer function. ECD states none (8-bit PNGs of the DAVIS APS readout), so
        by default ``Frames.encoding`` is ``"unknown"``; a declared value is stored instead and
        ``metadata.provenance["frame_encoding_source"]`` says which.

    Notes
    -----
    ECD gives one timestamp per frame and no exposure time, so :meth:`read_frames` uses it as both
    ``t_start_us`` and ``t_end_us``, unless the folder holds ``frame_exposures.txt`` (written by
    :class:`EcdWriter`: one ``t_start_us t_end_us`` integer pair per frame).

    Colour filter arrays are declared only from ``cfa.txt`` (module notes): colour images alone
    give RGB frames and no pattern (pass ``--cfa``).
    """

    format_name = "ecd"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        p = self.path
        if p.is_dir():
            self.folder = p
            self.events_path = p / "events.txt"
            if not self.events_path.is_file():
                raise FormatError(p, "ECD folder has no events.txt")
        else:
            self.events_path = p
            self.folder = p.parent if p.name == "events.txt" else None
        self.images_txt = None
        if self.folder is not None and (self.folder / "images.txt").is_file():
            self.images_txt = self.folder / "images.txt"
        self._frame_list = self._parse_images_txt() if self.images_txt is not None else []
        source = "option"
        note = None
        if self.sensor_size is None and self._frame_list:
            first = self._frame_list[0][1]
            try:
                self.sensor_size = _image_size(first)
            except LimitExceeded:
                raise
            except (OSError, ValueError) as exc:
                raise FormatError(self.images_txt, f"cannot read the first frame {first}: {exc}",
                                  record=self._frame_list[0][2]) from None
            source = "first frame"
        if self.sensor_size is None:
            mx, my, n = _scan_max_xy(self.events_path, lambda: open(self.events_path, "rb"), 1)
            if n == 0:
                raise FormatError(self.events_path, "no events and no frames: cannot infer the sensor size; "
                                                    "pass sensor_size=(height, width)")
            self.sensor_size = SensorSize(*check_sensor_size(my + 1, mx + 1, self.events_path,
                                                             "sensor inferred from the coordinates"))
            source = "inferred"
            note = ("ECD stores no sensor size and there are no frames: inferred as max coordinate + 1 "
                    "over all events (may be smaller than the real sensor)")
        calib = None
        if self.folder is not None and (self.folder / "calib.txt").is_file():
            calib = self._parse_calib(self.folder / "calib.txt")
        prov = {"source_file": str(self.path), "format": "ecd", "events_file": str(self.events_path),
                "sensor_size_source": source,
                "time_conversion": "t_us = rint(t_seconds * 1e6) (exact decimal parsing above 2^49 µs)",
                "frame_timestamps": "one timestamp per frame (images.txt), used as both t_start_us and "
                                    "t_end_us; exposure unknown"}
        if note:
            prov["sensor_size_note"] = note
        if self._frame_list:
            prov["frame_encoding"] = self._frame_encoding("unknown")
            prov["frame_encoding_source"] = ("declared (frame_encoding option)" if self.frame_encoding else
                                             "not stated by the ECD format (PNG frames, no transfer function)")
        if self.folder is not None and (self.folder / "groundtruth.txt").is_file():
            prov["groundtruth_file"] = str(self.folder / "groundtruth.txt")
        cfa = {}
        cfa_file = None if self.folder is None else self.folder / "cfa.txt"
        if cfa_file is not None and cfa_file.is_file():
            cfa = _parse_cfa_file(cfa_file)
            prov["cfa_source"] = f"{cfa_file.name} (a hybridhdr extension of ECD, written by its EcdWriter)"
        elif self._frame_list:
            prov["cfa_source"] = ("not stated: ECD has no colour filter field (a colour DAVIS's pattern must be "
                                  "given with --cfa)")
        if self._frame_list:
            try:
                colour = _image_is_colour(self._frame_list[0][1])
            except (OSError, ValueError, SyntaxError) as exc:  # and LimitExceeded: read_frames reports it
                colour = None
                prov["frame_colour"] = f"unknown: the first frame cannot be read ({getattr(exc, 'message', exc)})"
            if colour is not None:
                prov["frame_colour"] = ("rgb: colour images, read as (K, H, W, 3) demosaicked RGB; they do not "
                                        "tell the sensor's colour filter" if colour else
                                        "grey: single-channel images, (K, H, W)")
        fc = CameraInfo(self.sensor_size if self._frame_list else None, cfa=cfa.get("frame_camera"))
        self.metadata = Metadata(event_camera=CameraInfo(self.sensor_size, cfa=cfa.get("event_camera")),
                                 frame_camera=fc, calibration=calib, provenance=prov)

    def _parse_calib(self, path: Path) -> dict:
        try:
            vals = [float(v) for v in path.read_text().split()]
        except (ValueError, UnicodeDecodeError) as exc:
            raise FormatError(path, f"calib.txt must hold numbers 'fx fy cx cy k1 k2 p1 p2 k3': {exc}") from None
        if len(vals) < 4:
            raise FormatError(path, f"calib.txt must hold at least 'fx fy cx cy', got {len(vals)} numbers")
        fx, fy, cx, cy = vals[:4]
        dist = (vals[4:] + [0.0] * 5)[:5]
        return {"event_camera": {"camera_matrix": [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]],
                                 "dist_coeffs": dist, "distortion_model": "radtan (k1 k2 p1 p2 k3)",
                                 "source": "calib.txt"}}

    def _parse_images_txt(self) -> list[tuple[int, Path, int]]:
        """``(t_us, image_path, line_number)`` per frame, checked for order."""
        out = []
        try:
            text = self.images_txt.read_bytes()
        except OSError as exc:
            raise FormatError(self.images_txt, f"cannot read: {exc}") from None
        last = None
        for k, raw in enumerate(text.split(b"\n"), start=1):
            line = raw.strip()
            if not line or line.startswith(b"#"):
                continue
            toks = line.split(None, 1)
            if len(toks) != 2:
                raise FormatError(self.images_txt, f"line {k}: expected 't images/frame_XXXXXXXX.png', got "
                                                   f"{raw[:80]!r}", record=k)
            try:
                ts = float(toks[0])
                if not np.isfinite(ts) or abs(ts) * 1e6 >= 9.2e18:
                    raise ValueError("not finite or overflows int64 µs")
                rel = toks[1].decode("utf-8").strip()
            except (ValueError, UnicodeDecodeError) as exc:
                raise FormatError(self.images_txt, f"line {k}: bad timestamp or file name ({exc}): {raw[:80]!r}",
                                  record=k) from None
            t_us = int(np.rint(ts * 1e6)) if abs(ts) * 1e6 < _EXACT_LIMIT_US else int(parse_seconds_exact([toks[0]])[0])
            if last is not None and t_us < last:
                raise FormatError(self.images_txt, f"line {k}: frame timestamps must be non-decreasing; "
                                                   f"{t_us} µs after {last} µs", record=k)
            last = t_us
            from .._util.confine import inside_folder
            # an absolute name or one leading out of the folder is refused (untrusted data)
            out.append((t_us, inside_folder(rel, self.folder, what=f"line {k}: image", source=self.images_txt), k))
        return out

    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        parser = _TextEventParser(self.events_path, self.sensor_size)
        with open(self.events_path, "rb") as f:
            yield from _chunked((parser.parse(b, ln) for ln, b in _iter_blocks(f, 1, path=self.events_path)), chunk_events)

    def read_frames(self) -> Frames | None:
        """The frames listed in ``images.txt`` (None when there is no ``images.txt``).

        Returns
        -------
        Frames or None
            ``images`` (K, H, W) or (K, H, W, 3) with the PNG's dtype (uint8 for ECD); see the class
            notes for the timestamps. ``encoding`` is the declared ``frame_encoding``, else
            ``"unknown"`` (DAVIS APS frames as exported; ECD states no transfer function).
        """
        if self.images_txt is None:
            return None
        if not self._frame_list:
            return Frames.empty(*self.sensor_size.shape)
        imgs = []
        total = 0
        sizes: dict = {}
        for t_us, p, k in self._frame_list:  # before decoding anything: N references to one big PNG add up
            try:
                if p not in sizes:
                    sizes[p] = _decoded_bytes(p)
            except LimitExceeded as exc:
                raise LimitExceeded(self.images_txt, f"line {k}: {p}: {exc.message}", record=k) from None
            except (OSError, ValueError, SyntaxError) as exc:
                raise FormatError(self.images_txt, f"line {k}: cannot read frame {p}: "
                                                   f"{getattr(exc, 'message', exc)}", record=k) from None
            total += sizes[p]
            check_frame_bytes(total, self.images_txt, f"the {len(self._frame_list)} frames listed")
        for t_us, p, k in self._frame_list:
            try:
                im = _read_image(p)
            except LimitExceeded as exc:
                raise LimitExceeded(self.images_txt, f"line {k}: {p}: {exc.message}", record=k) from None
            except (OSError, ValueError, SyntaxError) as exc:  # FormatError of an unreadable image too
                raise FormatError(self.images_txt, f"line {k}: cannot read frame {p}: "
                                                   f"{getattr(exc, 'message', exc)}", record=k) from None
            if imgs and (im.shape != imgs[0].shape or im.dtype != imgs[0].dtype):
                raise FormatError(self.images_txt, f"line {k}: frame {p} has shape {im.shape} dtype {im.dtype}, "
                                                   f"unlike the first frame's {imgs[0].shape} {imgs[0].dtype}",
                                  record=k)
            imgs.append(im)
        t = np.array([f[0] for f in self._frame_list], np.int64)
        ts, te = t, t.copy()
        expo = self.folder / "frame_exposures.txt"
        if expo.is_file():
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)
                    e = np.loadtxt(expo, dtype=np.int64, ndmin=2)
            except ValueError as exc:
                raise FormatError(expo, f"expected one 't_start_us t_end_us' integer pair per frame: {exc}") from None
            if e.shape != (len(t), 2):
                raise FormatError(expo, f"expected {len(t)} rows of 2 integers, got shape {e.shape}")
            ts, te = e[:, 0].copy(), e[:, 1].copy()
        try:
            return Frames(np.stack(imgs), ts, te, encoding=self._frame_encoding("unknown"))
        except ValueError as exc:
            raise FormatError(self.images_txt, f"invalid frames: {exc}") from None


class EcdWriter(EventFileWriter):
    """Writer of an Event Camera Dataset folder (``events.txt``, ``images.txt``, ``images/``).

    The folder is written as ``NAME.partial`` and renamed to ``NAME`` on close. An existing
    non-empty folder ``NAME`` is not overwritten (``FileExistsError``).

    Events are written one per line as ``t x y p``: ``t`` in seconds with 9 decimals, produced
    exactly from the integer µs (so they read back identically), ``p`` as 1 (ON) / 0 (OFF).
    Frames (uint8 or uint16, grey or RGB) are written as ``images/frame_%08d.png`` with their
    mid-exposure time in ``images.txt``; when any frame has a non-zero exposure the exact
    ``t_start_us t_end_us`` pairs also go to ``frame_exposures.txt`` (a hybridhdr extension that
    :class:`EcdReader` reads), and when either camera of the metadata has a colour filter array
    both patterns go to ``cfa.txt`` (``event_camera RGGB`` / ``frame_camera none`` lines; another
    extension the reader reads). ECD has no place for the sensor size or triggers.
    """

    format_name = "ecd"
    supports = frozenset({"frames"})
    partial_is_dir = True

    def _open(self) -> None:
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise FileExistsError(f"{self.path}: exists and is not an empty folder; refusing to overwrite")
        # self.tmp_path was created (exclusively, with a marker) by EventFileWriter
        self._ev = open(self.tmp_path / "events.txt", "w", encoding="ascii", newline="\n")
        self._img = None
        self._n_frames = 0
        self._exposures: list[tuple[int, int]] = []

    @staticmethod
    def _format_seconds(t_us: np.ndarray) -> list[str]:
        a = np.abs(t_us.astype(np.int64))
        s, f = np.divmod(a, 1_000_000)
        neg = (t_us < 0).tolist()
        return [f"{'-' if n else ''}{si}.{fi:06d}000" for n, si, fi in zip(neg, s.tolist(), f.tolist())]

    def _write_events(self, events: np.ndarray) -> None:
        step = 1 << 18
        for i in range(0, len(events), step):
            e = events[i:i + step]
            ts = self._format_seconds(e["t"])
            p = (e["p"] > 0).astype(np.int8).tolist()
            self._ev.write("".join(f"{a} {b} {c} {d}\n" for a, b, c, d in
                                   zip(ts, e["x"].tolist(), e["y"].tolist(), p)))

    def _write_frames(self, frames: Frames) -> None:
        from PIL import Image
        im = frames.images
        if im.dtype not in (np.uint8, np.uint16) or (im.ndim == 4 and im.dtype != np.uint8):
            raise ValueError(f"ECD frames are PNG files: images must be uint8 (grey or RGB) or uint16 grey, "
                             f"got {im.dtype} with shape {im.shape}")
        if self._img is None:
            (self.tmp_path / "images").mkdir()
            self._img = open(self.tmp_path / "images.txt", "w", encoding="ascii", newline="\n")
        mids = self._format_seconds(frames.t_mid_us)
        for k in range(len(frames)):
            name = f"images/frame_{self._n_frames:08d}.png"
            arr = np.ascontiguousarray(im[k])
            img = Image.fromarray(arr.astype("<u2") if arr.dtype == np.uint16 else arr)
            img.save(self.tmp_path / name, format="PNG")
            self._img.write(f"{mids[k]} {name}\n")
            self._exposures.append((int(frames.t_start_us[k]), int(frames.t_end_us[k])))
            self._n_frames += 1

    def _finish(self) -> None:
        self._ev.close()
        if self._img is not None:
            self._img.close()
        if any(a != b for a, b in self._exposures):
            with open(self.tmp_path / "frame_exposures.txt", "w", encoding="ascii", newline="\n") as f:
                f.write("".join(f"{a} {b}\n" for a, b in self._exposures))
        md = self.metadata
        if md.event_camera.cfa is not None or md.frame_camera.cfa is not None:
            with open(self.tmp_path / "cfa.txt", "w", encoding="ascii", newline="\n") as f:
                f.write("".join(f"{key} {getattr(md, key).cfa or 'none'}\n" for key in CFA_FILE_KEYS))

    def _cleanup(self) -> None:
        for h in (getattr(self, "_ev", None), getattr(self, "_img", None)):
            if h is not None and not h.closed:
                h.close()


# ------------------------------------------------------------------------------------------------
# E2VID
# ------------------------------------------------------------------------------------------------

class E2vidReader(EventFileReader):
    """Reader of E2VID text events: a ``.txt`` (or a ``.zip`` holding one ``.txt``).

    The first line is ``width height``; every following line is ``t x y p`` as in ECD (see the
    module notes for the time and polarity conversion). A zip member is streamed, never extracted.

    Parameters
    ----------
    path : str or os.PathLike
    sensor_size : SensorSize or (height, width), optional
        Overrides the size in the first line.
    """

    format_name = "e2vid"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        self.member = None
        with open(self.path, "rb") as f:
            magic = f.read(4)
        if magic == b"PK\x03\x04":
            self.member = _zip_txt_member(self.path)
            if self.member is None:
                raise FormatError(self.path, "zip file must hold exactly one .txt member")
        try:
            with self._open() as f:
                first = f.readline(256)
        except _ZIP_ERRORS as exc:
            raise FormatError(self.path, f"cannot read ({type(exc).__name__}: {exc})") from None
        if first.startswith(_BOM):
            first = first[len(_BOM):]
        m = _LINE2INT.match(first.rstrip(b"\r\n"))
        if m is None:
            raise FormatError(self.path, f"line 1: expected 'width height', got {first[:80]!r}", record=1)
        w, h = int(m.group(1)), int(m.group(2))
        try:
            stored = SensorSize(*check_sensor_size(h, w, self.path))
        except LimitExceeded:
            raise
        except (TypeError, ValueError) as exc:
            raise FormatError(self.path, f"line 1: invalid sensor size: {exc}", record=1) from None
        src = "option" if self.sensor_size is not None else "file"
        if self.sensor_size is None:
            self.sensor_size = stored
        self.metadata = Metadata(event_camera=CameraInfo(self.sensor_size), provenance={
            "source_file": str(self.path), "format": "e2vid", "zip_member": self.member,
            "sensor_size_source": src, "stored_sensor_size": [h, w],
            "time_conversion": "t_us = rint(t_seconds * 1e6) (exact decimal parsing above 2^49 µs)"})

    def _open(self) -> BinaryIO:
        if self.member is None:
            return open(self.path, "rb")
        zf = zipfile.ZipFile(self.path)
        try:
            f = zf.open(self.member)
        except BaseException:
            zf.close()
            raise
        return _ZipMember(zf, f)

    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        parser = _TextEventParser(self.path, self.sensor_size)
        try:
            with self._open() as f:
                f.readline(256)

                def gen():
                    for ln, b in _iter_blocks(f, 2, path=self.path):
                        yield parser.parse(b, ln)
                yield from _chunked(gen(), chunk_events)
        except FormatError:
            raise
        except _ZIP_ERRORS as exc:  # zlib.error (corrupt deflate), RuntimeError (encrypted member), ...
            raise FormatError(self.path, f"cannot read the text (corrupt, encrypted or truncated zip?): "
                                         f"{type(exc).__name__}: {exc}") from None


class _ZipMember(io.RawIOBase):
    """A zip member file object that closes its archive with it."""

    def __init__(self, zf: zipfile.ZipFile, f):
        self._zf, self._f = zf, f

    def read(self, n=-1):
        return self._f.read(n)

    def readline(self, n=-1):
        return self._f.readline(n)

    def readable(self):
        return True

    def close(self):
        try:
            self._f.close()
            self._zf.close()
        finally:
            super().close()


READERS = {"ecd": EcdReader, "e2vid": E2vidReader}
WRITERS = {"ecd": EcdWriter}

register_formats(__name__, {
    "ecd": "Event Camera Dataset text folder (events.txt, images.txt, images/)",
    "e2vid": "E2VID text (.txt or .zip, first line 'width height')",
}, READERS, WRITERS)
