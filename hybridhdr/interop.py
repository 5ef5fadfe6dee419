"""Conversions to and from other event-camera libraries.

**Tonic** (``tonic``, the neuromorphic-datasets library): events are a structured NumPy array
with the fields ``("x", "y", "t", "p")`` in that order (dtypes vary: e.g. int16 x, y,
int64 t and bool p, or plain ints with p in {0, 1}), timestamps in µs, and
``sensor_size = (W, H, P)`` -- width first, then height, then the number of polarities (2).
hybridhdr uses ``EVENT_DTYPE`` (t int64 µs, x, y uint16, p int8 ±1) and ``SensorSize(height,
width)``. Polarity: tonic 1 / True = ON = hybridhdr +1; tonic 0 / False = OFF = hybridhdr -1
(tonic also allows a single polarity, P = 1, where every event counts as ON). Time: µs in both,
copied unchanged. Importing tonic is not needed.
"""

from __future__ import annotations

import numpy as np

from .events import EVENT_DTYPE, SensorSize

__all__ = ["TONIC_DTYPE", "to_tonic", "from_tonic"]

#: The dtype written by :func:`to_tonic` (int16 x, y would cap
#: sensors at 32767 px, so x and y are int32 here; tonic's transforms only read the field names).
TONIC_DTYPE = np.dtype([("x", "<i4"), ("y", "<i4"), ("t", "<i8"), ("p", "?")])


def _sensor_hw(sensor_size) -> tuple[int, int]:
    if isinstance(sensor_size, SensorSize):
        return int(sensor_size.height), int(sensor_size.width)
    s = tuple(int(v) for v in sensor_size)
    if len(s) != 2:
        raise ValueError(f"sensor_size must be a SensorSize or (height, width), got {sensor_size!r}")
    return s


def to_tonic(events: np.ndarray, sensor_size) -> tuple[np.ndarray, tuple[int, int, int]]:
    """hybridhdr events -> (tonic structured array, tonic ``sensor_size`` ``(W, H, 2)``).

    ``sensor_size``: a :class:`~hybridhdr.events.SensorSize` or ``(height, width)`` (hybridhdr
    order). ``p`` becomes bool (True = ON); ``t`` stays in µs.
    """
    ev = np.asarray(events)
    missing = {"t", "x", "y", "p"} - set(ev.dtype.names or ())
    if missing:
        raise ValueError(f"events need the fields t, x, y, p; missing {sorted(missing)}")
    p = ev["p"]
    if p.size and not np.isin(p, (-1, 1)).all():
        raise ValueError("hybridhdr polarity must be +1 or -1")
    h, w = _sensor_hw(sensor_size)
    out = np.empty(ev.shape[0], TONIC_DTYPE)
    out["x"], out["y"], out["t"] = ev["x"], ev["y"], ev["t"]
    out["p"] = p > 0
    return out, (w, h, 2)


def from_tonic(events: np.ndarray, sensor_size) -> tuple[np.ndarray, SensorSize]:
    """tonic events and ``sensor_size`` ``(W, H, P)`` -> (hybridhdr events, SensorSize).

    Accepts p as bool or integers in {0, 1} (also {-1, 1}); 1/True -> +1, 0/False/-1 -> -1.
    With ``P == 1`` every event is ON (+1). Events outside the sensor, negative times or other
    polarity values are errors; the order is kept (sort with ``np.argsort(ev["t"],
    kind="stable")`` if the source was not time-sorted).
    """
    ev = np.asarray(events)
    names = ev.dtype.names or ()
    missing = {"x", "y", "t", "p"} - set(names)
    if missing:
        raise ValueError(f"tonic events need the fields x, y, t, p; missing {sorted(missing)} (got {names})")
    ss = tuple(int(v) for v in sensor_size)
    if len(ss) != 3 or ss[0] <= 0 or ss[1] <= 0 or ss[2] not in (1, 2):
        raise ValueError(f"tonic sensor_size must be (W, H, P) with P 1 or 2, got {sensor_size!r}")
    w, h, n_pol = ss
    x, y, t = (np.asarray(ev[k]) for k in ("x", "y", "t"))
    if ev.size:
        if x.min() < 0 or y.min() < 0 or x.max() >= w or y.max() >= h:
            raise ValueError(f"events outside the sensor (W, H) = ({w}, {h}): x {x.min()}..{x.max()}, "
                             f"y {y.min()}..{y.max()}")
        if np.issubdtype(t.dtype, np.floating) and not np.array_equal(t, np.round(t)):
            raise ValueError("tonic timestamps must be whole microseconds")
        if t.min() < 0:
            raise ValueError(f"negative timestamps ({t.min()} µs)")
    p = np.asarray(ev["p"])
    if n_pol == 1:
        pol = np.ones(ev.shape[0], np.int8)
    else:
        if p.dtype == np.bool_:
            on = p
        else:
            if p.size and not np.isin(p, (-1, 0, 1)).all():
                raise ValueError(f"tonic polarity must be bool or in {{0, 1}} (or -1/1), got values {np.unique(p)[:5]}")
            on = p > 0
        pol = np.where(on, 1, -1).astype(np.int8)
    out = np.empty(ev.shape[0], EVENT_DTYPE)
    out["t"], out["x"], out["y"], out["p"] = t.astype(np.int64), x, y, pol
    return out, SensorSize(h, w)
