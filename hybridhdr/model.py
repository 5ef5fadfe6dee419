"""The recording model shared by all five parts: frames, HDR references, metadata, recordings."""

from __future__ import annotations

import math
import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ._util.checks import check_shape
from .events import (SensorSize, empty_events, empty_imu, empty_triggers, slice_time, time_window_indices,
                     validate_events, validate_imu, validate_triggers)

__all__ = ["Frames", "HDRReferences", "CameraInfo", "Metadata", "Recording", "FRAME_ENCODINGS", "source_metadata"]

#: The four Bayer layouts, named by the 2×2 tile read from the top-left pixel.
CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
#: Command-line choices (``--cfa``): the patterns and ``none`` (monochrome).
CFA_CHOICES = CFA_PATTERNS + ("none",)


def parse_cfa(name) -> str | None:
    """The canonical pattern name (``"RGGB"``, ...) of ``name``, or None for monochrome.

    Accepts any case and surrounding blanks; ``None``, ``""``, ``"none"`` and ``"mono"`` mean no
    colour filter array. Raises ValueError for anything else.

    >>> parse_cfa("rggb"), parse_cfa("none"), parse_cfa(None)
    ('RGGB', None, None)
    """
    if name is None:
        return None
    if not isinstance(name, str):
        raise ValueError(f"CFA must be a string, one of {', '.join(CFA_CHOICES)}; got {type(name).__name__} {name!r}")
    key = name.strip().upper()
    if key in ("", "NONE", "MONO", "MONOCHROME"):
        return None
    if key not in CFA_PATTERNS:
        raise ValueError(f"unknown colour filter array {name!r}; expected one of {', '.join(CFA_CHOICES)} "
                         f"(the 2x2 Bayer tile read from the top-left pixel)")
    return key


#: How frame pixel values relate to irradiance (after colour's domain-range tables): "raw" sensor
#: numbers and "linear" codes are proportional to it; "gamma" is display gamma 2.2
#: (code = max·I^(1/2.2)); "srgb" is the IEC 61966-2-1 transfer function; "unknown" states
#: nothing. Closed forms: :mod:`hybridhdr.camera.encoding`.
FRAME_ENCODINGS = ("raw", "linear", "gamma", "srgb", "unknown")


def _as_i64(a, name: str, n: int | None = None) -> np.ndarray:
    arr = np.asarray(a)
    check_shape(arr, "N", name if n is None else f"{name} (one per frame)", sizes=None if n is None else {"N": n})
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if not np.all(np.isfinite(arr)) or not np.all(arr == np.round(arr)):
            raise ValueError(f"{name} must hold whole microseconds (int64), got non-integral values")
    return np.ascontiguousarray(arr, dtype=np.int64)


