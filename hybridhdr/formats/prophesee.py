"""Prophesee RAW (EVT 2.0, EVT 2.1, EVT 3.0) and DAT readers, writers and streaming decoders.

Layouts follow ``docs/formats.md`` (Prophesee's "EVT 2.0/2.1/3.0 Format" pages
and the DAT layout of openeb's ``dat_tools.py``); the code is written from those specifications.

Reading
-------
Readers parse only the ``%`` header on construction and then decode the file in blocks
(``block_bytes``, default 8 MiB), so memory does not grow with the file size; the decoder state
(time high, loop count, row, vector base, ...) carries across blocks. The per-word loops are Numba
kernels in :mod:`._kernels`. :meth:`_PropheseeReader.read_all` decodes a whole file into one
preallocated array (the fast path used by :meth:`read` without a time window).

Reader options (keyword arguments of every reader and of :func:`hybridhdr.open_reader`):

``sensor_size``
    ``(height, width)`` overriding the header geometry.
``block_bytes`` : int, default 8 MiB
    Bytes read per block.
``reorder_window_us`` : int, default 1000
    Events may arrive up to this many µs earlier than the latest event decoded so far; they are
    re-sorted (stably, so equal timestamps keep file order). An event earlier than that is corrupt
    data and raises :class:`~hybridhdr.errors.FormatError`. Set 0 to require non-decreasing time.
    The sample files are strictly time-ordered; see :attr:`_PropheseeReader.stats` for the count
    of re-sorted events.
``strict`` : bool, default True
    Unused word types are errors (else skipped).
``allow_truncated`` : bool, default False
    Ignore a partial word (or DAT record) at the end of the file instead of raising.
``parallel`` : bool, default False
    DAT only: decode large blocks with the two-pass multi-threaded kernel (identical output).
    On a 2-core VM it measured no faster than the serial kernel (both are bound by page faults
    of the output array) and slower when other processes compete for the cores.

Time
----
Timestamps are absolute, in µs, as in the file (no offset is subtracted). EVT 2.0/2.1 count a
2^34 µs loop when TIME_HIGH drops by at least 0xFFFFFFF - 10; EVT 3.0 counts a 2^24 µs loop when
TIME_HIGH drops by at least 0xFFF - 10 (a TIME_LOW never signals a wrap); DAT unwraps the 32-bit
counter by reading consecutive differences as signed 32-bit numbers. Words before the first
TIME_HIGH are skipped (EVT 2.x and 3.0).

Writing
-------
Writers (EVT 2.0, EVT 3.0, DAT) are atomic (``NAME.partial`` renamed on close). EVT writers hold
the last batch of events until the next :meth:`write_events` call or :meth:`close`, and merge the
triggers given by :meth:`write_triggers` into it in time order (a trigger goes before events of
the same timestamp). A trigger earlier than events already encoded raises ``ValueError``; so
``write_chunk`` (events, then the triggers of the same span) and ``hybridhdr.write`` (all events,
then all triggers) both work. Timestamps must be >= 0 and < 2^44 µs (EVT) or fit the DAT limits
(first timestamp < 2^32 µs, consecutive events less than 2^31 µs apart).
"""

from __future__ import annotations

import datetime
import sys
from pathlib import Path
from typing import Iterator

import numpy as np

from .._util.limits import check_sensor_size
from ..errors import FormatError
from ..events import EVENT_DTYPE, TRIGGER_DTYPE, SensorSize, empty_events, empty_triggers
from ..model import CameraInfo, Metadata, Recording
from . import _kernels as K
from .base import EventChunk, EventFileReader, EventFileWriter, register_formats

__all__ = [
    "READERS", "WRITERS", "sniff", "Evt2Reader", "Evt21Reader", "Evt3Reader", "DatReader",
    "Evt2Writer", "Evt3Writer", "DatWriter", "Evt2Decoder", "Evt21Decoder", "Evt3Decoder",
    "decode_evt2", "decode_evt21", "decode_evt3", "parse_header", "RawHeader",
    "HEADER_MAX_BYTES", "DEFAULT_BLOCK_BYTES", "DEFAULT_REORDER_WINDOW_US",
]

if sys.byteorder != "little":  # pragma: no cover - the packed-record kernels assume it
    raise ImportError("hybridhdr.formats.prophesee needs a little-endian host")

#: Longest header accepted (bytes); a file without a newline in it cannot hang the parser.
HEADER_MAX_BYTES = 1 << 20
DEFAULT_BLOCK_BYTES = 8 << 20
DEFAULT_REORDER_WINDOW_US = 1000
#: Largest timestamp the EVT writers accept (µs, about 203 days).
EVT_MAX_T_US = 1 << 44
_TRIG_CAP = 1 << 14
_DAT_PARALLEL_MIN = 1 << 16

_RAW_KEYS = {"evt", "format", "plugin_name", "serial_number", "system_id", "integrator_name",
             "firmware_version", "geometry", "sensor_generation", "camera_integrator_name"}
_DAT_KEYS = {"version", "width", "height", "data"}
_DAT_CD_TYPES = {0: "Event2D", 12: "EventCD"}
_DAT_OTHER_TYPES = {14: "EventExtTrigger", 40: "EventOpticalFlow"}


# =============================================================================================
# Header
# =============================================================================================
class RawHeader(dict):
    """Header ``key -> value`` (strings) of a RAW or DAT file, plus where the data starts.

    Attributes
    ----------
    data_offset : int
        Byte offset of the first byte after the header.
    lines : list of str
        The header lines without the leading ``%``.
    terminated : bool
        Whether the header ended with ``% end``.
    """

    data_offset: int = 0
    lines: list
    terminated: bool = False

    def get_ci(self, key: str, default=None):
        """Case-insensitive lookup."""
        k = key.lower()
        for kk, v in self.items():
            if kk.lower() == k:
                return v
        return default


