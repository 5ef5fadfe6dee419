"""The hybridhdr recording container: one HDF5 file per recording.

Layout (format version 2.1; see ``docs/recording-format.md``)::

    /                       attrs: hybridhdr_format_version, sensor_height, sensor_width, metadata_json
    /events/t  int64 µs     chunked, compressed; non-decreasing
    /events/x  uint16       column
    /events/y  uint16       row
    /events/p  int8         +1 / -1
    /events/index_ms, /events/index_first  int64 (K,): sparse time index (format 2.0), attr index_stride;
                            index_first[k] = first i with t[i] >= 1000*index_ms[k]  (format 1.x files have
                            the dense /events/ms_to_idx instead, still read)
    /frames/images          (K, H, W[, 3]) any dtype, one chunk per frame; attrs: encoding
    /frames/t_start_us, /frames/t_end_us   int64 (K,)
    /frames/gain, /frames/iso              float64 (K,), optional
    /triggers/t int64, /triggers/channel uint16, /triggers/edge int8
    /imu/t int64 µs, /imu/accel_x_g ... /imu/mag_z_ut float32   (format 2.1; IMU samples on the event
                            clock, one dataset per ``IMU_DTYPE`` field, attr ``unit`` on each; a file
                            without /imu (2.0 and older) reads as holding no IMU samples)
    /hdr/images float32 (K, H, W[, 3]), /hdr/t_us int64 (K,)
    /thresholds/c_on, /thresholds/c_off  float64 (H, W), optional: per-pixel ON/OFF contrast
                            thresholds (log units; NaN = not estimated); attrs fallback_on,
                            fallback_off, method, provenance_json (``store_thresholds``)

The writer streams: events are appended in chunks with a bounded buffer, the sparse time index
(one entry per ``index_stride`` events at most, so its size follows the events, not the time span)
is built incrementally, and the file is written as ``NAME.partial`` and renamed on close. The reader is
lazy: it slices a time window through the millisecond index or iterates in chunks of N events or
T µs without loading the file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterator

import numpy as np

from .._util.checks import check_shape
from .._util.limits import check_finite, check_frame_bytes, check_frame_shape, check_h5_stored, check_sensor_size
from .._version import __version__
from ..errors import FormatError, WindowOutsideDataError
from ..events import (EVENT_DTYPE, IMU_DTYPE, IMU_FIELDS, TRIGGER_DTYPE, SensorSize, api_window, empty_events,
                      empty_imu, empty_triggers, slice_time, validate_events, validate_imu, validate_triggers)
from ..model import FRAME_ENCODINGS, Frames, HDRReferences, Metadata, Recording
from ._safe_h5 import close_and_remove, open_h5_for_writing
from .base import EventChunk, EventFileReader, EventFileWriter, register_formats
from .thresholds import ThresholdMap

__all__ = ["FORMAT_VERSION", "RecordingWriter", "RecordingFile", "write_recording", "read_recording",
           "READERS", "WRITERS", "sniff"]

#: 2.1 added the /imu group (optional to readers: a 2.0 file has none and reads with no IMU samples)
FORMAT_VERSION = "2.1"
#: major versions this reader understands: 1.x (dense millisecond index), 2.x (sparse index)
READABLE_MAJORS = ("1", "2")
#: at most one index entry per this many events (each entry at the start of a millisecond)
INDEX_STRIDE = 4096
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_EVENT_FIELDS = (("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1"))
_TRIGGER_FIELDS = (("t", "<i8"), ("channel", "<u2"), ("edge", "i1"))
_IMU_FIELDS = (("t", "<i8", "us"),) + tuple((name, "<f4", unit) for name, unit, _ in IMU_FIELDS)
_CHUNK_ELEMS = 1 << 17


def _h5py():
    try:
        import h5py
    except ImportError as e:  # pragma: no cover - h5py is a core dependency
        raise ImportError("the hybridhdr container needs h5py: pip install h5py") from e
    return h5py


def _compression_kwargs(compression):
    if compression in (None, "none"):
        return {}
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 1, "shuffle": True}
    if compression == "lzf":
        return {"compression": "lzf", "shuffle": True}
    raise ValueError(f"compression must be 'gzip', 'lzf' or None, got {compression!r}")


def _deflate_chunk(bufs, n):
    """zlib streams (HDF5's deflate filter format) of the staged chunk images ``bufs``.

    ISA-L's deflate (``isal``, when installed) at level 1 writes the same format 5-6x faster
    than zlib at level 1, for files about 5 % larger (``benchmarks/convert.py``); zlib level 1
    otherwise. Runs in any thread (both release the GIL).
    """
    return [_DEFLATE(b, _DEFLATE_LEVEL) for b in bufs]


def _pick_deflate():
    try:
        from isal import isal_zlib
        return isal_zlib.compress, 1, "isal"
    except ImportError:
        import zlib
        return zlib.compress, 1, "zlib"


_DEFLATE, _DEFLATE_LEVEL, DEFLATE_IMPL = _pick_deflate()


class RecordingWriter(EventFileWriter):
    """Streaming writer of the hybridhdr container.

    Parameters
    ----------
    path : path-like
        Final file name; data goes to ``path + '.partial'`` until :meth:`close`.
    sensor_size : SensorSize or (height, width)
        Event-camera size.
    metadata : Metadata, optional
    compression : {"gzip", "lzf", None}
        Dataset compression; deflate (ISA-L level 1 when ``isal`` is installed, else zlib level 1)
        with byte shuffle by default, readable by any HDF5 tool. "gzip" and None chunks are built
        by this writer and stored with direct chunk writes; "lzf" goes through h5py's filter.
    buffer_events : int
        Bounds the events held in memory: at most ``buffer_events // 131072 + threads`` chunks of
        131,072 events wait to be deflated and stored.
    threads : int, optional
        Deflate threads (default ``min(2, cpu_count)``; 0: deflate in the calling thread).

    Examples
    --------
    >>> import tempfile, os, hybridhdr
    >>> from hybridhdr.formats.container import RecordingWriter, RecordingFile
    >>> path = os.path.join(tempfile.mkdtemp(), "rec.h5")
    >>> with RecordingWriter(path, sensor_size=(4, 5)) as w:
    ...     w.write_events(hybridhdr.make_events([0, 10, 2000], [0, 1, 4], [0, 2, 3], [1, -1, 1]))
    >>> RecordingFile(path).n_events
    3
    """

    format_name = "hybridhdr"
    supports = frozenset({"triggers", "frames", "hdr", "imu"})

    def __init__(self, path, sensor_size=None, metadata: Metadata | None = None, *,
                 compression="gzip", buffer_events: int = 1 << 20, threads: int | None = None,
                 **options):
        self._comp = _compression_kwargs(compression)
        self._codec = "gzip" if compression == "gzip" else (None if compression in (None, "none") else "h5py")
        if int(buffer_events) < 1:
            raise ValueError(f"buffer_events must be >= 1, got {buffer_events}")
        self._buffer_events = int(buffer_events)
        if threads is None:
            threads = min(2, os.cpu_count() or 1)
        if int(threads) < 0:
            raise ValueError(f"threads must be >= 0, got {threads}")
        self._threads = int(threads)
        super().__init__(path, sensor_size, metadata, **options)

    # -- EventFileWriter hooks ----------------------------------------------------------------
    def _open(self):
        _h5py()
        self._f = self._guard = None
        self._pool = None
        self._f, self._guard = open_h5_for_writing(self.tmp_path)
        f = self._f
        f.attrs["hybridhdr_format_version"] = FORMAT_VERSION
        f.attrs["sensor_height"] = self.sensor_size.height
        f.attrs["sensor_width"] = self.sensor_size.width
        md = self.metadata.to_dict()
        md["event_camera"]["height"], md["event_camera"]["width"] = self.sensor_size.shape
        f.attrs["metadata_json"] = json.dumps(md)
        f.attrs["created_by"] = f"hybridhdr {__version__}"
        g = f.create_group("events")
        for name, dt in _EVENT_FIELDS:
            g.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dt, chunks=(_CHUNK_ELEMS,), **self._comp)
        for name in ("index_ms", "index_first"):
            g.create_dataset(name, shape=(0,), maxshape=(None,), dtype="<i8", chunks=(4096,))
        g["index_ms"].attrs["index_stride"] = INDEX_STRIDE
        gt = f.create_group("triggers")
        for name, dt in _TRIGGER_FIELDS:
            gt.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dt, chunks=(4096,))
        gi = f.create_group("imu")
        for name, dt, unit in _IMU_FIELDS:
            d = gi.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dt, chunks=(4096,), **self._comp)
            d.attrs["unit"] = unit
        self._ds = [g[name] for name, _ in _EVENT_FIELDS]
        self._idx_ds = (g["index_ms"], g["index_first"])
        # events are staged into chunk images (HDF5's shuffle layout when compressed with gzip),
        # deflated by a small thread pool and stored with direct chunk writes, in order
        self._shuffle = self._codec == "gzip"
        self._free: list = []  # recycled chunk buffers
        self._cur = self._new_buffers()
        self._pos = 0  # events in the current chunk
        self._chunk_no = 0  # chunk index of the current chunk
        self._pending: list = []  # (chunk_no, n_events, future or buffers) in chunk order
        self._max_pending = max(1, self._buffer_events // _CHUNK_ELEMS) + self._threads
        self._n_staged = 0  # events staged so far (= written once pending chunks are stored)
        self._n_extent = 0  # current extent of the event datasets
        self._idx_state = np.zeros(4, np.int64)
        self._idx_ms_buf = np.empty(_CHUNK_ELEMS // INDEX_STRIDE + 2, np.int64)
        self._idx_first_buf = np.empty_like(self._idx_ms_buf)
        self._idx_pending: list = []
        self._n_written = 0
        self._trig_last = None
        self._imu_last = None
        if self._codec == "gzip" and self._threads:
            from concurrent.futures import ThreadPoolExecutor
            self._pool = ThreadPoolExecutor(self._threads, thread_name_prefix="hybridhdr-deflate")
        self._guard.check()

    def _new_buffers(self):
        if self._free:
            return self._free.pop()
        return tuple(np.empty(_CHUNK_ELEMS * np.dtype(dt).itemsize, np.uint8) for _, dt in _EVENT_FIELDS)

    def _write_events(self, events):
        from . import _write_kernels as WK  # numba: loaded with the first write
        if not events.flags.c_contiguous:
            events = np.ascontiguousarray(events)
        rec = events.view(np.uint8).reshape(len(events), events.dtype.itemsize)
        t = events["t"]
        n = len(events)
        i = 0
        while i < n:
            k = min(n - i, _CHUNK_ELEMS - self._pos)
            bt, bx, by, bp = self._cur
            m = WK.stage_events(rec, t, i, k, bt, bx, by, bp, self._pos, _CHUNK_ELEMS, self._shuffle,
                                self._n_staged, self._idx_state, INDEX_STRIDE, self._idx_ms_buf,
                                self._idx_first_buf, 0)
            if m:
                self._idx_pending.append((self._idx_ms_buf[:m].copy(), self._idx_first_buf[:m].copy()))
            self._pos += k
            self._n_staged += k
            i += k
            if self._pos == _CHUNK_ELEMS:
                self._submit_chunk()

    def _submit_chunk(self):
        """Hand the full current chunk to the deflate pool (or store it now) and start the next."""
        bufs = self._cur
        if self._pool is not None:
            job = self._pool.submit(_deflate_chunk, bufs, self._pos)
        elif self._codec == "gzip":
            job = _deflate_chunk(bufs, self._pos)
        else:
            job = None
        self._pending.append((self._chunk_no, self._pos, job, bufs))
        self._chunk_no += 1
        self._pos = 0
        self._cur = self._new_buffers()
        if len(self._pending) > self._max_pending:
            self._store_pending(len(self._pending) - self._max_pending)

    def _store_pending(self, count=None):
        """Store the oldest ``count`` pending chunks (all: None) in order, then their index entries."""
        todo = self._pending if count is None else self._pending[:count]
        self._pending = [] if count is None else self._pending[count:]
        try:
            for chunk_no, n, job, bufs in todo:
                self._store_chunk(chunk_no, n, job, bufs)
                self._free.append(bufs)
        except BaseException:
            for _, _, job, _ in self._pending:  # nothing may run on after a failure
                if job is not None and hasattr(job, "cancel"):
                    job.cancel()
            self._pending = []
            raise
        self._store_index(force=False)
        self._guard.check()

    def _store_chunk(self, chunk_no, n, job, bufs):
        n1 = chunk_no * _CHUNK_ELEMS + n
        if n1 > self._n_extent:  # grown 64 chunks ahead; set exactly by _flush_events
            self._set_extent(max(n1, self._n_extent + 64 * _CHUNK_ELEMS))
        off = (chunk_no * _CHUNK_ELEMS,)
        if self._codec == "h5py":  # lzf: HDF5's own filter pipeline (plain layout staged)
            a = chunk_no * _CHUNK_ELEMS
            for ds, (_, dt), b in zip(self._ds, _EVENT_FIELDS, bufs):
                ds[a:a + n] = b.view(dt)[:n]
            return
        data = job.result() if hasattr(job, "result") else (job if job is not None else bufs)
        for ds, d in zip(self._ds, data):
            ds.id.write_direct_chunk(off, d)
        self._n_written = max(self._n_written, n1)

    def _set_extent(self, n):
        for ds in self._ds:
            ds.resize((n,))
        self._n_extent = n

    def _store_index(self, force=True):
        if not self._idx_pending or (not force and len(self._idx_pending) < 256):
            return
        ms = np.concatenate([a for a, _ in self._idx_pending])
        first = np.concatenate([b for _, b in self._idx_pending])
        self._idx_pending = []
        self._append_index(ms, first)

    def _flush_events(self):
        """Store every staged event, the current partial chunk too (padded; rewritten when it fills)."""
        if self._pos:
            bt, bx, by, bp = bufs = self._cur
            C, q = _CHUNK_ELEMS, self._pos
            for b in bufs:  # zero padding, as HDF5 fills a partial chunk
                s = b.size // C
                if self._shuffle:
                    b.reshape(s, C)[:, q:] = 0
                else:
                    b[q * s:] = 0
            job = _deflate_chunk(bufs, q) if self._codec == "gzip" else None
            self._store_pending()
            self._store_chunk(self._chunk_no, q, job, bufs)
        else:
            self._store_pending()
        if self._n_extent != self._n_staged:
            self._set_extent(self._n_staged)
        self._n_written = self._n_staged
        self._store_index()
        self._guard.check()

    def _append_index(self, ms, first):
        g = self._f["events"]
        m0 = g["index_ms"].shape[0]
        for name, v in (("index_ms", ms), ("index_first", first)):
            g[name].resize((m0 + len(v),))
            g[name][m0:] = v

    def _write_triggers(self, triggers):
        validate_triggers(triggers)
        if self._trig_last is not None and triggers["t"][0] < self._trig_last:
            raise ValueError(f"{self.path}: triggers must be appended in time order; chunk starts at "
                             f"{int(triggers['t'][0])} µs after {self._trig_last} µs")
        g = self._f["triggers"]
        n0 = g["t"].shape[0]
        for name, _ in _TRIGGER_FIELDS:
            g[name].resize((n0 + len(triggers),))
            g[name][n0:] = triggers[name]
        self._trig_last = int(triggers["t"][-1])
        self._guard.check()

    def _write_imu(self, imu):
        if self._imu_last is not None and imu["t"][0] < self._imu_last:
            raise ValueError(f"{self.path}: IMU samples must be appended in time order; chunk starts at "
                             f"{int(imu['t'][0])} µs after {self._imu_last} µs")
        g = self._f["imu"]
        n0 = g["t"].shape[0]
        for name, _, _ in _IMU_FIELDS:
            g[name].resize((n0 + len(imu),))
            g[name][n0:] = imu[name]
        self._imu_last = int(imu["t"][-1])
        self._guard.check()

    def _write_frames(self, frames: Frames):
        f = self._f
        im = frames.images
        check_finite(im, self.path, "frames")
        if "frames" not in f:
            g = f.create_group("frames")
            g.create_dataset("images", shape=(0,) + im.shape[1:], maxshape=(None,) + im.shape[1:],
                             dtype=im.dtype, chunks=(1,) + im.shape[1:], **self._comp)
            for name in ("t_start_us", "t_end_us"):
                g.create_dataset(name, shape=(0,), maxshape=(None,), dtype="<i8", chunks=(1024,))
            g.attrs["encoding"] = frames.encoding
            for name in ("gain", "iso"):
                if getattr(frames, name) is not None:
                    g.create_dataset(name, shape=(0,), maxshape=(None,), dtype="<f8", chunks=(1024,))
        g = f["frames"]
        ds = g["images"]
        if ds.shape[1:] != im.shape[1:] or ds.dtype != im.dtype:
            raise ValueError(f"{self.path}: frames must all have shape {ds.shape[1:]} and dtype {ds.dtype}; "
                             f"got {im.shape[1:]} {im.dtype}")
        if g.attrs["encoding"] != frames.encoding:
            raise ValueError(f"{self.path}: frame encoding {frames.encoding!r} differs from {g.attrs['encoding']!r}")
        k0 = ds.shape[0]
        if k0 and frames.t_start_us[0] < g["t_start_us"][k0 - 1]:
            raise ValueError(f"{self.path}: frames must be appended in order of exposure start")
        for name in ("gain", "iso"):
            if (getattr(frames, name) is not None) != (name in g):
                raise ValueError(f"{self.path}: frames.{name} must be given for all frames or for none")
        k1 = k0 + len(frames)
        ds.resize((k1,) + ds.shape[1:])
        ds[k0:k1] = im
        for name in ("t_start_us", "t_end_us", "gain", "iso"):
            if name in g:
                g[name].resize((k1,))
                g[name][k0:k1] = getattr(frames, name)
        self._guard.check()

    def write_hdr(self, hdr: HDRReferences) -> None:
        """Append HDR references (float32 linear radiance with timestamps)."""
        if not isinstance(hdr, HDRReferences):
            raise TypeError(f"hdr must be HDRReferences, got {type(hdr).__name__}")
        f = self._f
        im = hdr.images
        check_finite(im, self.path, "HDR references", allow_nan=True)
        if "hdr" not in f:
            g = f.create_group("hdr")
            g.create_dataset("images", shape=(0,) + im.shape[1:], maxshape=(None,) + im.shape[1:],
                             dtype="<f4", chunks=(1,) + im.shape[1:], **self._comp)
            g.create_dataset("t_us", shape=(0,), maxshape=(None,), dtype="<i8", chunks=(1024,))
        g = f["hdr"]
        if g["images"].shape[1:] != im.shape[1:]:
            raise ValueError(f"{self.path}: HDR references must have shape {g['images'].shape[1:]}, got {im.shape[1:]}")
        k0 = g["t_us"].shape[0]
        k1 = k0 + len(hdr)
        g["images"].resize((k1,) + im.shape[1:])
        g["images"][k0:k1] = im
        g["t_us"].resize((k1,))
        g["t_us"][k0:k1] = hdr.t_us
        self._guard.check()

    def flush(self) -> None:
        """Write buffered events and flush the HDF5 file to disk."""
        self._flush_events()
        self._f.flush()
        self._guard.check()

    def _finish(self):
        self._flush_events()
        self._shutdown_pool()
        self._f.attrs["n_events"] = self._n_written
        self._f.close()
        self._guard.check()
        self._guard.close()  # a failing close (e.g. NFS) is recorded too
        self._guard.check()

    def _shutdown_pool(self):
        pool, self._pool = getattr(self, "_pool", None), None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def _cleanup(self):
        self._shutdown_pool()
        close_and_remove(getattr(self, "_f", None), getattr(self, "_guard", None), self.tmp_path)


def _guarded(method):
    """Turn any low-level h5py/HDF5 failure inside a reader method into a FormatError with context."""
    import functools
    import inspect

    if inspect.isgeneratorfunction(method):
        @functools.wraps(method)
        def gen(self, *a, **k):
            try:
                yield from method(self, *a, **k)
            except (FormatError, WindowOutsideDataError):  # the API's own errors pass
                raise
            except Exception as e:
                raise FormatError(self.path, f"corrupt hybridhdr container ({type(e).__name__}: {e})") from None
        return gen

    @functools.wraps(method)
    def wrapper(self, *a, **k):
        try:
            return method(self, *a, **k)
        except (FormatError, WindowOutsideDataError):  # the API's own errors pass
            raise
        except Exception as e:
            raise FormatError(self.path, f"corrupt hybridhdr container ({type(e).__name__}: {e})") from None
    return wrapper


def _check_image_dataset(ds, path, name):
    """Size limits and stored chunks of an image stack before it is read."""
    check_shape(ds.shape, "K H W | K H W C", name, error=lambda m: FormatError(path, m))
    dt = ds.dtype
    if not ((dt.kind == "u" and dt.itemsize <= 2) or (dt.kind == "f" and dt.itemsize in (2, 4, 8))):
        # signed codes (-5), uint64 (2^63 wraps to black) and compound records are not pixel values
        raise FormatError(path, f"{name} must hold uint8, uint16 or floating-point pixels, got dtype {dt}")
    check_frame_shape(ds.shape, path, name)
    check_frame_bytes(float(np.prod(ds.shape, dtype=np.float64)) * ds.dtype.itemsize, path, name)
    check_h5_stored(ds, path, name)


def _check_vector(ds, k, path, what):
    """A per-image dataset must be (K,), K the number of images, and a numeric dtype (checked before reading)."""
    if not hasattr(ds, "shape") or len(ds.shape) != 1 or ds.shape[0] != k:
        raise FormatError(path, f"{what} must have shape ({k},), one value per image, got "
                                f"{getattr(ds, 'shape', type(ds).__name__)}")
    if ds.dtype.kind not in "iuf":
        raise FormatError(path, f"{what} must be numeric, got dtype {ds.dtype}")


def _require(f, name, path):
    if name not in f:
        raise FormatError(path, f"missing dataset {name!r} (expected the hybridhdr container layout, "
                                f"format version {FORMAT_VERSION})")
    return f[name]


class RecordingFile(EventFileReader):
    """Lazy reader of a hybridhdr container.

    Nothing is loaded on open beyond attributes and the millisecond index; :meth:`events` reads a
    time window, :meth:`iter_chunks` and :meth:`iter_time_windows` stream the file.
    """

    format_name = "hybridhdr"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        h5py = _h5py()
        try:
            self._f = h5py.File(self.path, "r")
        except OSError as e:
            raise FormatError(self.path, f"not a readable HDF5 file ({e})") from None
        try:
            from .._util.limits import check_h5_self_contained
            check_h5_self_contained(self._f, self.path)  # no external links / storage / virtual datasets
            self._open_checked()
        except FormatError:
            self._f.close()
            raise
        except Exception as e:  # corrupt internals surface as many h5py errors
            self._f.close()
            raise FormatError(self.path, f"corrupt hybridhdr container ({type(e).__name__}: {e})") from None

    def _open_checked(self):
        f, path = self._f, self.path
        ver = f.attrs.get("hybridhdr_format_version")
        if ver is None:
            raise FormatError(path, "HDF5 file is not a hybridhdr container (no 'hybridhdr_format_version' attribute)")
        ver = ver.decode() if isinstance(ver, bytes) else str(ver)
        if ver.split(".")[0] not in READABLE_MAJORS:
            raise FormatError(path, f"container format version {ver} is not supported (this reader reads "
                                    f"1.x and 2.x, and writes {FORMAT_VERSION}; written by a newer hybridhdr?)")
        self.format_version = ver
        try:
            md = json.loads(f.attrs.get("metadata_json", "{}"))
        except (ValueError, TypeError) as e:
            raise FormatError(path, f"metadata_json attribute is not valid JSON ({e})") from None
        self.metadata = Metadata.from_dict(md)
        ss = SensorSize(*check_sensor_size(f.attrs["sensor_height"], f.attrs["sensor_width"], path))
        if self.sensor_size is None:
            self.sensor_size = ss
        ds = [_require(f, f"events/{n}", path) for n, _ in _EVENT_FIELDS]
        n = ds[0].shape[0]
        for d, (name, dt) in zip(ds, _EVENT_FIELDS):
            if d.ndim != 1 or d.shape[0] != n:
                raise FormatError(path, f"events/{name} has shape {d.shape}; expected ({n},) like events/t")
            if d.dtype != np.dtype(dt):
                raise FormatError(path, f"events/{name} has dtype {d.dtype}; expected {np.dtype(dt)}")
        for d, (name, _) in zip(ds, _EVENT_FIELDS):
            check_h5_stored(d, path, f"events/{name}")
        self._ev = dict(zip([n_ for n_, _ in _EVENT_FIELDS], ds))
        self.n_events = int(n)
        if ver.split(".")[0] == "1":
            self._open_dense_index(n)
        else:
            self._open_sparse_index(n)

    def _open_dense_index(self, n):
        """Format 1.x: dense ``ms_to_idx``, read lazily (two entries per lookup; it may be huge)."""
        path = self.path
        ms = _require(self._f, "events/ms_to_idx", path)
        if ms.ndim != 1:
            raise FormatError(path, f"events/ms_to_idx has shape {ms.shape}; expected one dimension")
        check_h5_stored(ms, path, "events/ms_to_idx")
        self._index_kind = "dense"
        self._ms_ds = ms
        self._n_ms = int(ms.shape[0])
        try:
            self._origin = int(ms.attrs.get("origin_us", 0))
        except (TypeError, ValueError, OverflowError):
            raise FormatError(path, "events/ms_to_idx attribute origin_us is not an integer") from None
        if n and (self._n_ms == 0 or int(ms[self._n_ms - 1]) != n or int(ms[0]) < 0):
            raise FormatError(path, f"events/ms_to_idx is inconsistent with {n} events (expected a "
                                    f"non-decreasing index ending at {n}); the file may be truncated")

    def _open_sparse_index(self, n):
        """Format 2.x: sparse ``index_ms`` / ``index_first`` (at most one entry per stride of events)."""
        path = self.path
        a = _require(self._f, "events/index_ms", path)
        b = _require(self._f, "events/index_first", path)
        if a.ndim != 1 or b.shape != a.shape:
            raise FormatError(path, f"events/index_ms {a.shape} and events/index_first {b.shape} must be "
                                    f"one-dimensional and of equal length")
        if a.shape[0] > max(1, n):
            raise FormatError(path, f"the time index has {a.shape[0]:,} entries for {n:,} events (at most one "
                                    f"per event)")
        self._index_kind = "sparse"
        self._idx_ms = np.asarray(a[:], dtype=np.int64)
        self._idx_first = np.asarray(b[:], dtype=np.int64)
        k = len(self._idx_ms)
        if n and (k == 0 or self._idx_first[0] != 0 or np.any(np.diff(self._idx_ms) <= 0)
                  or np.any(np.diff(self._idx_first) <= 0) or self._idx_first[-1] >= n):
            raise FormatError(path, f"the time index (events/index_ms, events/index_first) is inconsistent "
                                    f"with {n} events (expected strictly increasing entries starting at 0)")

    @property
    def time_range_us(self) -> tuple[int, int] | None:
        if not self.n_events:
            return None
        return int(self._ev["t"][0]), int(self._ev["t"][self.n_events - 1])

    def _bounds(self, t_us, default):
        if t_us is None:
            return default
        t_us = int(t_us)
        n = self.n_events
        if self._index_kind == "dense":
            m = (t_us - self._origin) // 1000
            if m < 0:
                return 0
            if m >= self._n_ms - 1:
                return n
            lo, hi = (int(v) for v in self._ms_ds[m:m + 2])
        else:
            k = int(np.searchsorted(self._idx_ms, t_us // 1000, side="right")) - 1
            if k < 0:
                return 0
            lo = int(self._idx_first[k])
            hi = int(self._idx_first[k + 1]) if k + 1 < len(self._idx_first) else n
        if not 0 <= lo <= hi <= n:
            raise FormatError(self.path, f"the time index points outside the {n} events ({lo}..{hi})")
        return self._search(t_us, lo, hi)

    def _search(self, t_us, lo, hi):
        """First index in ``[lo, hi]`` with ``t >= t_us``; reads at most 2^20 times at once."""
        ds = self._ev["t"]
        while hi - lo > (1 << 20):  # bisect on the dataset for a huge stretch (one millisecond of a burst)
            mid = (lo + hi) // 2
            if int(ds[mid]) < t_us:
                lo = mid + 1
            else:
                hi = mid
        if lo == hi:
            return lo
        return lo + int(np.searchsorted(ds[lo:hi], t_us, side="left"))

    @_guarded
    def index_range(self, t_start_us=None, t_end_us=None) -> tuple[int, int]:
        """Event indices ``[i0, i1)`` of the half-open window ``[t_start_us, t_end_us)``."""
        i0 = self._bounds(t_start_us, 0)
        i1 = self._bounds(t_end_us, self.n_events)
        return i0, max(i0, i1)

    def _load(self, i0: int, i1: int, check: bool = True) -> np.ndarray:
        out = np.empty(i1 - i0, dtype=EVENT_DTYPE)
        if i1 > i0:
            try:
                for name, ds in self._ev.items():
                    out[name] = ds[i0:i1]
            except Exception as e:
                raise FormatError(self.path, f"cannot read events {i0}..{i1} ({type(e).__name__}: {e})",
                                  record=i0) from None
            if check:
                try:
                    validate_events(out, self.sensor_size, name="events")
                except ValueError as e:
                    raise FormatError(self.path, f"corrupt events in records {i0}..{i1}: {e}", record=i0) from None
        return out

    def _columns(self, i0: int, i1: int, t_prev: int | None = None) -> dict[str, np.ndarray]:
        """Validated contiguous columns of the records ``[i0, i1)``; ``t_prev`` = last t before."""
        try:
            cols = None
            if i1 - i0 >= (1 << 16):  # large reads: chunks inflated in two threads (formats._chunk_read)
                from ._chunk_read import read_columns
                if getattr(self, "_inflate_pool", None) is None:
                    from concurrent.futures import ThreadPoolExecutor
                    self._inflate_pool = ThreadPoolExecutor(2, thread_name_prefix="hybridhdr-inflate")
                cols = read_columns(self._ev, i0, i1, self._inflate_pool)
            if cols is None:  # any other filter pipeline, or a small read: through h5py
                cols = {name: np.ascontiguousarray(ds[i0:i1]) for name, ds in self._ev.items()}
        except Exception as e:
            raise FormatError(self.path, f"cannot read events {i0}..{i1} ({type(e).__name__}: {e})",
                              record=i0) from None
        t = cols["t"]
        if t.size and t_prev is not None and t[0] < t_prev:
            raise FormatError(self.path, f"events/t decreases at index {i0}", record=i0)
        if t.size and np.any(t[1:] < t[:-1]):
            i = int(np.flatnonzero(t[1:] < t[:-1])[0]) + 1
            raise FormatError(self.path, f"events/t decreases at index {i0 + i}", record=i0 + i)
        ss = self.sensor_size
        for field, lim, dim in (("x", ss.width, "width"), ("y", ss.height, "height")):
            v = cols[field]
            if v.size and v.max() >= lim:
                i = int(np.argmax(v >= lim))
                raise FormatError(self.path, f"events/{field} must be < sensor {dim} {lim}; record {i0 + i} "
                                             f"has {int(v[i])}", record=i0 + i)
        p = cols["p"]
        if p.size and np.any((p != 1) & (p != -1)):
            i = int(np.argmax((p != 1) & (p != -1)))
            raise FormatError(self.path, f"events/p must be +1 or -1; record {i0 + i} has {int(p[i])}",
                              record=i0 + i)
        return cols

    def data_span_us(self) -> tuple[int, int] | None:
        """``(start, last)`` µs sensor time: the first event or frame exposure start (the command
        line's origin) and the last event or frame exposure end (triggers when nothing else);
        reads only the ends of the time columns."""
        firsts, lasts = [], []
        tr = self.time_range_us
        if tr is not None:
            firsts.append(tr[0]); lasts.append(tr[1])
        for group, a, b in (("frames", "t_start_us", "t_end_us"), ("triggers", "t", "t")):
            if group == "triggers" and firsts:
                break
            g = self._f.get(group)
            try:
                if g is not None and a in g and b in g and g[a].shape[0] and g[b].shape[0]:
                    firsts.append(int(g[a][0])); lasts.append(int(g[b][g[b].shape[0] - 1]))
            except Exception:  # noqa: BLE001 - a corrupt group is reported by its own reader
                pass
        return (min(firsts), max(lasts)) if firsts else None

    def _window(self, t_start_us, t_end_us, absolute, what):
        if absolute is True and t_start_us is None and t_end_us is None:
            return None, None
        return api_window(t_start_us, t_end_us, absolute=absolute, span=self.data_span_us(),
                          what=f"{self.path}: RecordingFile.{what}")

    @_guarded
    def event_columns(self, t_start_us=None, t_end_us=None, *, absolute: bool = True) -> dict[str, np.ndarray]:
        """Contiguous columns ``{"t", "x", "y", "p"}`` of the window, for kernels (no record copy);
        the window as in :meth:`events`."""
        t_start_us, t_end_us = self._window(t_start_us, t_end_us, absolute, "event_columns")
        return self._columns(*self.index_range(t_start_us, t_end_us))

    def iter_event_columns(self, chunk_events: int = 1 << 20, t_start_us=None, t_end_us=None, *,
                           absolute: bool = True):
        """Yield validated ``(t, x, y, p)`` column tuples of about ``chunk_events`` events each.

        Reads the columns straight into contiguous arrays (no structured-record copy), which is
        what the reconstruction kernels take; time order is checked across chunk boundaries. The
        window as in :meth:`events`.
        """
        chunk_events = int(chunk_events)
        if chunk_events < 1:
            raise ValueError(f"chunk_events must be >= 1, got {chunk_events}")
        t_start_us, t_end_us = self._window(t_start_us, t_end_us, absolute, "iter_event_columns")
        i0, i1 = self.index_range(t_start_us, t_end_us)
        t_prev = None
        for a in range(i0, i1, chunk_events):
            try:
                c = self._columns(a, min(a + chunk_events, i1), t_prev)
            except FormatError:
                raise
            except Exception as e:  # corrupt internals surface as many h5py errors
                raise FormatError(self.path, f"cannot read events from record {a} ({type(e).__name__}: {e})",
                                  record=a) from None
            t_prev = int(c["t"][-1])
            yield c["t"], c["x"], c["y"], c["p"]

    @_guarded
    def events(self, t_start_us=None, t_end_us=None, *, absolute: bool = True) -> np.ndarray:
        """Events in ``[t_start_us, t_end_us)`` (loads only that window).

        ``absolute=True`` (default): µs sensor time, as stored; ``absolute=False``: µs from the
        recording's start (:meth:`data_span_us`), as the command line's ``--start``/``--end``. A
        window wholly outside the data raises :class:`~hybridhdr.errors.WindowOutsideDataError`
        naming the span."""
        t_start_us, t_end_us = self._window(t_start_us, t_end_us, absolute, "events")
        return self._load(*self.index_range(t_start_us, t_end_us))

    @_guarded
    def read_triggers(self) -> np.ndarray:
        if "triggers" not in self._f:
            return empty_triggers()
        g = self._f["triggers"]
        t = _require(g, "t", self.path)
        if len(t.shape) != 1:
            raise FormatError(self.path, f"triggers/t must have shape (N,), got {t.shape}")
        n = t.shape[0]
        # declared sizes checked against what is stored and the limits before anything is allocated
        for name, _ in _TRIGGER_FIELDS:
            d = _require(g, name, self.path)
            check_shape(d.shape, "N", f"triggers/{name}", sizes={"N": n}, error=lambda m: FormatError(self.path, m))
            check_h5_stored(d, self.path, f"triggers/{name}")
        from .._util.limits import check_packet_size
        check_packet_size(n * TRIGGER_DTYPE.itemsize, self.path, f"triggers ({n:,} declared)")
        out = np.empty(n, dtype=TRIGGER_DTYPE)
        for name, _ in _TRIGGER_FIELDS:
            out[name] = g[name][:]
        try:
            return validate_triggers(out)
        except ValueError as e:
            raise FormatError(self.path, f"corrupt triggers: {e}") from None

    @_guarded
    def read_imu(self) -> np.ndarray:
        """The stored IMU samples (``IMU_DTYPE``); empty for a file without /imu (format 2.0 and
        older, or a recording without IMU)."""
        if "imu" not in self._f:
            return empty_imu()
        g = self._f["imu"]
        t = _require(g, "t", self.path)
        if len(t.shape) != 1:
            raise FormatError(self.path, f"imu/t must have shape (N,), got {t.shape}")
        n = t.shape[0]
        # declared sizes and dtypes checked against what is stored and the limits before anything is allocated
        for name, dt, _ in _IMU_FIELDS:
            d = _require(g, name, self.path)
            check_shape(d.shape, "N", f"imu/{name}", sizes={"N": n}, error=lambda m: FormatError(self.path, m))
            if d.dtype.kind not in ("i" if name == "t" else "f"):
                raise FormatError(self.path, f"imu/{name} must hold {'integers' if name == 't' else 'floats'}, "
                                             f"got dtype {d.dtype}")
            check_h5_stored(d, self.path, f"imu/{name}")
        from .._util.limits import check_packet_size
        check_packet_size(n * IMU_DTYPE.itemsize, self.path, f"IMU samples ({n:,} declared)")
        out = np.empty(n, dtype=IMU_DTYPE)
        for name, _, _ in _IMU_FIELDS:
            out[name] = g[name][:]
        try:
            return validate_imu(out)
        except ValueError as e:
            raise FormatError(self.path, f"corrupt IMU samples: {e}") from None

    @_guarded
    def _iter_chunks(self, chunk_events: int) -> Iterator[EventChunk]:
        trig = self.read_triggers()
        ti = 0
        n = self.n_events
        if n == 0:
            if len(trig):
                yield EventChunk(empty_events(), trig)
            return
        for i0 in range(0, n, chunk_events):
            i1 = min(n, i0 + chunk_events)
            ev = self._load(i0, i1)
            if i1 < n:
                t_next = int(self._ev["t"][i1])
                tj = int(np.searchsorted(trig["t"], t_next, side="left"))
            else:
                tj = len(trig)
            yield EventChunk(ev, trig[ti:tj])
            ti = tj

    @_guarded
    def read_frames(self) -> Frames | None:
        if "frames" not in self._f:
            return None
        g = self._f["frames"]
        try:
            k = _require(g, "images", self.path).shape[0] if len(g["images"].shape) else -1
            # per-frame vectors: (K,) like the images, checked before they are read
            for name in ("t_start_us", "t_end_us", "gain", "iso"):
                if name in g or name.startswith("t_"):
                    _check_vector(_require(g, name, self.path), k, self.path, f"/frames/{name}")
            kw = {name: g[name][:] for name in ("gain", "iso") if name in g}
            enc = g.attrs.get("encoding", "unknown")
            enc = enc.decode() if isinstance(enc, bytes) else str(enc)
            if enc not in FRAME_ENCODINGS and self.frame_encoding is None:
                raise FormatError(self.path, f"/frames has encoding {enc!r}, which this version of hybridhdr does "
                                             f"not know (known: {', '.join(FRAME_ENCODINGS)}); written by a newer "
                                             f"version? Declare the encoding to read it anyway "
                                             f"(frame_encoding=..., --frame-encoding)")
            enc = self._frame_encoding(enc)
            ims = _require(g, "images", self.path)
            _check_image_dataset(ims, self.path, "/frames/images")
            images = ims[:]
            check_finite(images, self.path, "/frames/images")
            return Frames(images, _require(g, "t_start_us", self.path)[:],
                          _require(g, "t_end_us", self.path)[:], encoding=enc, **kw)
        except FormatError:
            raise
        except Exception as e:
            raise FormatError(self.path, f"corrupt /frames group: {e}") from None

    @_guarded
    def read_hdr(self) -> HDRReferences | None:
        if "hdr" not in self._f:
            return None
        g = self._f["hdr"]
        try:
            ims = _require(g, "images", self.path)
            _check_image_dataset(ims, self.path, "/hdr/images")
            _check_vector(_require(g, "t_us", self.path), ims.shape[0] if len(ims.shape) else -1, self.path,
                          "/hdr/t_us")
            images = ims[:]
            check_finite(images, self.path, "/hdr/images", allow_nan=True)
            return HDRReferences(images, _require(g, "t_us", self.path)[:])
        except FormatError:
            raise
        except Exception as e:
            raise FormatError(self.path, f"corrupt /hdr group: {e}") from None

    def read_thresholds(self):
        """The stored per-pixel ON/OFF threshold map (``ThresholdMap``), or None."""
        if "thresholds" not in self._f:
            return None
        g = self._f["thresholds"]
        try:
            c_on, c_off = _require(g, "c_on", self.path), _require(g, "c_off", self.path)
            for ds, name in ((c_on, "c_on"), (c_off, "c_off")):
                if self.sensor_size is not None and tuple(ds.shape) != self.sensor_size.shape:
                    raise FormatError(self.path, f"/thresholds/{name} has shape {ds.shape}, the sensor is "
                                                 f"{self.sensor_size.shape}")
            prov = json.loads(str(g.attrs.get("provenance_json", "{}")))
            return ThresholdMap(c_on=c_on[:], c_off=c_off[:], fallback_on=float(g.attrs["fallback_on"]),
                                fallback_off=float(g.attrs["fallback_off"]),
                                method=str(g.attrs.get("method", "unknown")), provenance=prov)
        except FormatError:
            raise
        except Exception as e:
            raise FormatError(self.path, f"corrupt /thresholds group: {e}") from None

    @_guarded
    def read(self, t_start_us=None, t_end_us=None, *, absolute: bool = True) -> Recording:
        """The recording, or its window (as in :meth:`events`)."""
        t_start_us, t_end_us = self._window(t_start_us, t_end_us, absolute, "read")
        ev = self.events(t_start_us, t_end_us)
        trig = self.read_triggers()
        trig = slice_time(trig, t_start_us, t_end_us)
        imu = slice_time(self.read_imu(), t_start_us, t_end_us)
        frames = self.read_frames()
        hdr = self.read_hdr()
        if t_start_us is not None or t_end_us is not None:
            if frames is not None:
                frames = frames.slice_time(t_start_us, t_end_us)
            if hdr is not None:
                from ..events import time_window_indices
                a, b = time_window_indices(hdr.t_us, t_start_us, t_end_us)
                hdr = HDRReferences(hdr.images[a:b], hdr.t_us[a:b])
        return Recording(ev, self.sensor_size, frames, trig, hdr, self.metadata, imu)

    def close(self):
        pool = getattr(self, "_inflate_pool", None)
        if pool is not None:
            pool.shutdown(wait=True)
            self._inflate_pool = None
        try:
            self._f.close()
        except Exception:
            pass


def store_thresholds(path, threshold_map) -> None:
    """Store a per-pixel ON/OFF threshold map (``hybridhdr.formats.thresholds.ThresholdMap``) in an
    existing container, replacing any stored one.

    The group is written under a temporary name and then linked as ``/thresholds`` (one metadata
    operation), so a failure leaves the previous map, or none, never a half-written one.
    """
    h5py = _h5py()
    path = Path(path)
    c_on, c_off = np.asarray(threshold_map.c_on, np.float64), np.asarray(threshold_map.c_off, np.float64)
    with RecordingFile(path) as r:
        ss = r.sensor_size
    if ss is not None and c_on.shape != ss.shape:
        raise ValueError(f"{path}: threshold map has shape {c_on.shape}, the recording's sensor is {ss.shape}")
    try:
        with h5py.File(path, "r+") as f:
            if "thresholds_tmp" in f:
                del f["thresholds_tmp"]
            g = f.create_group("thresholds_tmp")
            g.create_dataset("c_on", data=c_on)
            g.create_dataset("c_off", data=c_off)
            g.attrs["fallback_on"] = float(threshold_map.fallback_on)
            g.attrs["fallback_off"] = float(threshold_map.fallback_off)
            g.attrs["method"] = str(getattr(threshold_map, "method", ""))
            g.attrs["provenance_json"] = json.dumps(getattr(threshold_map, "provenance", {}), default=str)
            f.flush()
            if "thresholds" in f:
                del f["thresholds"]
            f.move("thresholds_tmp", "thresholds")
    except OSError as e:
        raise FormatError(path, f"could not store the threshold map: {e}") from None


def write_recording(recording: Recording, path, **options) -> Path:
    """Write a whole :class:`~hybridhdr.Recording` to a container file (atomically)."""
    if recording.sensor_size is None:
        raise ValueError("recording.sensor_size is required to write a hybridhdr container")
    with RecordingWriter(path, recording.sensor_size, recording.metadata, **options) as w:
        ev = recording.events
        step = 1 << 22
        for i in range(0, len(ev), step):
            w.write_events(ev[i:i + step])
        w.write_triggers(recording.triggers)
        w.write_imu(recording.imu)
        w.write_frames(recording.frames)
        if recording.hdr is not None and len(recording.hdr):
            w.write_hdr(recording.hdr)
    return Path(path)


def read_recording(path, t_start_us=None, t_end_us=None, *, absolute: bool = True) -> Recording:
    """The recording in a container file, or its window (:meth:`RecordingFile.events`'s time base)."""
    with RecordingFile(path) as r:
        return r.read(t_start_us, t_end_us, absolute=absolute)


def sniff(path: Path, head: bytes) -> str | None:
    if not head.startswith(_HDF5_MAGIC):
        return None
    try:
        h5py = _h5py()
        with h5py.File(path, "r") as f:
            return "hybridhdr" if "hybridhdr_format_version" in f.attrs else None
    except Exception:
        return None


READERS = {"hybridhdr": RecordingFile}
WRITERS = {"hybridhdr": RecordingWriter}

register_formats(__name__, {
    "hybridhdr": "hybridhdr HDF5 recording container (.h5)",
}, READERS, WRITERS)
