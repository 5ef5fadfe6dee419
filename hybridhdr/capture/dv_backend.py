"""iniVation DAVIS / DVXplorer cameras and DV network streams through dv-processing.

Two kinds of input give the same reader interface in dv-processing (``getNextEventBatch``,
``getNextFrame``, ``getNextTriggerBatch``, ``getNextImuBatch``, ``isRunning``, each non-blocking,
returning ``None`` when nothing is waiting):

* a **camera** on USB, ``dv.io.camera.open(serial)`` (DAVIS240/346, DVXplorer; every stream the
  model has comes from one object);
* a **DV network stream**, ``dv.io.NetworkReader(host, port)`` or ``NetworkReader(socket_path)``
  for a UNIX socket: what iniVation's DV software (its "Network output" modules) or a
  ``dv.io.NetworkWriter`` serves. One stream carries ONE kind (events, frames, triggers or IMU), so
  a DAVIS streamed over the network is several streams: :class:`DvCapture` takes any number of
  inputs and finds out what each carries.

:class:`DvCapture` holds the inputs; :meth:`DvCapture.event_source` and
:meth:`DvCapture.frame_source` (call it before the stream flows: frames that arrive before are read
and counted as not recorded) are the recorder's :class:`~hybridhdr.capture.sources.EventSource`
(events with the triggers merged in) and :class:`~hybridhdr.capture.sources.FrameSource` over them.
The readers are polled by pump threads into bounded buffers (:class:`DvCapture`), so the recorder
may make the sources wait; a full buffer drops and counts, as a camera driver would.

Conversions (``docs/conventions.md``), the same as the AEDAT4 reader's
(:mod:`hybridhdr.formats.aedat4`), so a stream and the file it was served from store the same data:

* events: ``timestamp`` µs -> ``t``; ``polarity`` 1/0 -> ``p`` +1/-1;
* triggers: ``dv::TriggerType`` -> (channel, edge) by :data:`~hybridhdr.formats.aedat4.TRIGGER_TYPE_MAP`
  (``TIMESTAMP_RESET`` is counted, not stored);
* frames: ``dv::Frame.timestamp`` is the start of exposure, so the exposure interval is
  ``[timestamp, timestamp + exposure)``; colour frames arrive BGR and are stored RGB; a frame
  smaller than the stream resolution (an ROI) is pasted at its position into a zero image;
* IMU: ``dv.IMU`` -> ``IMU_DTYPE`` (:func:`imu_from_dv`): ``timestamp`` µs -> ``t``, the
  accelerometer (g), gyroscope (°/s), temperature (°C) and magnetometer (µT) float32 values into the
  fields named with those units (:data:`hybridhdr.events.IMU_FIELDS`), bit for bit. They travel
  with the event source's chunks (``EventChunk.imu``) into the recording (``Recording.imu``).

Nothing is lost silently:

* a stream that ends (the camera unplugged, the DV software stopped, the network down) is an
  *interruption*: counted, logged with the time of the last data, and the input is reconnected
  for up to ``reconnect_timeout_s`` (network streams; a USB camera is reopened by serial number);
  each reconnection is a *restart*;
* data whose timestamps go back in time (a timestamp reset, a restarted camera, a stream replayed
  from its start) cannot be appended to a recording whose time must not decrease; such events,
  triggers, IMU samples and frames are dropped and counted (``events_out_of_order``,
  ``imu_out_of_order`` ...), never written out of order;
* IMU samples received are counted (``imu_samples``); those a full buffer drops are counted
  (``imu_dropped_in_buffer``) as for the other kinds, samples with an infinite reading (which
  the container refuses) are dropped and counted (``imu_not_finite``), and the recorder counts
  what it stores (``imu_written``).

The counts are in :meth:`DvEventSource.counters` / :meth:`DvFrameSource.counters`, which the
recorder copies into every flush record and the recording's provenance.

Host-clock samples: every batch received records ``(host monotonic µs, newest data timestamp µs)``;
the lower envelope of ``host - data`` (minimum transport latency) per second is kept, for mapping
the stream's clock onto the host clock (:mod:`hybridhdr.capture.rig`).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from urllib.parse import urlparse

import numpy as np

from ..events import EVENT_DTYPE, IMU_DTYPE, IMU_FIELDS, TRIGGER_DTYPE, SensorSize, empty_imu, empty_triggers
from ..formats import EventChunk
from ..formats.aedat4 import TRIGGER_TYPE_MAP
from .devices import NoDeviceFound
from .sources import EventSource, FrameItem, FrameSource

__all__ = ["dv_available", "DvInput", "DvCapture", "DvEventSource", "DvFrameSource", "parse_dv_source",
           "list_dv_cameras", "DV_SCHEMES", "HostClockSamples", "resolve_free_ports"]

log = logging.getLogger(__name__)

#: URL schemes of ``--source``: ``dv-tcp://HOST:PORT`` and ``dv-unix:///path/to/socket``.
DV_SCHEMES = ("dv-tcp", "dv-unix")

_TRIG_CH = np.zeros(16, np.uint16)
_TRIG_EDGE = np.zeros(16, np.int8)
for _code, (_ch, _edge) in TRIGGER_TYPE_MAP.items():
    _TRIG_CH[_code], _TRIG_EDGE[_code] = _ch, _edge


def _dv():
    try:
        import dv_processing as dv
    except ImportError as e:
        raise ImportError("DAVIS/DVXplorer cameras and DV network streams need dv-processing: "
                          "pip install 'hybridhdr[dv]'") from e
    return dv


def dv_available() -> bool:
    try:
        _dv()
    except ImportError:
        return False
    return True


def _host_us() -> int:
    return time.monotonic_ns() // 1000


# -- conversions --------------------------------------------------------------------------------
def events_from_dv(store) -> np.ndarray:
    """A ``dv.EventStore`` -> ``EVENT_DTYPE`` array (a copy)."""
    a = store.numpy()
    ev = np.empty(len(a), EVENT_DTYPE)
    if len(a):
        ev["t"] = a["timestamp"]
        ev["x"] = a["x"]
        ev["y"] = a["y"]
        ev["p"] = np.where(a["polarity"] != 0, 1, -1)
    return ev


def triggers_from_dv(batch) -> tuple[np.ndarray, int]:
    """A dv trigger vector -> (``TRIGGER_DTYPE`` array, number of ``TIMESTAMP_RESET`` markers)."""
    n = len(batch)
    t = np.empty(n, np.int64)
    codes = np.empty(n, np.int64)
    for k in range(n):
        tr = batch[k]
        t[k] = int(tr.timestamp)
        codes[k] = int(tr.type)
    bad = np.flatnonzero((codes < 0) | (codes > 9))
    if bad.size:
        raise ValueError(f"unknown dv trigger type {int(codes[bad[0]])} (expected 0..9, dv::TriggerType)")
    keep = codes != 0
    out = np.empty(int(keep.sum()), TRIGGER_DTYPE)
    out["t"] = t[keep]
    out["channel"] = _TRIG_CH[codes[keep]]
    out["edge"] = _TRIG_EDGE[codes[keep]]
    if len(out) > 1 and np.any(out["t"][1:] < out["t"][:-1]):
        out = out[np.argsort(out["t"], kind="stable")]
    return out, int(n - keep.sum())


def imu_from_dv(batch) -> np.ndarray:
    """A dv IMU vector (``dv.IMU`` objects) -> ``IMU_DTYPE`` array, sorted by time (stable)."""
    n = len(batch)
    out = np.empty(n, IMU_DTYPE)
    cols = [(out[name], dv_name) for name, _, dv_name in IMU_FIELDS]
    t = out["t"]
    for k in range(n):
        s = batch[k]
        t[k] = int(s.timestamp)
        for col, dv_name in cols:
            col[k] = getattr(s, dv_name)
    if n > 1 and np.any(t[1:] < t[:-1]):
        out = out[np.argsort(t, kind="stable")]
    return out


def frame_from_dv(frame, size: SensorSize | None, sequence: int) -> FrameItem:
    """A ``dv.Frame`` -> :class:`FrameItem` (exposure ``[timestamp, timestamp + exposure)``)."""
    im = np.asarray(frame.image)
    if im.ndim == 3:
        if im.shape[2] == 1:
            im = im[..., 0]
        elif im.shape[2] in (3, 4):
            im = im[..., 2::-1]  # BGR(A) -> RGB
        else:
            raise ValueError(f"dv frame with {im.shape[2]} channels (expected 1, 3 or 4)")
    im = np.ascontiguousarray(im)
    ox, oy = int(frame.positionX), int(frame.positionY)
    if size is not None and (im.shape[:2] != size.shape or ox or oy):
        h, w = im.shape[:2]
        if ox < 0 or oy < 0 or oy + h > size.height or ox + w > size.width:
            raise ValueError(f"dv frame of shape {(h, w)} at ({ox}, {oy}) does not fit the {size} frame stream")
        full = np.zeros(size.shape + im.shape[2:], im.dtype)
        full[oy:oy + h, ox:ox + w] = im
        im = full
    exp_us = int(round(frame.exposure.total_seconds() * 1e6))
    t0 = int(frame.timestamp)
    return FrameItem(im, t0, t0 + max(exp_us, 0), max(exp_us, 0), sequence=sequence)


# -- host clock samples -------------------------------------------------------------------------
class HostClockSamples:
    """``(data timestamp µs, host monotonic µs)`` pairs, thinned to the lowest-latency one per bin.

    The host receives each batch some time after its newest timestamp; that latency is never
    negative, so the smallest ``host - data`` in a bin is the best estimate of the clock offset
    there (the lower envelope). Bins start at ``bin_us`` (100 ms); when more than ``max_bins`` are
    held the bin width doubles and neighbours merge (keeping the lower envelope), so memory and the
    JSON stored in the recording stay bounded for any length.
    """

    def __init__(self, bin_us: int = 100_000, max_bins: int = 1024):
        self.bin_us, self.max_bins = int(bin_us), int(max_bins)
        self._bins: dict[int, tuple[int, int]] = {}
        self._lock = threading.Lock()

    def _insert(self, data_us: int, host_us: int) -> None:
        b = host_us // self.bin_us
        cur = self._bins.get(b)
        if cur is None or host_us - data_us < cur[1] - cur[0]:
            self._bins[b] = (data_us, host_us)

    def add(self, data_us: int, host_us: int) -> None:
        with self._lock:
            self._insert(int(data_us), int(host_us))
            if len(self._bins) > self.max_bins:
                old = list(self._bins.values())
                self._bins = {}
                self.bin_us *= 2
                for d, h in old:
                    self._insert(d, h)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            v = sorted(self._bins.values(), key=lambda p: p[1])
        return np.array([p[0] for p in v], np.int64), np.array([p[1] for p in v], np.int64)

    def to_dict(self) -> dict:
        d, h = self.arrays()
        return {"data_us": d.tolist(), "host_us": h.tolist(), "bin_us": self.bin_us}


# -- inputs -------------------------------------------------------------------------------------
@dataclass
class DvInput:
    """One dv-processing reader: a USB camera or one network stream, with how to (re)open it.

    ``spec`` is ``"davis"``, ``"davis:SERIAL"``, ``"dv-tcp://HOST:PORT"`` or
    ``"dv-unix:///path/to/socket"``. ``opener`` (tests) replaces the dv-processing call.
    """

    spec: str
    opener: object = None
    reader: object = None

    @property
    def is_camera(self) -> bool:
        return not self.spec.startswith(tuple(s + "://" for s in DV_SCHEMES))

    def open(self):
        if self.opener is not None:
            self.reader = self.opener()
            return self.reader
        dv = _dv()
        if self.is_camera:
            serial = self.spec.split(":", 1)[1] if ":" in self.spec else ""
            found = dv.io.camera.discover()
            if not found:
                raise NoDeviceFound("no device found: dv-processing sees no DAVIS or DVXplorer camera (check the "
                                    "cable and the udev rule for USB vendor 152a, docs/capture.md)")
            self.reader = dv.io.camera.open(serial) if serial else dv.io.camera.open()
            return self.reader
        kind, where = parse_dv_source(self.spec)
        try:
            if kind == "unix":
                self.reader = dv.io.NetworkReader(dv.Path(where))
            else:
                self.reader = dv.io.NetworkReader(where[0], int(where[1]))
        except RuntimeError as e:
            raise ConnectionError(f"{self.spec}: cannot connect to the DV stream ({e}); is the DV software's "
                                  f"network output (or a dv.io.NetworkWriter) running there?") from None
        return self.reader

    def close(self) -> None:
        self.reader = None  # dv-processing closes the socket / device in the destructor

    def kinds(self) -> set:
        r = self.reader
        out = set()
        for k, m in (("events", "isEventStreamAvailable"), ("frames", "isFrameStreamAvailable"),
                     ("triggers", "isTriggerStreamAvailable"), ("imu", "isImuStreamAvailable")):
            try:
                if getattr(r, m)():
                    out.add(k)
            except (AttributeError, RuntimeError):
                pass
        return out

    def running(self) -> bool:
        try:
            return bool(self.reader.isRunning())
        except (AttributeError, RuntimeError):
            return False

    def info(self) -> dict:
        r = self.reader
        d = {"spec": self.spec, "kinds": sorted(self.kinds()) if r is not None else []}
        for k, m in (("camera", "getCameraName"), ("event_resolution", "getEventResolution"),
                     ("frame_resolution", "getFrameResolution")):
            try:
                v = getattr(r, m)()
                d[k] = list(v) if isinstance(v, tuple) else (None if v is None else str(v))
            except (AttributeError, RuntimeError, TypeError):
                pass
        return d


def parse_dv_source(spec: str):
    """``dv-tcp://HOST:PORT`` -> ("tcp", (host, port)); ``dv-unix:///path`` -> ("unix", path)."""
    u = urlparse(spec)
    if u.scheme == "dv-tcp":
        if not u.hostname or u.port is None:
            raise ValueError(f"--source {spec!r}: expected dv-tcp://HOST:PORT")
        return "tcp", (u.hostname, u.port)
    if u.scheme == "dv-unix":
        path = (u.netloc + u.path) if u.netloc else u.path
        if not path:
            raise ValueError(f"--source {spec!r}: expected dv-unix:///path/to/socket")
        return "unix", path
    raise ValueError(f"--source {spec!r}: expected dv-tcp://HOST:PORT or dv-unix:///path/to/socket")


