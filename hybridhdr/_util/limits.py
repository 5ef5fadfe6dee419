"""Limits on what file headers may ask for, checked before any memory is allocated or work done.

A header is data an attacker (or a bug) controls: a sensor of 65536², a frame ROI of 10000², a
declared event count with nothing stored behind it, a packet that inflates to gigabytes, a PNG
bomb, or ``--fps 1e12`` all become a :class:`LimitExceeded` error naming the value, the limit and
the override, instead of hours of work or an out-of-memory kill.

Defaults (see ``docs/security.md``):

====================  ==========================================================
``max_side``          8192 pixels per side of a sensor, frame or ROI
``max_frame_bytes``   4 GiB of decoded frames held by one reader
``max_packet_bytes``  256 MiB decompressed per packet / zip member / .mat array
``max_outputs``       1,000,000 output frames for ``--fps`` / ``--times-us``
====================  ==========================================================

Users with genuinely huge data lift them with ``--allow-huge`` on the command line,
``HYBRIDHDR_ALLOW_HUGE=1`` in the environment, or :func:`allow_huge` in Python (a context
manager). Checks of *consistency* (a declared count larger than the bytes stored, non-finite
values) are never lifted: they describe broken files, not big ones.
"""

from __future__ import annotations

import contextlib
import math
import os
import threading

import numpy as np

from ..errors import FormatError

__all__ = ["LimitExceeded", "LIMITS", "allow_huge", "huge_allowed", "check_sensor_size", "check_frame_shape",
           "check_frame_bytes", "check_output_count", "output_count_for_fps", "check_fps_outputs",
           "check_packet_size", "check_declared_count", "check_h5_stored", "check_finite", "open_image",
           "check_h5_self_contained", "check_number", "check_input_file", "read_bytes_bounded",
           "read_text_bounded", "read_json_bounded", "check_json_depth", "MAX_JSON_DEPTH", "check_memory",
           "memory_budget_bytes",
           "OVERRIDE_HINT"]

LIMITS = {
    "max_side": 8192,
    "max_frame_bytes": 4 << 30,
    "max_packet_bytes": 256 << 20,
    "max_outputs": 1_000_000,
    "max_duration_us": 3_600_000_000,   # simulated time of a scene / bench dataset: 1 hour
    "max_runs": 10_000,                 # runs of one bench after grids are expanded
    "max_spp": 4096,                    # renderer samples per pixel
    "max_subdivisions": 8,              # icosphere subdivisions (20 * 4^8 = 1.3 M faces)
    "max_text_bytes": 64 << 20,         # a config / profile / CRF / --times-us file read whole
    "max_events": 1_000_000_000,        # events one simulation may emit (16 GB as records)
}

OVERRIDE_HINT = "if the data really is that large, pass --allow-huge (or set HYBRIDHDR_ALLOW_HUGE=1)"

_state = {"allow": 0}  # process-wide: the recorder's source threads see it too
_lock = threading.Lock()


class LimitExceeded(FormatError):
    """A header (or an option) asks for more than the configured limit; see ``docs/security.md``."""


def huge_allowed() -> bool:
    """True when the limits are lifted (``allow_huge`` or ``HYBRIDHDR_ALLOW_HUGE=1``)."""
    if _state["allow"]:
        return True
    return os.environ.get("HYBRIDHDR_ALLOW_HUGE", "").strip().lower() in ("1", "true", "yes", "on")


@contextlib.contextmanager
def allow_huge(enabled: bool = True):
    """Lift the size limits inside the block (process-wide, nestable) when ``enabled``."""
    if not enabled:
        yield
        return
    with _lock:
        _state["allow"] += 1
    try:
        yield
    finally:
        with _lock:
            _state["allow"] -= 1


def _exceeded(path, what: str, value, limit, offset=None, record=None):
    raise LimitExceeded(path, f"{what} ({value:,}) exceeds the limit of {limit:,}; {OVERRIDE_HINT}",
                        offset=offset, record=record)


