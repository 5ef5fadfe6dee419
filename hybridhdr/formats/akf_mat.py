"""AKF MATLAB ``.mat`` files (format ``akf_mat``): reader of v7.3 and v5, writer of v7.3.

The datasets of Wang et al., "An Asynchronous Kalman Filter for Hybrid Event Cameras", ICCV 2021
(doi:10.1109/ICCV48922.2021.00050; ``ziweiWWANG/AKF``) are MATLAB files holding

* ``events`` N x 4 double: ``[t (µs), x, y, p]`` with **1-based** x and y, ``p == 1`` ON, any
  other value OFF;
* ``image`` H x W x K uint8 frames, ``time_image`` (K values, mid-exposure µs), ``exposure``
  (µs, one per frame or a scalar);
* ``im_height``, ``im_width`` (sensor size), ``ct`` (contrast threshold), ``f_Q`` (256-entry
  intensity confidence LUT) and optionally ``HDR_mat`` H x W x 3 x K (HDR references).

MATLAB v7.3 files are HDF5 with a 512-byte MATLAB header as the HDF5 user block; h5py returns each
array with its axes reversed (``events`` reads as 4 x N), which this module undoes. v5 files are
parsed by :func:`read_mat5`, a small bounds-checked reader of numeric variables written from the
MAT-file format description (MathWorks, "MAT-File Format", level 5): ``scipy.io.loadmat`` crashes
the interpreter (segmentation fault) on some corrupt files, found by fuzzing.

Conversions:

* ``t`` rounded to int64 µs with ``np.rint`` (AKF stores whole µs in doubles, so this is exact);
  x, y -> 0-based uint16; p -> +1/-1.
* Frames: ``t_start_us = rint(time_image - exposure / 2)`` and
  ``t_end_us = t_start_us + rint(exposure)``; without ``exposure`` both equal ``rint(time_image)``.
  The writer stores ``time_image = t_start_us + (t_end_us - t_start_us) / 2`` (a multiple of
  0.5 µs, exact in a double), so integer exposure intervals round-trip exactly.
* ``ct`` and ``f_Q`` go to ``metadata.provenance["akf_mat"]``; ``HDR_mat`` is read by
  :meth:`AkfMatReader.read_hdr` and becomes the recording's HDR references in ``read()``, as
  stored (the authors' HDR and AHDR sequences: registered RGB in the frames' code units, so
  ``HDR_mat / 255`` is in frame-linear units; **0 marks unregistered pixels**, which their
  evaluation masks out: ``hybridhdr evaluate metrics --protocol akf2021``).

Detection: the MATLAB text header at byte 0 (v7.3 and v5), or, for a v7.3-style HDF5 file
written without MATLAB's header, HDF5 holding ``events`` together with ``time_image`` and
``image`` or ``HDR_mat`` (the keys of the authors' files).

Frame encoding and ``f_Q``: the files state no transfer function for ``image``, and the authors'
code (``ziweiWWANG/AKF:akf_reconstruction.m``) reads the codes as linear
intensity, ``I = I^F / 255``, with no inverse CRF: the CRF enters only through ``f_Q``. So the
frames are ``encoding="unknown"`` unless the ``frame_encoding`` option declares one. ``f_Q`` is
the inverse of eq. 6's R̄ per code (README; ``f_Q = 7e5 * max(f_w, 0.09)``), and is honoured as a
camera profile in ``metadata.provenance["camera_profile"]`` (:func:`profile_from_f_q`):
``frame_precision_scale = max(f_Q)``, ``weighting = f_Q / max(f_Q)``, ``min_weighting =
min(weighting)``, so ``1 / (scale * max(weighting, min_weighting)) = 1 / f_Q`` per code; its
``inverse_crf`` follows the frame encoding (linear, as in the authors' code, unless one is
declared: ``(code/255)**2.2`` for ``gamma2.2``, the IEC 61966-2-1 curve for ``srgb``). The
writer writes ``f_Q`` back from such a profile.
"""

from __future__ import annotations

import dataclasses

import time
from pathlib import Path
from typing import Iterator

import numpy as np

from .._util.limits import LimitExceeded, check_finite, check_frame_bytes, check_sensor_size
from ..camera import CameraProfile
from ..camera.encoding import inverse_crf_table, parse_frame_encoding
from ..errors import FormatError
from ..events import EVENT_DTYPE, SensorSize
from ..model import CameraInfo, Frames, HDRReferences, Metadata
from ._safe_h5 import close_and_remove, open_h5_for_writing
from .base import EventChunk, EventFileReader, EventFileWriter, register_formats

__all__ = ["AkfMatReader", "AkfMatWriter", "READERS", "WRITERS", "sniff", "matlab_v73_header", "read_mat5",
           "profile_from_f_q", "f_q_from_profile"]

_V73 = b"MATLAB 7.3 MAT-file"
_V5 = b"MATLAB 5.0 MAT-file"
_MATLAB_CLASS = {np.dtype(np.float64): b"double", np.dtype(np.float32): b"single",
                 np.dtype(np.uint8): b"uint8", np.dtype(np.uint16): b"uint16", np.dtype(np.int8): b"int8",
                 np.dtype(np.int16): b"int16", np.dtype(np.int32): b"int32", np.dtype(np.uint32): b"uint32",
                 np.dtype(np.int64): b"int64", np.dtype(np.uint64): b"uint64"}
_MAX_SAFE = float(1 << 53)


_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
#: Keys of the authors' datasets that identify an AKF file stored as plain HDF5 (no MATLAB header).
AKF_KEYS = ("events", "time_image")
AKF_IMAGE_KEYS = ("image", "HDR_mat")