def _is_text_line(line: bytes) -> bool:
    for b in line:
        if b < 0x20 and b not in (0x09, 0x0D):
            return False
        if b == 0x7F:
            return False
    try:
        line.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def parse_header(data: bytes, *, complete: bool = True, path=None) -> RawHeader:
    """Parse the ``%`` header at the start of ``data``.

    A header line starts with ``%``, ends with a newline and holds text only; the header ends at
    the first line that is not such a line, or after a ``% end`` line. A ``%`` line holding control
    bytes is taken as the start of binary data (an event word may begin with 0x25).

    Parameters
    ----------
    data : bytes
        The first bytes of the file (at most :data:`HEADER_MAX_BYTES` are looked at).
    complete : bool
        Whether ``data`` is the whole file. If not and the header does not end inside ``data``,
        :class:`FormatError` is raised (header too long).
    path : path-like, optional
        File name used in error messages.

    Returns
    -------
    RawHeader
    """
    data = bytes(data[:HEADER_MAX_BYTES + 1]) if len(data) > HEADER_MAX_BYTES + 1 else bytes(data)
    h = RawHeader()
    h.lines = []
    pos = 0
    n = len(data)
    while pos < n and data[pos] == 0x25:
        nl = data.find(b"\n", pos)
        if nl < 0:
            if not complete or n > HEADER_MAX_BYTES:
                raise FormatError(path, f"header is longer than {HEADER_MAX_BYTES} bytes or has a line "
                                        "without a newline; expected '%' lines ending in '\\n'", offset=pos)
            # last line of a header-only file without a final newline: text => header line
            line = data[pos:]
            if not _is_text_line(line):
                break
            nl = n - 1 if data.endswith(b"\n") else n
            end = n
        else:
            line = data[pos:nl]
            end = nl + 1
            if not _is_text_line(line):
                break
        if end > HEADER_MAX_BYTES:
            raise FormatError(path, f"header is longer than {HEADER_MAX_BYTES} bytes; expected the "
                                    "binary data to start sooner", offset=pos)
        text = line.decode("utf-8").rstrip("\r")[1:].strip()
        h.lines.append(text)
        pos = end
        if text.lower() == "end":
            h.terminated = True
            break
        if text:
            parts = text.split(None, 1)
            h[parts[0]] = parts[1].strip() if len(parts) > 1 else ""
    if pos >= n and not complete and not h.terminated:
        raise FormatError(path, f"header does not end within the first {n} bytes; expected at most "
                                f"{HEADER_MAX_BYTES} bytes of '%' lines", offset=n)
    h.data_offset = pos
    return h


def _format_fields(h: RawHeader) -> tuple[str | None, dict]:
    """The ``format`` line split into its name and ``key=value`` fields."""
    fmt = h.get_ci("format")
    if not fmt:
        return None, {}
    parts = [s.strip() for s in fmt.split(";")]
    fields = {}
    for s in parts[1:]:
        if "=" in s:
            k, v = s.split("=", 1)
            fields[k.strip().lower()] = v.strip()
    return parts[0], fields


def _raw_format_of(h: RawHeader) -> str | None:
    """EVT version declared by a RAW header (``evt2``/``evt21``/``evt3``), or None."""
    name, _ = _format_fields(h)
    if name:
        key = name.upper().replace(".", "").replace("_", "").replace(" ", "")
        m = {"EVT2": "evt2", "EVT20": "evt2", "EVT21": "evt21", "EVT3": "evt3", "EVT30": "evt3"}
        if key in m:
            return m[key]
    evt = h.get_ci("evt")
    if evt:
        m = {"2.0": "evt2", "2": "evt2", "2.1": "evt21", "3.0": "evt3", "3": "evt3"}
        if evt.strip() in m:
            return m[evt.strip()]
    return None


def _geometry(h: RawHeader, path=None) -> SensorSize | None:
    """Sensor size from the header: format fields, ``geometry WxH``, DAT Width/Height, plugin.

    A size the header states but that is not valid (not integers, zero, above the limit) is an
    error, never dropped in favour of a guess."""
    _, fields = _format_fields(h)
    stated = None
    if "height" in fields and "width" in fields:
        stated = (fields["height"], fields["width"], "format height/width")
    else:
        g = h.get_ci("geometry")
        if g and "x" in g.lower():
            w, hh = g.lower().split("x", 1)
            stated = (hh, w, "geometry")
        elif h.get_ci("width") or h.get_ci("height"):
            stated = (h.get_ci("height"), h.get_ci("width"), "Width/Height")
    if stated is not None:
        hh, w, what = stated
        try:
            hv, wv = int(str(hh).strip()), int(str(w).strip())
        except (ValueError, TypeError):
            raise FormatError(path, f"header {what} {w!r} x {hh!r} (width x height) is not a pair of integers") from None
        return SensorSize(*check_sensor_size(hv, wv, path, f"header {what}"))
    return _geometry_from_generation(h)


def _geometry_from_generation(h: RawHeader) -> SensorSize | None:
    """Infer the size from ``plugin_name`` / ``sensor_generation`` (Gen3 VGA, Gen4.x and IMX636 HD,
    GenX320 320x320, IMX637/IMX647 640x512)."""
    text = " ".join(str(h.get_ci(k, "")) for k in ("plugin_name", "sensor_generation", "sensor_name")).lower()
    text = text.replace(".", "").replace("-", "").replace("_", "")
    if not text.strip():
        return None
    if "genx320" in text or "gx320" in text or "x320" in text:
        return SensorSize(320, 320)
    if "imx637" in text or "imx647" in text:
        return SensorSize(512, 640)
    if "imx636" in text or "imx646" in text or "gen41" in text or "gen4" in text or "saphir" in text:
        return SensorSize(720, 1280)
    if "gen31" in text or "gen3" in text:
        return SensorSize(480, 640)
    return None


def _read_head(path, n: int = HEADER_MAX_BYTES + 1) -> tuple[bytes, bool]:
    with open(path, "rb") as f:
        data = f.read(n)
        complete = len(data) < n or not f.read(1)
    return data, complete


# =============================================================================================
# Sniffing
# =============================================================================================
def sniff(path, head: bytes) -> str | None:
    """Detect a Prophesee file from its first bytes: ``"evt2"``, ``"evt21"``, ``"evt3"``, ``"dat"``.

    RAW files are recognised by an ``evt``/``format`` header key; DAT files by DAT keys (``Version``,
    ``Width``, ``Height``, ``Data file containing ...``) plus a known event type byte and size 8
    after the header. A ``%`` header with RAW-only keys (``plugin_name``, ``serial_number`` ...) but
    no EVT version is taken as EVT 2.0 only when the file name ends in ``.raw``; a bare ``%``
    header is decided by the extension (``.raw`` -> evt2, ``.dat`` -> dat). Anything else: None.
    """
    if not head or head[:1] != b"%":
        return None
    text = head
    if len(head) >= 4096:  # possibly cut mid-line: only look at whole lines
        text = head[:head.rfind(b"\n") + 1]
        if not text:
            return None
    try:
        h = parse_header(text, complete=True)
    except FormatError:
        return None
    if not h.lines:
        return None
    fmt = _raw_format_of(h)
    if fmt:
        return fmt
    keys = {k.lower() for k in h}
    ext = Path(path).suffix.lower()
    rest = head[h.data_offset:]
    if keys & _DAT_KEYS:
        if len(rest) >= 2 and rest[1] == 8 and rest[0] in (_DAT_CD_TYPES.keys() | _DAT_OTHER_TYPES.keys()):
            return "dat"
        if ext == ".dat":
            return "dat"
    if keys & _RAW_KEYS:
        return "evt2" if ext == ".raw" else None
    if ext == ".dat":
        return "dat"
    if ext == ".raw":
        return "evt2"
    return None


