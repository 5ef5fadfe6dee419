"""Luxonis OAK cameras through depthai v3: manual exposure/ISO, frame sync, exposure brackets.

The camera is reached through a small *device* object so that everything above it can be tested
without hardware. :class:`DepthaiDevice` is the real one (depthai 3.x: ``dai.Pipeline`` with a
``dai.node.Camera`` built on a board socket, ``requestOutput(size, type, fps=...)`` and
``createOutputQueue()``; controls go through ``camera.inputControl.createInputQueue()``). A device
object provides:

* ``start()`` / ``stop()`` and ``info() -> dict``;
* ``frame_queue`` with ``get()`` (blocking) and ``tryGet()`` returning ImgFrame-like messages
  (``getExposureTime() -> timedelta``, ``getSensitivity() -> ISO``, ``getSequenceNum()``,
  ``getTimestampDevice(offset) -> timedelta``);
* ``control_queue.send(control)`` and ``new_control()`` returning a ``dai.CameraControl``
  (``setManualExposure(exposure_us, iso)``, ``setFrameSyncMode(mode)``,
  ``setExternalTrigger(burst, discard)``, ``setStrobeSensor(level)``);
* ``frame_sync_mode(name)`` mapping ``"off" | "input" | "output"`` to
  ``dai.CameraControl.FrameSyncMode``; ``exposure_offsets`` = (START, END) of
  ``dai.CameraExposureOffset``; ``image(msg) -> ndarray``.

**Exposure changes apply several frames late** (the sensor registers are written between frames
and the pipeline is a few frames deep), so :meth:`DepthaiFrameSource.capture_brackets` sends the
control, discards frames until the metadata of a frame reports the requested exposure and ISO
(within ``exposure_tolerance``), and then tags every kept frame with the exposure and ISO from ITS
OWN metadata, never with the requested value (the sensor quantises exposure to whole lines).

Timestamps are the device's monotonic clock (``getTimestampDevice``) at exposure start and end, in
µs. With ``frame_sync="input"`` the sensor follows an FSIN pulse; ``"output"`` drives FSYNC from
this sensor (wire it to the event camera's trigger input and use :mod:`hybridhdr.capture.sync`);
``external_trigger=(burst, discard)`` switches to snapshot mode on FSIN rising edges.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .devices import NoDeviceFound
from .sources import FrameItem, FrameSource

__all__ = ["DepthaiDevice", "DepthaiFrameSource", "FRAME_SYNC_MODES", "depthai_available"]

FRAME_SYNC_MODES = ("off", "input", "output")


def _depthai():
    try:
        import depthai as dai
    except ImportError as e:
        raise ImportError("the OAK backend needs depthai 3.x: pip install depthai") from e
    return dai


def depthai_available() -> bool:
    try:
        _depthai()
    except ImportError:
        return False
    return True


def _us(td) -> int:
    """timedelta -> whole µs."""
    return int(round(td.total_seconds() * 1e6))


class DepthaiDevice:
    """The real depthai v3 device (see the module docstring for the interface it implements).

    Parameters
    ----------
    socket : str
        Board socket, e.g. ``"CAM_A"`` (colour) or ``"CAM_B"``/``"CAM_C"`` (mono).
    size : (width, height)
        Output size in pixels.
    fps : float
    frame_type : str
        ``dai.ImgFrame.Type`` name: ``"GRAY8"`` (ISP, gamma), ``"NV12"`` (ISP colour), ``"RAW16"`` ...
    device_id : str, optional
        Device ID (MX ID) or IP; default the first available device.
    queue_size : int
        Host-side frame queue length (non-blocking: the camera never stalls; frames lost there show
        as sequence gaps, counted by the recorder).
    """

    def __init__(self, socket: str = "CAM_A", size=(1280, 800), fps: float = 30.0, frame_type: str = "GRAY8",
                 device_id: str | None = None, queue_size: int = 8):
        self.socket, self.size, self.fps = socket, tuple(int(v) for v in size), float(fps)
        self.frame_type, self.device_id, self.queue_size = frame_type, device_id, int(queue_size)
        self._device = self._pipeline = None
        self.frame_queue = self.control_queue = None

    def start(self) -> None:
        dai = _depthai()
        infos = dai.Device.getAllAvailableDevices()
        if not infos:
            raise NoDeviceFound("no device found: no Luxonis OAK camera is attached or visible to depthai "
                                "(check the cable and the udev rule for USB vendor 03e7)")
        if self.device_id is not None:
            self._device = dai.Device(dai.DeviceInfo(self.device_id))
        else:
            self._device = dai.Device()
        self._pipeline = dai.Pipeline(self._device)
        try:
            sock = getattr(dai.CameraBoardSocket, self.socket)
        except AttributeError:
            raise ValueError(f"unknown board socket {self.socket!r}; expected one of "
                             f"{sorted(dai.CameraBoardSocket.__members__)}") from None
        cam = self._pipeline.create(dai.node.Camera).build(sock)
        out = cam.requestOutput(self.size, getattr(dai.ImgFrame.Type, self.frame_type), fps=self.fps)
        self.frame_queue = out.createOutputQueue(maxSize=self.queue_size, blocking=False)
        self.control_queue = cam.inputControl.createInputQueue()
        self._pipeline.start()

    @property
    def exposure_offsets(self):
        dai = _depthai()
        return dai.CameraExposureOffset.START, dai.CameraExposureOffset.END

    def new_control(self):
        return _depthai().CameraControl()

    def frame_sync_mode(self, name: str):
        return getattr(_depthai().CameraControl.FrameSyncMode, name.upper())

    def image(self, msg) -> np.ndarray:
        im = msg.getCvFrame()
        if im.ndim == 3:
            im = im[..., ::-1]  # OpenCV BGR -> RGB
        return np.ascontiguousarray(im)

    def info(self) -> dict:
        d = self._device
        return {"kind": "depthai", "name": "" if d is None else d.getDeviceName(),
                "serial": "" if d is None else d.getDeviceId(), "socket": self.socket,
                "size": list(self.size), "fps": self.fps, "frame_type": self.frame_type}

    def stop(self) -> None:
        if self._pipeline is not None:
            self._pipeline.stop()
        if self._device is not None:
            self._device.close()
        self._pipeline = self._device = None


class DepthaiFrameSource(FrameSource):
    """A :class:`FrameSource` for an OAK camera with manual exposure and frame-sync settings.

    Parameters
    ----------
    device : object, optional
        A device object (module docstring); default a :class:`DepthaiDevice` built from
        ``device_options``.
    exposure_us, iso : int, optional
        Manual exposure (µs) and ISO (usual range 100-1600) sent at open; both or neither.
    frame_sync : {"off", "input", "output"}, optional
        FSIN/FSYNC role (``CameraControl.setFrameSyncMode``).
    external_trigger : (int, int), optional
        ``(frames_per_burst, frames_discarded)``: snapshot mode on FSIN rising edges.
    strobe : bool
        Drive the sensor's STROBE pin high during exposure (``setStrobeSensor(1)``), e.g. to feed
        the event camera's trigger input.
    encoding : str
        ``Frames.encoding`` of the delivered pixels: ``"gamma"`` for ISP outputs, ``"raw"`` for RAW.
    poll_s : float
        Polling period of the frame queue while waiting (stop() is checked between polls).
    """

    can_backpressure = False  # a camera: the recorder drops and counts when it cannot keep up

    def __init__(self, device=None, *, exposure_us: int | None = None, iso: int | None = None,
                 frame_sync: str | None = None, external_trigger=None, strobe: bool = False,
                 encoding: str = "gamma", poll_s: float = 0.002, **device_options):
        super().__init__()
        if (exposure_us is None) != (iso is None):
            raise ValueError("give exposure_us and iso together (manual exposure) or neither (auto exposure)")
        if exposure_us is not None:
            self._check_exposure(exposure_us, iso)
        if frame_sync is not None and frame_sync not in FRAME_SYNC_MODES:
            raise ValueError(f"frame_sync must be one of {FRAME_SYNC_MODES}, got {frame_sync!r}")
        if external_trigger is not None:
            burst, discard = (int(v) for v in external_trigger)
            if burst < 1 or discard < 0:
                raise ValueError(f"external_trigger must be (frames_per_burst >= 1, discarded >= 0), "
                                 f"got {external_trigger}")
            external_trigger = (burst, discard)
        self.device = device if device is not None else DepthaiDevice(**device_options)
        self.exposure_us, self.iso = exposure_us, iso
        self.frame_sync, self.external_trigger, self.strobe = frame_sync, external_trigger, bool(strobe)
        self.encoding = encoding
        self.poll_s = float(poll_s)
        self._started = False

    @staticmethod
    def _check_exposure(exposure_us, iso):
        if not (int(exposure_us) >= 1):
            raise ValueError(f"exposure_us must be >= 1 µs, got {exposure_us}")
        if not (1 <= int(iso) <= 100_000):
            raise ValueError(f"iso must be a positive ISO value (usual range 100-1600), got {iso}")

    # -- lifecycle -----------------------------------------------------------------------------
    def open(self):
        if not self._started:
            self.device.start()
            self._started = True
            ctrl = self.device.new_control()
            changed = False
            if self.exposure_us is not None:
                ctrl.setManualExposure(int(self.exposure_us), int(self.iso))
                changed = True
            if self.frame_sync is not None:
                ctrl.setFrameSyncMode(self.device.frame_sync_mode(self.frame_sync))
                changed = True
            if self.external_trigger is not None:
                ctrl.setExternalTrigger(*self.external_trigger)
                changed = True
            if self.strobe:
                ctrl.setStrobeSensor(1)
                changed = True
            if changed:
                self.device.control_queue.send(ctrl)
        return super().open()

    def close(self) -> None:
        if self._started:
            self.device.stop()
            self._started = False
        super().close()

    def device_info(self) -> dict:
        d = dict(self.device.info())
        d.update({"exposure_us": self.exposure_us, "iso": self.iso, "frame_sync": self.frame_sync,
                  "external_trigger": self.external_trigger, "strobe": self.strobe})
        return d

    # -- frames --------------------------------------------------------------------------------
    def _next_msg(self, timeout_s: float | None = None):
        """Next message from the frame queue, or None on stop()/timeout."""
        q = self.device.frame_queue
        t_end = None if timeout_s is None else time.perf_counter() + timeout_s
        while not self.stopped:
            msg = q.tryGet()
            if msg is not None:
                return msg
            if t_end is not None and time.perf_counter() >= t_end:
                return None
            time.sleep(self.poll_s)
        return None

    def to_item(self, msg) -> FrameItem:
        """A :class:`FrameItem` with the frame's OWN exposure, ISO, sequence number and times."""
        off_start, off_end = self.device.exposure_offsets
        t0 = _us(msg.getTimestampDevice(off_start))
        t1 = _us(msg.getTimestampDevice(off_end))
        return FrameItem(self.device.image(msg), t0, max(t0, t1), _us(msg.getExposureTime()),
                         iso=float(msg.getSensitivity()), sequence=int(msg.getSequenceNum()))

    def _iter(self):
        while not self.stopped:
            msg = self._next_msg()
            if msg is None:
                return
            yield self.to_item(msg)

    def set_exposure(self, exposure_us: int, iso: int) -> None:
        """Send a manual exposure (applies a few frames later; see :meth:`wait_for_exposure`)."""
        self._check_exposure(exposure_us, iso)
        ctrl = self.device.new_control()
        ctrl.setManualExposure(int(exposure_us), int(iso))
        self.device.control_queue.send(ctrl)
        self.exposure_us, self.iso = int(exposure_us), int(iso)

    @staticmethod
    def _matches(item: FrameItem, exposure_us, iso, tol) -> bool:
        return (abs(item.exposure_us - exposure_us) <= max(tol * exposure_us, 1.0)
                and (iso is None or item.iso is None or abs(item.iso - iso) <= max(tol * iso, 1.0)))

    def wait_for_exposure(self, exposure_us: int, iso: int | None, *, max_frames: int = 30,
                          tolerance: float = 0.05, timeout_s: float = 10.0) -> tuple[FrameItem, int]:
        """Discard frames until one reports ``exposure_us`` (and ``iso``); returns it and the count discarded."""
        skipped = 0
        t_end = time.perf_counter() + timeout_s
        while True:
            msg = self._next_msg(max(0.0, t_end - time.perf_counter()))
            if msg is None:
                raise TimeoutError(f"no frame from the camera within {timeout_s} s while waiting for exposure "
                                   f"{exposure_us} µs")
            item = self.to_item(msg)
            if self._matches(item, exposure_us, iso, tolerance):
                return item, skipped
            skipped += 1
            if skipped > max_frames:
                raise TimeoutError(f"requested exposure {exposure_us} µs / ISO {iso}, but the camera still "
                                   f"reports {item.exposure_us} µs / ISO {item.iso} after {skipped} frames "
                                   f"(outside the sensor's range, or auto exposure still on?)")

    def capture_brackets(self, exposures_us, iso: int, frames_per_step: int = 1, folder=None, *,
                         max_wait_frames: int = 30, tolerance: float = 0.05, camera: dict | None = None,
                         overwrite: bool = False):
        """Capture an exposure bracket; optionally write it as a bracket-set folder.

        Parameters
        ----------
        exposures_us : sequence of int
            Requested exposures (µs); consecutive values must differ by more than ``tolerance``
            (otherwise the switch cannot be seen in the metadata).
        iso : int
        frames_per_step : int
            Frames kept per exposure (each one is written, tagged with its own exposure).
        folder : path-like, optional
            Write a bracket set there (:func:`hybridhdr.formats.brackets.write_bracket_set`).
        max_wait_frames : int
            Frames to wait for a change to show in the metadata before giving up.
        tolerance : float
            Relative tolerance between the requested and the reported exposure / ISO.

        Returns
        -------
        items : list of FrameItem
            In capture order, ``frames_per_step`` per exposure, each with its own metadata.
        report : dict
            ``requested_us``, ``reported_us`` (per item), ``frames_discarded`` (per step).
        """
        exps = [int(e) for e in exposures_us]
        if not exps:
            raise ValueError("exposures_us is empty; give at least one exposure in µs")
        if int(frames_per_step) < 1:
            raise ValueError(f"frames_per_step must be >= 1, got {frames_per_step}")
        for e in exps:
            self._check_exposure(e, iso)
        for a, b in zip(exps[:-1], exps[1:]):
            if abs(a - b) <= tolerance * max(a, b):
                raise ValueError(f"consecutive exposures {a} and {b} µs differ by less than the tolerance "
                                 f"({tolerance:.0%}); the camera metadata could not tell them apart")
        self.open()
        items, discarded, requested = [], [], []
        for e in exps:
            self.set_exposure(e, iso)
            first, skipped = self.wait_for_exposure(e, iso, max_frames=max_wait_frames, tolerance=tolerance)
            discarded.append(skipped)
            step = [first]
            while len(step) < int(frames_per_step):
                msg = self._next_msg(10.0)
                if msg is None:
                    raise TimeoutError("the camera stopped delivering frames during the bracket")
                it = self.to_item(msg)
                if not self._matches(it, e, iso, tolerance):
                    raise RuntimeError(f"exposure changed by itself during the bracket step {e} µs "
                                       f"(frame {it.sequence} reports {it.exposure_us} µs)")
                step.append(it)
            items += step
            requested += [e] * len(step)
        report = {"requested_us": requested, "reported_us": [it.exposure_us for it in items],
                  "frames_discarded": discarded, "iso": [it.iso for it in items],
                  "sequence": [it.sequence for it in items]}
        if folder is not None:
            from ..formats.brackets import write_bracket_set
            cam = dict(self.device.info())
            cam.update(camera or {})
            cam.setdefault("name", cam.get("name") or "Luxonis OAK")
            write_bracket_set(Path(folder), [it.image for it in items],
                              [it.exposure_us * 1e-6 for it in items], encoding=self.encoding, camera=cam,
                              iso=[it.iso for it in items], t_us=[it.t_start_us for it in items],
                              overwrite=overwrite)
        return items, report