def check_sensor_size(height, width, path=None, what: str = "sensor") -> tuple[int, int]:
    """Validate a sensor (or frame, ROI) size from a header: positive integers up to ``max_side``."""
    try:
        if any(isinstance(v, (float, np.floating)) and not float(v).is_integer() for v in (height, width)):
            raise ValueError("not integral")  # 33.5 is not a size (it used to become 33)
        h, w = int(height), int(width)
    except (TypeError, ValueError, OverflowError):
        raise FormatError(path, f"{what} size {height!r} x {width!r} is not a pair of integers") from None
    if h < 1 or w < 1:
        raise FormatError(path, f"{what} size {w}x{h} (width x height) must be at least 1x1")
    lim = LIMITS["max_side"]
    if (h > lim or w > lim) and not huge_allowed():
        raise LimitExceeded(path, f"{what} of {w}x{h} pixels (width x height) is larger than the limit of {lim} "
                                  f"pixels per side; {OVERRIDE_HINT}")
    return h, w


def check_frame_shape(shape, path=None, what: str = "frames") -> None:
    """The height and width of a frame stack (K, H, W[, C]) within ``max_side``."""
    shape = tuple(int(s) for s in shape)
    hw = shape[1:3] if len(shape) >= 3 else shape[-2:]
    if hw and max(hw) > LIMITS["max_side"] and not huge_allowed():
        raise LimitExceeded(path, f"{what} of shape {shape} have a side larger than the limit of "
                                  f"{LIMITS['max_side']} pixels; {OVERRIDE_HINT}")


def check_frame_bytes(n_bytes, path=None, what: str = "decoded frames") -> None:
    n_bytes = int(n_bytes)
    if n_bytes > LIMITS["max_frame_bytes"] and not huge_allowed():
        _exceeded(path, f"{what} would take {n_bytes:,} bytes of memory; that", n_bytes, LIMITS["max_frame_bytes"])


def check_packet_size(n_bytes, path=None, what: str = "decompressed packet", offset=None) -> None:
    """A decompressed size declared by a header (packet, zip member, array) within ``max_packet_bytes``."""
    n_bytes = int(n_bytes)
    if n_bytes < 0:
        raise FormatError(path, f"{what} declares a negative size {n_bytes}", offset=offset)
    if n_bytes > LIMITS["max_packet_bytes"] and not huge_allowed():
        raise LimitExceeded(path, f"{what} declares {n_bytes:,} bytes, above the limit of "
                                  f"{LIMITS['max_packet_bytes']:,}; {OVERRIDE_HINT}", offset=offset)


def check_output_count(n, what: str = "output frames", limit: int | None = None) -> int:
    """Refuse more than ``max_outputs`` outputs (``--fps``/``--times-us``) before any work; returns ``n``.

    >>> check_output_count(300)
    300
    """
    if isinstance(n, float) and not math.isfinite(n):
        raise ValueError(f"the number of {what} is not finite ({n}); check --fps / --times-us")
    n = int(n)
    if n < 0:
        raise ValueError(f"the number of {what} is negative ({n})")
    lim = LIMITS["max_outputs"] if limit is None else int(limit)
    if n > lim and not huge_allowed():
        raise LimitExceeded(None, f"{n:,} {what} requested, above the limit of {lim:,} (check --fps / "
                                  f"--times-us); {OVERRIDE_HINT}")
    return n


def output_count_for_fps(t_start_us, t_end_us, fps) -> float:
    """How many outputs ``fps`` frames per second over ``[t_start_us, t_end_us]`` make (a float: may be huge)."""
    fps = float(fps)
    if not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"--fps must be a positive finite number, got {fps}")
    span = float(t_end_us) - float(t_start_us)
    if not math.isfinite(span) or span < 0:
        raise ValueError(f"the time range [{t_start_us}, {t_end_us}] µs is empty or not finite")
    return math.floor(span * fps / 1e6) + 1