# =============================================================================================
# Decoding cores (kernel + state), shared by readers and the public stream decoders
# =============================================================================================
class _Core:
    """One format's kernel with its state; ``run`` decodes as much as fits in ``out``."""

    format_name = ""
    word_bytes = 4
    word_dtype = np.uint32
    max_per_word = 1

    def __init__(self, width: int, height: int, window_us: int, strict: bool):
        self.width = int(width)
        self.height = int(height)
        self.window_us = int(window_us)
        self.strict = bool(strict)
        self.st = K.new_state()

    def words(self, buf: np.ndarray) -> np.ndarray:
        return buf.view(self.word_dtype)

    def n_words(self, words: np.ndarray) -> int:
        return words.shape[0]

    def estimate(self, n_words: int) -> int:
        return n_words

    #: whether :meth:`count` gives an upper bound of the events in some words (else estimate)
    counts = False

    def count(self, words) -> int:
        return self.estimate(self.n_words(words))

    def run(self, words, start, out, n, cap, tt, tc, te, nt, tcap):
        raise NotImplementedError

    def describe(self, err: int) -> str:
        a, b = int(self.st[K.ST_ERR_A]), int(self.st[K.ST_ERR_B])
        if err == K.ERR_X_RANGE:
            return f"event x = {a} lies outside the sensor; expected x < width {b}"
        if err == K.ERR_Y_RANGE:
            return f"event y = {a} lies outside the sensor; expected y < height {b}"
        if err == K.ERR_BACKWARDS:
            return (f"timestamp goes backwards: event at {a} µs after an event at {b} µs ({b - a} µs "
                    f"earlier, more than the reorder window of {self.window_us} µs); expected "
                    "non-decreasing time (corrupt data or wrong format?)")
        if err == K.ERR_WORD_TYPE:
            return (f"unused {self.format_name} word type 0x{a:X} (word 0x{b:X}); expected one of "
                    f"{self.valid_types} (wrong format or corrupt data?)")
        return f"decoder error {err}"


class _Evt2Core(_Core):
    format_name = "EVT 2.0"
    valid_types = "0x0 CD_OFF, 0x1 CD_ON, 0x8 TIME_HIGH, 0xA EXT_TRIGGER, 0xD IMU, 0xE OTHERS, 0xF CONTINUED"

    def run(self, words, start, out, n, cap, tt, tc, te, nt, tcap):
        return K.evt2_decode(words, start, out, n, cap, tt, tc, te, nt, tcap, self.st, self.width,
                             self.height, self.window_us, self.strict)


class _Evt21Core(_Core):
    format_name = "EVT 2.1"
    word_bytes = 8
    max_per_word = 32
    valid_types = "0x0 NEG, 0x1 POS, 0x8 TIME_HIGH, 0xA EXT_TRIGGER, 0xD IMU, 0xE OTHERS, 0xF CONTINUED"

    def __init__(self, width, height, window_us, strict, legacy: bool = False):
        super().__init__(width, height, window_us, strict)
        self.legacy = bool(legacy)

    def n_words(self, words):
        return words.shape[0] // 2

    def estimate(self, n_words):
        return 4 * n_words

    counts = True

    def count(self, words):
        return int(K.evt21_count(words, self.legacy))

    def run(self, words, start, out, n, cap, tt, tc, te, nt, tcap):
        return K.evt21_decode(words, start, out, n, cap, tt, tc, te, nt, tcap, self.st, self.width,
                              self.height, self.window_us, self.strict, self.legacy)


class _Evt3Core(_Core):
    format_name = "EVT 3.0"
    word_bytes = 2
    word_dtype = np.uint16
    max_per_word = 12
    valid_types = ("0x0 ADDR_Y, 0x2 ADDR_X, 0x3 VECT_BASE_X, 0x4 VECT_12, 0x5 VECT_8, 0x6 TIME_LOW, "
                   "0x7 CONTINUED_4, 0x8 TIME_HIGH, 0xA EXT_TRIGGER, 0xD IMU, 0xE OTHERS, 0xF CONTINUED_12")

    counts = True

    def count(self, words):
        return int(K.evt3_count(words))

    def run(self, words, start, out, n, cap, tt, tc, te, nt, tcap):
        return K.evt3_decode(words, start, out, n, cap, tt, tc, te, nt, tcap, self.st, self.width,
                             self.height, self.window_us, self.strict)


class _DatCore(_Core):
    format_name = "DAT"
    word_bytes = 8
    parallel = False

    def n_words(self, words):
        return words.shape[0] // 2

    def run(self, words, start, out, n, cap, tt, tc, te, nt, tcap):
        nrec = words.shape[0] // 2
        k = min(cap - n, nrec - start)
        if k <= 0:
            return start, n, nt, 0, start
        w = words[2 * start:2 * (start + k)]
        o = out[2 * n:2 * (n + k)]
        if self.parallel and k >= _DAT_PARALLEL_MIN:
            import numba
            nseg = numba.get_num_threads()
            done, err, erec = K.dat_decode_parallel(w, o, self.st, self.width, self.height,
                                                    self.window_us, nseg)
        else:
            done, err, erec = K.dat_decode(w, o, self.st, self.width, self.height, self.window_us)
        if err:
            return start + erec, n + erec, nt, err, start + erec
        return start + k, n + k, nt, 0, start + k


# =============================================================================================
# Hold-back re-sorting
# =============================================================================================
class _Reorderer:
    """Release events in time order although the source may be locally out of order.

    Events earlier than the latest decoded time by at most ``window_us`` may still arrive, so
    events later than ``tmax - window_us`` are held back until the next push (or flush).
    """

    def __init__(self, window_us: int):
        self.window_us = int(window_us)
        self.pending = empty_events()
        self.seen_disorder = 0

    def push(self, ev: np.ndarray, disorder: int, tmax: int, final: bool = False) -> np.ndarray:
        if len(self.pending):
            ev = np.concatenate([self.pending, ev])
        ev, held = self.split(ev, disorder, tmax, final)
        self.pending = held.copy() if len(held) else empty_events()
        return ev

    def split(self, ev: np.ndarray, disorder: int, tmax: int, final: bool = False):
        """``(released, held)``: ``ev`` (the held events of the last split first, then the new ones)
        re-sorted if the decoder saw disorder since, cut where later events could still precede."""
        if disorder > self.seen_disorder:
            self.seen_disorder = disorder
            ev = ev[np.argsort(ev["t"], kind="stable")]
        if final or self.window_us == 0 or len(ev) == 0:
            return ev, ev[len(ev):]
        cut = int(np.searchsorted(ev["t"], tmax - self.window_us, side="right"))
        return ev[:cut], ev[cut:]