@dataclass(frozen=True, eq=False)
class Frames:
    """Frames with their exposure intervals.

    Parameters
    ----------
    images : ndarray of shape (K, H, W) or (K, H, W, 3)
        Pixel values; the dtype is kept (uint8, uint16, float32 ...).
    t_start_us, t_end_us : ndarray of shape (K,), int64
        Exposure start and end of each frame in µs (``t_end_us >= t_start_us``).
    gain : ndarray of shape (K,), float, optional
        Analogue gain (linear factor) per frame.
    iso : ndarray of shape (K,), float, optional
        ISO per frame.
    encoding : {"raw", "linear", "gamma", "srgb", "unknown"}
        How pixel values relate to irradiance (see :data:`FRAME_ENCODINGS`).
    """

    images: np.ndarray
    t_start_us: np.ndarray
    t_end_us: np.ndarray
    gain: np.ndarray | None = None
    iso: np.ndarray | None = None
    encoding: str = "unknown"

    def __post_init__(self):
        im = np.asarray(self.images)
        k = check_shape(im, "K H W | K H W 3", "frames.images")["K"]
        ts = _as_i64(self.t_start_us, "frames.t_start_us", k)
        te = _as_i64(self.t_end_us, "frames.t_end_us", k)
        bad = te < ts
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"frame {i}: exposure end {te[i]} µs is before its start {ts[i]} µs")
        if k > 1 and np.any(ts[1:] < ts[:-1]):
            i = int(np.flatnonzero(ts[1:] < ts[:-1])[0]) + 1
            raise ValueError(f"frames must be sorted by exposure start; frame {i} starts at {ts[i]} "
                             f"µs after frame {i - 1} at {ts[i - 1]} µs")
        for name in ("gain", "iso"):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=np.float64)
                check_shape(v, "K", f"frames.{name}", sizes={"K": k})
                object.__setattr__(self, name, v)
        if self.encoding not in FRAME_ENCODINGS:
            raise ValueError(f"frames.encoding must be one of {FRAME_ENCODINGS}, got {self.encoding!r}")
        object.__setattr__(self, "images", im)
        object.__setattr__(self, "t_start_us", ts)
        object.__setattr__(self, "t_end_us", te)

    def __len__(self) -> int:
        return self.images.shape[0]

    @property
    def shape(self) -> tuple[int, int]:
        """Image ``(height, width)``."""
        return tuple(self.images.shape[1:3])

    @property
    def t_mid_us(self) -> np.ndarray:
        """Mid-exposure timestamps (µs, int64, rounded down)."""
        return self.t_start_us + (self.t_end_us - self.t_start_us) // 2

    @property
    def exposure_us(self) -> np.ndarray:
        return self.t_end_us - self.t_start_us

    def exposure_scale(self) -> np.ndarray:
        """Per frame, the factor that puts its linear intensity in the units of the median frame.

        A frame records the mean intensity over its exposure times the exposure and the gain, so
        ``CRF⁻¹(code) × median(T·g) / (T_k·g_k)`` is the mean intensity over exposure k in the
        units of a frame exposed for the median ``T·g`` of these frames. float64 (K,); all ones
        when every frame has the same ``T·g`` or some frame has no exposure (an instantaneous or
        unknown one: nothing to divide by). The camera model (``calibrate``) and the frame
        measurements of the filters (``reconstruct``) both read frames through it, so a log
        offset I0 means one thing in both.
        """
        ref = self.reference_exposure()
        return np.ones(len(self)) if ref is None else ref / self._exposure_gain()

    def _exposure_gain(self) -> np.ndarray:
        ex = self.exposure_us.astype(np.float64)
        return ex if self.gain is None else ex * np.asarray(self.gain, np.float64)

    def reference_exposure(self) -> float | None:
        """``median(T·g)`` of these frames (exposure in µs times gain): the exposure whose units
        :meth:`exposure_scale` puts every frame in; None when some frame has no exposure (or
        there are no frames), where frames are read as they are."""
        ex = self._exposure_gain()
        return float(np.median(ex)) if ex.size and np.all(ex > 0) else None

    def units_factor(self, k: int, reference: float | None) -> float:
        """The factor from the units of ``reference`` (another frame set's
        :meth:`reference_exposure`) to frame ``k``'s own: ``T_k·g_k / reference``; 1 when either
        is unknown. A filter's output on those frames times it compares with ``CRF⁻¹(code_k)``."""
        ex = float(self._exposure_gain()[int(k)])
        return ex / reference if reference is not None and ex > 0 else 1.0

    def select(self, idx) -> "Frames":
        sel = lambda a: None if a is None else a[idx]  # noqa: E731
        return Frames(self.images[idx], self.t_start_us[idx], self.t_end_us[idx],
                      sel(self.gain), sel(self.iso), self.encoding)

    def shifted(self, dt_us: int) -> "Frames":
        """These frames with every exposure interval moved by ``dt_us`` µs (images untouched): the
        time a frame stands for when its stamps mean something else (a calibrated frame time
        offset). ``dt_us == 0`` returns the frames themselves."""
        if isinstance(dt_us, bool) or not isinstance(dt_us, (int, np.integer)):
            raise TypeError(f"dt_us must be an int (µs), got {type(dt_us).__name__}")
        dt = int(dt_us)
        if dt == 0:
            return self
        return dataclasses.replace(self, t_start_us=self.t_start_us + dt, t_end_us=self.t_end_us + dt)

    def slice_time(self, t_start_us=None, t_end_us=None) -> "Frames":
        """Frames whose mid-exposure time lies in ``[t_start_us, t_end_us)``."""
        i0, i1 = time_window_indices(self.t_mid_us, t_start_us, t_end_us)
        return self.select(slice(i0, i1))

    @classmethod
    def empty(cls, height: int = 1, width: int = 1, dtype=np.uint8) -> "Frames":
        return cls(np.zeros((0, height, width), dtype), np.zeros(0, np.int64), np.zeros(0, np.int64))


@dataclass(frozen=True, eq=False)
class HDRReferences:
    """HDR reference images: float32 linear radiance, one timestamp each.

    Parameters
    ----------
    images : ndarray of shape (K, H, W) or (K, H, W, 3), float32
    t_us : ndarray of shape (K,), int64
    """

    images: np.ndarray
    t_us: np.ndarray

    def __post_init__(self):
        im = np.asarray(self.images)
        check_shape(im, "K H W | K H W 3", "hdr.images")
        object.__setattr__(self, "images", np.ascontiguousarray(im, dtype=np.float32))
        object.__setattr__(self, "t_us", _as_i64(self.t_us, "hdr.t_us", im.shape[0]))

    def __len__(self) -> int:
        return self.images.shape[0]