def _has_akf_keys(path) -> bool:
    try:
        import h5py
        with h5py.File(path, "r") as f:
            keys = set(f.keys())
    except Exception:  # sniffing must never raise
        return False
    return all(k in keys for k in AKF_KEYS) and any(k in keys for k in AKF_IMAGE_KEYS)


def sniff(path: Path, head: bytes) -> str | None:
    """``"akf_mat"`` for MATLAB v7.3 or v5 MAT files (text header at byte 0), or an HDF5 file
    with the AKF keys (``events``, ``time_image`` and ``image`` or ``HDR_mat``), else None."""
    if head[:116].startswith((_V73, _V5)):
        return "akf_mat"
    if head.startswith(_HDF5_MAGIC) and _has_akf_keys(path):
        return "akf_mat"
    return None


def matlab_v73_header(created: str | None = None) -> bytes:
    """The first 128 bytes of a MATLAB v7.3 file (the rest of the 512-byte user block is zeros).

    Bytes 0-115 hold descriptive text padded with spaces, 116-123 the subsystem offset (unused),
    124-125 the version 0x0200 and 126-127 the endian indicator ``IM`` (little-endian).
    """
    created = created or time.strftime("%a %b %d %H:%M:%S %Y")
    text = f"MATLAB 7.3 MAT-file, Platform: hybridhdr, Created on: {created} HDF5 schema 1.00 .".encode("ascii")
    return text[:116].ljust(116, b" ") + b"\x00" * 8 + (0x0200).to_bytes(2, "little") + b"IM"


# MAT v5 data types (miXXX) -> NumPy element type; array classes (mxXXX) -> NumPy dtype.
_MI_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 9: "f8", 12: "i8", 13: "u8"}
_MX_CLASSES = {6: "f8", 7: "f4", 8: "i1", 9: "u1", 10: "i2", 11: "u2", 12: "i4", 13: "u4", 14: "i8", 15: "u8"}
_MX_OTHER = {1: "cell", 2: "struct", 3: "object", 4: "char", 5: "sparse", 16: "function handle", 17: "opaque"}
#: MATLAB_class values of numeric arrays in v7.3 files
_NUMERIC_CLASSES = {b"double", b"single", b"int8", b"uint8", b"int16", b"uint16", b"int32", b"uint32", b"int64",
                    b"uint64", b"logical"}
_MI_MATRIX, _MI_COMPRESSED = 14, 15
_MAX_MAT5_BYTES = 1 << 31


def _mat5_tag(path, buf: bytes, pos: int, end: int, e: str, what: str) -> tuple[int, int, int, int]:
    """``(type, nbytes, data_start, next_pos)`` of the data element at ``pos`` (bounds-checked)."""
    if pos + 8 > end:
        raise FormatError(path, f"{what}: data element tag runs past the end", offset=pos)
    word = int.from_bytes(buf[pos:pos + 4], "little" if e == "<" else "big")
    if word >> 16:  # small data element: bytes in the upper 16 bits, data in the next 4 bytes
        typ, nbytes = word & 0xFFFF, word >> 16
        if nbytes > 4:
            raise FormatError(path, f"{what}: small data element claims {nbytes} bytes", offset=pos)
        return typ, nbytes, pos + 4, pos + 8
    typ = word
    nbytes = int.from_bytes(buf[pos + 4:pos + 8], "little" if e == "<" else "big")
    start = pos + 8
    if start + nbytes > end:
        raise FormatError(path, f"{what}: element of {nbytes} bytes runs past the end ({end - start} left)",
                          offset=pos)
    nxt = start + nbytes
    if typ not in (_MI_MATRIX, _MI_COMPRESSED):
        nxt += (-nbytes) % 8  # padding to 8 bytes (may be absent at the very end)
    return typ, nbytes, start, nxt