def list_dv_cameras() -> list[dict]:
    """DAVIS/DVXplorer cameras dv-processing discovers (empty when dv-processing is absent)."""
    if not dv_available():
        return []
    dv = _dv()
    out = []
    for d in dv.io.camera.discover():
        rec = {"maker": "iniVation", "kind": "event+frame" if "DAVIS" in str(getattr(d, "cameraModel", "")) else "event",
               "sdk": "dv-processing"}
        for k in ("serialNumber", "cameraModel", "busNumber", "devAddress", "firmwareVersion", "deviceBusy"):
            if hasattr(d, k):
                v = getattr(d, k)
                rec[k] = v if isinstance(v, (int, bool, str)) else str(v)
        rec["model"] = str(rec.get("cameraModel", "DV camera"))
        rec["serial"] = str(rec.get("serialNumber", ""))
        rec["open_with"] = f"--camera davis:{rec['serial']}" if rec["serial"] else "--camera davis"
        out.append(rec)
    return out


# -- capture ------------------------------------------------------------------------------------
_END = object()


class DvCapture:
    """A DAVIS/DVXplorer camera or a set of DV network streams, opened together.

    :meth:`open` connects every input and starts one *pump* thread per input that polls its reader
    without pause and converts what arrives into NumPy arrays in a bounded queue per kind. The
    readers are never left unread while the recorder starts or its writer is busy: dv-processing's
    ``NetworkReader`` buffers only a little and stops its stream when its buffer overflows. A full
    queue here drops the newest batch and counts it (``*_dropped_in_buffer``).

    Parameters
    ----------
    specs : list of str or DvInput
        ``"davis"`` / ``"davis:SERIAL"`` (a USB camera: one input carries every stream), or one
        ``dv-tcp://`` / ``dv-unix://`` URL per network stream (each carries one kind).
    exposure_us : int, optional
        DAVIS APS exposure (``setExposureDuration``; turns auto exposure off). Cameras only.
    frame_interval_us : int, optional
        DAVIS APS frame interval (``setFrameInterval``). Cameras only.
    reconnect_timeout_s : float
        How long to keep reconnecting an interrupted input before ending its stream.
    buffer_items : int
        Capacity of each kind's queue, in batches (event or trigger packets, frames).
    poll_s : float
        Sleep of a pump thread after a poll that found nothing.
    """

    def __init__(self, specs, *, exposure_us: int | None = None, frame_interval_us: int | None = None,
                 reconnect_timeout_s: float = 5.0, buffer_items: int = 4096, poll_s: float = 0.0005):
        self.inputs = [s if isinstance(s, DvInput) else DvInput(str(s)) for s in specs]
        if not self.inputs:
            raise ValueError("DvCapture needs at least one input (a camera or a DV stream URL)")
        if exposure_us is not None and int(exposure_us) < 1:
            raise ValueError(f"exposure_us must be >= 1 µs, got {exposure_us}")
        if frame_interval_us is not None and int(frame_interval_us) < 1:
            raise ValueError(f"frame_interval_us must be >= 1 µs, got {frame_interval_us}")
        if (exposure_us is not None or frame_interval_us is not None) and not any(i.is_camera for i in self.inputs):
            raise ValueError("exposure and frame-interval controls need a camera (--camera davis); a DV network "
                             "stream is set up in the DV software that serves it")
        if int(buffer_items) < 1:
            raise ValueError(f"buffer_items must be >= 1, got {buffer_items}")
        self.exposure_us, self.frame_interval_us = exposure_us, frame_interval_us
        self.reconnect_timeout_s, self.poll_s = float(reconnect_timeout_s), float(poll_s)
        self.buffer_items = int(buffer_items)
        self._opened = False
        self.kinds: dict[str, list[DvInput]] = {}
        self.sensor_size: SensorSize | None = None
        self.frame_size: SensorSize | None = None
        self._ev = self._fr = None
        self._queues: dict[str, queue.Queue] = {}
        self._pumps: list[threading.Thread] = []
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.counters = {"interruptions": 0, "restarts": 0, "ended": 0, "gaps_us": [], "imu_samples": 0,
                         "timestamp_resets": 0, "events_dropped_in_buffer": 0, "triggers_dropped_in_buffer": 0,
                         "imu_dropped_in_buffer": 0, "imu_not_finite": 0, "frames_dropped_in_buffer": 0, "frames_not_recorded": 0,
                         "interruption_log": []}
        self.clock = {"events": HostClockSamples(), "frames": HostClockSamples()}
        self.errors: list[BaseException] = []
        self._want_frames = False  # set by frame_source(): frames are buffered only when recorded

    # -- lifecycle ------------------------------------------------------------------------------
    def open(self) -> "DvCapture":
        if self._opened:
            return self
        self._stop.clear()
        for inp in self.inputs:
            inp.open()
        self._apply_controls()
        self._classify()
        self._queues = {k: queue.Queue(self.buffer_items) for k in ("events", "triggers", "imu", "frames")}
        self._pumps = [threading.Thread(target=self._pump, args=(inp,), name=f"dv-pump-{k}", daemon=True)
                       for k, inp in enumerate(self.inputs)]
        for t in self._pumps:
            t.start()
        self._opened = True
        return self

    def close(self) -> None:
        self._stop.set()
        for t in self._pumps:
            t.join()
        self._pumps = []
        for inp in self.inputs:
            inp.close()
        self._opened = False

    def _apply_controls(self):
        import datetime
        for inp in self.inputs:
            if not inp.is_camera:
                continue
            r = inp.reader
            if self.exposure_us is not None:
                if not hasattr(r, "setExposureDuration"):
                    raise ValueError(f"{inp.spec}: this camera has no APS exposure control (a DVXplorer has no frames)")
                if hasattr(r, "setAutoExposure"):
                    r.setAutoExposure(False)
                r.setExposureDuration(datetime.timedelta(microseconds=int(self.exposure_us)))
            if self.frame_interval_us is not None:
                if not hasattr(r, "setFrameInterval"):
                    raise ValueError(f"{inp.spec}: this camera has no APS frame-interval control")
                r.setFrameInterval(datetime.timedelta(microseconds=int(self.frame_interval_us)))

    def _classify(self):
        self.kinds = {}
        for inp in self.inputs:
            for k in inp.kinds():
                self.kinds.setdefault(k, []).append(inp)
        for k in ("events", "frames", "imu"):
            if len(self.kinds.get(k, [])) > 1:
                raise ValueError(f"{len(self.kinds[k])} inputs carry {k} ({[i.spec for i in self.kinds[k]]}); "
                                 f"give one {k} stream per recording")
        if "events" not in self.kinds:
            raise ValueError(f"no input carries events ({[(i.spec, sorted(i.kinds())) for i in self.inputs]}); "
                             f"add the event stream's URL")
        w, h = self.kinds["events"][0].reader.getEventResolution()
        self.sensor_size = SensorSize(int(h), int(w))
        if "frames" in self.kinds:
            fs = self.kinds["frames"][0].reader.getFrameResolution()
            self.frame_size = None if fs is None else SensorSize(int(fs[1]), int(fs[0]))

    def event_source(self) -> "DvEventSource":
        if self._ev is None:
            self._ev = DvEventSource(self)
        return self._ev

    def frame_source(self) -> "DvFrameSource | None":
        """The frame source, or None when no input carries frames (opens the capture to find out).

        Frames are buffered only once this was called; before, a camera's or a stream's frames are
        read and counted (``frames_not_recorded``) but not kept."""
        self._want_frames = True
        self.open()
        if "frames" not in self.kinds:
            return None
        if self._fr is None:
            self._fr = DvFrameSource(self)
        return self._fr

    def info(self) -> dict:
        return {"kind": "dv-processing", "inputs": [i.info() for i in self.inputs],
                "exposure_us": self.exposure_us, "frame_interval_us": self.frame_interval_us}

    def get_counters(self) -> dict:
        with self._lock:
            d = dict(self.counters)
            d["gaps_us"] = list(d["gaps_us"])
            d["interruption_log"] = list(d["interruption_log"])
        return d

    # -- pumps ----------------------------------------------------------------------------------
    def _put(self, kind: str, item, n: int) -> None:
        try:
            self._queues[kind].put_nowait(item)
        except queue.Full:
            with self._lock:
                self.counters[f"{kind}_dropped_in_buffer"] += n
            log.warning("dv %s buffer full: dropped %d (the recorder is not keeping up)", kind, n)

    def _pump(self, inp: DvInput) -> None:
        kinds = inp.kinds()
        last = {"events": None, "frames": None}
        try:
            while not self._stop.is_set():
                r = inp.reader
                got = False
                if "events" in kinds:
                    e = r.getNextEventBatch()
                    if e is not None and len(e):
                        a = events_from_dv(e)
                        host = _host_us()
                        last["events"] = int(a["t"][-1])
                        self.clock["events"].add(last["events"], host)
                        self._put("events", a, len(a))
                        got = True
                if "triggers" in kinds:
                    t = r.getNextTriggerBatch()
                    if t is not None and len(t):
                        a, resets = triggers_from_dv(t)
                        if resets:
                            with self._lock:
                                self.counters["timestamp_resets"] += resets
                        if len(a):
                            self._put("triggers", a, len(a))
                        got = True
                if "frames" in kinds:
                    f = r.getNextFrame()
                    if f is not None and not self._want_frames:
                        # frames nobody records (another frame camera, or --frames none): read so the
                        # reader never overflows, count, keep out of the drop counts
                        with self._lock:
                            self.counters["frames_not_recorded"] += 1
                        got = True
                    elif f is not None:
                        item = frame_from_dv(f, self.frame_size, 0)
                        host = _host_us()
                        last["frames"] = item.t_end_us
                        self.clock["frames"].add(item.t_end_us, host)
                        self._put("frames", item, 1)
                        got = True
                if "imu" in kinds:
                    m = r.getNextImuBatch()
                    if m is not None and len(m):
                        a = imu_from_dv(m)
                        bad = np.any([np.isinf(a[name]) for name, _, _ in IMU_FIELDS], axis=0)
                        with self._lock:
                            self.counters["imu_samples"] += len(a)
                            self.counters["imu_not_finite"] += int(bad.sum())
                        if bad.any():  # an infinite reading cannot be stored; counted, never silent
                            a = a[~bad]
                        if len(a):
                            self._put("imu", a, len(a))
                        got = True
                if got:
                    continue
                if not inp.running():
                    if not self._reconnect(inp, last):
                        break
                    continue
                self._stop.wait(self.poll_s)
        except BaseException as e:  # reported by the sources
            self.errors.append(e)
        finally:
            for k in kinds & {"events", "triggers", "imu", "frames"}:
                while True:  # waits only while a consumer drains; after close() nobody needs it
                    try:
                        self._queues[k].put(_END, timeout=0.05)
                        break
                    except queue.Full:
                        if self._stop.is_set():
                            break

    def _reconnect(self, inp: DvInput, last: dict) -> bool:
        """Reopen an input that stopped; True when it runs again (counted as a restart)."""
        t0 = _host_us()
        with self._lock:
            self.counters["interruptions"] += 1
            n = self.counters["interruptions"]
            self.counters["interruption_log"].append({"input": inp.spec, "host_us": t0, "last_event_t_us": last["events"],
                                                      "last_frame_t_us": last["frames"]})
        log.warning("dv input %s stopped (interruption %d); reconnecting for up to %.1f s", inp.spec, n,
                    self.reconnect_timeout_s)
        inp.close()
        t_end = time.monotonic() + self.reconnect_timeout_s
        while not self._stop.is_set() and time.monotonic() < t_end:
            try:
                inp.open()
                if inp.is_camera:
                    self._apply_controls()
            except (ConnectionError, NoDeviceFound, RuntimeError, OSError):
                self._stop.wait(0.05)
                continue
            with self._lock:
                self.counters["restarts"] += 1
                self.counters["gaps_us"].append(_host_us() - t0)
            log.warning("dv input %s reconnected", inp.spec)
            return True
        with self._lock:
            self.counters["ended"] += 1
        if not self._stop.is_set():
            log.warning("dv input %s did not come back within %.1f s; its stream ends", inp.spec,
                        self.reconnect_timeout_s)
        return False