@dataclass(frozen=True)
class CameraInfo:
    """One camera's description: sensor size, model, serial number, colour filter array.

    ``cfa`` is the Bayer pattern of the sensor (``"RGGB"``, ``"BGGR"``, ``"GRBG"``, ``"GBRG"``:
    the 2×2 tile read from the top-left pixel, :mod:`hybridhdr.camera.cfa`) or None for a
    monochrome sensor. For the frame camera it describes the sensor: frames stored as (K, H, W)
    are then its raw mosaic, frames stored as (K, H, W, 3) were demosaicked. Any case is accepted
    and stored upper case; ``"none"`` means None.

    ``contrast_threshold_on`` / ``contrast_threshold_off``: an event sensor's nominal ON and OFF
    contrast thresholds in natural-log units (> 0), when the recording states them (a simulated
    sensor does; a real camera's biases rarely say); None: not stated. The reconstruction uses
    them when it is given no threshold.
    """

    sensor_size: SensorSize | None = None
    model: str = ""
    serial: str = ""
    cfa: str | None = None
    contrast_threshold_on: float | None = None
    contrast_threshold_off: float | None = None

    def __post_init__(self):
        if self.cfa is not None:
            object.__setattr__(self, "cfa", parse_cfa(self.cfa))
        for name in ("contrast_threshold_on", "contrast_threshold_off"):
            v = getattr(self, name)
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(float(v)) or float(v) <= 0:
                raise ValueError(f"CameraInfo.{name} must be a finite number > 0 (log units) or None, got {v!r}")
            object.__setattr__(self, name, float(v))

    @property
    def contrast_thresholds(self) -> tuple[float, float] | None:
        """``(on, off)`` when both are stated, else None."""
        if self.contrast_threshold_on is None or self.contrast_threshold_off is None:
            return None
        return self.contrast_threshold_on, self.contrast_threshold_off

    def to_dict(self) -> dict:
        d = {"height": None if self.sensor_size is None else self.sensor_size.height,
             "width": None if self.sensor_size is None else self.sensor_size.width,
             "model": self.model, "serial": self.serial}
        if self.cfa is not None:  # monochrome metadata stays as it was
            d["cfa"] = self.cfa
        for name in ("contrast_threshold_on", "contrast_threshold_off"):  # likewise, only when stated
            if getattr(self, name) is not None:
                d[name] = getattr(self, name)
        return d

    @classmethod
    def from_dict(cls, d: dict | None) -> "CameraInfo":
        d = d or {}
        ss = None
        if d.get("height") is not None and d.get("width") is not None:
            ss = SensorSize(int(d["height"]), int(d["width"]))
        return cls(ss, str(d.get("model", "") or ""), str(d.get("serial", "") or ""), d.get("cfa") or None,
                   d.get("contrast_threshold_on"), d.get("contrast_threshold_off"))


@dataclass(frozen=True)
class Metadata:
    """Recording metadata: both cameras, calibration (a JSON-able dict) and provenance."""

    event_camera: CameraInfo = field(default_factory=CameraInfo)
    frame_camera: CameraInfo = field(default_factory=CameraInfo)
    calibration: dict | None = None
    provenance: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"event_camera": self.event_camera.to_dict(), "frame_camera": self.frame_camera.to_dict(),
                "calibration": self.calibration, "provenance": dict(self.provenance)}

    @classmethod
    def from_dict(cls, d: dict | None) -> "Metadata":
        d = d or {}
        return cls(CameraInfo.from_dict(d.get("event_camera")), CameraInfo.from_dict(d.get("frame_camera")),
                   d.get("calibration"), dict(d.get("provenance") or {}))


