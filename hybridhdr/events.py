"""Event arrays: the one structured dtype used at every API and file boundary.

Conventions (see ``docs/conventions.md``): ``t`` is int64 microseconds and non-decreasing,
``x`` is the column (0 = left), ``y`` the row (0 = top), ``p`` is +1 (ON) or -1 (OFF).
Time windows are half-open, ``[t0, t1)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import EventValidationError, WindowOutsideDataError

__all__ = [
    "EVENT_DTYPE",
    "TRIGGER_DTYPE",
    "IMU_DTYPE",
    "IMU_FIELDS",
    "SensorSize",
    "make_events",
    "empty_events",
    "make_triggers",
    "empty_triggers",
    "validate_events",
    "validate_triggers",
    "empty_imu",
    "validate_imu",
    "slice_time",
    "time_window_indices",
    "api_window",
    "concatenate_events",
    "events_fields",
]

#: Structured dtype of one event: 16 bytes per record with ``align=True``.
EVENT_DTYPE = np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")], align=True)

#: Structured dtype of one trigger edge: ``edge`` is +1 (rising) or -1 (falling).
TRIGGER_DTYPE = np.dtype([("t", "<i8"), ("channel", "<u2"), ("edge", "i1")], align=True)

#: The measured quantities of one IMU sample, ``(field, unit, dv-processing's dv.IMU name)``: the
#: accelerometer in g (9.81 m/s²), the gyroscope in degrees per second, the die temperature in
#: degrees Celsius and the magnetometer in microtesla (zeros when the IMU has none, as DAVIS
#: cameras report it). The unit is the last part of each name. float32, as the cameras send them.
IMU_FIELDS = (
    ("accel_x_g", "g", "accelerometerX"), ("accel_y_g", "g", "accelerometerY"),
    ("accel_z_g", "g", "accelerometerZ"),
    ("gyro_x_deg_s", "deg/s", "gyroscopeX"), ("gyro_y_deg_s", "deg/s", "gyroscopeY"),
    ("gyro_z_deg_s", "deg/s", "gyroscopeZ"),
    ("temperature_c", "degC", "temperature"),
    ("mag_x_ut", "uT", "magnetometerX"), ("mag_y_ut", "uT", "magnetometerY"), ("mag_z_ut", "uT", "magnetometerZ"),
)

#: Structured dtype of one IMU sample: ``t`` int64 µs on the event clock, then the
#: :data:`IMU_FIELDS` as float32 (48 bytes per record).
IMU_DTYPE = np.dtype([("t", "<i8")] + [(name, "<f4") for name, _, _ in IMU_FIELDS], align=True)


@dataclass(frozen=True)
class SensorSize:
    """Sensor size in pixels, ``(height, width)`` in that order (unlike OpenCV's (w, h)), as
    ``repr`` shows it (``SensorSize(height=480, width=640)``); ``str`` prints ``640x480``, width
    first as cameras are sold. Give the fields by name (``SensorSize(height=480, width=640)``)
    where the order could be misread.

    Examples
    --------
    >>> SensorSize(260, 346).shape
    (260, 346)
    """

    height: int
    width: int

    def __post_init__(self):
        for name in ("height", "width"):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
                raise TypeError(f"SensorSize.{name} must be an int, got {type(v).__name__} {v!r}")
            if not 0 < int(v) <= 65536:
                raise ValueError(f"SensorSize.{name} must be in 1..65536 pixels, got {v}")
            object.__setattr__(self, name, int(v))

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``, the shape of an image on this sensor."""
        return (self.height, self.width)

    @property
    def n_pixels(self) -> int:
        return self.height * self.width

    def __str__(self) -> str:
        return f"{self.width}x{self.height}"

    @classmethod
    def from_any(cls, value) -> "SensorSize | None":
        """Accept ``SensorSize``, ``None`` or a ``(height, width)`` pair (not the printed
        ``"WxH"`` string, whose order is the other way round)."""
        if value is None or isinstance(value, SensorSize):
            return value
        try:
            h, w = value
        except (TypeError, ValueError):
            raise TypeError(f"sensor_size must be SensorSize or (height, width), got {value!r}") from None
        return cls(int(h), int(w))


def empty_events(n: int = 0) -> np.ndarray:
    """Return a zero-filled event array of length ``n``."""
    return np.zeros(n, dtype=EVENT_DTYPE)


def make_events(t, x, y, p) -> np.ndarray:
    """Build an event array from columns.

    Parameters
    ----------
    t : array_like of int, shape (N,)
        Timestamps in µs.
    x, y : array_like of int, shape (N,)
        Column and row.
    p : array_like, shape (N,)
        Polarity: ±1, or 0/1, or bool (0/False -> -1).

    Returns
    -------
    events : ndarray of shape (N,), dtype EVENT_DTYPE
    """
    t = np.asarray(t)
    n = t.shape[0] if t.ndim else 1
    ev = np.empty(n, dtype=EVENT_DTYPE)
    ev["t"] = t
    ev["x"] = x
    ev["y"] = y
    pa = np.asarray(p)
    if pa.dtype == np.bool_:
        ev["p"] = np.where(pa, 1, -1)
    else:
        ev["p"] = np.where(pa > 0, 1, -1)
    return ev


def empty_triggers(n: int = 0) -> np.ndarray:
    return np.zeros(n, dtype=TRIGGER_DTYPE)


def empty_imu(n: int = 0) -> np.ndarray:
    """A zero-filled IMU array (``IMU_DTYPE``) of length ``n``."""
    return np.zeros(n, dtype=IMU_DTYPE)


def make_triggers(t, channel, edge) -> np.ndarray:
    """Build a trigger array; ``edge`` > 0 (or True) is rising (+1), else falling (-1)."""
    t = np.asarray(t)
    tr = np.empty(t.shape[0] if t.ndim else 1, dtype=TRIGGER_DTYPE)
    tr["t"] = t
    tr["channel"] = channel
    e = np.asarray(edge)
    tr["edge"] = np.where(e.astype(bool) if e.dtype == np.bool_ else e > 0, 1, -1)
    return tr


def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def validate_events(events, sensor_size=None, *, name: str = "events") -> np.ndarray:
    """Check dtype, time order, polarity and coordinates; return the array unchanged.

    Raises
    ------
    TypeError
        If ``events`` is not an ndarray of dtype ``EVENT_DTYPE``.
    EventValidationError
        If timestamps decrease, a polarity is not ±1, or a coordinate lies outside ``sensor_size``.
    """
    if not isinstance(events, np.ndarray) or events.dtype != EVENT_DTYPE:
        got = type(events).__name__ if not isinstance(events, np.ndarray) else f"ndarray of dtype {events.dtype}"
        raise TypeError(f"{name} must be an ndarray of dtype EVENT_DTYPE {EVENT_DTYPE.descr}, got {got}")
    if events.ndim != 1:
        raise EventValidationError(f"{name} must be 1-D, got shape {events.shape}")
    if events.size == 0:
        return events
    t = events["t"]
    dec = t[1:] < t[:-1]
    if dec.any():
        i = _first_bad(dec) + 1
        raise EventValidationError(
            f"{name}['t'] must be non-decreasing; index {i} has {int(t[i])} after {int(t[i - 1])}")
    p = events["p"]
    badp = (p != 1) & (p != -1)
    if badp.any():
        i = _first_bad(badp)
        raise EventValidationError(f"{name}['p'] must be +1 or -1; index {i} has {int(p[i])}")
    ss = SensorSize.from_any(sensor_size)
    if ss is not None:
        for field, lim, dim in (("x", ss.width, "width"), ("y", ss.height, "height")):
            v = events[field]
            bad = v >= lim
            if bad.any():
                i = _first_bad(bad)
                raise EventValidationError(
                    f"{name}[{field!r}] must be < sensor {dim} {lim}; index {i} has {int(v[i])}")
    return events


def validate_triggers(triggers, *, name: str = "triggers") -> np.ndarray:
    if not isinstance(triggers, np.ndarray) or triggers.dtype != TRIGGER_DTYPE:
        got = type(triggers).__name__ if not isinstance(triggers, np.ndarray) else f"dtype {triggers.dtype}"
        raise TypeError(f"{name} must be an ndarray of dtype TRIGGER_DTYPE, got {got}")
    if triggers.size:
        t = triggers["t"]
        dec = t[1:] < t[:-1]
        if dec.any():
            i = _first_bad(dec) + 1
            raise EventValidationError(
                f"{name}['t'] must be non-decreasing; index {i} has {int(t[i])} after {int(t[i - 1])}")
        e = triggers["edge"]
        bad = (e != 1) & (e != -1)
        if bad.any():
            i = _first_bad(bad)
            raise EventValidationError(f"{name}['edge'] must be +1 or -1; index {i} has {int(e[i])}")
    return triggers


def validate_imu(imu, *, name: str = "imu") -> np.ndarray:
    """Check an IMU array: dtype ``IMU_DTYPE``, one dimension, non-decreasing ``t``, no infinite
    value (NaN is allowed: a quantity not measured). Returns it unchanged."""
    if not isinstance(imu, np.ndarray) or imu.dtype != IMU_DTYPE:
        got = type(imu).__name__ if not isinstance(imu, np.ndarray) else f"dtype {imu.dtype}"
        raise TypeError(f"{name} must be an ndarray of dtype IMU_DTYPE, got {got}")
    if imu.ndim != 1:
        raise EventValidationError(f"{name} must be 1-D, got shape {imu.shape}")
    if imu.size:
        t = imu["t"]
        dec = t[1:] < t[:-1]
        if dec.any():
            i = _first_bad(dec) + 1
            raise EventValidationError(
                f"{name}['t'] must be non-decreasing; index {i} has {int(t[i])} after {int(t[i - 1])}")
        for field, _, _ in IMU_FIELDS:
            bad = np.isinf(imu[field])
            if bad.any():
                i = _first_bad(bad)
                raise EventValidationError(f"{name}[{field!r}] must be finite (NaN: not measured); index {i} "
                                           f"has {float(imu[field][i])}")
    return imu


def time_window_indices(t: np.ndarray, t_start_us=None, t_end_us=None) -> tuple[int, int]:
    """Indices ``[i0, i1)`` of the half-open window ``[t_start_us, t_end_us)`` in sorted ``t``."""
    i0 = 0 if t_start_us is None else int(np.searchsorted(t, np.int64(t_start_us), side="left"))
    i1 = len(t) if t_end_us is None else int(np.searchsorted(t, np.int64(t_end_us), side="left"))
    return i0, max(i0, i1)


def api_window(t_start_us, t_end_us, *, absolute: bool, span, what: str = "recording") -> tuple:
    """The absolute ``[t_start_us, t_end_us)`` of a window given to the API, checked against the data.

    The one time base of the API (docs/conventions.md, "Time windows"): ``absolute=True`` (the
    default everywhere, as before) takes the bounds as sensor-time µs, as timestamps are stored;
    ``absolute=False`` counts them from the recording's start ``span[0]`` (its first event or
    frame exposure start), as the command line's ``--start``/``--end`` do. ``span``: the data's
    ``(first, last)`` µs sensor time, or None for a recording without data (then no check).
    A window that lies wholly outside ``span`` raises :class:`WindowOutsideDataError` naming the
    span (a window inside, even one that holds nothing, is returned as it is).
    """
    for name, v in (("t_start_us", t_start_us), ("t_end_us", t_end_us)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer))):
            raise TypeError(f"{name} must be an int (µs) or None, got {type(v).__name__}")
    if not isinstance(absolute, (bool, np.bool_)):
        raise TypeError(f"absolute must be True or False, got {absolute!r}")
    t0 = None if t_start_us is None else int(t_start_us)
    t1 = None if t_end_us is None else int(t_end_us)
    if not absolute:
        if span is None:
            if t0 is not None or t1 is not None:
                raise WindowOutsideDataError(f"{what}: a window relative to the start (absolute=False) needs data, "
                                             f"and the recording holds no events or frames")
            return t0, t1
        t0 = None if t0 is None else t0 + int(span[0])
        t1 = None if t1 is None else t1 + int(span[0])
    if span is not None and (t0 is not None or t1 is not None):
        first, last = int(span[0]), int(span[1])
        if (t1 is not None and t1 <= first) or (t0 is not None and t0 > last):
            given = (f"[{t_start_us if t_start_us is not None else '-'}, {t_end_us if t_end_us is not None else '-'}) "
                     f"µs {'sensor time' if absolute else 'from the start'}")
            hint = ("; absolute=False counts from the recording's start, as the command line's --start/--end do"
                    if absolute else "")
            raise WindowOutsideDataError(
                f"{what}: the window {given} lies outside the data, which spans {first:,}..{last:,} µs sensor "
                f"time (0..{(last - first) / 1e6:g} s from the start){hint}")
    return t0, t1


def slice_time(events: np.ndarray, t_start_us=None, t_end_us=None) -> np.ndarray:
    """Events in the half-open window ``[t_start_us, t_end_us)`` (a view, no copy).

    Examples
    --------
    >>> ev = make_events([0, 5, 5, 9], [0, 1, 2, 3], [0, 0, 0, 0], [1, -1, 1, 1])
    >>> slice_time(ev, 5, 9)["t"].tolist()
    [5, 5]
    """
    i0, i1 = time_window_indices(events["t"], t_start_us, t_end_us)
    return events[i0:i1]


def concatenate_events(chunks) -> np.ndarray:
    chunks = [c for c in chunks if len(c)]
    if not chunks:
        return empty_events()
    return np.concatenate(chunks)


def events_fields(events: np.ndarray):
    """Contiguous copies ``(t, x, y, p)`` for Numba kernels (made once, see conventions)."""
    return (np.ascontiguousarray(events["t"]), np.ascontiguousarray(events["x"]),
            np.ascontiguousarray(events["y"]), np.ascontiguousarray(events["p"]))