class _DvSourceMixin:
    def _get(self, kind: str, timeout: float = 0.05):
        try:
            return self.capture._queues[kind].get(timeout=timeout)
        except queue.Empty:
            return None

    def _check_errors(self):
        if self.capture.errors:
            e = self.capture.errors[0]
            raise RuntimeError(f"dv input failed ({type(e).__name__}: {e})") from e


class DvEventSource(_DvSourceMixin, EventSource):
    """Events, with the triggers of every trigger input and the IMU samples of the IMU input handed
    over in the same chunks (``EventChunk.triggers``, ``EventChunk.imu``), of a :class:`DvCapture`.

    Ends when the event input ends (after its reconnection window). Events, triggers and IMU
    samples whose timestamps go back are dropped and counted (``events_out_of_order``,
    ``triggers_out_of_order``, ``imu_out_of_order``).
    """

    #: the pump threads buffer (and count what their full buffer drops), so the recorder may make
    #: this source wait: the camera or the network is never the one that waits
    can_backpressure = True

    def __init__(self, capture: DvCapture):
        super().__init__()
        self.capture = capture
        self._own = {"events_out_of_order": 0, "triggers_out_of_order": 0, "imu_out_of_order": 0, "batches": 0}

    def open(self):
        self.capture.open()
        self.sensor_size = self.capture.sensor_size
        return super().open()

    def close(self) -> None:
        super().close()
        if self.capture._fr is None or not self.capture._fr._opened:
            self.capture.close()

    def device_info(self) -> dict:
        return self.capture.info()

    def counters(self) -> dict:
        return {**self.capture.get_counters(), **self._own}

    def clock_samples(self) -> dict:
        return self.capture.clock["events"].to_dict()

    def _drain(self, kind, last_t):
        """What the ``kind`` ("triggers" or "imu") queue holds now, without what goes back in time."""
        out = []
        q = self.capture._queues[kind] if kind in self.capture.kinds else None
        while q is not None:
            try:
                a = q.get_nowait()
            except queue.Empty:
                break
            if a is _END:
                self._aux_done[kind] = True
                continue
            if last_t is not None and len(a) and a["t"][0] < last_t:
                bad = a["t"] < last_t
                self._own[f"{kind}_out_of_order"] += int(bad.sum())
                a = a[~bad]
            if len(a):
                last_t = int(a["t"][-1])
                out.append(a)
        return out, last_t

    def _drain_aux(self, last, got):
        for kind in ("triggers", "imu"):
            more, last[kind] = self._drain(kind, last[kind])
            got[kind] += more

    def _iter(self):
        last_ev = None
        last = {"triggers": None, "imu": None}
        self._aux_done = {k: k not in self.capture.kinds for k in ("triggers", "imu")}
        while not self.stopped:
            self._check_errors()
            a = self._get("events")
            done = a is _END
            evs = []
            if a is not None and not done:
                if last_ev is not None and a["t"][0] < last_ev:
                    bad = a["t"] < last_ev
                    self._own["events_out_of_order"] += int(bad.sum())
                    a = a[~bad]
                if len(a) > 1 and np.any(a["t"][1:] < a["t"][:-1]):
                    keep = a["t"] >= np.maximum.accumulate(a["t"])
                    self._own["events_out_of_order"] += int((~keep).sum())
                    a = a[keep]
                if len(a):
                    last_ev = int(a["t"][-1])
                    evs.append(a)
            got = {"triggers": [], "imu": []}
            if done and not all(self._aux_done.values()):
                # the event stream ended: wait briefly for the trigger and IMU inputs' ends
                t_end = time.monotonic() + self.capture.reconnect_timeout_s + 1.0
                while not all(self._aux_done.values()) and time.monotonic() < t_end and not self.stopped:
                    self._drain_aux(last, got)
                    if not all(self._aux_done.values()):
                        time.sleep(0.01)
            else:
                self._drain_aux(last, got)
            trs, ims = got["triggers"], got["imu"]
            if evs or trs or ims:
                ev = evs[0] if evs else np.zeros(0, EVENT_DTYPE)
                tr = np.concatenate(trs) if len(trs) > 1 else (trs[0] if trs else empty_triggers())
                im = np.concatenate(ims) if len(ims) > 1 else (ims[0] if ims else empty_imu())
                self._own["batches"] += 1
                yield EventChunk(ev, tr, im)
            if done:
                return