@dataclass(frozen=True, eq=False)
class Recording:
    """A hybrid recording: events, frames, triggers, HDR references, metadata and IMU samples.

    Parameters
    ----------
    events : ndarray of shape (N,), dtype EVENT_DTYPE
        Sorted by ``t`` (µs).
    sensor_size : SensorSize or None
        Event-camera size; when given, event coordinates are checked against it.
    frames : Frames, optional
    triggers : ndarray of shape (M,), dtype TRIGGER_DTYPE
    hdr : HDRReferences, optional
    metadata : Metadata
    imu : ndarray of shape (L,), dtype IMU_DTYPE
        Inertial samples (accelerometer, gyroscope, temperature, magnetometer; units in the field
        names, :data:`hybridhdr.events.IMU_FIELDS`) on the event clock, sorted by ``t``; empty
        when the source has no IMU. Auxiliary data: it does not widen :meth:`data_span_us`.
    """

    events: np.ndarray = field(default_factory=empty_events)
    sensor_size: SensorSize | None = None
    frames: Frames | None = None
    triggers: np.ndarray = field(default_factory=empty_triggers)
    hdr: HDRReferences | None = None
    metadata: Metadata = field(default_factory=Metadata)
    imu: np.ndarray = field(default_factory=empty_imu)

    def __post_init__(self):
        ss = SensorSize.from_any(self.sensor_size)
        if ss is None and self.metadata.event_camera.sensor_size is not None:
            ss = self.metadata.event_camera.sensor_size
        object.__setattr__(self, "sensor_size", ss)
        validate_events(self.events, ss, name="recording.events")
        validate_triggers(self.triggers, name="recording.triggers")
        validate_imu(self.imu, name="recording.imu")
        if ss is not None and self.metadata.event_camera.sensor_size != ss:
            ec = dataclasses.replace(self.metadata.event_camera, sensor_size=ss)
            object.__setattr__(self, "metadata", dataclasses.replace(self.metadata, event_camera=ec))
        if self.frames is not None and not isinstance(self.frames, Frames):
            raise TypeError(f"recording.frames must be Frames or None, got {type(self.frames).__name__}")
        if self.hdr is not None and not isinstance(self.hdr, HDRReferences):
            raise TypeError(f"recording.hdr must be HDRReferences or None, got {type(self.hdr).__name__}")

    @property
    def n_events(self) -> int:
        return int(self.events.shape[0])

    def time_range_us(self) -> tuple[int, int] | None:
        """``(first, last)`` timestamp over events, frames and triggers, or None when empty."""
        lo, hi = [], []
        if self.events.size:
            lo.append(int(self.events["t"][0])); hi.append(int(self.events["t"][-1]))
        if self.frames is not None and len(self.frames):
            lo.append(int(self.frames.t_start_us.min())); hi.append(int(self.frames.t_end_us.max()))
        if self.triggers.size:
            lo.append(int(self.triggers["t"][0])); hi.append(int(self.triggers["t"][-1]))
        return (min(lo), max(hi)) if lo else None

    def data_span_us(self) -> tuple[int, int] | None:
        """``(start, last)`` µs sensor time of the data: the start is the first event or frame
        exposure start (the command line's origin for ``--start``), triggers only when there is
        neither; the last is the latest event, frame exposure end, trigger or HDR reference."""
        firsts, lasts = [], []
        if self.events.size:
            firsts.append(int(self.events["t"][0])); lasts.append(int(self.events["t"][-1]))
        if self.frames is not None and len(self.frames):
            firsts.append(int(self.frames.t_start_us.min())); lasts.append(int(self.frames.t_end_us.max()))
        if self.triggers.size:
            lasts.append(int(self.triggers["t"][-1]))
            if not firsts:
                firsts.append(int(self.triggers["t"][0]))
        if self.hdr is not None and len(self.hdr.t_us):
            lasts.append(int(np.max(self.hdr.t_us)))
            if not firsts:
                firsts.append(int(np.min(self.hdr.t_us)))
        return (min(firsts), max(lasts)) if firsts else None

    def slice_time(self, t_start_us=None, t_end_us=None, *, absolute: bool = True) -> "Recording":
        """Events, triggers, IMU samples and HDR references in ``[t_start_us, t_end_us)``; frames by
        mid-exposure.

        ``absolute=True`` (default): µs sensor time, as the timestamps are stored.
        ``absolute=False``: µs from the recording's start (:meth:`data_span_us`), as the command
        line's ``--start``/``--end``. A window wholly outside the data raises
        :class:`~hybridhdr.errors.WindowOutsideDataError` naming the recording's span."""
        from .events import api_window
        t_start_us, t_end_us = api_window(t_start_us, t_end_us, absolute=absolute, span=self.data_span_us(),
                                          what="Recording.slice_time")
        hdr = self.hdr
        if hdr is not None:
            i0, i1 = time_window_indices(hdr.t_us, t_start_us, t_end_us)
            hdr = HDRReferences(hdr.images[i0:i1], hdr.t_us[i0:i1])
        return Recording(slice_time(self.events, t_start_us, t_end_us), self.sensor_size,
                         None if self.frames is None else self.frames.slice_time(t_start_us, t_end_us),
                         slice_time(self.triggers, t_start_us, t_end_us), hdr, self.metadata,
                         slice_time(self.imu, t_start_us, t_end_us))


def source_metadata(source):
    """A source's ``Metadata``: a recording's attribute or a reader's ``metadata()``; None when it
    declares none (or a reader cannot read it)."""
    md = getattr(source, "metadata", None)
    if callable(md):
        try:
            md = md()
        except Exception:  # noqa: BLE001 - a reader without readable metadata declares nothing
            return None
    return md
