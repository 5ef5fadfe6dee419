"""hybridhdr <-> tonic event conversion (hybridhdr.interop)."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.events import EVENT_DTYPE, SensorSize, make_events
from hybridhdr.interop import TONIC_DTYPE, from_tonic, to_tonic


def _events(n=500, h=260, w=346, seed=0):
    rng = np.random.default_rng(seed)
    return make_events(np.sort(rng.integers(0, 10**9, n)), rng.integers(0, w, n), rng.integers(0, h, n),
                       rng.choice([-1, 1], n))


def test_round_trip_and_layout():
    ev = _events()
    tv, ss = to_tonic(ev, SensorSize(260, 346))
    assert ss == (346, 260, 2)  # tonic: (W, H, P)
    assert tv.dtype.names == ("x", "y", "t", "p") and tv.dtype == TONIC_DTYPE
    np.testing.assert_array_equal(tv["t"], ev["t"])  # µs both
    np.testing.assert_array_equal(tv["p"], ev["p"] > 0)  # ON = True
    back, sensor = from_tonic(tv, ss)
    assert sensor == SensorSize(260, 346) and back.dtype == EVENT_DTYPE
    np.testing.assert_array_equal(back, ev)
    assert to_tonic(ev, (260, 346))[1] == ss  # (height, width) tuple in hybridhdr order
    empty, _ = to_tonic(ev[:0], SensorSize(2, 3))
    assert empty.shape == (0,) and from_tonic(empty, (3, 2, 2))[0].shape == (0,)


def test_from_tonic_integer_polarity_and_single_polarity():
    dt = np.dtype([("x", int), ("y", int), ("t", int), ("p", int)])  # as tonic's dataset examples
    tv = np.array([(1, 2, 10, 0), (3, 4, 20, 1)], dt)
    ev, sensor = from_tonic(tv, (5, 6, 2))
    assert sensor == SensorSize(6, 5)
    assert ev["p"].tolist() == [-1, 1] and ev["t"].tolist() == [10, 20] and ev["x"].tolist() == [1, 3]
    ev1, _ = from_tonic(tv, (5, 6, 1))
    assert ev1["p"].tolist() == [1, 1]


def test_from_tonic_errors():
    dt = np.dtype([("x", int), ("y", int), ("t", int), ("p", int)])
    with pytest.raises(ValueError, match="outside the sensor"):
        from_tonic(np.array([(5, 0, 0, 1)], dt), (5, 6, 2))
    with pytest.raises(ValueError, match="polarity"):
        from_tonic(np.array([(0, 0, 0, 2)], dt), (5, 6, 2))
    with pytest.raises(ValueError, match="missing"):
        from_tonic(np.zeros(1, [("x", int), ("y", int), ("t", int)]), (5, 6, 2))
    with pytest.raises(ValueError, match=r"\(W, H, P\)"):
        from_tonic(np.array([(0, 0, 0, 1)], dt), (5, 6))
    with pytest.raises(ValueError, match="whole microseconds"):
        from_tonic(np.array([(0, 0, 0.5, 1)], [("x", int), ("y", int), ("t", float), ("p", int)]), (5, 6, 2))


def test_through_tonic_if_installed():
    tonic = pytest.importorskip("tonic")
    import tonic.transforms as T
    ev = _events(2000, 32, 48)
    tv, ss = to_tonic(ev, SensorSize(32, 48))
    frames = T.ToFrame(sensor_size=ss, n_time_bins=2)(tv)
    assert frames.shape == (2, 2, 32, 48)  # (bins, P, H, W)
    assert frames.sum() == len(ev)
    del tonic