def _mat5_matrix(path, buf: bytes, pos: int, end: int, e: str, base: int):
    """Parse one miMATRIX body ``buf[pos:end]``: returns ``(name, array)``.

    Non-numeric classes (cell, struct, char, sparse, object) give an empty object array.
    ``base`` is the file offset of the element, for error messages.
    """
    where = f"variable at byte {base}"
    typ, n, p, nxt = _mat5_tag(path, buf, pos, end, e, where)
    if typ != 6 or n != 8:
        raise FormatError(path, f"{where}: expected the 8-byte array-flags element, got type {typ}", offset=base)
    flags = int.from_bytes(buf[p:p + 4], "little" if e == "<" else "big")
    cls, complex_ = flags & 0xFF, bool(flags & 0x0800)
    typ, n, p, nxt = _mat5_tag(path, buf, nxt, end, e, where)
    if typ != 5 or n % 4 or n < 8:
        raise FormatError(path, f"{where}: invalid dimensions element (type {typ}, {n} bytes)", offset=base)
    dims = np.frombuffer(buf, e + "i4", n // 4, p).astype(np.int64)
    if (dims < 0).any():
        raise FormatError(path, f"{where}: negative dimension {dims.tolist()}", offset=base)
    typ, n, p, nxt = _mat5_tag(path, buf, nxt, end, e, where)
    if typ not in (1, 2, 16):
        raise FormatError(path, f"{where}: invalid array-name element (type {typ})", offset=base)
    try:
        name = bytes(buf[p:p + n]).decode("ascii")
    except UnicodeDecodeError:
        raise FormatError(path, f"{where}: variable name is not ASCII", offset=base) from None
    if cls not in _MX_CLASSES:
        # a 0-d object array naming the class: readers turn it into an error, never 0 events
        return name, np.array(_MX_OTHER.get(cls, f"class-{cls}"), dtype=object)
    if complex_:
        raise FormatError(path, f"{where}: variable {name!r} is complex; expected a real array", offset=base)
    count = int(np.prod(dims)) if dims.size else 0
    if count > _MAX_MAT5_BYTES:
        raise FormatError(path, f"{where}: variable {name!r} has implausible dimensions {dims.tolist()}", offset=base)
    typ, n, p, nxt = _mat5_tag(path, buf, nxt, end, e, where)
    if typ not in _MI_TYPES:
        raise FormatError(path, f"{where}: variable {name!r} has unsupported data type {typ}", offset=base)
    item = np.dtype(_MI_TYPES[typ]).itemsize
    if n != count * item:
        raise FormatError(path, f"{where}: variable {name!r} of shape {dims.tolist()} needs {count * item} data "
                                f"bytes, element has {n}", offset=base)
    data = np.frombuffer(buf, e + _MI_TYPES[typ], count, p)
    with np.errstate(all="ignore"):
        arr = data.astype(_MX_CLASSES[cls])
    return name, arr.reshape(tuple(dims.tolist()), order="F")


def read_mat5(path, names=None) -> dict:
    """Numeric variables of a MATLAB level-5 MAT-file, with every length checked.

    Parameters
    ----------
    path : str or os.PathLike
    names : collection of str, optional
        Variables to return (default all).

    Returns
    -------
    dict
        name -> ndarray in MATLAB axis order (at least 2-D, Fortran data reordered), with the
        class's dtype (``double`` -> float64, ``uint8`` -> uint8 ...). Cell, struct, char, sparse
        and object variables map to an empty object array.

    Raises
    ------
    FormatError
        On any structural problem (truncation, inconsistent sizes, bad compression).
    """
    import zlib
    import os
    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size > _MAX_MAT5_BYTES:  # never ask read() for 2 GB up front
            raise FormatError(path, "MAT v5 files are limited to 2 GB")
        buf = f.read()
    if len(buf) < 128:
        raise FormatError(path, f"truncated MAT-file header ({len(buf)} bytes)", offset=len(buf))
    e = {b"IM": "<", b"MI": ">"}.get(bytes(buf[126:128]))
    if e is None:
        raise FormatError(path, f"invalid endian indicator {bytes(buf[126:128])!r} (expected b'IM' or b'MI')",
                          offset=126)
    want = None if names is None else set(names)
    out: dict = {}
    pos = 128
    while pos < len(buf):
        if len(buf) - pos < 8 and not any(buf[pos:]):
            break  # zero padding at the end
        typ, n, p, nxt = _mat5_tag(path, buf, pos, len(buf), e, f"element at byte {pos}")
        if typ == _MI_COMPRESSED:
            from .._util.limits import LIMITS, OVERRIDE_HINT, LimitExceeded, huge_allowed
            limit = _MAX_MAT5_BYTES if huge_allowed() else min(_MAX_MAT5_BYTES, LIMITS["max_packet_bytes"])
            d = zlib.decompressobj()
            try:
                inner = d.decompress(bytes(buf[p:p + n]), limit)
            except zlib.error as exc:
                raise FormatError(path, f"corrupt compressed variable: {exc}", offset=pos) from None
            if d.unconsumed_tail:
                raise LimitExceeded(path, f"a compressed variable expands beyond {limit:,} bytes; {OVERRIDE_HINT}",
                                    offset=pos)
            ityp, inn, ip, _ = _mat5_tag(path, inner, 0, len(inner), e, f"compressed element at byte {pos}")
            if ityp != _MI_MATRIX:
                raise FormatError(path, f"compressed element holds type {ityp}, expected a matrix", offset=pos)
            name, arr = _mat5_matrix(path, inner, ip, ip + inn, e, pos)
        elif typ == _MI_MATRIX:
            if n == 0:
                pos = nxt
                continue
            name, arr = _mat5_matrix(path, buf, p, p + n, e, pos)
        else:
            raise FormatError(path, f"unexpected top-level data element type {typ} (expected a matrix)", offset=pos)
        if want is None or name in want:
            if name in out:
                raise FormatError(path, f"variable {name!r} appears twice", offset=pos)
            out[name] = arr
        pos = nxt
    return out


def profile_from_f_q(f_q, encoding: str = "unknown", source: str = ""):
    """The camera profile that reproduces an AKF ``f_Q`` table (1/R̄ per code, eq. 6).

    Parameters
    ----------
    f_q : array_like of shape (max_code + 1,)
        ``f_Q[code]``: the frame precision 1/R̄ of each code (the authors' code indexes it with
        ``round(I^F) + 1``, MATLAB's 1-based, i.e. 0-based ``f_Q[code]``). Finite, >= 0, with a
        positive maximum.
    encoding : str
        The frames' encoding; it sets the profile's ``inverse_crf``: None (linear, ``code /
        max_code``, as in the authors' code) for ``"unknown"``, ``"linear"``, ``"raw"``;
        ``decode(code)`` for ``"gamma"`` (``(code/max)**2.2``) and ``"srgb"``.
    source : str
        Where ``f_Q`` came from (stored in the profile).

    Returns
    -------
    CameraProfile
        ``frame_precision_scale = max(f_Q)``, ``weighting = f_Q / max(f_Q)``, ``min_weighting =
        min(weighting)`` (if that is 0, the smallest positive weighting: a profile cannot hold
        an infinite R̄, so zero-precision codes get the least precision of the table).

    Raises
    ------
    ValueError
        When ``f_Q`` is not a finite, non-negative table of at least 2 entries with a positive
        maximum.
    """
    fq = np.asarray(f_q, dtype=np.float64).reshape(-1)
    if fq.size < 2 or not np.isfinite(fq).all() or (fq < 0).any() or not fq.max() > 0:
        raise ValueError(f"f_Q must be a finite, non-negative table of at least 2 entries with a positive "
                         f"maximum; got {fq.size} entries in [{fq.min() if fq.size else None}, "
                         f"{fq.max() if fq.size else None}]")
    enc = parse_frame_encoding(encoding)
    scale = float(fq.max())
    w = fq / scale
    pos = w[w > 0]
    floor = float(min(1.0, pos.min()))
    return CameraProfile(weighting=w, inverse_crf=inverse_crf_table(enc, fq.size - 1),
                         frame_precision_scale=scale, min_weighting=floor, name="akf .mat f_Q", source=str(source),
                         extra={"from": "f_Q", "frame_encoding": enc,
                                "f_Q_zero_codes": int(np.count_nonzero(fq == 0)),
                                "note": "R̄ = 1/f_Q per code (AKF README; eq. 6); inverse_crf follows the frame "
                                        "encoding (None = linear code/max, the authors' reading)"})


def f_q_from_profile(profile) -> np.ndarray:
    """The AKF ``f_Q`` table of a camera profile (dict or CameraProfile): ``1 / R̄`` per code.

    ``f_Q[code] = frame_precision_scale * max(weighting[code], min_weighting)`` (eq. 6), the
    inverse of :func:`profile_from_f_q`. The profile's inverse CRF has no place in the file.
    """
    prof = profile if isinstance(profile, CameraProfile) else CameraProfile.from_dict(profile)
    return prof.frame_precision_scale * np.maximum(prof.weighting, prof.min_weighting)


def _wrap(path, what: str, exc: BaseException) -> FormatError:
    return FormatError(path, f"{what}: {type(exc).__name__}: {exc}")


class AkfMatReader(EventFileReader):
    """Reader of AKF ``.mat`` files (MATLAB v7.3 via h5py, v5 via :func:`read_mat5`).

    Parameters
    ----------
    path : str or os.PathLike
    sensor_size : SensorSize or (height, width), optional
        Overrides ``im_height``/``im_width``. Without either, the frame size is used, else max
        coordinate + 1 (noted in provenance).
    frame_encoding : {"linear", "gamma2.2", "srgb"}, optional
        The frames' transfer function (the file states none; default ``Frames.encoding``
        ``"unknown"``, read linearly as in the authors' code). It also sets the ``inverse_crf`` of
        the ``f_Q`` camera profile (module notes).

    Notes
    -----
    v7.3 files are streamed by slices of the ``events`` dataset. v5 files cannot be sliced:
    ``events`` is loaded whole and then yielded in chunks.
    """

    format_name = "akf_mat"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        with open(self.path, "rb") as f:
            head = f.read(128)
        if head.startswith(_V73) or (head.startswith(_HDF5_MAGIC) and _has_akf_keys(self.path)):
            self.version = "7.3"
        elif head.startswith(_V5):
            self.version = "5"
        else:
            raise FormatError(self.path, f"not a MATLAB v5/v7.3 MAT-file (header {head[:20]!r})", offset=0)
        self._v5_cache: dict | None = None
        small = self._load_small()
        n = self._n_events()
        self.n_events = n
        h = self._scalar(small, "im_height")
        w = self._scalar(small, "im_width")
        frame_shape = self._frame_shape()
        src = "option"
        note = None
        if self.sensor_size is None:
            if h is not None and w is not None:
                try:
                    self.sensor_size = SensorSize(*check_sensor_size(h, w, self.path, "im_height/im_width"))
                except LimitExceeded:
                    raise
                except (TypeError, ValueError) as exc:
                    raise FormatError(self.path, f"invalid im_height/im_width {h!r}/{w!r}: {exc}") from None
                src = "im_height/im_width"
            elif frame_shape is not None:
                self.sensor_size = SensorSize(*frame_shape)
                src = "image shape"
            else:
                self.sensor_size = self._infer_size()
                src = "inferred"
                note = "no im_height/im_width and no image: inferred as max coordinate + 1"
        akf = {}
        ct = small.get("ct")
        if ct is not None:
            c = np.asarray(ct, dtype=np.float64).reshape(-1)
            akf["ct"] = float(c[0]) if c.size == 1 else c.tolist()
        fq = small.get("f_Q")
        if fq is not None:
            akf["f_Q"] = np.asarray(fq, dtype=np.float64).reshape(-1).tolist()
        enc = self._frame_encoding("unknown")
        prov = {"source_file": str(self.path), "format": "akf_mat", "mat_version": self.version,
                "n_events": n, "sensor_size_source": src, "akf_mat": akf,
                "coordinates": "x, y stored 1-based; converted to 0-based",
                "frame_timestamps": "t_start = rint(time_image - exposure/2), t_end = t_start + rint(exposure)"}
        if note:
            prov["sensor_size_note"] = note
        if frame_shape is not None:
            prov["frame_encoding"] = enc
            prov["frame_encoding_source"] = (
                "declared (frame_encoding option)" if self.frame_encoding else
                "not stated by the file; the authors' code reads image/255 as linear intensity (no inverse CRF)")
        if fq is not None:
            try:
                prov["camera_profile"] = profile_from_f_q(fq, enc, source=str(self.path)).to_dict()
            except ValueError as exc:
                prov["camera_profile_note"] = f"f_Q not usable as a camera profile: {exc}"
        self.metadata = Metadata(event_camera=CameraInfo(self.sensor_size),
                                 frame_camera=CameraInfo(SensorSize(*frame_shape) if frame_shape else None),
                                 provenance=prov)

    # -- low-level access ---------------------------------------------------------------------
    def _h5(self):
        import h5py
        try:
            f = h5py.File(self.path, "r")
        except Exception as exc:
            raise _wrap(self.path, "cannot open the MATLAB v7.3 (HDF5) file; corrupt or truncated?", exc) from None
        try:
            from .._util.limits import check_h5_self_contained
            check_h5_self_contained(f, self.path)  # no external links / storage / virtual datasets
        except BaseException:
            f.close()
            raise
        return f

    def _h5_var(self, f, name: str, required: bool = False):
        import h5py
        try:
            obj = f.get(name)
        except Exception as exc:
            raise _wrap(self.path, f"cannot access variable {name!r}", exc) from None
        if obj is None:
            if required:
                raise FormatError(self.path, f"MAT-file has no {name!r} variable; variables: {sorted(f.keys())}")
            return None
        if not isinstance(obj, h5py.Dataset):
            raise FormatError(self.path, f"variable {name!r} must be a numeric array, got a {type(obj).__name__}")
        cls = obj.attrs.get("MATLAB_class")
        if cls is not None:
            cls = cls if isinstance(cls, bytes) else str(np.asarray(cls).astype(str)).encode()
            if cls not in _NUMERIC_CLASSES:
                raise FormatError(self.path, f"variable {name!r} is a MATLAB {cls.decode(errors='replace')} array; "
                                             f"expected a numeric one")
        if "MATLAB_sparse" in obj.attrs:
            raise FormatError(self.path, f"variable {name!r} is a MATLAB sparse array; expected a full numeric one")
        if obj.attrs.get("MATLAB_empty", 0):
            return "empty"
        if obj.dtype.kind not in "uifb":
            raise FormatError(self.path, f"variable {name!r} must be numeric, got dtype {obj.dtype}")
        return obj

    def _v5(self, names=None) -> dict:
        return read_mat5(self.path, names)

    def _load_small(self) -> dict:
        names = ("im_height", "im_width", "ct", "f_Q", "time_image", "exposure")
        out = {}
        if self.version == "7.3":
            with self._h5() as f:
                for k in names:
                    ds = self._h5_var(f, k)
                    if ds is None or isinstance(ds, str):
                        continue
                    if ds.size > 1 << 24:
                        raise FormatError(self.path, f"variable {k!r} is implausibly large ({ds.shape})")
                    try:
                        out[k] = np.asarray(ds[()]).T
                    except Exception as exc:
                        raise _wrap(self.path, f"cannot read variable {k!r}", exc) from None
        else:
            d = self._v5(list(names) + ["events", "image"])
            self._v5_cache = d
            for k in names:
                if k in d:
                    v = np.asarray(d[k])
                    if v.dtype == object:
                        raise FormatError(self.path, f"variable {k!r} is a MATLAB {v.item() if v.ndim == 0 else ''} "
                                                     f"array; expected a numeric one")
                    if v.dtype.kind not in "uifb":
                        raise FormatError(self.path, f"variable {k!r} must be numeric, got {v.dtype}")
                    out[k] = v
        return out

    def _scalar(self, small: dict, name: str):
        v = small.get(name)
        if v is None:
            return None
        a = np.asarray(v, dtype=np.float64).reshape(-1)
        if a.size != 1 or not np.isfinite(a[0]) or a[0] != np.floor(a[0]):
            raise FormatError(self.path, f"{name} must be one whole number, got {np.asarray(v).tolist()!r}")
        return int(a[0])

    def _n_events(self) -> int:
        if self.version == "7.3":
            with self._h5() as f:
                ds = self._h5_var(f, "events", required=True)
                if isinstance(ds, str):
                    return 0
                if ds.ndim != 2 or ds.shape[0] != 4:
                    raise FormatError(self.path, f"events must be an N x 4 matrix, got MATLAB shape "
                                                 f"{tuple(reversed(ds.shape))}")
                return int(ds.shape[1])
        ev = self._v5_cache.get("events")
        if ev is None:
            raise FormatError(self.path, f"MAT-file has no 'events' variable; variables: "
                                         f"{sorted(k for k in self._v5_cache if not k.startswith('__'))}")
        ev = np.asarray(ev)
        if ev.dtype == object:
            raise FormatError(self.path, f"events is a MATLAB {ev.item() if ev.ndim == 0 else 'non-numeric'} array; "
                                         f"expected a numeric N x 4 matrix")
        if ev.size == 0:
            return 0
        if ev.ndim != 2 or ev.shape[1] != 4 or ev.dtype.kind not in "uifb":
            raise FormatError(self.path, f"events must be a numeric N x 4 matrix, got shape {ev.shape} dtype {ev.dtype}")
        return int(ev.shape[0])

    def _frame_shape(self) -> tuple[int, int] | None:
        if self.version == "7.3":
            with self._h5() as f:
                ds = self._h5_var(f, "image")
                if ds is None or isinstance(ds, str):
                    return None
                shp = tuple(reversed(ds.shape))
        else:
            im = self._v5_cache.get("image")
            if im is None:
                return None
            shp = np.asarray(im).shape
        if len(shp) not in (2, 3, 4) or 0 in shp[:2]:
            raise FormatError(self.path, f"image must be H x W x K (or H x W x 3 x K), got shape {shp}")
        try:
            SensorSize(*check_sensor_size(int(shp[0]), int(shp[1]), self.path, "image"))
            check_frame_bytes(float(np.prod(shp, dtype=np.float64)) * 8, self.path, "image")
        except LimitExceeded:
            raise
        except ValueError as exc:
            raise FormatError(self.path, f"invalid image shape {shp}: {exc}") from None
        return int(shp[0]), int(shp[1])

    def _event_blocks(self, chunk_events: int) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(first_index, block)`` with blocks of shape (n, 4), float64."""
        if self.n_events == 0:
            return
        if self.version == "7.3":
            with self._h5() as f:
                ds = self._h5_var(f, "events", required=True)
                for i0 in range(0, self.n_events, chunk_events):
                    try:
                        blk = ds[:, i0:i0 + chunk_events]
                    except Exception as exc:
                        raise FormatError(self.path, f"cannot read events[{i0}:{i0 + chunk_events}]: "
                                                     f"{type(exc).__name__}: {exc}", record=i0) from None
                    yield i0, np.asarray(blk, dtype=np.float64).T
        else:
            ev = np.asarray(self._v5_cache["events"])
            if ev.dtype == object or ev.dtype.kind not in "uifb":
                raise FormatError(self.path, f"events must be numeric, got dtype {ev.dtype}")
            for i0 in range(0, self.n_events, chunk_events):
                yield i0, np.asarray(ev[i0:i0 + chunk_events], dtype=np.float64)

    def _infer_size(self) -> SensorSize:
        mx = my = 0
        for i0, b in self._event_blocks(1 << 20):
            xy = b[:, 1:3]
            bad = ~np.isfinite(xy).all(axis=1) | (xy < 1).any(axis=1) | (xy > 65536).any(axis=1)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise FormatError(self.path, f"event {i0 + i}: 1-based x, y = {xy[i].tolist()} outside 1..65536",
                                  record=i0 + i)
            mx, my = max(mx, int(xy[:, 0].max())), max(my, int(xy[:, 1].max()))
        if mx == 0:
            raise FormatError(self.path, "no events, no image and no im_height/im_width: pass sensor_size")
        return SensorSize(*check_sensor_size(my, mx, self.path, "sensor inferred from the coordinates"))

    # -- reader API ---------------------------------------------------------------------------
    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        ss = self.sensor_size
        last_t = None
        for i0, b in self._event_blocks(chunk_events):
            bad = ~np.isfinite(b).all(axis=1)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise FormatError(self.path, f"event {i0 + i}: non-finite value {b[i].tolist()}", record=i0 + i)
            t, x, y, p = b[:, 0], b[:, 1], b[:, 2], b[:, 3]
            bad = np.abs(t) >= _MAX_SAFE
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise FormatError(self.path, f"event {i0 + i}: t = {t[i].item()!r} µs is beyond 2^53", record=i0 + i)
            for name, v, lim, dim in (("x", x, ss.width, "width"), ("y", y, ss.height, "height")):
                bad = (v != np.floor(v)) | (v < 1) | (v > lim)
                if bad.any():
                    i = int(np.flatnonzero(bad)[0])
                    raise FormatError(self.path, f"event {i0 + i}: 1-based {name} = {v[i].item()!r} is not in 1..{lim} "
                                                 f"(sensor {dim})", record=i0 + i)
            tt = np.rint(t).astype(np.int64)
            dec = np.flatnonzero(tt[1:] < tt[:-1])
            if dec.size:
                i = int(dec[0]) + 1
                raise FormatError(self.path, f"event {i0 + i}: timestamps must be non-decreasing; {int(tt[i])} µs "
                                             f"after {int(tt[i - 1])} µs", record=i0 + i)
            if last_t is not None and tt.size and tt[0] < last_t:
                raise FormatError(self.path, f"event {i0}: timestamps must be non-decreasing; {int(tt[0])} µs "
                                             f"after {last_t} µs", record=i0)
            ev = np.empty(tt.size, EVENT_DTYPE)
            ev["t"] = tt
            ev["x"] = (x - 1).astype(np.uint16)
            ev["y"] = (y - 1).astype(np.uint16)
            ev["p"] = np.where(p == 1, 1, -1)
            if ev.size:
                last_t = int(tt[-1])
                yield EventChunk(ev)

    def _read_var(self, name: str):
        """Whole variable in MATLAB axis order (None when absent)."""
        if self.version == "7.3":
            with self._h5() as f:
                ds = self._h5_var(f, name)
                if ds is None:
                    return None
                if isinstance(ds, str):
                    return np.zeros((0,))
                try:
                    return np.asarray(ds[()]).T
                except Exception as exc:
                    raise _wrap(self.path, f"cannot read variable {name!r}", exc) from None
        if self._v5_cache is not None and name in self._v5_cache:
            return np.asarray(self._v5_cache[name])
        d = self._v5([name])
        return None if name not in d else np.asarray(d[name])

    def _numeric(self, name: str, v) -> np.ndarray:
        a = np.asarray(v)
        if a.dtype.kind not in "uifb":
            raise FormatError(self.path, f"{name} must be numeric, got dtype {a.dtype}")
        return a.astype(np.float64).reshape(-1)

    def _times(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        ti = self._read_var("time_image")
        if ti is None:
            raise FormatError(self.path, "MAT-file has an image but no time_image")
        ti = self._numeric("time_image", ti)
        if ti.size != k or not np.isfinite(ti).all() or (np.abs(ti) >= _MAX_SAFE).any():
            raise FormatError(self.path, f"time_image must hold {k} finite µs values, got {ti.size}")
        ex = self._read_var("exposure")
        if ex is None:
            t = np.rint(ti).astype(np.int64)
            return t, t.copy()
        ex = self._numeric("exposure", ex)
        if ex.size == 1:
            ex = np.full(k, ex[0])
        if ex.size != k or not np.isfinite(ex).all() or (ex < 0).any() or (ex >= _MAX_SAFE).any():
            raise FormatError(self.path, f"exposure must hold 1 or {k} non-negative µs values, got {ex.size}")
        ts = np.rint(ti - ex / 2).astype(np.int64)
        return ts, ts + np.rint(ex).astype(np.int64)

    def read_frames(self) -> Frames | None:
        """Frames from ``image`` (H x W x K) with ``time_image``/``exposure`` (see module notes).

        Returns
        -------
        Frames or None
            ``images`` (K, H, W) uint8 (dtype kept) or (K, H, W, 3) for H x W x 3 x K colour;
            ``encoding`` the declared ``frame_encoding``, else ``"unknown"`` (module notes).
            None when the file has no ``image``.
        """
        im = self._read_var("image")
        if im is None:
            return None
        if im.size == 0:
            e = Frames.empty(*self.sensor_size.shape)
            return Frames(e.images, e.t_start_us, e.t_end_us, encoding=self._frame_encoding("unknown"))
        if im.ndim == 2:
            frames = im[np.newaxis]
        elif im.ndim == 3:
            frames = np.transpose(im, (2, 0, 1))
        elif im.ndim == 4 and im.shape[2] == 3:
            frames = np.transpose(im, (3, 0, 1, 2))
        else:
            raise FormatError(self.path, f"image must be H x W x K or H x W x 3 x K, got shape {im.shape}")
        if frames.dtype.kind not in "uif":
            raise FormatError(self.path, f"image must be numeric, got dtype {frames.dtype}")
        check_finite(frames, self.path, "image")
        ts, te = self._times(frames.shape[0])
        order = np.argsort(ts, kind="stable")
        try:
            return Frames(np.ascontiguousarray(frames[order]), ts[order], te[order],
                          encoding=self._frame_encoding("unknown"))
        except ValueError as exc:
            raise FormatError(self.path, f"invalid frames: {exc}") from None

    def read_hdr(self) -> HDRReferences | None:
        """HDR references from ``HDR_mat`` (H x W x 3 x K, or H x W x K), timestamped ``time_image``.

        Returns
        -------
        HDRReferences or None
            float32 images (K, H, W, 3) or (K, H, W); ``t_us`` = ``rint(time_image)``. None when
            the file has no ``HDR_mat``.
        """
        hdr = self._read_var("HDR_mat")
        if hdr is None:
            return None
        if hdr.ndim == 4 and hdr.shape[2] == 3:
            imgs = np.transpose(hdr, (3, 0, 1, 2))
        elif hdr.ndim == 3 and hdr.shape[2] == 3 and self._count_time_image() == 1:
            imgs = hdr[np.newaxis]
        elif hdr.ndim == 3:
            imgs = np.transpose(hdr, (2, 0, 1))
        elif hdr.ndim == 2:
            imgs = hdr[np.newaxis]
        else:
            raise FormatError(self.path, f"HDR_mat must be H x W x 3 x K or H x W x K, got shape {hdr.shape}")
        if imgs.dtype.kind not in "uif":
            raise FormatError(self.path, f"HDR_mat must be numeric, got dtype {imgs.dtype}")
        if imgs.dtype.kind == "f":
            finite = np.isfinite(imgs)
            if not finite.all() or (np.abs(imgs) > np.finfo(np.float32).max).any():
                raise FormatError(self.path, "HDR_mat holds values that are not finite float32 numbers")
        ti = self._read_var("time_image")
        if ti is None:
            raise FormatError(self.path, "MAT-file has HDR_mat but no time_image")
        ti = np.asarray(ti)
        if ti.dtype.kind not in "uif":
            raise FormatError(self.path, f"time_image must be numeric, got dtype {ti.dtype}")
        ti = ti.astype(np.float64).reshape(-1)
        if ti.size != imgs.shape[0] or not np.isfinite(ti).all() or (np.abs(ti) >= _MAX_SAFE).any():
            raise FormatError(self.path, f"HDR_mat has {imgs.shape[0]} images but time_image has {ti.size} "
                                         f"finite µs values below 2^53")
        return HDRReferences(imgs.astype(np.float32), np.rint(ti).astype(np.int64))

    def read(self, t_start_us=None, t_end_us=None):
        """The recording, with ``HDR_mat`` (when present) as its HDR references, as stored."""
        rec = super().read(t_start_us, t_end_us)
        hdr = self.read_hdr()
        if hdr is not None and (t_start_us is not None or t_end_us is not None):
            t = hdr.t_us
            keep = np.ones(t.size, bool)
            if t_start_us is not None:
                keep &= t >= t_start_us
            if t_end_us is not None:
                keep &= t < t_end_us
            hdr = HDRReferences(hdr.images[keep], t[keep])
        if hdr is None:
            return rec
        order = np.argsort(hdr.t_us, kind="stable")
        hdr = HDRReferences(hdr.images[order], hdr.t_us[order])
        return dataclasses.replace(rec, hdr=hdr)

    def _count_time_image(self) -> int:
        ti = self._read_var("time_image")
        return 0 if ti is None else int(np.asarray(ti).size)


class AkfMatWriter(EventFileWriter):
    """Writer of AKF ``.mat`` files in MATLAB v7.3 (HDF5) layout.

    Events go to a resizable, chunked ``events`` dataset (double, MATLAB N x 4, 1-based x and y,
    p = 1 ON / 0 OFF), appended chunk by chunk, so memory stays bounded. Frames (uint8/uint16/float
    grey, (K, H, W)) go to ``image`` (MATLAB H x W x K) with ``time_image`` (mid-exposure µs) and
    ``exposure`` (µs); ``im_height``/``im_width`` hold the sensor size. ``ct`` is written from the
    option ``ct=``, else ``metadata.provenance["akf_mat"]["ct"]``. ``f_Q`` is written from the
    option ``f_Q=``, else from ``metadata.provenance["camera_profile"]`` (:func:`f_q_from_profile`,
    the table that reproduces its R̄; its inverse CRF cannot be stored), else from
    ``metadata.provenance["akf_mat"]["f_Q"]``.

    Every variable carries the ``MATLAB_class`` attribute, and the 512-byte user block starts with
    the MATLAB v7.3 header (:func:`matlab_v73_header`), so MATLAB ``load`` and MATLAB-aware HDF5
    readers accept the file.
    """

    format_name = "akf_mat"
    supports = frozenset({"frames"})

    def _open(self) -> None:
        self._f = self._guard = self._ev = self._img = None
        self._f, self._guard = open_h5_for_writing(self.tmp_path, userblock_size=512, libver="earliest")
        self._ev = self._f.create_dataset("events", shape=(4, 0), maxshape=(4, None), dtype="<f8",
                                          chunks=(4, 1 << 15))
        self._ev.attrs["MATLAB_class"] = np.bytes_(b"double")
        self._img = None
        self._last_frame_t: int | None = None

    def _var(self, name: str, matlab_array) -> None:
        a = np.asarray(matlab_array)
        if a.ndim < 2:
            a = a.reshape(1, -1) if a.ndim == 1 else a.reshape(1, 1)
        ds = self._f.create_dataset(name, data=np.ascontiguousarray(a.T))
        ds.attrs["MATLAB_class"] = np.bytes_(_MATLAB_CLASS[a.dtype])

    def _write_events(self, events: np.ndarray) -> None:
        n0 = self._ev.shape[1]
        blk = np.empty((4, len(events)), np.float64)
        blk[0] = events["t"]
        blk[1] = events["x"].astype(np.float64) + 1
        blk[2] = events["y"].astype(np.float64) + 1
        blk[3] = (events["p"] > 0)
        if np.abs(events["t"]).max() >= (1 << 53):
            raise ValueError("AKF .mat stores t as double: timestamps must be below 2^53 µs")
        self._ev.resize((4, n0 + len(events)))
        self._ev[:, n0:] = blk
        self._guard.check()

    def _write_frames(self, frames: Frames) -> None:
        im = frames.images
        if im.ndim != 3:
            raise ValueError(f"AKF .mat frames must be grey (K, H, W), got shape {im.shape}")
        if im.dtype not in _MATLAB_CLASS:
            raise ValueError(f"unsupported frame dtype {im.dtype} for a MATLAB array")
        k, h, w = im.shape
        if self._img is None:
            self._img = self._f.create_dataset("image", shape=(0, w, h), maxshape=(None, w, h), dtype=im.dtype,
                                               chunks=(1, w, h))
            self._img.attrs["MATLAB_class"] = np.bytes_(_MATLAB_CLASS[im.dtype])
            self._ti = self._f.create_dataset("time_image", shape=(1, 0), maxshape=(1, None), dtype="<f8",
                                              chunks=(1, 1024))
            self._ex = self._f.create_dataset("exposure", shape=(1, 0), maxshape=(1, None), dtype="<f8",
                                              chunks=(1, 1024))
            for ds in (self._ti, self._ex):
                ds.attrs["MATLAB_class"] = np.bytes_(b"double")
        elif self._img.shape[1:] != (w, h) or self._img.dtype != im.dtype:
            raise ValueError(f"frames must all have the same shape and dtype; got {im.shape[1:]} {im.dtype} after "
                             f"{(self._img.shape[2], self._img.shape[1])} {self._img.dtype}")
        if self._last_frame_t is not None and frames.t_start_us[0] < self._last_frame_t:
            raise ValueError("frames must be appended in order of exposure start")
        n0 = self._img.shape[0]
        self._img.resize((n0 + k, w, h))
        self._img[n0:] = np.transpose(im, (0, 2, 1))
        ex = (frames.t_end_us - frames.t_start_us).astype(np.float64)
        ti = frames.t_start_us.astype(np.float64) + ex / 2
        for ds, v in ((self._ti, ti), (self._ex, ex)):
            ds.resize((1, n0 + k))
            ds[0, n0:] = v
        self._last_frame_t = int(frames.t_start_us[-1])
        self._guard.check()

    def _finish(self) -> None:
        if self._ev.shape[1] == 0:  # MATLAB's own encoding of an empty (0 x 4) array
            del self._f["events"]
            ds = self._f.create_dataset("events", data=np.array([0, 4], np.uint64))
            ds.attrs["MATLAB_class"] = np.bytes_(b"double")
            ds.attrs["MATLAB_empty"] = np.uint8(1)
        ss = self.sensor_size
        if ss is not None:
            self._var("im_height", np.float64(ss.height))
            self._var("im_width", np.float64(ss.width))
        prov = (self.metadata.provenance or {}).get("akf_mat") or {}
        ct = self.options.get("ct", prov.get("ct"))
        fq = self.options.get("f_Q")
        profile = (self.metadata.provenance or {}).get("camera_profile")
        if fq is None and profile is not None:
            fq = f_q_from_profile(profile)
        if fq is None:
            fq = prov.get("f_Q")
        if ct is not None:
            self._var("ct", np.asarray(ct, dtype=np.float64))
        if fq is not None:
            self._var("f_Q", np.asarray(fq, dtype=np.float64).reshape(-1, 1))
        # datasets first, then the file, then the descriptor; each step's I/O error is raised once
        self._ev = self._img = self._ti = self._ex = None
        self._f.close()
        self._guard.check()
        self._guard.seek(0)
        self._guard.write(matlab_v73_header())
        self._guard.close()
        self._guard.check()

    def _cleanup(self) -> None:
        self._ev = self._img = self._ti = self._ex = None
        close_and_remove(getattr(self, "_f", None), getattr(self, "_guard", None), self.tmp_path)


READERS = {"akf_mat": AkfMatReader}
WRITERS = {"akf_mat": AkfMatWriter}

register_formats(__name__, {
    "akf_mat": "AKF MATLAB .mat (v7.3 HDF5 or v5)",
}, READERS, WRITERS)
