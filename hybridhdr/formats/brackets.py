"""Exposure-bracket sets: a folder of images of one static scene at several exposure times.

Layout (see ``docs/brackets.md``): a folder holding the images and a ``brackets.json``::

    {"format": "hybridhdr-brackets", "version": 1,
     "encoding": "raw" | "linear" | "gamma" | "unknown",
     "camera": {"name": "...", "serial": "...", "bit_depth": 8, "black_level": 0, "white_level": 255},
     "images": [{"file": "exp_000.png", "exposure_s": 0.001, "iso": 100, "gain": 1.0, "t_us": null}]}

:func:`read_bracket_set` also reads folders without ``brackets.json``:

* a list file ``exposures.txt`` (or ``image_list.txt``, the HDRShop/Debevec list): one line per
  image, ``<file> <exposure>`` with the exposure in seconds (``0.004``) or as ``1/N``; further
  columns and ``#`` comments are ignored;
* otherwise the exposure time is read from each file's EXIF ``ExposureTime`` (tag 0x829A):
  through Pillow for JPEG/TIFF, and by a small TIFF-IFD parser for TIFF-based RAW files
  (DNG, CR2, NEF, ARW, PEF, SRW, NRW, ORF/RW2 when TIFF-like). RAF, CR3 and other non-TIFF RAWs
  need a list file.

RAW files (``.dng .cr2 .nef .arw ...``) are decoded with rawpy (LibRaw) **without
demosaicing**: ``(raw_image_visible - black_level_per_channel[c]) / (white_level - black[c])``
per CFA colour ``c``, then each 2x2 CFA cell is binned into one RGB pixel (R, mean of the two
greens, B), giving half-resolution linear RGB in [0, 1]. This is used instead of
``postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16)`` because LibRaw's postprocess
applies white balance multipliers and a colour matrix before clipping, so the saturation level
differs per channel and can no longer be detected reliably; the raw values are linear in the
exposure by construction and a cell with any value at or above 0.98 x white level
(calibration.md, "HDR merge") is set to exactly 1.0, which :meth:`BracketSet.saturated` reports.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from .._util.atomic import atomic_folder, atomic_outputs
from .._util.checks import check_shape
from ..errors import FormatError
from ..model import FRAME_ENCODINGS

__all__ = ["BracketSet", "read_bracket_set", "write_bracket_set", "parse_exposure", "exif_exposure_s",
           "RAW_EXTENSIONS", "IMAGE_EXTENSIONS", "BRACKETS_FORMAT", "colour_mask"]

BRACKETS_FORMAT = "hybridhdr-brackets"
BRACKETS_VERSION = 1
#: RAW file extensions decoded with rawpy.
RAW_EXTENSIONS = (".dng", ".cr2", ".nef", ".arw", ".orf", ".rw2", ".pef", ".srw", ".nrw", ".raf", ".cr3",
                  ".rwl", ".3fr", ".iiq", ".erf", ".mef", ".mos", ".kdc", ".dcr")
#: Ordinary image extensions read with imageio (dtype kept: uint8 or uint16).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".pgm", ".ppm", ".bmp")
#: RAW formats whose container is TIFF, so their EXIF can be parsed here.
_TIFF_RAWS = (".dng", ".cr2", ".nef", ".arw", ".pef", ".srw", ".nrw", ".orf", ".rw2", ".3fr", ".erf",
              ".mef", ".mos", ".kdc", ".dcr", ".iiq", ".rwl")
_LIST_FILES = ("exposures.txt", "image_list.txt")
#: A RAW value at or above this fraction of the white level counts as saturated.
RAW_SATURATION = 0.98


@dataclass(frozen=True, eq=False)
class BracketSet:
    """Images of one static scene at several exposures.

    Parameters
    ----------
    images : list of ndarray of shape (H, W) or (H, W, 3)
        Pixel values as stored (uint8/uint16 codes), or for RAW files linear float32 RGB in
        [0, 1] (black level 0, white level 1; saturated 2x2 cells exactly 1.0).
    exposures_s : ndarray of shape (K,), float64
        Exposure time of each image in seconds (times gain, if a gain is given: the relative
        exposure is what matters for the response).
    encoding : {"raw", "linear", "gamma", "unknown"}
        How pixel values relate to irradiance (``Frames.encoding``).
    camera : dict
        ``bit_depth``, ``black_level``, ``white_level``, ``name``, ``serial`` ... (free form).
    files : list of str
        File name of each image inside the folder.
    iso, gain : ndarray of shape (K,) or None
    t_us : ndarray of shape (K,), int64, or None
        Capture times in µs when known.
    """

    images: list
    exposures_s: np.ndarray
    encoding: str = "unknown"
    camera: dict = field(default_factory=dict)
    files: list = field(default_factory=list)
    iso: np.ndarray | None = None
    gain: np.ndarray | None = None
    t_us: np.ndarray | None = None

    def __post_init__(self):
        imgs = [np.asarray(im) for im in self.images]
        k = len(imgs)
        if k == 0:
            raise ValueError("a bracket set needs at least one image, got none")
        for i, im in enumerate(imgs):
            check_shape(im, "H W | H W 3", f"bracket image {i}")
        shapes = {im.shape for im in imgs}
        if len(shapes) != 1:
            detail = ", ".join(f"{self._name(i)}: {im.shape}" for i, im in enumerate(imgs))
            raise ValueError(f"all bracket images must have the same size and channels; found {detail}")
        dtypes = {im.dtype for im in imgs}
        if len(dtypes) != 1:
            raise ValueError(f"all bracket images must have one dtype, found {sorted(map(str, dtypes))}")
        ex = np.asarray(self.exposures_s, dtype=np.float64)
        check_shape(ex, "K", "exposures_s (one per image)", sizes={"K": k})
        if not np.all(np.isfinite(ex)) or np.any(ex <= 0):
            i = int(np.flatnonzero(~(np.isfinite(ex) & (ex > 0)))[0])
            raise ValueError(f"exposure times must be finite and > 0 s; {self._name(i)} has {ex[i]}")
        if self.encoding not in FRAME_ENCODINGS:
            raise ValueError(f"encoding must be one of {FRAME_ENCODINGS}, got {self.encoding!r}")
        files = list(self.files) or [f"image_{i:03d}" for i in range(k)]
        if len(files) != k:
            raise ValueError(f"files must name each of the {k} images, got {len(files)} names")
        for name in ("iso", "gain"):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=np.float64)
                check_shape(v, "K", name, sizes={"K": k})
                object.__setattr__(self, name, v)
        if self.t_us is not None:
            t = np.asarray(self.t_us, dtype=np.int64)
            check_shape(t, "K", "t_us", sizes={"K": k})
            object.__setattr__(self, "t_us", t)
        object.__setattr__(self, "images", imgs)
        object.__setattr__(self, "exposures_s", ex)
        object.__setattr__(self, "files", files)
        object.__setattr__(self, "camera", dict(self.camera or {}))

    def _name(self, i):
        return self.files[i] if self.files and i < len(self.files) else f"image {i}"

    def __len__(self) -> int:
        return len(self.images)

    @property
    def shape(self) -> tuple:
        """Image shape ``(H, W)`` or ``(H, W, 3)``."""
        return self.images[0].shape

    @property
    def n_channels(self) -> int:
        return 1 if self.images[0].ndim == 2 else 3

    @property
    def max_code(self) -> int:
        """Largest code: ``2**camera["bit_depth"] - 1``, else from the dtype (255 for uint8)."""
        im = self.images[0]
        if "bit_depth" in self.camera:
            return (1 << int(self.camera["bit_depth"])) - 1
        if im.dtype.kind in "ui":
            return int(np.iinfo(im.dtype).max)
        return 1

    def stack(self) -> np.ndarray:
        """All images as one array of shape (K, H, W) or (K, H, W, 3), dtype kept."""
        return np.stack(self.images)

    def sorted(self) -> "BracketSet":
        """The same set ordered by increasing exposure."""
        o = np.argsort(self.exposures_s, kind="stable")
        sel = lambda a: None if a is None else a[o]  # noqa: E731
        return BracketSet([self.images[i] for i in o], self.exposures_s[o], self.encoding, self.camera,
                          [self.files[i] for i in o], sel(self.iso), sel(self.gain), sel(self.t_us))

    def linear_stack(self) -> np.ndarray:
        """Linear irradiance x exposure, float32 in [0, 1] (1 = white level), shape (K, H, W[, 3]).

        Only for ``encoding`` "raw" or "linear": ``(value - black_level) / (white_level -
        black_level)`` with ``black_level`` (default 0) and ``white_level`` (default
        :attr:`max_code`) from :attr:`camera`. Gamma or unknown encodings need a response
        curve: use :func:`hybridhdr.calibrate.crf.estimate_crf` instead.
        """
        if self.encoding not in ("raw", "linear"):
            raise ValueError(f"linear_stack() needs a 'raw' or 'linear' bracket set, got encoding "
                             f"{self.encoding!r}; estimate the response with hybridhdr.calibrate.crf first")
        black = float(self.camera.get("black_level", 0.0))
        white = float(self.camera.get("white_level", self.max_code))
        if not white > black:
            raise ValueError(f"camera white_level ({white}) must exceed black_level ({black})")
        s = self.stack().astype(np.float32)
        return np.clip((s - black) / (white - black), 0.0, 1.0)

    def saturated(self) -> np.ndarray:
        """Boolean (K, H, W[, 3]) mask of clipped values (code >= max code, or RAW cells at 1.0)."""
        s = self.stack()
        if s.dtype.kind == "f":
            return s >= 1.0
        white = float(self.camera.get("white_level", self.max_code))
        return s >= RAW_SATURATION * white if self.encoding == "raw" else s >= self.max_code


# -- exposure parsing ------------------------------------------------------------------------
def parse_exposure(text: str) -> float:
    """``"0.004"``, ``"1/250"`` or ``"4e-3"`` -> seconds (float); ValueError otherwise."""
    s = str(text).strip().rstrip("s")
    try:
        v = float(Fraction(s)) if "/" in s else float(s)
    except (ValueError, ZeroDivisionError):
        raise ValueError(f"exposure must be seconds ('0.004') or '1/N', got {text!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"exposure must be > 0 s, got {text!r}")
    return v


def _read_list_file(path: Path) -> dict[str, float]:
    out = {}
    from .._util.limits import read_text_bounded
    for n, line in enumerate(read_text_bounded(path, "exposure list file").splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) < 2:
            raise FormatError(path, f"line {n}: expected '<file> <exposure seconds or 1/N>', got {line!r}")
        try:
            out[parts[0]] = parse_exposure(parts[1])
        except ValueError as e:
            raise FormatError(path, f"line {n}: {e}") from None
    if not out:
        raise FormatError(path, "no '<file> <exposure>' lines found")
    return out


def _tiff_exposure(path: Path) -> float | None:
    """EXIF ExposureTime (0x829A) from a TIFF-structured file (IFD0, its SubIFDs and EXIF IFD)."""
    with open(path, "rb") as f:
        data = f.read(4 << 20)
    if len(data) < 8 or data[:2] not in (b"II", b"MM"):
        return None
    e = "<" if data[:2] == b"II" else ">"
    magic = struct.unpack(e + "H", data[2:4])[0]
    if magic not in (42, 0x4F52, 0x5352, 0x55):  # TIFF, ORF ('RO'/'RS'), RW2 (0x55)
        return None
    sizes = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 7: 1, 9: 4, 10: 8}
    todo, seen = [struct.unpack(e + "I", data[4:8])[0]], set()
    while todo:
        off = todo.pop(0)
        if off in seen or off <= 0 or off + 2 > len(data) or len(seen) > 64:
            continue
        seen.add(off)
        (n,) = struct.unpack(e + "H", data[off:off + 2])
        for k in range(min(n, 1000)):
            p = off + 2 + 12 * k
            if p + 12 > len(data):
                break
            tag, typ, cnt = struct.unpack(e + "HHI", data[p:p + 8])
            size = sizes.get(typ, 1) * cnt
            voff = p + 8 if size <= 4 else struct.unpack(e + "I", data[p + 8:p + 12])[0]
            if tag == 0x829A and typ in (5, 10) and voff + 8 <= len(data):
                num, den = struct.unpack(e + ("II" if typ == 5 else "ii"), data[voff:voff + 8])
                if den and num > 0:
                    return num / den
            elif tag in (0x8769, 0x014A) and typ in (4, 13) and size <= 4 * 16:
                todo.extend(struct.unpack(e + "I" * cnt, data[voff:voff + 4 * cnt]) if cnt > 1
                            else [struct.unpack(e + "I", data[p + 8:p + 12])[0]])
        p = off + 2 + 12 * n
        if p + 4 <= len(data):
            todo.append(struct.unpack(e + "I", data[p:p + 4])[0])
    return None


def exif_exposure_s(path) -> float | None:
    """EXIF exposure time in seconds of a JPEG/TIFF (Pillow) or TIFF-based RAW file, else None."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext in _TIFF_RAWS or ext in (".tif", ".tiff"):
        v = _tiff_exposure(path)
        if v is not None:
            return v
    if ext in (".jpg", ".jpeg", ".tif", ".tiff", ".png"):
        try:
            from PIL import Image
            with Image.open(path) as im:
                exif = im.getexif()
                v = exif.get(0x829A) or exif.get_ifd(0x8769).get(0x829A)
        except Exception:
            return None
        if v is not None and float(v) > 0:
            return float(v)
    return None


