"""Machine-vision frame cameras through Basler pylon (pypylon): brackets, fixed exposure, triggers.

pylon drives Basler's USB3 Vision and GigE cameras and, through its GenTL consumer, other vendors'
GenICam producers. Its camera-emulation transport layer (``PYLON_CAMEMU=N`` in the environment)
enumerates N emulated cameras with the same GenICam features (ExposureTime, Gain, PixelFormat,
TriggerMode/TriggerSource, test images or images from files): the tests run this module against it.

:class:`PylonFrameSource` is a :class:`~hybridhdr.capture.sources.FrameSource` (the interface of the
OAK backend):

* **exposure and gain** are set on the camera (``ExposureAuto``/``GainAuto`` off) and READ BACK from
  it after every change: the camera quantises them (exposure to its clock or line time), and every
  frame is tagged with the value the camera reports, never the requested one;
* **trigger**: ``"free"`` (free-running at ``AcquisitionFrameRate``), ``"software"``
  (``TriggerMode=On``, ``TriggerSource=Software``: :meth:`PylonFrameSource.trigger` fires one
  exposure; with ``software_rate_hz`` the source triggers at that rate itself) or a hardware line
  (``"Line1"`` ...: the camera waits for an edge on that input; wire the event camera's trigger
  output or a common generator to it);
* **timestamps on the host clock** (``time.monotonic_ns``, µs), in this order of preference:

  1. ``"camera"``: the frame's own ``TimeStamp`` (camera ticks; ns on USB3 Vision, ``GevTimestampTickFrequency``
     on GigE), mapped to the host clock by a robust line fit (:func:`hybridhdr.capture.sync.robust_line_fit`)
     to latch samples ``(TimestampLatch`` / ``GevTimestampControlLatch`` read between two host
     clock reads, the midpoint taken), re-latched every ``relatch_s``;
  2. ``"host-trigger"`` (software trigger, camera without a timestamp): exposure start = the host
     time at which the trigger command returned;
  3. ``"host-arrival"``: exposure end = the host time the frame arrived (an upper bound: transfer
     time is not known).

  ``device_info()["timestamp_source"]`` says which one a recording used. The emulator has no
  camera clock (its ``TimeStamp`` is 0): the tests exercise 2 and 3; path 1 runs only on a real
  camera.

:meth:`PylonFrameSource.capture_brackets` captures an exposure bracket (the input of
``hybridhdr calibrate crf`` and ``calibrate hdr-reference``) with software triggers, one
exposure change between frames, each frame tagged with the exposure read back from the camera.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np

from .devices import NoDeviceFound
from .sources import FrameItem, FrameSource

__all__ = ["pylon_available", "PylonFrameSource", "list_pylon_cameras", "TRIGGERS"]

log = logging.getLogger(__name__)

#: trigger modes: free-running, software, or a hardware input line
TRIGGERS = ("free", "software", "Line1", "Line2", "Line3", "Line4")

#: pixel formats delivered as they are (others are refused: no silent conversion)
_FORMATS = {"Mono8": (np.uint8, "gamma"), "Mono10": (np.uint16, "raw"), "Mono12": (np.uint16, "raw"),
            "Mono16": (np.uint16, "raw"), "RGB8Packed": (np.uint8, "gamma"), "RGB8": (np.uint8, "gamma")}


def _pylon():
    import warnings
    try:
        # pypylon's SWIG module emits a DeprecationWarning ("builtin type SwigPyPacked has no __module__
        # attribute") while it initialises; turned into an exception (python -W error, pytest's
        # filterwarnings = error) it aborts the initialisation and the interpreter crashes
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            from pypylon import genicam, pylon
    except ImportError as e:
        raise ImportError("Basler and GenICam cameras need pypylon: pip install 'hybridhdr[pylon]'") from e
    return pylon, genicam


def pylon_available() -> bool:
    try:
        _pylon()
    except ImportError:
        return False
    return True


def _host_us() -> int:
    return time.monotonic_ns() // 1000


def list_pylon_cameras() -> list[dict]:
    """Cameras pylon enumerates (USB3 Vision, GigE, GenTL producers, emulated); [] without pypylon."""
    if not pylon_available():
        return []
    pylon, _ = _pylon()
    out = []
    for d in pylon.TlFactory.GetInstance().EnumerateDevices():
        serial = d.GetSerialNumber()
        out.append({"maker": d.GetVendorName(), "model": d.GetModelName(), "serial": serial,
                    "kind": "frame", "sdk": "pypylon", "transport": d.GetDeviceClass(),
                    "name": d.GetFriendlyName(), "open_with": f"--frames pylon:{serial}"})
    return out


def _node(cam, name):
    """A readable/writable GenICam node or None when the camera lacks it."""
    _, genicam = _pylon()
    try:
        n = cam.GetNodeMap().GetNode(name)
    except Exception:  # noqa: BLE001 - pylon raises its own exception types for unknown nodes
        return None
    if n is None or not genicam.IsAvailable(n):
        return None
    return n


class PylonFrameSource(FrameSource):
    """A :class:`FrameSource` for a pylon camera (module docstring).

    Parameters
    ----------
    serial : str, optional
        Serial number (default: the first camera pylon finds).
    exposure_us : float, optional
        Fixed exposure (µs); ``ExposureAuto`` is switched off. Default: the camera's current value.
    gain_db : float, optional
        Fixed gain (dB); ``GainAuto`` off.
    pixel_format : str, optional
        ``Mono8``, ``Mono12``, ``Mono16``, ``RGB8`` ... (kept as delivered; uint8 or uint16).
    trigger : {"free", "software", "Line1", ...}
    software_rate_hz : float, optional
        With ``trigger="software"``, fire triggers at this rate while iterating.
    frame_rate_hz : float, optional
        Free-running frame rate (``AcquisitionFrameRate``).
    relatch_s : float
        Period of the camera-clock latch samples (timestamp path 1).
    buffers : int
        pylon's host buffers (``MaxNumBuffer``); frames the host misses show as skipped images
        (``GetNumberOfSkippedImages``), counted in :meth:`counters` and as sequence gaps.
    camera : object, optional
        An already created ``pylon.InstantCamera`` (tests).
    """

    can_backpressure = False  # a camera: the recorder drops and counts when it cannot keep up

    def __init__(self, serial: str | None = None, *, exposure_us: float | None = None, gain_db: float | None = None,
                 pixel_format: str | None = None, trigger: str = "free", software_rate_hz: float | None = None,
                 frame_rate_hz: float | None = None, relatch_s: float = 10.0, buffers: int = 16,
                 timeout_ms: int = 5000, camera=None):
        super().__init__()
        if trigger not in TRIGGERS:
            raise ValueError(f"trigger must be one of {TRIGGERS}, got {trigger!r}")
        if exposure_us is not None and not (float(exposure_us) > 0):
            raise ValueError(f"exposure_us must be > 0 µs, got {exposure_us}")
        if software_rate_hz is not None and (trigger != "software" or not float(software_rate_hz) > 0):
            raise ValueError("software_rate_hz needs trigger='software' and a rate > 0 Hz")
        if pixel_format is not None and pixel_format not in _FORMATS:
            raise ValueError(f"pixel_format must be one of {sorted(_FORMATS)}, got {pixel_format!r}")
        self.serial, self.exposure_us, self.gain_db = serial, exposure_us, gain_db
        self.pixel_format, self.trigger = pixel_format, trigger
        self.software_rate_hz, self.frame_rate_hz = software_rate_hz, frame_rate_hz
        self.relatch_s, self.buffers, self.timeout_ms = float(relatch_s), int(buffers), int(timeout_ms)
        self.cam = camera
        self._pending_triggers: list[int] = []
        self._trig_lock = threading.Lock()
        self._latch: list[tuple[float, float]] = []   # (camera µs, host µs)
        self._last_latch = 0.0
        self._tick_hz = None
        self.timestamp_source = None
        self._skipped = 0
        self._last_t = None
        self._nonmonotonic = 0
        self.encoding = "unknown"

    # -- lifecycle ---------------------------------------------------------------------------
    def open(self):
        if self.cam is None:
            pylon, _ = _pylon()
            tlf = pylon.TlFactory.GetInstance()
            devs = tlf.EnumerateDevices()
            if not devs:
                raise NoDeviceFound("no device found: pylon sees no camera (USB3 Vision / GigE; check the cable, "
                                    "the udev rules and, for GigE, the network; PYLON_CAMEMU=1 emulates one)")
            if self.serial:
                match = [d for d in devs if d.GetSerialNumber() == self.serial]
                if not match:
                    raise NoDeviceFound(f"no pylon camera with serial {self.serial}; found "
                                        f"{[d.GetSerialNumber() for d in devs]}")
                dev = match[0]
            else:
                dev = devs[0]
            self.cam = pylon.InstantCamera(tlf.CreateDevice(dev))
        if not self.cam.IsOpen():
            self.cam.Open()
        self._configure()
        return super().open()

    def _set(self, name, value):
        n = _node(self.cam, name)
        if n is None:
            return False
        n.SetValue(value)
        return True

    def _get(self, name, default=None):
        n = _node(self.cam, name)
        if n is None:
            return default
        return n.GetValue()

    def _configure(self):
        cam = self.cam
        if self.pixel_format is not None:
            self._set("PixelFormat", self.pixel_format)
        pf = str(self._get("PixelFormat", "Mono8"))
        if pf not in _FORMATS:
            raise ValueError(f"the camera delivers {pf}; set pixel_format to one of {sorted(_FORMATS)} "
                             f"(Bayer formats are not demosaiced here)")
        self.encoding = _FORMATS[pf][1]
        self._set("ExposureAuto", "Off")
        self._set("GainAuto", "Off")
        if self.exposure_us is not None:
            self.set_exposure(self.exposure_us)
        if self.gain_db is not None:
            if not self._set("Gain", float(self.gain_db)):
                raise ValueError("this camera has no Gain (dB) feature")
        if self.frame_rate_hz is not None:
            self._set("AcquisitionFrameRateEnable", True)
            if not (self._set("AcquisitionFrameRate", float(self.frame_rate_hz))
                    or self._set("AcquisitionFrameRateAbs", float(self.frame_rate_hz))):
                raise ValueError("this camera has no AcquisitionFrameRate feature")
        self._set("TriggerSelector", "FrameStart")
        if self.trigger == "free":
            self._set("TriggerMode", "Off")
        else:
            self._set("TriggerMode", "On")
            src = "Software" if self.trigger == "software" else self.trigger
            if not self._set("TriggerSource", src):
                raise ValueError(f"this camera has no TriggerSource {src}")
        cam.MaxNumBuffer.SetValue(self.buffers) if _node(cam, "MaxNumBuffer") is not None else None
        # camera clock: tick frequency and a latch command
        self._tick_hz = None
        if _node(cam, "TimestampLatch") is not None and _node(cam, "TimestampLatchValue") is not None:
            self._tick_hz = 1e9  # USB3 Vision (SFNC): TimestampLatchValue in ns
            self._latch_cmd, self._latch_val = "TimestampLatch", "TimestampLatchValue"
        elif _node(cam, "GevTimestampControlLatch") is not None and _node(cam, "GevTimestampValue") is not None:
            self._tick_hz = float(self._get("GevTimestampTickFrequency", 1e9))
            self._latch_cmd, self._latch_val = "GevTimestampControlLatch", "GevTimestampValue"
        self._latch = []
        if self._tick_hz is not None:
            for _ in range(5):
                self._latch_once()
        # the path frames will take (a camera clock is confirmed by the first frame's TimeStamp)
        self.timestamp_source = ("camera" if self._tick_hz is not None
                                 else "host-trigger" if self.trigger == "software" else "host-arrival")

    def close(self) -> None:
        if self.cam is not None:
            if self.cam.IsGrabbing():
                self.cam.StopGrabbing()
            if self.cam.IsOpen():
                self.cam.Close()
        super().close()

    def device_info(self) -> dict:
        d = {"kind": "pylon", "trigger": self.trigger, "timestamp_source": self.timestamp_source,
             "encoding": self.encoding}
        if self.cam is not None:
            try:
                di = self.cam.GetDeviceInfo()
                d.update({"maker": di.GetVendorName(), "model": di.GetModelName(), "serial": di.GetSerialNumber(),
                          "transport": di.GetDeviceClass()})
            except Exception:  # noqa: BLE001 - info is optional
                pass
            d.update({"exposure_us": self._get("ExposureTime"), "gain_db": self._get("Gain"),
                      "pixel_format": str(self._get("PixelFormat", ""))})
        d["clock_fit"] = self.clock_fit()
        return d

    def counters(self) -> dict:
        return {"frames_skipped_by_camera_or_driver": self._skipped, "timestamps_not_increasing": self._nonmonotonic}

    # -- controls ----------------------------------------------------------------------------
    def set_exposure(self, exposure_us: float) -> float:
        """Set the exposure; returns the value the camera reports back (µs)."""
        if not (float(exposure_us) > 0):
            raise ValueError(f"exposure_us must be > 0 µs, got {exposure_us}")
        if not (self._set("ExposureTime", float(exposure_us)) or self._set("ExposureTimeAbs", float(exposure_us))):
            raise ValueError("this camera has no ExposureTime feature")
        return self.read_exposure_us()

    def read_exposure_us(self) -> float:
        v = self._get("ExposureTime")
        if v is None:
            v = self._get("ExposureTimeAbs")
        return float(v)

    def trigger_now(self) -> int:
        """Fire one software trigger; returns the host time (µs) when the command returned."""
        pylon, _ = _pylon()
        if self.trigger != "software":
            raise ValueError("trigger_now needs trigger='software'")
        self.cam.WaitForFrameTriggerReady(self.timeout_ms, pylon.TimeoutHandling_ThrowException)
        self.cam.ExecuteSoftwareTrigger()
        t = _host_us()
        with self._trig_lock:
            self._pending_triggers.append(t)
        return t

    # -- clock -------------------------------------------------------------------------------
    def _latch_once(self):
        a = _host_us()
        n = _node(self.cam, self._latch_cmd)
        n.Execute()
        b = _host_us()
        v = float(self._get(self._latch_val))
        self._latch.append((v / self._tick_hz * 1e6, 0.5 * (a + b)))
        self._last_latch = time.monotonic()

    def clock_fit(self):
        """``(offset_us, slope, rms_us, n)`` of host = offset + slope · camera µs, or None."""
        if len(self._latch) < 2:
            return None
        from .sync import robust_line_fit
        x = np.array([p[0] for p in self._latch])
        y = np.array([p[1] for p in self._latch])
        if np.ptp(x) == 0:
            return None
        a, b, inl, r = robust_line_fit(x, y)
        return {"offset_us": a, "slope": b, "rms_us": float(np.sqrt(np.mean(r[inl] ** 2))), "samples": len(x)}

    def _times(self, res, exposure_us: float, arrival_us: int) -> tuple[int, int]:
        ts = int(res.TimeStamp)
        exp = int(round(exposure_us))
        if self._tick_hz is not None and ts:
            if time.monotonic() - self._last_latch > self.relatch_s:
                self._latch_once()
            fit = self.clock_fit()
            if fit is not None:
                self.timestamp_source = "camera"
                t0 = int(round(fit["offset_us"] + fit["slope"] * (ts / self._tick_hz * 1e6)))
                return t0, t0 + exp
        with self._trig_lock:
            trig = self._pending_triggers.pop(0) if self._pending_triggers else None
        if trig is not None:
            self.timestamp_source = "host-trigger"
            return trig, trig + exp
        self.timestamp_source = "host-arrival"
        return arrival_us - exp, arrival_us

    # -- frames ------------------------------------------------------------------------------
    def _start(self):
        pylon, _ = _pylon()
        if not self.cam.IsGrabbing():
            self.cam.StartGrabbing(pylon.GrabStrategy_OneByOne)

    def _retrieve(self) -> FrameItem:
        pylon, _ = _pylon()
        res = self.cam.RetrieveResult(self.timeout_ms, pylon.TimeoutHandling_ThrowException)
        arrival = _host_us()
        try:
            if not res.GrabSucceeded():
                raise RuntimeError(f"pylon grab failed: {res.GetErrorCode()} {res.GetErrorDescription()}")
            im = np.array(res.Array, copy=True)
            skipped = int(res.GetNumberOfSkippedImages())
            self._skipped += skipped
            seq = int(res.ImageNumber)
            exposure = self.read_exposure_us()
            t0, t1 = self._times(res, exposure, arrival)
        finally:
            res.Release()
        if self._last_t is not None and t0 <= self._last_t:
            self._nonmonotonic += 1
        self._last_t = t0
        return FrameItem(im, t0, t1, int(round(exposure)), gain=self._get("Gain"), sequence=seq)

    def _iter(self):
        self._start()
        period = None if self.software_rate_hz is None else 1.0 / float(self.software_rate_hz)
        next_t = time.perf_counter()
        while not self.stopped:
            if period is not None:
                self._sleep_until(next_t)
                if self.stopped:
                    return
                next_t += period
                self.trigger_now()
            try:
                item = self._retrieve()
            except Exception as e:  # noqa: BLE001 - pylon's TimeoutException has no Python base to name
                if "Timeout" in type(e).__name__ or "timeout" in str(e).lower():
                    if self.trigger not in ("free", "software") or period is None:
                        continue  # waiting for a hardware trigger or a manual software trigger
                raise
            yield item

    def grab_triggered(self) -> FrameItem:
        """Fire one software trigger and return its frame (grabbing starts if needed)."""
        self._start()
        self.trigger_now()
        return self._retrieve()

    def capture_brackets(self, exposures_us, *, gain_db: float | None = None, frames_per_step: int = 1,
                         folder=None, tolerance: float = 0.05, camera: dict | None = None,
                         overwrite: bool = False):
        """Capture an exposure bracket with software triggers; optionally write a bracket-set folder.

        The exposure is set while no exposure is running (the trigger for the next frame is fired
        only after the change), read back from the camera, and every frame is tagged with the read
        back value. A read-back further than ``tolerance`` (relative) from the request is refused:
        the camera clamped it to its range.

        Returns
        -------
        items : list of FrameItem
        report : dict
            ``requested_us``, ``reported_us`` (per frame), ``gain_db``, ``sequence``,
            ``timestamp_source``.
        """
        exps = [float(e) for e in exposures_us]
        if not exps:
            raise ValueError("exposures_us is empty; give at least one exposure in µs")
        if int(frames_per_step) < 1:
            raise ValueError(f"frames_per_step must be >= 1, got {frames_per_step}")
        if self.trigger != "software":
            raise ValueError("capture_brackets needs trigger='software' (one exposure change between frames)")
        if not self._opened:
            self.open()
        if gain_db is not None:
            if not self._set("Gain", float(gain_db)):
                raise ValueError("this camera has no Gain (dB) feature")
        items, requested = [], []
        for e in exps:
            got = self.set_exposure(e)
            if abs(got - e) > tolerance * e:
                raise ValueError(f"requested exposure {e:g} µs, the camera reports {got:g} µs (outside its range?)")
            for _ in range(int(frames_per_step)):
                items.append(self.grab_triggered())
                requested.append(e)
        report = {"requested_us": requested, "reported_us": [it.exposure_us for it in items],
                  "gain_db": [it.gain for it in items], "sequence": [it.sequence for it in items],
                  "timestamp_source": self.timestamp_source}
        if folder is not None:
            from ..formats.brackets import write_bracket_set
            cam = {k: v for k, v in self.device_info().items() if k in ("maker", "model", "serial", "transport",
                                                                       "pixel_format")}
            cam.update(camera or {})
            cam.setdefault("name", f"{cam.get('maker', 'pylon')} {cam.get('model', '')}".strip())
            write_bracket_set(Path(folder), [it.image for it in items], [it.exposure_us * 1e-6 for it in items],
                              encoding=self.encoding, camera=cam, gain=[it.gain for it in items],
                              t_us=[it.t_start_us for it in items], overwrite=overwrite)
        return items, report
