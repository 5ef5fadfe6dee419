"""Data model: events, sensor size, frames, recordings."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridhdr as hh
from hybridhdr.errors import EventValidationError


def _ev(t, x=None, y=None, p=None):
    n = len(t)
    return hh.make_events(t, x if x is not None else np.zeros(n), y if y is not None else np.zeros(n),
                          p if p is not None else np.ones(n))


def test_event_dtype_layout():
    assert hh.EVENT_DTYPE.itemsize == 16
    assert hh.EVENT_DTYPE["t"] == np.dtype("<i8") and hh.EVENT_DTYPE["x"] == np.dtype("<u2")
    assert hh.EVENT_DTYPE["p"] == np.dtype("i1")


def test_make_events_polarity_encodings():
    assert hh.make_events([0, 1, 2], [0] * 3, [0] * 3, [0, 1, 0])["p"].tolist() == [-1, 1, -1]
    assert hh.make_events([0, 1], [0, 0], [0, 0], [True, False])["p"].tolist() == [1, -1]
    assert hh.make_events([0, 1], [0, 0], [0, 0], [-1, 1])["p"].tolist() == [-1, 1]


def test_sensor_size():
    s = hh.SensorSize(260, 346)
    assert s.shape == (260, 346) and s.n_pixels == 260 * 346 and str(s) == "346x260"
    assert hh.SensorSize.from_any((4, 5)) == hh.SensorSize(4, 5)
    with pytest.raises(ValueError, match="height"):
        hh.SensorSize(0, 5)
    with pytest.raises(TypeError, match="width"):
        hh.SensorSize(5, 2.5)
    with pytest.raises(TypeError):
        hh.SensorSize.from_any("346x260")


def test_validate_errors_name_index_and_values():
    ev = _ev([0, 10, 5])
    with pytest.raises(EventValidationError, match=r"non-decreasing; index 2 has 5 after 10"):
        hh.validate_events(ev)
    ev = _ev([0, 1], x=[3, 7])
    with pytest.raises(EventValidationError, match=r"'x'.*width 5; index 1 has 7"):
        hh.validate_events(ev, (4, 5))
    ev = _ev([0, 1], y=[4, 0])
    with pytest.raises(EventValidationError, match=r"'y'.*height 4; index 0 has 4"):
        hh.validate_events(ev, hh.SensorSize(4, 5))
    bad = _ev([0, 1])
    bad["p"][1] = 0
    with pytest.raises(EventValidationError, match="index 1 has 0"):
        hh.validate_events(bad)
    with pytest.raises(TypeError, match="EVENT_DTYPE"):
        hh.validate_events(np.zeros(3))
    assert hh.validate_events(hh.empty_events(), (1, 1)).size == 0


def test_validation_is_not_assert_based():
    # python -O strips asserts; ours must still raise (checked by calling the function directly)
    import subprocess
    import sys
    code = ("import hybridhdr as hh\ntry:\n hh.validate_events(hh.make_events([1,0],[0,0],[0,0],[1,1]))\n"
            "except ValueError: print('raised')\n")
    out = subprocess.run([sys.executable, "-O", "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "raised"


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(-2**62, 2**62), min_size=0, max_size=60),
       st.integers(-2**62, 2**62), st.integers(-2**62, 2**62), st.integers(-2**62, 2**62))
def test_half_open_windows_partition(ts, a, b, c):
    t = np.sort(np.array(ts, dtype=np.int64))
    ev = _ev(t)
    t0, t1, t2 = sorted([a, b, c])
    left, right, whole = hh.slice_time(ev, t0, t1), hh.slice_time(ev, t1, t2), hh.slice_time(ev, t0, t2)
    assert np.array_equal(np.concatenate([left, right]), whole)
    assert np.all(left["t"] >= t0) and np.all(left["t"] < t1)
    assert len(hh.slice_time(ev, t1, t1)) == 0


def test_slice_time_edges_past_int32():
    base = 2**31 + 5
    ev = _ev([base, base, base + 1, base + 2])
    assert len(hh.slice_time(ev, base, base + 1)) == 2
    assert len(hh.slice_time(ev, None, base + 2)) == 3
    assert len(hh.slice_time(ev, base + 1, None)) == 2


def test_frames_validation_and_properties():
    im = np.zeros((3, 4, 5), np.uint16)
    f = hh.Frames(im, [0, 10, 20], [4, 14, 25], gain=[1, 2, 3])
    assert f.images.dtype == np.uint16 and f.shape == (4, 5) and len(f) == 3
    assert f.exposure_us.tolist() == [4, 4, 5] and f.t_mid_us.tolist() == [2, 12, 22]
    assert len(f.slice_time(10, 20)) == 1
    with pytest.raises(ValueError, match=r"frame 1: exposure end 5 µs is before its start 10 µs"):
        hh.Frames(im, [0, 10, 20], [4, 5, 25])
    with pytest.raises(ValueError, match=r"t_start_us \(one per frame\) must have shape \(3,\)"):
        hh.Frames(im, [0, 10], [4, 14])
    with pytest.raises(ValueError, match=r"\(K, H, W\)"):
        hh.Frames(np.zeros((4, 5)), [0], [1])
    with pytest.raises(ValueError, match="whole microseconds"):
        hh.Frames(im, [0, 10.5, 20], [4, 14, 25])
    with pytest.raises(ValueError, match="encoding"):
        hh.Frames(im, [0, 10, 20], [4, 14, 25], encoding="srgb?")
    rgb = hh.Frames(np.zeros((2, 4, 5, 3), np.float32), [0, 1], [1, 2], encoding="linear")
    assert rgb.images.shape == (2, 4, 5, 3)


def test_recording_checks_sensor_and_slices():
    ev = _ev([0, 5, 10], x=[0, 4, 2], y=[0, 3, 1])
    rec = hh.Recording(ev, (4, 5), hh.Frames(np.zeros((2, 4, 5), np.uint8), [0, 8], [2, 10]),
                       hh.make_triggers([1, 9], [0, 0], [1, -1]))
    assert rec.metadata.event_camera.sensor_size == hh.SensorSize(4, 5)
    assert rec.time_range_us() == (0, 10)
    s = rec.slice_time(5, 10)
    assert s.events["t"].tolist() == [5] and s.triggers["t"].tolist() == [9] and len(s.frames) == 1
    with pytest.raises(EventValidationError, match="width 4"):
        hh.Recording(ev, (4, 4))
    md = hh.Metadata.from_dict(rec.metadata.to_dict())
    assert md == rec.metadata