class DvFrameSource(_DvSourceMixin, FrameSource):
    """APS frames of a :class:`DvCapture` (a DAVIS, or a DV frame stream); sequence numbers count
    the frames received (a DV frame carries none). Frames whose start goes back are dropped and
    counted (``frames_out_of_order``)."""

    can_backpressure = True  # buffered by the pump threads, as the event source
    encoding = "raw"

    def __init__(self, capture: DvCapture):
        super().__init__()
        self.capture = capture
        self._own = {"frames_out_of_order": 0, "frames": 0}

    def open(self):
        self.capture.open()
        return super().open()

    def close(self) -> None:
        super().close()
        if self.capture._ev is None or not self.capture._ev._opened:
            self.capture.close()

    def device_info(self) -> dict:
        return self.capture.info()

    def counters(self) -> dict:
        """This source's own counts (the inputs' interruptions are in the event source's)."""
        return dict(self._own)

    def clock_samples(self) -> dict:
        return self.capture.clock["frames"].to_dict()

    def _iter(self):
        last_t = None
        seq = 0
        while not self.stopped:
            self._check_errors()
            item = self._get("frames")
            if item is None:
                continue
            if item is _END:
                return
            if last_t is not None and item.t_start_us < last_t:
                self._own["frames_out_of_order"] += 1
                continue
            last_t = item.t_start_us
            self._own["frames"] += 1
            yield FrameItem(item.image, item.t_start_us, item.t_end_us, item.exposure_us, sequence=seq)
            seq += 1