def check_fps_outputs(t_start_us, t_end_us, fps, limit: int | None = None) -> int:
    """:func:`output_count_for_fps` then :func:`check_output_count`, without building the time array."""
    n = output_count_for_fps(t_start_us, t_end_us, fps)
    lim = LIMITS["max_outputs"] if limit is None else int(limit)
    if n > lim and not huge_allowed():
        raise LimitExceeded(None, f"--fps {float(fps):g} over {(float(t_end_us) - float(t_start_us)) / 1e6:g} s "
                                  f"makes {n:,.0f} output frames, above the limit of {lim:,}; {OVERRIDE_HINT}")
    return int(n)


def check_declared_count(n, available_bytes, bytes_per_item, path=None, what: str = "events", offset=None) -> int:
    """A count from a header must fit in the bytes actually stored (never lifted: a broken file)."""
    n = int(n)
    if n < 0:
        raise FormatError(path, f"declared number of {what} is negative ({n})", offset=offset)
    need = n * int(bytes_per_item)
    if need > int(available_bytes):
        raise FormatError(path, f"the header declares {n:,} {what} ({need:,} bytes) but only "
                                f"{int(available_bytes):,} bytes are stored", offset=offset)
    return n


def check_h5_stored(ds, path=None, name: str | None = None) -> None:
    """An HDF5 dataset's declared shape must be backed by stored data (no fill-value-only giants).

    Chunked datasets need every chunk allocated; contiguous ones need their full size stored.
    Small datasets (< 1 MiB declared) are not checked (a fill value there is harmless).
    """
    name = name or getattr(ds, "name", "dataset")
    try:
        n_bytes = int(np.prod(ds.shape, dtype=np.float64) * ds.dtype.itemsize)
    except Exception:
        return
    if n_bytes < (1 << 20):
        return
    try:
        chunks = ds.chunks
        if chunks is None:
            if ds.compression is None and ds.id.get_storage_size() < n_bytes:
                raise FormatError(path, f"{name} declares shape {ds.shape} ({n_bytes:,} bytes) but stores only "
                                        f"{ds.id.get_storage_size():,} bytes; the file is truncated or forged")
            return
        need = 1
        for s, c in zip(ds.shape, chunks):
            need *= -(-int(s) // int(c))
        have = ds.id.get_num_chunks()
    except FormatError:
        raise
    except Exception:
        return
    if have < need:
        raise FormatError(path, f"{name} declares shape {ds.shape} in {need:,} chunks but only {have:,} chunks are "
                                f"stored; the file is truncated or its size is forged")


def check_finite(a, path=None, what: str = "frames", allow_nan: bool = False) -> None:
    """Floating-point data must be finite (NaN / ±inf are errors, never silently propagated).

    ``allow_nan``: NaN is a documented mask of the data (HDR references: pixel not covered), so
    only ±inf is an error."""
    a = np.asarray(a)
    if a.dtype.kind not in "fc" or a.size == 0:
        return
    bad = np.isinf(a) if allow_nan else ~np.isfinite(a)
    if bad.any():
        idx = np.unravel_index(int(np.argmax(bad)), a.shape)
        n = int(bad.sum())
        raise FormatError(path, f"{what} hold {n:,} non-finite values (first {a[idx]!r} at index "
                                f"{tuple(int(i) for i in idx)}); "
                                + ("infinity is not a valid radiance (NaN marks uncovered pixels)" if allow_nan
                                   else "NaN and infinity are not valid intensities"))


def open_image(path, what: str = "image"):
    """Open an image with PIL with the size limits applied: a bomb or a giant is a clean error.

    Returns the lazy ``PIL.Image`` (header read only); decode with ``np.asarray(im)``.
    """
    from PIL import Image
    old = Image.MAX_IMAGE_PIXELS
    try:
        Image.MAX_IMAGE_PIXELS = None if huge_allowed() else LIMITS["max_side"] ** 2
        try:
            im = Image.open(path)
        except Image.DecompressionBombError as e:
            raise LimitExceeded(path, f"{what} is too large to decode safely ({e}); {OVERRIDE_HINT}") from None
        except (OSError, SyntaxError, ValueError) as e:
            raise FormatError(path, f"cannot read the {what} ({type(e).__name__}: {e})") from None
    finally:
        Image.MAX_IMAGE_PIXELS = old
    w, h = im.size
    check_sensor_size(h, w, path, what)
    return im


def check_number(value, what: str, *, lo=None, limit: str | None = None, hi=None, integer: bool = False,
                 path=None):
    """A number from a scene, bench or option: finite, ``>= lo``, an integer if ``integer``, at
    most ``hi`` (never lifted) and at most ``LIMITS[limit]`` (lifted by ``--allow-huge``).
    Checked before anything is allocated (a duration of 9e18 µs used to end in a segfault)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{what} must be a number, got {type(value).__name__} {value!r}")
    v = float(value)
    if not math.isfinite(v) or (lo is not None and v < lo):
        raise ValueError(f"{what} must be finite" + (f" and >= {lo:g}" if lo is not None else "") + f", got {value!r}")
    if integer and not v.is_integer():
        raise ValueError(f"{what} must be a whole number, got {value!r}")
    if hi is not None and v > hi:
        raise ValueError(f"{what} must be at most {hi:g}, got {value!r}")
    if limit is not None and v > LIMITS[limit] and not huge_allowed():
        raise LimitExceeded(path, f"{what} = {value!r} exceeds the limit of {LIMITS[limit]:,}; {OVERRIDE_HINT}")
    return int(v) if integer else v


def memory_budget_bytes() -> int:
    """Memory one working set may take: half the machine's RAM, and no more than the address
    space this process may still map (``RLIMIT_AS``) minus 256 MiB of headroom."""
    budget = 1 << 62
    try:
        with open("/proc/meminfo") as f:
            for ln in f:
                if ln.startswith("MemTotal:"):
                    budget = int(ln.split()[1]) * 1024 // 2
                    break
    except (OSError, ValueError, IndexError):
        pass
    try:
        import resource
        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            vm = 0
            with open("/proc/self/status") as f:
                for ln in f:
                    if ln.startswith("VmSize:"):
                        vm = int(ln.split()[1]) * 1024
            budget = min(budget, max(0, soft - vm - (256 << 20)))
    except (ImportError, OSError, ValueError):
        pass
    return int(budget)


def check_memory(n_bytes, path=None, what: str = "working set") -> None:
    """``n_bytes`` (an estimate made before allocating) within :func:`memory_budget_bytes`."""
    n_bytes = int(n_bytes)
    budget = memory_budget_bytes()
    if n_bytes > budget and not huge_allowed():
        raise LimitExceeded(path, f"{what} would take about {n_bytes:,} bytes of memory, more than the "
                                  f"{budget:,} available to it; {OVERRIDE_HINT}")


def check_input_file(path, what: str = "input") -> None:
    """``path`` must be a regular file (or a folder, for folder formats) - never a FIFO, a device
    or a socket, which would hang the reader (a FIFO) or never end (``/dev/zero``)."""
    import stat
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} {path} does not exist") from None
    except OSError as e:
        raise OSError(e.errno, f"cannot access {what} {path}: {e.strerror}") from None
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else "a character device" if stat.S_ISCHR(st.st_mode)
                else "a block device" if stat.S_ISBLK(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode)
                else "not a regular file")
        raise FormatError(path, f"{what} is {kind}; only regular files (and folders) are read")


def read_bytes_bounded(path, what: str = "file", limit: int | None = None) -> bytes:
    """The bytes of a small input file (config, profile, CRF, time list), refused when it is not a
    regular file or larger than ``max_text_bytes`` (64 MiB; ``--allow-huge`` lifts it)."""
    check_input_file(path, what)
    lim = LIMITS["max_text_bytes"] if limit is None else int(limit)
    with open(path, "rb") as f:
        data = f.read(lim + 1)
    if len(data) > lim and not huge_allowed():
        raise LimitExceeded(path, f"{what} is larger than {lim:,} bytes; {OVERRIDE_HINT}")
    if len(data) > lim:
        with open(path, "rb") as f:
            data = f.read()
    return data


def read_text_bounded(path, what: str = "file", encoding: str = "utf-8", limit: int | None = None) -> str:
    """:func:`read_bytes_bounded` decoded (a decoding error names the file)."""
    data = read_bytes_bounded(path, what, limit)
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as e:
        raise FormatError(path, f"{what} is not {encoding} text ({e.reason} at byte {e.start})") from None


#: Deepest JSON nesting any input may have (a profile, a run record, a bracket set's metadata
#: nest a few levels); deeper is refused before anything walks it.
MAX_JSON_DEPTH = 64


def check_json_depth(obj, path=None, what: str = "JSON", max_depth: int = MAX_JSON_DEPTH) -> None:
    """Refuse a parsed JSON value nested deeper than ``max_depth`` (iterative: never recursion)."""
    stack = [(obj, 1)]
    while stack:
        o, d = stack.pop()
        if isinstance(o, (dict, list)):
            if d > max_depth:
                raise FormatError(path, f"{what} is nested more than {max_depth} levels deep")
            stack.extend((v, d + 1) for v in (o.values() if isinstance(o, dict) else o))


def read_json_bounded(path, what: str = "JSON file", limit: int | None = None, max_depth: int = MAX_JSON_DEPTH,
                      **loads_kw):
    """A small JSON input: :func:`read_text_bounded` (a regular file within ``limit`` bytes),
    parsed with its nesting bounded (5,000 levels of ``[`` is a clean error, never a
    RecursionError traceback)."""
    import json
    text = read_text_bounded(path, what, limit=limit)
    try:
        obj = json.loads(text, **loads_kw)
    except RecursionError:
        raise FormatError(path, f"{what} is nested more than {max_depth} levels deep") from None
    except ValueError as e:
        raise FormatError(path, f"{what} is not valid JSON ({e})") from None
    check_json_depth(obj, path, what, max_depth)
    return obj


def check_h5_self_contained(f, path=None, max_objects: int = 1_000_000) -> None:
    """An HDF5 file must hold all its data itself: external links, external raw storage and
    virtual datasets are refused (they make a reader open other files: ``/etc/passwd`` as frames,
    fill values for a missing source). Never lifted (``docs/security.md``)."""
    import h5py
    seen = [0]

    def walk(g, prefix):
        for name in g:
            seen[0] += 1
            if seen[0] > max_objects:
                raise FormatError(path, f"holds more than {max_objects:,} HDF5 objects; refusing to walk it")
            full = f"{prefix}/{name}"
            link = g.get(name, getlink=True)
            if isinstance(link, h5py.ExternalLink):
                raise FormatError(path, f"{full} is an HDF5 external link to {link.filename}:{link.path}; links to "
                                        f"other files are not followed (docs/security.md)")
            if isinstance(link, h5py.SoftLink):
                continue  # points inside this file; the target is checked where it lives
            obj = g.get(name)
            if isinstance(obj, h5py.Group):
                walk(obj, full)
            elif isinstance(obj, h5py.Dataset):
                if obj.is_virtual:
                    raise FormatError(path, f"{full} is an HDF5 virtual dataset (data mapped from other files); "
                                            f"not read (docs/security.md)")
                if obj.external:
                    raise FormatError(path, f"{full} stores its data in external file(s) "
                                            f"{[e[0] for e in obj.external][:3]}; not read (docs/security.md)")
    try:
        walk(f, "")
    except FormatError:
        raise
    except (KeyError, OSError, RuntimeError, ValueError) as e:
        raise FormatError(path, f"cannot walk the HDF5 structure ({type(e).__name__}: {e})") from None
