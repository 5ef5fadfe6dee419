"""Readers of two third-party HDF5 event layouts: DSEC (``dsec``) and Monash/event_cnn (``monash``).

DSEC (Gehrig et al., "DSEC: A Stereo Event Camera Dataset for Driving Scenarios", RA-L 2021,
doi:10.1109/LRA.2021.3068942), as read by ``uzh-rpg/DSEC:scripts/utils/eventslicer.py``:

* ``/events/x``, ``/events/y`` (uint16), ``/events/t`` (µs, relative), ``/events/p`` (0/1);
* ``/ms_to_idx``: ``t[ms_to_idx[m]] >= 1000*m > t[ms_to_idx[m] - 1]``;
* ``/t_offset``: added to ``t`` to reach the image (and disparity) clock. **This reader adds it**,
  as DSEC's own slicer does, and records it in ``metadata.provenance["t_offset_us"]``;
* datasets are Blosc (ZSTD) compressed: the HDF5 filter comes from the ``hdf5plugin`` package,
  which is imported here when installed. DSEC event files store no sensor size; DSEC's event
  cameras are 640x480 (unrectified), used by default.

Monash / event_cnn (``TimoStoff/event_utils`` packager, read by ``TimoStoff/event_cnn_minimal``):

* ``events/xs``, ``events/ys`` (int16), ``events/ts`` (float64 seconds), ``events/ps`` (bool or
  0/1; mapped to +1/-1);
* ``images/image%09d`` (uint8) with attributes ``timestamp`` (seconds) and ``event_idx``;
* root attributes ``sensor_resolution`` = (height, width) and ``num_events``.

Seconds are converted to µs by ``np.rint(t * 1e6)``. Frames carry one timestamp each, used as both
``t_start_us`` and ``t_end_us`` (exposure unknown).

Both readers stream the event datasets by slices of ``chunk_events`` (bounded memory).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from .._util.limits import (LimitExceeded, check_finite, check_frame_bytes, check_frame_shape, check_h5_stored,
                        check_sensor_size)
from ..errors import FormatError
from ..events import EVENT_DTYPE, SensorSize
from ..model import CameraInfo, Frames, Metadata
from .base import EventChunk, EventFileReader, register_formats

__all__ = ["DsecReader", "MonashReader", "READERS", "WRITERS", "sniff", "HDF5_MAGIC", "DSEC_SENSOR_SIZE"]

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
#: DSEC event cameras (Prophesee Gen3.1): 640 x 480, used when the file stores no size.
DSEC_SENSOR_SIZE = SensorSize(480, 640)

_KNOWN_FILTERS = {32001: "Blosc", 32004: "LZ4", 32008: "Bitshuffle", 32015: "Zstandard",
                  32026: "Blosc2", 0x8ECF: "Prophesee ECF"}

try:  # registers Blosc/Zstd/LZ4... HDF5 filters with h5py when available
    import hdf5plugin  # noqa: F401
    _HAVE_HDF5PLUGIN = True
except ImportError:  # pragma: no cover - depends on the environment
    _HAVE_HDF5PLUGIN = False


def _h5py():
    import h5py
    return h5py


def _classify(f) -> str | None:
    """``"dsec"``, ``"monash"`` or None for an open h5py File."""
    if "hybridhdr_format_version" in f.attrs:
        return None
    ev = f.get("events")
    if ev is None or not isinstance(ev, _h5py().Group):
        return None
    if "t" in ev and "x" in ev and ("ms_to_idx" in f or "t_offset" in f):
        return "dsec"
    if "xs" in ev and "ts" in ev:
        return "monash"
    return None


def undetected_hint(path: Path, head: bytes) -> str | None:
    """For an HDF5 file no layout claims: what it holds (its top-level groups and datasets, the
    datasets of ``/events``) and, when ``/events`` has ``t``, ``x``, ``y``, ``p`` (DSEC's event
    datasets without its ``ms_to_idx``/``t_offset``), the ``--format dsec`` that reads it. None for
    a file that is not HDF5 or cannot be listed."""
    if not head.startswith(HDF5_MAGIC):
        return None
    try:
        h5py = _h5py()
        with h5py.File(path, "r") as f:
            top = sorted(f.keys())[:20]
            ev = f.get("events")
            inner = sorted(ev.keys())[:20] if isinstance(ev, h5py.Group) else []
    except Exception:  # a hint must never raise
        return None
    found = f"an HDF5 file holding {', '.join('/' + k for k in top) or 'nothing'}"
    if inner:
        found += f" (/events: {', '.join(inner)})"
    if {"t", "x", "y", "p"} <= set(inner):
        found += ("; its /events/{t,x,y,p} read as DSEC's layout with --format dsec (format='dsec' in Python; "
                  "sensor size from root attributes height/width, else DSEC's 640x480)")
    return found


def sniff(path: Path, head: bytes) -> str | None:
    """Detect DSEC or Monash HDF5 files (HDF5 magic at offset 0, then the dataset names)."""
    if not head.startswith(HDF5_MAGIC):
        return None
    try:
        h5py = _h5py()
        with h5py.File(path, "r") as f:
            return _classify(f)
    except Exception:  # sniffing must never raise
        return None


def _check_filters(path, ds) -> None:
    """Raise a clear FormatError when a dataset needs an HDF5 filter that is not available."""
    h5py = _h5py()
    try:
        plist = ds.id.get_create_plist()
        n = plist.get_nfilters()
        for i in range(n):
            fid = int(plist.get_filter(i)[0])
            if not h5py.h5z.filter_avail(fid):
                name = _KNOWN_FILTERS.get(fid, f"id {fid}")
                hint = ("pip install hdf5plugin (hybridhdr imports it automatically)"
                        if fid != 0x8ECF else "install Prophesee's hdf5_ecf plugin on HDF5_PLUGIN_PATH")
                raise FormatError(path, f"dataset {ds.name} is compressed with the HDF5 {name} filter, which is "
                                        f"not available: {hint}")
    except FormatError:
        raise
    except Exception:  # filter introspection is best effort; reading will report problems
        return


def _open(path):
    h5py = _h5py()
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise FormatError(path, f"cannot open as HDF5 (corrupt or truncated?): {exc}") from None
    try:
        from .._util.limits import check_h5_self_contained
        check_h5_self_contained(f, path)  # no external links / storage / virtual datasets
    except BaseException:
        f.close()
        raise
    return f


def _dataset(f, path, name: str, required: bool = True):
    h5py = _h5py()
    try:
        obj = f.get(name)
    except Exception as exc:
        raise FormatError(path, f"cannot access {name}: {exc}") from None
    if obj is None:
        if required:
            raise FormatError(path, f"missing dataset {name}")
        return None
    if not isinstance(obj, h5py.Dataset):
        raise FormatError(path, f"{name} must be a dataset, got a {type(obj).__name__}")
    return obj


def _read_slice(path, ds, i0: int, i1: int) -> np.ndarray:
    try:
        return ds[i0:i1]
    except Exception as exc:
        _check_filters(path, ds)
        raise FormatError(path, f"cannot read {ds.name}[{i0}:{i1}] (corrupt file or missing compression "
                                f"filter; for Blosc-compressed files: pip install hdf5plugin): {exc}",
                          record=i0) from None


def _check_columns(path, cols: dict, n: int) -> None:
    for name, ds in cols.items():
        if ds.ndim != 1:
            raise FormatError(path, f"{ds.name} must be 1-D, got shape {ds.shape}")
    for name, ds in cols.items():
        if ds.shape[0] != n:
            raise FormatError(path, f"{ds.name} has {ds.shape[0]} entries but the event count is {n}")
        if ds.dtype.kind not in "uifb":
            raise FormatError(path, f"{ds.name} must be numeric, got dtype {ds.dtype}")
        check_h5_stored(ds, path, ds.name)  # a declared count with no data behind it


def _build_events(path, i0: int, t_us: np.ndarray, x, y, p, ss: SensorSize, last_t: int | None) -> np.ndarray:
    """Validate one slice of columns and pack it into EVENT_DTYPE (record = global event index)."""
    n = t_us.shape[0]
    for name, v in (("x", x), ("y", y)):
        if v.dtype.kind == "f":
            bad = ~np.isfinite(v) | (v != np.floor(v))
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise FormatError(path, f"event {i0 + i}: {name} = {v[i].item()!r} is not an integer", record=i0 + i)
        if v.dtype.kind in "if" or v.dtype.kind == "b":
            bad = v < 0
            if np.any(bad):
                i = int(np.flatnonzero(bad)[0])
                raise FormatError(path, f"event {i0 + i}: negative {name} = {v[i]}", record=i0 + i)
    for name, v, lim, dim in (("x", x, ss.width, "width"), ("y", y, ss.height, "height")):
        bad = v >= lim
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise FormatError(path, f"event {i0 + i}: {name} = {int(v[i])} is outside the sensor {dim} {lim}",
                              record=i0 + i)
    if p.dtype == np.bool_:
        pol = np.where(p, 1, -1).astype(np.int8)
    else:
        pv = p.astype(np.float64) if p.dtype.kind == "f" else p.astype(np.int64)
        bad = (pv != 0) & (pv != 1) & (pv != -1)
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise FormatError(path, f"event {i0 + i}: polarity {p[i].item()!r} is not 0/1 (or -1/1)", record=i0 + i)
        pol = np.where(pv > 0, 1, -1).astype(np.int8)
    dec = np.flatnonzero(t_us[1:] < t_us[:-1])
    if dec.size:
        i = int(dec[0]) + 1
        raise FormatError(path, f"event {i0 + i}: timestamps must be non-decreasing; {int(t_us[i])} µs after "
                                f"{int(t_us[i - 1])} µs", record=i0 + i)
    if last_t is not None and n and t_us[0] < last_t:
        raise FormatError(path, f"event {i0}: timestamps must be non-decreasing; {int(t_us[0])} µs after "
                                f"{last_t} µs", record=i0)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = t_us
    ev["x"] = x
    ev["y"] = y
    ev["p"] = pol
    return ev


def _int_time(path, i0: int, t: np.ndarray, offset: int = 0) -> np.ndarray:
    """Integer µs column (+ offset) as int64, with overflow checks."""
    if t.dtype.kind == "f":
        bad = ~np.isfinite(t) | (t != np.floor(t))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise FormatError(path, f"event {i0 + i}: t = {t[i].item()!r} is not a whole number of µs", record=i0 + i)
    if t.dtype.kind == "u" and t.dtype.itemsize == 8 and t.size and t.max() > np.iinfo(np.int64).max - abs(offset):
        raise FormatError(path, "event timestamps overflow int64 µs", record=i0)
    tt = t.astype(np.int64)
    if offset:
        if tt.size and (int(tt.max()) > np.iinfo(np.int64).max - offset or int(tt.min()) < np.iinfo(np.int64).min - offset):
            raise FormatError(path, f"t + t_offset ({offset} µs) overflows int64", record=i0)
        tt = tt + np.int64(offset)
    return tt


class DsecReader(EventFileReader):
    """Streaming reader of DSEC event HDF5 files (``events.h5`` / ``events_left.h5``).

    Parameters
    ----------
    path : str or os.PathLike
    sensor_size : SensorSize or (height, width), optional
        Default 480x640 (DSEC's event cameras); root attributes ``height``/``width`` are used when
        a file has them.
    add_t_offset : bool, default True
        Add ``/t_offset`` (µs) to every timestamp, as DSEC's ``EventSlicer`` does, so event times
        are on the image clock.
    """

    format_name = "dsec"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        with _open(self.path) as f:
            cols = {k: _dataset(f, self.path, f"events/{k}") for k in ("x", "y", "t", "p")}
            n = int(cols["t"].shape[0]) if cols["t"].ndim == 1 else -1
            _check_columns(self.path, cols, n)
            for ds in cols.values():
                _check_filters(self.path, ds)
            t_offset = 0
            tod = _dataset(f, self.path, "t_offset", required=False)
            if tod is not None:
                try:
                    val = np.asarray(tod[()])
                except Exception as exc:
                    raise FormatError(self.path, f"cannot read /t_offset: {exc}") from None
                if val.size != 1 or val.dtype.kind not in "iuf" or not np.isfinite(val).all():
                    raise FormatError(self.path, f"/t_offset must be one number of µs, got {val!r}")
                t_offset = int(val.reshape(-1)[0])
            ms = _dataset(f, self.path, "ms_to_idx", required=False)
            n_ms = None if ms is None else int(ms.shape[0]) if ms.ndim == 1 else None
            stored = None
            if "height" in f.attrs and "width" in f.attrs:
                try:
                    stored = SensorSize(*check_sensor_size(f.attrs["height"], f.attrs["width"], self.path))
                except (TypeError, ValueError, OverflowError) as e:
                    if isinstance(e, LimitExceeded):
                        raise
                    stored = None
        self.n_events = n
        self.add_t_offset = bool(options.get("add_t_offset", True))
        self.t_offset_us = t_offset
        src = "option"
        if self.sensor_size is None:
            self.sensor_size = stored or DSEC_SENSOR_SIZE
            src = "file attributes" if stored else "DSEC default 640x480 (not stored in the file)"
        self.metadata = Metadata(event_camera=CameraInfo(self.sensor_size, "Prophesee Gen3.1 (DSEC)"),
                                 provenance={
            "source_file": str(self.path), "format": "dsec", "n_events": n, "t_offset_us": t_offset,
            "t_offset_added": self.add_t_offset, "ms_to_idx_entries": n_ms, "sensor_size_source": src,
            "hdf5plugin": _HAVE_HDF5PLUGIN})

    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        off = self.t_offset_us if self.add_t_offset else 0
        last_t = None
        with _open(self.path) as f:
            cols = {k: _dataset(f, self.path, f"events/{k}") for k in ("x", "y", "t", "p")}
            _check_columns(self.path, cols, self.n_events)
            for i0 in range(0, self.n_events, chunk_events):
                i1 = min(i0 + chunk_events, self.n_events)
                c = {k: _read_slice(self.path, ds, i0, i1) for k, ds in cols.items()}
                t = _int_time(self.path, i0, c["t"], off)
                ev = _build_events(self.path, i0, t, c["x"], c["y"], c["p"], self.sensor_size, last_t)
                if ev.size:
                    last_t = int(ev["t"][-1])
                    yield EventChunk(ev)


class MonashReader(EventFileReader):
    """Streaming reader of Monash / event_cnn HDF5 files (``events/xs, ys, ts, ps``; ``images/``).

    Parameters
    ----------
    path : str or os.PathLike
    sensor_size : SensorSize or (height, width), optional
        Default: root attribute ``sensor_resolution``, read as (height, width) as in event_utils
        (if the frames have the transposed shape, the frames' (height, width) is used and
        provenance says so); else the first image's shape; else max coordinate + 1 (one pass).
    """

    format_name = "monash"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        note = None
        with _open(self.path) as f:
            cols = {k: _dataset(f, self.path, f"events/{k}") for k in ("xs", "ys", "ts", "ps")}
            n = int(cols["ts"].shape[0]) if cols["ts"].ndim == 1 else -1
            _check_columns(self.path, cols, n)
            for ds in cols.values():
                _check_filters(self.path, ds)
            self._image_names = self._list_images(f)
            first_shape = None
            if self._image_names:
                ds = f["images"][self._image_names[0]]
                first_shape = tuple(ds.shape[:2]) if ds.ndim in (2, 3) else None
            res = f.attrs.get("sensor_resolution")
            stored = None
            if res is not None:
                r = np.asarray(res).reshape(-1)
                if r.size >= 2 and r.dtype.kind in "iuf" and np.all(r[:2] > 0) and np.all(r[:2] <= 65536):
                    stored = check_sensor_size(r[0], r[1], self.path)
                else:
                    raise FormatError(self.path, f"root attribute sensor_resolution must be (height, width), got {res!r}")
            attrs = {k: f.attrs[k] for k in ("num_events", "num_imgs", "t0", "tk", "duration") if k in f.attrs}
        self.n_events = n
        src = "option"
        if self.sensor_size is None:
            if stored is not None:
                h, w = stored
                if first_shape is not None and first_shape == (w, h) and (w, h) != (h, w):
                    h, w = w, h
                    note = "sensor_resolution is stored as (width, height) in this file (transposed to the frames)"
                self.sensor_size = SensorSize(h, w)
                src = "sensor_resolution attribute (height, width)"
            elif first_shape is not None:
                self.sensor_size = SensorSize(*first_shape)
                src = "first image shape"
            else:
                self.sensor_size = self._infer_size()
                src = "inferred"
                note = "no sensor_resolution attribute and no images: inferred as max coordinate + 1"
        num = attrs.get("num_events")
        if num is not None and int(np.asarray(num).reshape(-1)[0]) != n:
            raise FormatError(self.path, f"root attribute num_events = {int(np.asarray(num).reshape(-1)[0])} but "
                                         f"events/ts holds {n} events")
        prov = {"source_file": str(self.path), "format": "monash", "n_events": n, "sensor_size_source": src,
                "time_conversion": "t_us = rint(ts_seconds * 1e6)",
                "frame_timestamps": "images/*.attrs['timestamp'] (s) used as both t_start_us and t_end_us; "
                                    "exposure unknown",
                "attrs": {k: np.asarray(v).tolist() for k, v in attrs.items()}}
        if note:
            prov["sensor_size_note"] = note
        self.metadata = Metadata(event_camera=CameraInfo(self.sensor_size),
                                 frame_camera=CameraInfo(SensorSize(*first_shape) if first_shape else None),
                                 provenance=prov)

    def _list_images(self, f) -> list[str]:
        g = f.get("images")
        if g is None:
            return []
        h5py = _h5py()
        if not isinstance(g, h5py.Group):
            raise FormatError(self.path, f"/images must be a group, got a {type(g).__name__}")
        return sorted(k for k in g.keys() if isinstance(g.get(k), h5py.Dataset))

    def _infer_size(self) -> SensorSize:
        mx = my = -1
        with _open(self.path) as f:
            xs, ys = f["events/xs"], f["events/ys"]
            for i0 in range(0, self.n_events, 1 << 20):
                x = _read_slice(self.path, xs, i0, i0 + (1 << 20))
                y = _read_slice(self.path, ys, i0, i0 + (1 << 20))
                if x.size:
                    if x.min() < 0 or y.min() < 0:
                        raise FormatError(self.path, "negative event coordinates", record=i0)
                    mx, my = max(mx, int(x.max())), max(my, int(y.max()))
        if mx < 0:
            raise FormatError(self.path, "no events, no images and no sensor_resolution: pass sensor_size")
        try:
            return SensorSize(*check_sensor_size(my + 1, mx + 1, self.path, "sensor inferred from the coordinates"))
        except LimitExceeded:
            raise
        except ValueError as exc:
            raise FormatError(self.path, f"cannot infer the sensor size: {exc}") from None

    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        last_t = None
        with _open(self.path) as f:
            cols = {k: _dataset(f, self.path, f"events/{k}") for k in ("xs", "ys", "ts", "ps")}
            _check_columns(self.path, cols, self.n_events)
            for i0 in range(0, self.n_events, chunk_events):
                i1 = min(i0 + chunk_events, self.n_events)
                c = {k: _read_slice(self.path, ds, i0, i1) for k, ds in cols.items()}
                ts = c["ts"]
                if ts.dtype.kind == "f":
                    bad = ~np.isfinite(ts) | (np.abs(ts) * 1e6 >= 9.2e18)
                    if bad.any():
                        i = int(np.flatnonzero(bad)[0])
                        raise FormatError(self.path, f"event {i0 + i}: timestamp {ts[i].item()!r} s is not finite or "
                                                     f"overflows int64 µs", record=i0 + i)
                    t = np.rint(ts * 1e6).astype(np.int64)
                else:
                    raise FormatError(self.path, f"events/ts must hold float seconds, got dtype {ts.dtype}")
                ev = _build_events(self.path, i0, t, c["xs"], c["ys"], c["ps"], self.sensor_size, last_t)
                if ev.size:
                    last_t = int(ev["t"][-1])
                    yield EventChunk(ev)

    def read_frames(self) -> Frames | None:
        """The ``images/image%09d`` frames (None when the file has no ``images`` group).

        Returns
        -------
        Frames or None
            ``images`` (K, H, W) or (K, H, W, 3), dtype as stored; ``t_start_us`` = ``t_end_us`` =
            ``rint(timestamp * 1e6)``; frames are ordered by timestamp. ``encoding`` is the
            declared ``frame_encoding`` option, else ``"unknown"`` (the layout states none).
        """
        if not self._image_names:
            with _open(self.path) as f:
                return None if "images" not in f else Frames.empty(*self.sensor_size.shape)
        imgs, ts = [], []
        with _open(self.path) as f:
            g = f["images"]
            total = 0
            for k, name in enumerate(self._image_names):
                ds = g[name]
                if ds.ndim not in (2, 3):
                    raise FormatError(self.path, f"images/{name} must be (H, W) or (H, W, 3), got {ds.shape}",
                                      record=k)
                check_frame_shape((1,) + tuple(ds.shape), self.path, f"images/{name}")
                total += int(np.prod(ds.shape, dtype=np.float64)) * ds.dtype.itemsize
                check_frame_bytes(total, self.path, "the images")
                check_h5_stored(ds, self.path, f"images/{name}")
                try:
                    im = ds[()]
                    t = ds.attrs.get("timestamp")
                except Exception as exc:
                    raise FormatError(self.path, f"cannot read images/{name}: {exc}", record=k) from None
                if t is None:
                    raise FormatError(self.path, f"images/{name} has no 'timestamp' attribute", record=k)
                tv = np.asarray(t, dtype=np.float64).reshape(-1)
                if tv.size != 1 or not np.isfinite(tv[0]):
                    raise FormatError(self.path, f"images/{name}: timestamp must be one finite number of "
                                                 f"seconds, got {t!r}", record=k)
                im = np.asarray(im)
                if im.ndim == 3 and im.shape[2] == 1:
                    im = im[..., 0]
                if not (im.ndim == 2 or (im.ndim == 3 and im.shape[2] == 3)):
                    raise FormatError(self.path, f"images/{name} must be (H, W) or (H, W, 3), got {im.shape}",
                                      record=k)
                if imgs and (im.shape != imgs[0].shape or im.dtype != imgs[0].dtype):
                    raise FormatError(self.path, f"images/{name} has shape {im.shape} dtype {im.dtype}, unlike "
                                                 f"the first image's {imgs[0].shape} {imgs[0].dtype}", record=k)
                if im.dtype.kind not in "uifb":
                    raise FormatError(self.path, f"images/{name} must be numeric, got dtype {im.dtype}", record=k)
                check_finite(im, self.path, f"images/{name}")
                if abs(tv[0]) * 1e6 >= 2.0 ** 63:
                    raise FormatError(self.path, f"images/{name}: timestamp {tv[0]!r} s overflows int64 µs", record=k)
                imgs.append(im)
                ts.append(int(np.rint(tv[0] * 1e6)))
        t = np.asarray(ts, np.int64)
        order = np.argsort(t, kind="stable")
        return Frames(np.stack(imgs)[order], t[order], t[order].copy(), encoding=self._frame_encoding("unknown"))


READERS = {"dsec": DsecReader, "monash": MonashReader}
WRITERS: dict = {}

register_formats(__name__, {
    "dsec": "DSEC events HDF5 (/events/{x,y,t,p}, /ms_to_idx, /t_offset)",
    "monash": "Monash / event_cnn HDF5 (events/xs, ys, ts, ps; images/)",
}, READERS, WRITERS)