# -- serving a recording as DV network streams --------------------------------------------------
def _remove_stale_socket(path: str) -> None:
    """Remove a UNIX socket file nobody listens on (left by a server that was killed)."""
    import os
    import socket
    import stat
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(st.st_mode):
        raise FileExistsError(f"{path} exists and is not a socket; choose another socket path")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.connect(path)
    except ConnectionRefusedError:
        os.unlink(path)
        return
    finally:
        s.close()
    raise FileExistsError(f"{path}: another server is listening on this socket")


def resolve_free_ports(urls: dict) -> dict:
    """``urls`` with every ``dv-tcp://HOST:0`` given a free port of HOST (distinct ones: the probe
    sockets are held together), so a server started with port 0 never collides with another.

    dv-processing's ``NetworkWriter`` cannot say which port the system gave it, so the port is
    chosen here and handed to it; another program could take it in between (then the writer fails
    with an error naming the URL, never silently)."""
    import socket
    out, socks = dict(urls), []
    try:
        for k, url in urls.items():
            kind, where = parse_dv_source(url)
            if kind == "tcp" and int(where[1]) == 0:
                fam = socket.AF_INET6 if ":" in where[0] else socket.AF_INET
                sk = socket.socket(fam, socket.SOCK_STREAM)
                socks.append(sk)
                sk.bind((where[0], 0))
                host = f"[{where[0]}]" if fam == socket.AF_INET6 else where[0]
                out[k] = f"dv-tcp://{host}:{sk.getsockname()[1]}"
    finally:
        for sk in socks:
            sk.close()
    return out