def _triggers_from(tt, tc, te, nt) -> np.ndarray:
    tr = np.empty(nt, TRIGGER_DTYPE)
    if nt:
        tr["t"] = tt[:nt]
        tr["channel"] = tc[:nt]
        tr["edge"] = te[:nt]
        if np.any(tr["t"][1:] < tr["t"][:-1]):
            tr = tr[np.argsort(tr["t"], kind="stable")]
    return tr


# =============================================================================================
# Public stream decoders
# =============================================================================================
class _StreamDecoder:
    """Stateful decoder of a byte stream split into arbitrary pieces."""

    _core_cls = _Core

    def __init__(self, sensor_size=None, *, reorder_window_us: int = DEFAULT_REORDER_WINDOW_US,
                 strict: bool = True, **core_options):
        ss = SensorSize.from_any(sensor_size)
        self.sensor_size = ss
        if int(reorder_window_us) < 0:
            raise ValueError(f"reorder_window_us must be >= 0 µs, got {reorder_window_us}")
        w, h = (2048, 2048) if ss is None else (ss.width, ss.height)
        self._core = self._core_cls(w, h, reorder_window_us, strict, **core_options)
        self._reorder = _Reorderer(reorder_window_us)
        self._carry = b""
        self.bytes_consumed = 0

    def decode(self, buf) -> tuple[np.ndarray, np.ndarray]:
        """Decode the next piece of the stream.

        Parameters
        ----------
        buf : bytes, bytearray, memoryview or ndarray
            Any number of bytes; a partial word at the end is kept for the next call.

        Returns
        -------
        events : ndarray of shape (N,), dtype EVENT_DTYPE
            Events (``t`` in µs) released so far, in time order. Events within the reorder window
            of the latest time are held back until the next call or :meth:`flush`.
        triggers : ndarray of shape (M,), dtype TRIGGER_DTYPE

        Raises
        ------
        FormatError
            On corrupt data; ``offset`` counts bytes from the start of the stream.
        """
        if isinstance(buf, np.ndarray):
            data = np.ascontiguousarray(buf).view(np.uint8).reshape(-1).tobytes()
        else:
            data = bytes(buf)
        if self._carry:
            data = self._carry + data
        wb = self._core.word_bytes
        whole = len(data) - len(data) % wb
        self._carry = data[whole:]
        arr = np.frombuffer(data, np.uint8, whole)
        ev, tr = self._decode_words(self._core.words(arr))
        self.bytes_consumed += whole
        return self._reorder.push(ev, int(self._core.st[K.ST_DISORDER]), int(self._core.st[K.ST_TMAX])), tr

    def flush(self) -> tuple[np.ndarray, np.ndarray]:
        """Events held back for re-sorting (and no triggers); call at the end of the stream.

        Raises
        ------
        FormatError
            If the stream ended with a partial word.
        """
        if self._carry:
            raise FormatError(None, f"stream ends with {len(self._carry)} byte(s) of a partial "
                                    f"{self._core.word_bytes}-byte {self._core.format_name} word",
                              offset=self.bytes_consumed)
        ev = self._reorder.push(empty_events(), int(self._core.st[K.ST_DISORDER]),
                                int(self._core.st[K.ST_TMAX]), final=True)
        return ev, empty_triggers()

    def _decode_words(self, words):
        core = self._core
        nw = core.n_words(words)
        cap = max(16, core.estimate(nw) + core.max_per_word)
        raw = np.empty(2 * cap, np.int64)
        tt = np.empty(_TRIG_CAP, np.int64)
        tc = np.empty(_TRIG_CAP, np.uint16)
        te = np.empty(_TRIG_CAP, np.int8)
        trigs = []
        n = nt = 0
        pos = 0
        while pos < nw:
            pos, n, nt, err, epos = core.run(words, pos, raw, n, cap, tt, tc, te, nt, _TRIG_CAP)
            if err:
                raise FormatError(None, core.describe(err), offset=self.bytes_consumed + epos * core.word_bytes)
            if pos < nw:
                if nt >= _TRIG_CAP:
                    trigs.append(_triggers_from(tt, tc, te, nt))
                    nt = 0
                else:
                    cap = cap + max(cap // 2, core.max_per_word * 64)
                    raw.resize(2 * cap, refcheck=False)
        trigs.append(_triggers_from(tt, tc, te, nt))
        raw.resize(2 * n, refcheck=False)
        tr = np.concatenate(trigs) if len(trigs) > 1 else trigs[0]
        return raw.view(EVENT_DTYPE), tr


class Evt3Decoder(_StreamDecoder):
    """Streaming EVT 3.0 decoder (e.g. for ``event_camera_msgs/EventPacket`` payloads).

    Parameters
    ----------
    sensor_size : SensorSize or (height, width), optional
        Coordinates are checked against it (else only against the 11-bit range).
    reorder_window_us : int, default 1000
        Tolerated local time disorder in µs (see the module docstring).
    strict : bool, default True
        Unused word types raise :class:`FormatError`.

    Examples
    --------
    >>> dec = Evt3Decoder((720, 1280), reorder_window_us=0)
    >>> ev, tr = dec.decode(bytes([0x00, 0x80, 0x05, 0x60, 0x07, 0x00, 0x03, 0x28]))
    >>> ev[["t", "x", "y", "p"]].tolist()
    [(5, 3, 7, 1)]
    """

    _core_cls = _Evt3Core


class Evt2Decoder(_StreamDecoder):
    """Streaming EVT 2.0 decoder; parameters as in :class:`Evt3Decoder`."""

    _core_cls = _Evt2Core


class Evt21Decoder(_StreamDecoder):
    """Streaming EVT 2.1 decoder; ``legacy=True`` for ``endianness=legacy`` streams (header
    word in bytes 0-3); other parameters as in :class:`Evt3Decoder`."""

    _core_cls = _Evt21Core

    def __init__(self, sensor_size=None, *, legacy: bool = False, **options):
        super().__init__(sensor_size, legacy=legacy, **options)


def _one_shot(dec: _StreamDecoder, buf):
    ev, tr = dec.decode(buf)
    ev2, _ = dec.flush()
    if len(ev2):
        ev = np.concatenate([ev, ev2]) if len(ev) else ev2
    return ev, tr


def decode_evt3(buf, sensor_size=None, **options) -> tuple[np.ndarray, np.ndarray]:
    """Decode a complete EVT 3.0 byte buffer (no header) into ``(events, triggers)``."""
    return _one_shot(Evt3Decoder(sensor_size, **options), buf)


def decode_evt2(buf, sensor_size=None, **options) -> tuple[np.ndarray, np.ndarray]:
    """Decode a complete EVT 2.0 byte buffer (no header) into ``(events, triggers)``."""
    return _one_shot(Evt2Decoder(sensor_size, **options), buf)


def decode_evt21(buf, sensor_size=None, *, legacy: bool = False, **options):
    """Decode a complete EVT 2.1 byte buffer (no header) into ``(events, triggers)``."""
    return _one_shot(Evt21Decoder(sensor_size, legacy=legacy, **options), buf)


# =============================================================================================
# Readers
# =============================================================================================
# "frame_encoding" is common to every reader (EventFileReader); these formats hold no frames.
_READER_OPTIONS = {"sensor_size", "block_bytes", "reorder_window_us", "strict", "allow_truncated",
                   "parallel", "frame_encoding"}


class _PropheseeReader(EventFileReader):
    """Common part of the RAW and DAT readers (header, block reading, chunking)."""

    _core_cls = _Core
    _max_coord = 2048

    def __init__(self, path, **options):
        super().__init__(path, **options)
        unknown = set(options) - _READER_OPTIONS
        if unknown:
            raise TypeError(f"{type(self).__name__}: unknown option(s) {sorted(unknown)}; expected "
                            f"some of {sorted(_READER_OPTIONS)}")
        self.block_bytes = int(options.get("block_bytes", DEFAULT_BLOCK_BYTES))
        if self.block_bytes < 1:
            raise ValueError(f"block_bytes must be >= 1 (rounded to whole words), got {self.block_bytes}")
        self.reorder_window_us = int(options.get("reorder_window_us", DEFAULT_REORDER_WINDOW_US))
        if self.reorder_window_us < 0:
            raise ValueError(f"reorder_window_us must be >= 0 µs, got {self.reorder_window_us}")
        self.strict = bool(options.get("strict", True))
        self.allow_truncated = bool(options.get("allow_truncated", False))
        #: counters of the last full pass: ``out_of_order_events`` (re-sorted within the window)
        self.stats: dict = {}
        data, complete = _read_head(self.path)
        if not data.startswith(b"%"):
            raise FormatError(self.path, f"expected a Prophesee '%' header, found {data[:16]!r}", offset=0)
        self.header = parse_header(data, complete=complete, path=self.path)
        self._data_offset = self.header.data_offset
        self._check_header(data)
        if self.sensor_size is None:
            self.sensor_size = _geometry(self.header, self.path)
        ss = self.sensor_size
        if ss is not None and (ss.width > self._max_coord or ss.height > self._max_coord):
            raise FormatError(self.path, f"sensor size {ss} exceeds the {self._max_coord}-pixel "
                                         f"coordinate range of {self.format_name}")
        self._file_size = self.path.stat().st_size
        model = self.header.get_ci("plugin_name") or self.header.get_ci("system_ID") or ""
        serial = self.header.get_ci("serial_number") or ""
        self.metadata = Metadata(
            event_camera=CameraInfo(ss, str(model), str(serial)),
            provenance={"source_file": str(self.path), "format": self.format_name,
                        "header": dict(self.header)})

    # -- per format ----------------------------------------------------------------------------
    def _check_header(self, data: bytes) -> None:
        declared = _raw_format_of(self.header)
        if declared is not None and declared != self.format_name:
            raise FormatError(self.path, f"the header declares {declared!r} "
                                         f"({self.header.get_ci('format') or self.header.get_ci('evt')}) "
                                         f"but the file is being read as {self.format_name!r}", offset=0)
        if self._data_offset >= len(data) and self._data_offset == self.path.stat().st_size:
            raise FormatError(self.path, "the file holds a header but no event data; expected "
                                         f"{self.format_name} words after the header",
                              offset=self._data_offset)

    def _new_core(self) -> _Core:
        ss = self.sensor_size
        w, h = (self._max_coord, self._max_coord) if ss is None else (ss.width, ss.height)
        core = self._core_cls(w, h, self.reorder_window_us, self.strict)
        core.parallel = bool(self.options.get("parallel", False))
        return core

    # -- block reading ---------------------------------------------------------------------------
    def _blocks(self, core: _Core) -> Iterator[tuple[np.ndarray, int]]:
        """Yield ``(words, byte_offset)``; the buffer is reused, so consume each before the next."""
        wb = core.word_bytes
        bb = max(wb, self.block_bytes - self.block_bytes % wb)
        buf = np.empty(bb, np.uint8)
        mv = memoryview(buf)
        off = self._data_offset
        with open(self.path, "rb", buffering=0) as f:
            f.seek(off)
            while True:
                got = 0
                while got < bb:
                    k = f.readinto(mv[got:])
                    if not k:
                        break
                    got += k
                whole = got - got % wb
                if whole:
                    yield core.words(buf[:whole]), off
                    off += whole
                if got < bb:
                    if got % wb and not self.allow_truncated:
                        raise FormatError(self.path, f"file ends with {got % wb} byte(s) of a partial "
                                                     f"{wb}-byte {core.format_name} "
                                                     f"{'record' if self.format_name == 'dat' else 'word'} "
                                                     "(truncated file?); expected whole "
                                                     f"{wb}-byte units after the header", offset=off)
                    return

    def _error(self, core: _Core, err: int, offset: int) -> FormatError:
        return FormatError(self.path, core.describe(err), offset=offset)

    # -- streaming -------------------------------------------------------------------------------
    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        core = self._new_core()
        reorder = _Reorderer(self.reorder_window_us)
        wb = core.word_bytes
        mpw = core.max_per_word
        cap = chunk_events + mpw
        raw = np.empty(2 * cap, np.int64)
        tcap = min(_TRIG_CAP, max(1, chunk_events))
        tt = np.empty(tcap, np.int64)
        tc = np.empty(tcap, np.uint16)
        te = np.empty(tcap, np.int8)
        # the events held back for re-sorting (h of them) are copied to the start of the next
        # buffer and the kernel decodes after them: no concatenation of whole chunks
        h = n = nt = 0  # n counts the held events too
        for words, off in self._blocks(core):
            nw = core.n_words(words)
            pos = 0
            while pos < nw:
                pos, n, nt, err, epos = core.run(words, pos, raw, n, h + cap, tt, tc, te, nt, tcap)
                if err:
                    raise self._error(core, err, off + epos * wb)
                if pos < nw or n - h >= chunk_events:
                    ev, held = reorder.split(raw[:2 * n].view(EVENT_DTYPE), int(core.st[K.ST_DISORDER]),
                                             int(core.st[K.ST_TMAX]))
                    tr = _triggers_from(tt, tc, te, nt)
                    if len(ev) or len(tr):
                        yield EventChunk(ev, tr)
                    h = n = len(held)
                    raw = np.empty(2 * (h + cap), np.int64)
                    raw[:2 * h] = held.view(np.int64)
                    nt = 0
        ev, _ = reorder.split(raw[:2 * n].view(EVENT_DTYPE), int(core.st[K.ST_DISORDER]),
                              int(core.st[K.ST_TMAX]), final=True)
        tr = _triggers_from(tt, tc, te, nt)
        self.stats = {"out_of_order_events": int(core.st[K.ST_DISORDER])}
        if len(ev) or len(tr):
            yield EventChunk(ev, tr)

    def read_all(self) -> EventChunk:
        """Decode the whole file into one event array (the fast path).

        Returns
        -------
        EventChunk
            ``events`` of shape (N,), dtype EVENT_DTYPE (``t`` in µs, sorted) and ``triggers``.

        Raises
        ------
        FormatError
            On corrupt or truncated data, with the byte offset.
        """
        core = self._new_core()
        wb = core.word_bytes
        mpw = core.max_per_word
        nbytes = max(0, self._file_size - self._data_offset)
        if core.counts:  # exact upper bound from a cheap first pass (no regrowth of the output)
            cap = sum(core.count(words) for words, _ in self._blocks(core)) + mpw
        else:
            cap = core.estimate(nbytes // wb) + mpw
        raw = np.empty(2 * cap, np.int64)
        tt = np.empty(_TRIG_CAP, np.int64)
        tc = np.empty(_TRIG_CAP, np.uint16)
        te = np.empty(_TRIG_CAP, np.int8)
        trigs = []
        n = nt = 0
        for words, off in self._blocks(core):
            nw = core.n_words(words)
            pos = 0
            while pos < nw:
                pos, n, nt, err, epos = core.run(words, pos, raw, n, cap, tt, tc, te, nt, _TRIG_CAP)
                if err:
                    raise self._error(core, err, off + epos * wb)
                if pos < nw:
                    if nt >= _TRIG_CAP:
                        trigs.append(_triggers_from(tt, tc, te, nt))
                        nt = 0
                    else:
                        cap = cap + max(cap // 2, mpw * (nw - pos) // 4 + mpw)
                        raw.resize(2 * cap, refcheck=False)
        trigs.append(_triggers_from(tt, tc, te, nt))
        raw.resize(2 * n, refcheck=False)
        ev = raw.view(EVENT_DTYPE)
        dis = int(core.st[K.ST_DISORDER])
        if dis:
            ev = ev[np.argsort(ev["t"], kind="stable")]
        self.stats = {"out_of_order_events": dis}
        tr = np.concatenate(trigs) if len(trigs) > 1 else trigs[0]
        if len(trigs) > 1 and np.any(tr["t"][1:] < tr["t"][:-1]):
            tr = tr[np.argsort(tr["t"], kind="stable")]
        return EventChunk(ev, tr)

    def read(self, t_start_us=None, t_end_us=None) -> Recording:
        """Read the whole file (or the window ``[t_start_us, t_end_us)``) into a Recording."""
        if t_start_us is not None or t_end_us is not None:
            return super().read(t_start_us, t_end_us)
        c = self.read_all()
        return Recording(c.events, self.sensor_size, None, c.triggers, None, self.metadata)


class Evt2Reader(_PropheseeReader):
    """Prophesee RAW EVT 2.0 reader (options in the module docstring).

    Examples
    --------
    >>> from hybridhdr import open_reader  # doctest: +SKIP
    >>> rec = open_reader("sparklers_gen3_evt2.raw").read()  # doctest: +SKIP
    """

    format_name = "evt2"
    _core_cls = _Evt2Core


class Evt21Reader(_PropheseeReader):
    """Prophesee RAW EVT 2.1 reader; the byte order comes from ``endianness=legacy`` in the
    ``format`` header line (or the ``legacy=`` option, which overrides it)."""

    format_name = "evt21"
    _core_cls = _Evt21Core

    def __init__(self, path, *, legacy: bool | None = None, **options):
        super().__init__(path, **options)
        if legacy is None:
            _, fields = _format_fields(self.header)
            legacy = fields.get("endianness", "").lower() == "legacy"
        self.legacy = bool(legacy)
        self.metadata.provenance["endianness"] = "legacy" if self.legacy else "little"

    def _new_core(self):
        ss = self.sensor_size
        w, h = (self._max_coord, self._max_coord) if ss is None else (ss.width, ss.height)
        return _Evt21Core(w, h, self.reorder_window_us, self.strict, legacy=self.legacy)


class Evt3Reader(_PropheseeReader):
    """Prophesee RAW EVT 3.0 reader (options in the module docstring)."""

    format_name = "evt3"
    _core_cls = _Evt3Core


class DatReader(_PropheseeReader):
    """Prophesee DAT reader (CD events, type 0 or 12, 8-byte records).

    DAT holds no triggers here; files of other event types (14 ExtTrigger, 40 OpticalFlow) raise
    :class:`FormatError`. Bits 29-31 of the packed word are ignored.
    """

    format_name = "dat"
    _core_cls = _DatCore
    _max_coord = 16384

    def _check_header(self, data: bytes) -> None:
        declared = _raw_format_of(self.header)
        if declared is not None:
            raise FormatError(self.path, f"the header declares a RAW {declared!r} file, not DAT", offset=0)
        off = self._data_offset
        size = self.path.stat().st_size
        if size < off + 2:
            raise FormatError(self.path, f"file ends after the header ({size - off} of the 2 bytes "
                                         "event type + event size); expected a DAT type and size byte",
                              offset=size)
        typ, esize = data[off], data[off + 1]
        if typ in _DAT_OTHER_TYPES:
            raise FormatError(self.path, f"DAT event type {typ} ({_DAT_OTHER_TYPES[typ]}) holds no CD "
                                         f"events; expected type 0 or 12 (CD)", offset=off)
        if typ not in _DAT_CD_TYPES or esize != 8:
            raise FormatError(self.path, f"unknown DAT event type {typ} / size {esize}; expected type 0 "
                                         "or 12 (CD events) with size 8", offset=off)
        self.dat_event_type = int(typ)
        self._data_offset = off + 2


READERS = {"evt2": Evt2Reader, "evt21": Evt21Reader, "evt3": Evt3Reader, "dat": DatReader}


# =============================================================================================
# Writers
# =============================================================================================
def _now() -> str:
    return datetime.datetime.now().strftime("%Y-%m-%d %H:%M:%S")


def _clean(s) -> str:
    return " ".join(str(s).split())


class _EvtWriter(EventFileWriter):
    """Common part of the EVT 2.0 / 3.0 writers (header, trigger merging, encoding)."""

    supports = frozenset({"triggers"})
    _evt = ""
    _fmt = ""
    _max_channel = 16
    _word_dtype = np.uint32

    def _open(self) -> None:
        ss = self.sensor_size
        if ss.width > 2048 or ss.height > 2048:
            raise ValueError(f"{self.format_name} holds 11-bit coordinates; sensor {ss} exceeds 2048x2048")
        self._f = open(self.tmp_path, "wb")
        cam = self.metadata.event_camera
        lines = [f"date {_now()}", f"evt {self._evt}", f"format {self._fmt};height={ss.height};width={ss.width}",
                 f"geometry {ss.width}x{ss.height}", "integrator_name hybridhdr"]
        if cam.model:
            lines.append(f"plugin_name {_clean(cam.model)}")
        if cam.serial:
            lines.append(f"serial_number {_clean(cam.serial)}")
        lines.append("end")
        self._f.write("".join(f"% {s}\n" for s in lines).encode("utf-8"))
        self._es = np.full(4, -1, np.int64)
        self._pending_ev = None
        self._pending_tr = empty_triggers()
        self._encoded_t = -1  # latest time already encoded
        self._words_written = 0

    def _write_events(self, events: np.ndarray) -> None:
        if events["t"][0] < 0:
            raise ValueError(f"{self.path}: timestamps must be >= 0 µs, got {int(events['t'][0])}")
        if events["t"][-1] >= EVT_MAX_T_US:
            raise ValueError(f"{self.path}: timestamps must be < 2^44 µs, got {int(events['t'][-1])}")
        cols = (np.ascontiguousarray(events["t"]), np.ascontiguousarray(events["x"]),
                np.ascontiguousarray(events["y"]), np.ascontiguousarray(events["p"]))
        if self._pending_ev is not None:
            self._flush(upto_t=int(cols[0][0]))
        self._pending_ev = cols

    def _write_triggers(self, triggers: np.ndarray) -> None:
        tr = np.asarray(triggers)
        t = tr["t"]
        if np.any(t < 0):
            raise ValueError(f"{self.path}: trigger timestamps must be >= 0 µs, got {int(t.min())}")
        if np.any(t >= EVT_MAX_T_US):
            raise ValueError(f"{self.path}: trigger timestamps must be < 2^44 µs, got {int(t.max())}")
        if np.any(tr["channel"] >= self._max_channel):
            raise ValueError(f"{self.path}: {self.format_name} trigger channels must be < "
                             f"{self._max_channel}, got {int(tr['channel'].max())}")
        if np.any((tr["edge"] != 1) & (tr["edge"] != -1)):
            raise ValueError(f"{self.path}: trigger edges must be +1 or -1")
        if len(t) and int(t.min()) < self._encoded_t:
            raise ValueError(f"{self.path}: trigger at {int(t.min())} µs is earlier than events already "
                             f"encoded (up to {self._encoded_t} µs); {self.format_name} stores words in time "
                             "order, so write triggers with (or before) the next events")
        allt = np.concatenate([self._pending_tr, tr])
        self._pending_tr = allt[np.argsort(allt["t"], kind="stable")]

    def _flush(self, upto_t: int | None) -> None:
        """Encode the pending events with the pending triggers at or before ``upto_t`` (all: None)."""
        tr = self._pending_tr
        k = len(tr) if upto_t is None else int(np.searchsorted(tr["t"], upto_t, side="right"))
        use, self._pending_tr = tr[:k], tr[k:]
        if self._pending_ev is None:
            t, x, y, p = (np.zeros(0, np.int64), np.zeros(0, np.uint16), np.zeros(0, np.uint16),
                          np.zeros(0, np.int8))
        else:
            t, x, y, p = self._pending_ev
        self._pending_ev = None
        if len(t) == 0 and k == 0:
            return
        tt = np.ascontiguousarray(use["t"])
        tch = np.ascontiguousarray(use["channel"])
        te = np.ascontiguousarray(use["edge"])
        tmax = max(int(t[-1]) if len(t) else 0, int(tt[-1]) if k else 0)
        nmax = self._capacity(len(t) + k, tmax)
        out = np.empty(nmax, self._word_dtype)
        nw = self._encode(t, x, y, p, tt, tch, te, out)
        self._f.write(memoryview(out[:nw]))
        self._words_written += nw
        self._encoded_t = max(self._encoded_t, tmax)

    def _finish(self) -> None:
        self._flush(None)
        if self._words_written == 0:
            # never leave a header-only file: one TIME_HIGH word at t = 0
            out = np.zeros(1, self._word_dtype)
            out[0] = 8 << (28 if self._word_dtype == np.uint32 else 12)
            self._f.write(memoryview(out))
        self._f.close()

    def _cleanup(self) -> None:
        f = getattr(self, "_f", None)
        if f is not None and not f.closed:
            f.close()


class Evt2Writer(_EvtWriter):
    """Prophesee RAW EVT 2.0 writer (events and triggers on channels 0-31).

    Examples
    --------
    >>> import hybridhdr, tempfile, os
    >>> ev = hybridhdr.make_events([0, 70, 70], [1, 2, 3], [4, 5, 6], [1, -1, 1])
    >>> path = os.path.join(tempfile.mkdtemp(), "a.raw")
    >>> with Evt2Writer(path, sensor_size=(480, 640)) as w:
    ...     w.write_events(ev)
    >>> Evt2Reader(path).read().events["t"].tolist()
    [0, 70, 70]
    """

    format_name = "evt2"
    _evt = "2.0"
    _fmt = "EVT2"
    _max_channel = 32
    _word_dtype = np.uint32

    def _capacity(self, n, tmax):
        cur = max(0, int(self._es[0]))
        return 2 * n + 2 * ((tmax >> 34) - (cur >> 28) + 2) + 8

    def _encode(self, t, x, y, p, tt, tch, te, out):
        return K.evt2_encode(t, x, y, p, tt, tch, te, self._es, out)


class Evt3Writer(_EvtWriter):
    """Prophesee RAW EVT 3.0 writer with vector encoding (triggers on channels 0-15).

    Options
    -------
    use_vectors : bool, default True
        Encode runs of neighbouring same-row, same-time, same-polarity events as VECT_12/VECT_8.
    """

    format_name = "evt3"
    _evt = "3.0"
    _fmt = "EVT3"
    _max_channel = 16
    _word_dtype = np.uint16

    def _open(self):
        unknown = set(self.options) - {"use_vectors"}
        if unknown:
            raise TypeError(f"Evt3Writer: unknown option(s) {sorted(unknown)}")
        self._use_vectors = bool(self.options.get("use_vectors", True))
        super()._open()

    def _capacity(self, n, tmax):
        cur = max(0, int(self._es[0]))
        return 4 * n + 2 * ((tmax >> 24) - (cur >> 12) + 2) + 8

    def _encode(self, t, x, y, p, tt, tch, te, out):
        return K.evt3_encode(t, x, y, p, tt, tch, te, self._es, out, self._use_vectors)


class DatWriter(EventFileWriter):
    """Prophesee DAT writer (CD events, type 12, 8-byte records).

    The 32-bit time field wraps every 2^32 µs; readers unwrap it from consecutive differences, so
    the first timestamp must be < 2^32 µs and consecutive events less than 2^31 µs (35.8 min)
    apart, else ``ValueError``. Triggers are not stored.

    :meth:`write_events` checks and packs contiguous event arrays in one kernel pass
    (:func:`._kernels.dat_encode`); arrays it refuses, and other layouts, take the base class's
    path, whose checks name the problem.
    """

    format_name = "dat"

    def _open(self) -> None:
        ss = self.sensor_size
        if ss.width > 16384 or ss.height > 16384:
            raise ValueError(f"DAT holds 14-bit coordinates; sensor {ss} exceeds 16384x16384")
        self._f = open(self.tmp_path, "wb")
        lines = ["Data file containing CD events.", "Version 2", f"Date {_now()}",
                 f"Height {ss.height}", f"Width {ss.width}"]
        self._f.write("".join(f"% {s}\n" for s in lines).encode("ascii"))
        self._f.write(bytes([12, 8]))
        self._buf = np.empty(0, np.uint32)  # output words, reused (grown to the largest batch)

    def write_events(self, events: np.ndarray) -> None:
        """Append events; they must continue the time order of everything written so far."""
        if (not self._closed and isinstance(events, np.ndarray) and events.dtype == EVENT_DTYPE
                and events.ndim == 1 and events.flags.c_contiguous and len(events)):
            packed = self._pack(events)
            if packed is not None:  # valid (as the base class checks them) and packed
                self._store(events, *packed)
                self._last_t = int(events["t"][-1])
                self.n_events += len(events)
                return
        super().write_events(events)

    def _write_events(self, events: np.ndarray) -> None:
        # the base class's path: events already checked (order, polarity, coordinates)
        if not events.flags.c_contiguous:
            events = np.ascontiguousarray(events)
        packed = self._pack(events)
        if packed is None:  # pragma: no cover - validated by the base class
            raise ValueError(f"{self.path}: events failed the DAT writer's checks after validation")
        self._store(events, *packed)

    def _pack(self, events: np.ndarray):
        """``(words, gap)``: the DAT words of ``events`` (a view of the reused buffer) and the
        largest time step (µs); None if an event is out of time order (also with the last event
        written), has p not +1 or -1 or lies outside the sensor."""
        n2 = 2 * len(events)
        if len(self._buf) < n2:
            self._buf = np.empty(n2, np.uint32)
        words = self._buf[:n2]
        prev = int(events["t"][0]) if self._last_t is None else self._last_t
        bad, gap = K.dat_encode(events.view(np.int64), prev, self.sensor_size.width,
                                self.sensor_size.height, words)
        return None if bad >= 0 else (words, gap)

    def _store(self, events: np.ndarray, words: np.ndarray, gap: int) -> None:
        """Check the DAT time limits of packed ``events`` and append their ``words``."""
        t0 = int(events["t"][0])
        if t0 < 0:
            raise ValueError(f"{self.path}: timestamps must be >= 0 µs, got {t0}")
        if self._last_t is None and t0 >= 1 << 32:
            raise ValueError(f"{self.path}: the first DAT timestamp must be < 2^32 µs (71.6 min), got "
                             f"{t0}; subtract an offset first")
        if gap >= 1 << 31:
            raise ValueError(f"{self.path}: DAT cannot store a gap of 2^31 µs (35.8 min) or more between "
                             "consecutive events (its 32-bit time would be ambiguous)")
        self._f.write(memoryview(words).cast("B"))

    def _finish(self) -> None:
        self._f.close()

    def _cleanup(self) -> None:
        f = getattr(self, "_f", None)
        if f is not None and not f.closed:
            f.close()


WRITERS = {"evt2": Evt2Writer, "evt3": Evt3Writer, "dat": DatWriter}

register_formats(__name__, {
    "evt2": "Prophesee RAW EVT 2.0 (.raw)",
    "evt21": "Prophesee RAW EVT 2.1, standard or legacy byte order (.raw)",
    "evt3": "Prophesee RAW EVT 3.0 (.raw)",
    "dat": "Prophesee DAT CD events (.dat)",
}, READERS, WRITERS)


# =============================================================================================
# EVT 2.1 encoder (tests and benchmarks only: Prophesee's cameras write EVT 2.1 themselves)
# =============================================================================================
def _encode_evt21(events: np.ndarray, legacy: bool = False) -> bytes:
    """Encode sorted events as EVT 2.1 64-bit words (no header, no 2^34 µs loop bridging).

    Consecutive events with equal t, y and p, the same 32-column group (x >> 5) and strictly
    increasing x share one word (mask bit x & 31 over base x & ~31), so decoding restores the exact
    order. A TIME_HIGH word precedes each change of t >> 6. ``legacy`` puts the header in bytes
    0-3 and the mask in bytes 4-7; otherwise the whole word is little-endian (mask first).
    """
    n = len(events)
    if n == 0:
        words = np.array([[0, 8 << 28]], np.uint32)
        return (words[:, ::-1] if legacy else words).tobytes()
    t = events["t"].astype(np.int64)
    x = events["x"].astype(np.int64)
    y = events["y"].astype(np.int64)
    p = events["p"]
    new = np.ones(n, bool)
    new[1:] = ((t[1:] != t[:-1]) | (y[1:] != y[:-1]) | (p[1:] != p[:-1])
               | ((x[1:] >> 5) != (x[:-1] >> 5)) | (x[1:] <= x[:-1]))
    starts = np.flatnonzero(new)
    mask = np.bitwise_or.reduceat(np.left_shift(np.int64(1), x & 31), starts).astype(np.uint32)
    gt, gx, gy, gp = t[starts], x[starts] & ~31, y[starts], p[starts]
    header = ((np.where(gp > 0, 1, 0) << 28) | ((gt & 63) << 22) | (gx << 11) | gy).astype(np.uint32)
    hi = gt >> 6
    th_needed = np.ones(len(starts), bool)
    th_needed[1:] = hi[1:] != hi[:-1]
    nth = int(th_needed.sum())
    words = np.zeros((len(starts) + nth, 2), np.uint32)  # [mask, header]
    pos = np.arange(len(starts)) + np.cumsum(th_needed)
    words[pos, 0] = mask
    words[pos, 1] = header
    words[pos[th_needed] - 1, 1] = ((8 << 28) | (hi[th_needed] & 0xFFFFFFF)).astype(np.uint32)
    if legacy:
        words = words[:, ::-1]
    return np.ascontiguousarray(words).tobytes()