# -- image reading ---------------------------------------------------------------------------
def _read_raw(path: Path) -> tuple[np.ndarray, dict]:
    try:
        import rawpy
    except ImportError as e:  # pragma: no cover
        raise ImportError("reading RAW brackets needs rawpy (pip install rawpy)") from e
    try:
        with rawpy.imread(str(path)) as r:
            raw = r.raw_image_visible.astype(np.float32)
            cols = r.raw_colors_visible.copy()
            black = np.asarray(r.black_level_per_channel, dtype=np.float32)
            white = float(r.white_level)
            desc = r.color_desc.decode("ascii", "replace")
            pattern = np.asarray(r.raw_pattern)
    except Exception as e:
        raise FormatError(path, f"cannot decode as a RAW file ({type(e).__name__}: {e})") from None
    if raw.ndim != 2 or pattern.shape != (2, 2):
        raise FormatError(path, f"only 2x2 Bayer RAW files are supported, got CFA pattern shape "
                          f"{pattern.shape} ({desc})")
    b = black[cols]
    lin = (raw - b) / np.maximum(white - b, 1.0)
    sat = raw >= RAW_SATURATION * white
    h, w = (raw.shape[0] // 2) * 2, (raw.shape[1] // 2) * 2
    lin, sat, cols = lin[:h, :w], sat[:h, :w], cols[:h, :w]
    out = np.zeros((h // 2, w // 2, 3), np.float32)
    cnt = np.zeros((h // 2, w // 2, 3), np.float32)
    cell_sat = np.zeros((h // 2, w // 2), bool)
    for dy in (0, 1):
        for dx in (0, 1):
            c = int(cols[dy, dx])
            ch = {"R": 0, "G": 1, "B": 2}.get(desc[c] if c < len(desc) else "G", 1)
            out[..., ch] += lin[dy::2, dx::2]
            cnt[..., ch] += 1
            cell_sat |= sat[dy::2, dx::2]
    out = np.clip(out / np.maximum(cnt, 1), 0.0, 1.0)
    out[cell_sat] = 1.0
    return out, {"black_level": 0.0, "white_level": 1.0, "raw_white_level": white,
                 "raw_black_level_per_channel": [float(v) for v in black], "cfa": desc}


def _read_image(path: Path) -> np.ndarray:
    import imageio.v3 as iio
    try:
        im = np.asarray(iio.imread(path))
    except Exception as e:
        raise FormatError(path, f"cannot read image ({type(e).__name__}: {e})") from None
    if im.ndim == 3 and im.shape[2] == 4:
        im = im[..., :3]
    if im.ndim == 3 and im.shape[2] == 1:
        im = im[..., 0]
    check_shape(im, "H W | H W 3", "a grey or RGB image", error=lambda m: FormatError(path, m))
    if im.dtype not in (np.uint8, np.uint16):
        raise FormatError(path, f"expected 8- or 16-bit codes, got dtype {im.dtype}")
    return im


def read_bracket_set(folder) -> BracketSet:
    """Read a bracket set folder (``brackets.json``, a list file, or EXIF; see the module doc).

    Raises
    ------
    FormatError
        Unreadable image/RAW file (named), malformed ``brackets.json`` or list file, or a file
        whose exposure cannot be found.
    ValueError
        Images of different sizes, non-positive exposures.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"bracket set folder {folder} does not exist or is not a folder")
    meta = folder / "brackets.json"
    iso = gain = t_us = None
    camera: dict = {}
    if meta.exists() or meta.is_symlink():
        from .._util.limits import read_json_bounded
        d = read_json_bounded(meta, "brackets.json", limit=16 << 20)  # regular, bounded, nesting bounded
        if not isinstance(d, dict) or d.get("format") != BRACKETS_FORMAT:
            raise FormatError(meta, f"'format' must be {BRACKETS_FORMAT!r}, got "
                              f"{d.get('format') if isinstance(d, dict) else type(d).__name__!r}")
        if d.get("version") != BRACKETS_VERSION:
            raise FormatError(meta, f"'version' must be {BRACKETS_VERSION}, got {d.get('version')!r}")
        entries = d.get("images")
        if not isinstance(entries, list) or not entries:
            raise FormatError(meta, "'images' must be a non-empty list")
        encoding = d.get("encoding", "unknown")
        camera = dict(d.get("camera") or {})
        files, exposures = [], []
        for i, ent in enumerate(entries):
            if not isinstance(ent, dict) or "file" not in ent or "exposure_s" not in ent:
                raise FormatError(meta, f"images[{i}] needs 'file' and 'exposure_s', got {ent!r}")
            files.append(str(ent["file"]))
            exposures.append(float(ent["exposure_s"]))
        def col(key, dtype):
            vals = [e.get(key) for e in entries]
            return None if any(v is None for v in vals) else np.asarray(vals, dtype=dtype)
        iso, gain, t_us = col("iso", np.float64), col("gain", np.float64), col("t_us", np.int64)
    else:
        names = sorted(p.name for p in folder.iterdir()
                       if p.suffix.lower() in RAW_EXTENSIONS + IMAGE_EXTENSIONS and not p.name.startswith("."))
        listed = None
        for lf in _LIST_FILES:
            if (folder / lf).exists():
                listed = _read_list_file(folder / lf)
                break
        if listed is not None:
            from .._util.confine import inside_folder
            for n in listed:  # absolute names and links out of the folder are refused, like '../'
                inside_folder(n, folder, what="listed image", source=folder / lf)
            missing = [n for n in listed if not (folder / n).exists()]
            if missing:
                raise FormatError(folder / lf, f"lists files that are not in the folder: {missing[:5]}")
            files, exposures = list(listed), list(listed.values())
        else:
            if not names:
                raise FormatError(folder, f"no images ({', '.join(IMAGE_EXTENSIONS + RAW_EXTENSIONS[:4])}, ...) "
                                  "and no brackets.json")
            files, exposures = names, []
            for n in names:
                v = exif_exposure_s(folder / n)
                if v is None:
                    raise FormatError(folder / n, "no EXIF ExposureTime; add an exposures.txt list file "
                                      "('<file> <seconds or 1/N>' per line) or a brackets.json")
                exposures.append(v)
        encoding = None
    images, raw_info = [], None
    for n in files:
        p = folder / n
        if not p.exists():
            raise FormatError(p, "listed in the bracket set but not found")
        if p.suffix.lower() in RAW_EXTENSIONS:
            im, raw_info = _read_raw(p)
        else:
            im = _read_image(p)
        images.append(im)
    if encoding is None:
        if raw_info is not None and any(Path(n).suffix.lower() not in RAW_EXTENSIONS for n in files):
            raise FormatError(folder, "mixes RAW and non-RAW images; use one kind per bracket set")
        encoding = "raw" if raw_info is not None else "unknown"
    if raw_info is not None:
        camera = {**camera, **raw_info}
    return BracketSet(images, np.asarray(exposures), encoding, camera, files, iso, gain, t_us)


def write_bracket_set(folder, images, exposures_s, *, encoding, camera=None, iso=None, gain=None,
                      t_us=None, overwrite: bool = False) -> Path:
    """Write images (uint8/uint16 PNG) and ``brackets.json`` into ``folder``, atomically.

    Everything is written into ``folder.partial/`` and renamed to ``folder`` when complete.
    ``folder`` must not exist yet (or be empty), unless ``overwrite``: then the old set's
    ``brackets.json`` and ``exp_*.png`` are replaced (``brackets.json`` removed first and moved in
    last, so an interrupted replace never leaves a set whose list names the wrong images); other
    files in ``folder`` are left alone.

    Parameters
    ----------
    images : sequence of ndarray of shape (H, W) or (H, W, 3), uint8 or uint16
    exposures_s : sequence of float (K,)
        Exposure times in seconds.
    encoding : {"raw", "linear", "gamma", "unknown"}
    camera : dict, optional
        ``name``, ``serial``, ``bit_depth`` (default from the dtype), ``black_level``,
        ``white_level`` (RAW) ...
    iso, gain : sequence of float (K,), optional
    t_us : sequence of int (K,), optional
        Capture time of each image in µs.
    """
    folder = Path(folder)
    imgs = [np.asarray(im) for im in images]
    for i, im in enumerate(imgs):
        if im.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"bracket image {i} must be uint8 or uint16 codes, got dtype {im.dtype}")
    bs = BracketSet(imgs, exposures_s, encoding, camera or {}, [f"exp_{i:03d}.png" for i in range(len(imgs))],
                    iso, gain, t_us)
    cam = dict(bs.camera)
    cam.setdefault("bit_depth", 8 if imgs[0].dtype == np.uint8 else 16)
    replace = folder.is_dir() and not folder.is_symlink() and any(folder.iterdir())
    if (folder.exists() or folder.is_symlink()) and not replace and not folder.is_dir():
        raise FileExistsError(f"bracket set folder {folder} exists and is not a folder")
    if replace and not overwrite:
        raise FileExistsError(f"bracket set folder {folder} already exists and is not empty")
    import imageio.v3 as iio
    with (atomic_outputs(folder, last=("brackets.json",)) if replace else atomic_folder(folder)) as tmp:
        entries = []
        for i, (im, name) in enumerate(zip(bs.images, bs.files)):
            iio.imwrite(tmp / name, im, extension=".png")
            entries.append({"file": name, "exposure_s": float(bs.exposures_s[i]),
                            "iso": None if bs.iso is None else float(bs.iso[i]),
                            "gain": None if bs.gain is None else float(bs.gain[i]),
                            "t_us": None if bs.t_us is None else int(bs.t_us[i])})
        doc = {"format": BRACKETS_FORMAT, "version": BRACKETS_VERSION, "encoding": encoding,
               "camera": cam, "images": entries}
        (tmp / "brackets.json").write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        if replace:  # the new set is complete: the old one goes, its list first
            for old in [folder / "brackets.json", *sorted(folder.glob("exp_*.png"))]:
                if old.is_file() or old.is_symlink():
                    old.unlink()
    return folder


def colour_mask(images, colour) -> np.ndarray:
    """(H, W) bool mask of pixels equal to ``colour`` (e.g. (0, 0, 255)) in any image.

    Debevec's Memorial Church scans mark shifted border areas in pure blue, "not to be used in
    the HDR assembly" (its README); pass ``~colour_mask(...)`` as the valid mask.
    """
    c = np.asarray(colour)
    m = None
    for im in images:
        im = np.asarray(im)
        if im.ndim != 3 or im.shape[2] != c.shape[0]:
            raise ValueError(f"colour_mask needs (H, W, {c.shape[0]}) images, got {im.shape}")
        hit = np.all(im == c, axis=2)
        m = hit if m is None else (m | hit)
    return m