def _writer(dv, url: str, stream):
    kind, where = parse_dv_source(url)
    try:
        if kind == "unix":
            _remove_stale_socket(where)
            return dv.io.NetworkWriter(dv.Path(where), stream)
        return dv.io.NetworkWriter(where[0], int(where[1]), stream)
    except RuntimeError as e:
        reason = str(e).split(" [", 1)[0]  # dv-processing appends the C++ source location
        hint = "; another program listens there: pick another port, or port 0 for a free one" \
            if "in use" in reason else ""
        raise OSError(f"{url}: cannot serve a DV stream there ({reason}){hint}") from None


def serve_recording(path, urls: dict, *, speed: float | None = 1.0, wait_clients_s: float = 30.0,
                    t_from_us: int | None = None, t_to_us: int | None = None, on_ready=None,
                    linger_s: float = 0.5) -> dict:
    """Serve an AEDAT4 recording's events, frames, triggers and IMU samples as DV network streams.

    The stand-in for a live DAVIS behind iniVation's DV software: one ``dv.io.NetworkWriter`` per
    kind in ``urls`` (``{"events": URL, "frames": URL, "triggers": URL, "imu": URL}``, any subset
    with events, URLs as for ``--source``).
    Waits until every stream has a client (data written with no client is lost), then writes each
    packet when the (scaled) clock reaches its LAST timestamp (a frame: its exposure end), as a
    camera delivers a packet once it is complete, at ``speed`` × the recorded rate (``None``: as
    fast as possible), and waits until every queued packet has been sent.

    A TCP URL with port 0 is served on a free port (:func:`resolve_free_ports`); ``on_ready`` is
    called as ``on_ready()`` or, if it takes one argument, ``on_ready(urls)`` with the URLs served.

    ``t_from_us`` / ``t_to_us`` serve only ``[t_from_us, t_to_us)`` (events, triggers, IMU samples
    and frame starts), e.g. to stop a stream part-way and restart it where it stopped.

    Returns the counts served by kind. The writers are left to the caller's process exit: a
    ``NetworkWriter`` whose client is still connected blocks in its destructor.
    """
    dv = _dv()
    unknown = set(urls) - {"events", "frames", "triggers", "imu"}
    if unknown:
        raise ValueError(f"serve_recording serves events, frames, triggers and imu; got {sorted(unknown)}")
    urls = resolve_free_ports(urls)
    rec = dv.io.MonoCameraRecording(str(path))
    name = rec.getCameraName()
    writers = {}
    sid = 0
    for kind, url in urls.items():
        if kind == "events":
            if not rec.isEventStreamAvailable():
                raise ValueError(f"{path}: no event stream to serve")
            st = dv.io.Stream.EventStream(sid, "events", name, rec.getEventResolution())
        elif kind == "frames":
            if not rec.isFrameStreamAvailable():
                raise ValueError(f"{path}: no frame stream to serve")
            st = dv.io.Stream.FrameStream(sid, "frames", name, rec.getFrameResolution())
        elif kind == "imu":
            if not rec.isImuStreamAvailable():
                raise ValueError(f"{path}: no IMU stream to serve")
            st = dv.io.Stream.IMUStream(sid, "imu", name)
        else:
            if not rec.isTriggerStreamAvailable():
                raise ValueError(f"{path}: no trigger stream to serve")
            st = dv.io.Stream.TriggerStream(sid, "triggers", name)
        writers[kind] = _writer(dv, url, st)
        sid += 1
    if on_ready is not None:
        import inspect
        try:
            takes_urls = len(inspect.signature(on_ready).parameters) >= 1
        except (TypeError, ValueError):
            takes_urls = False
        on_ready(dict(urls)) if takes_urls else on_ready()
    t_end = time.monotonic() + wait_clients_s
    while any(w.getClientCount() < 1 for w in writers.values()):
        if time.monotonic() > t_end:
            raise TimeoutError(f"no client connected to {[k for k, w in writers.items() if w.getClientCount() < 1]} "
                               f"within {wait_clients_s} s")
        time.sleep(0.005)
    lo = -(1 << 62) if t_from_us is None else int(t_from_us)
    hi = (1 << 62) if t_to_us is None else int(t_to_us)

    def events():
        while True:
            e = rec.getNextEventBatch()
            if e is None:
                return
            if len(e) and (e.getLowestTime() < lo or e.getHighestTime() >= hi):
                e = e.sliceTime(lo, hi)
            if len(e):
                yield int(e.getHighestTime()), "events", e

    def frames():
        while True:
            f = rec.getNextFrame()
            if f is None:
                return
            if lo <= f.timestamp < hi:
                yield int(f.timestamp) + int(round(f.exposure.total_seconds() * 1e6)), "frames", f

    def batches(get_next, vector_type, kind):
        # a packet cut to [lo, hi), each batch keyed by its last sample's time
        while True:
            b = get_next()
            if b is None:
                return
            keep = [x for x in b if lo <= x.timestamp < hi]
            if len(keep) < len(b):
                v = vector_type()
                for x in keep:
                    v.append(x)
                b = v
            if keep:
                yield int(keep[-1].timestamp), kind, b

    def triggers():
        return batches(rec.getNextTriggerBatch, dv.TriggerPacket.TriggersVector, "triggers")

    def imu():
        return batches(rec.getNextImuBatch, dv.IMUPacket.ImuVector, "imu")

    import heapq
    gens = {"events": events, "frames": frames, "triggers": triggers, "imu": imu}
    merged = heapq.merge(*(gens[k]() for k in writers), key=lambda v: v[0])
    counts = {k: 0 for k in writers}
    wall0 = t0 = None
    for t, kind, obj in merged:
        if speed is not None:
            if wall0 is None:
                wall0, t0 = time.perf_counter(), t
            d = wall0 + (t - t0) / (1e6 * speed) - time.perf_counter()
            if d > 0:
                time.sleep(d)
        w = writers[kind]
        if kind == "events":
            w.writeEvents(obj)
            counts[kind] += len(obj)
        elif kind == "frames":
            w.writeFrame(obj)
            counts[kind] += 1
        elif kind == "imu":
            w.writeImu(obj)
            counts[kind] += len(obj)
        else:
            w.writeTriggers(obj)
            counts[kind] += len(obj)
    t_end = time.monotonic() + 30
    while any(w.getQueuedPacketCount() for w in writers.values()) and time.monotonic() < t_end:
        time.sleep(0.005)
    time.sleep(linger_s)
    # a NetworkWriter whose client is still connected blocks in its destructor: keep the writers
    # until the process exits (the serving process is a stand-in for a camera and ends with it)
    _SERVED_WRITERS.extend(writers.values())
    return counts


_SERVED_WRITERS: list = []
