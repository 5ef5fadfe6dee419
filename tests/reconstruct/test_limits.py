"""reconstruct checks what it is asked for before any work (docs/security.md)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from hybridhdr._util.limits import LimitExceeded, allow_huge
from hybridhdr.events import EVENT_DTYPE, SensorSize
from hybridhdr.model import Frames, Recording
from hybridhdr.reconstruct import reconstruct


def _rec(h=4, w=5):
    ts = np.array([0, 50_000], np.int64)
    fr = Frames(np.full((2, h, w), 100, np.uint8), ts, ts + 1_000, encoding="linear")
    ev = np.zeros(3, EVENT_DTYPE)
    ev["t"] = [1_000, 2_000, 3_000]
    ev["p"] = 1
    return Recording(ev, SensorSize(h, w), fr)


@pytest.mark.parametrize("mode", ["offline", "causal"])
def test_absurd_fps_is_refused_before_any_work(mode):
    t0 = time.perf_counter()
    with pytest.raises(LimitExceeded, match="allow-huge"):
        reconstruct(_rec(), "akf", fps=1e12, mode=mode)
    assert time.perf_counter() - t0 < 5.0


def test_too_many_requested_times_are_refused():
    with pytest.raises(LimitExceeded):
        reconstruct(_rec(), "cf", times_us=np.arange(2_000_001, dtype=np.int64))


def test_huge_sensor_is_refused_and_the_override_is_honoured():
    h, w = 9000, 2
    ts = np.array([0, 50_000], np.int64)
    fr = Frames(np.zeros((2, h, w), np.uint8), ts, ts + 1_000, encoding="linear")
    rec = Recording(np.zeros(0, EVENT_DTYPE), SensorSize(h, w), fr)
    with pytest.raises(LimitExceeded, match="sensor"):
        reconstruct(rec, "frames", times_us=[500])
    with allow_huge():
        assert reconstruct(rec, "frames", times_us=[500]).frames.shape == (1, h, w)


def test_threshold_map_stored_in_the_container_is_used(tmp_path):
    from hybridhdr.formats.thresholds import ThresholdMap
    from hybridhdr.formats.container import RecordingFile, store_thresholds, write_recording
    rec = _rec()
    path = write_recording(rec, tmp_path / "r.h5")
    on = np.full((4, 5), 0.15)
    on[0, 0] = np.nan  # not estimated: takes the fallback
    tm = ThresholdMap(c_on=on, c_off=np.full((4, 5), 0.25), fallback_on=0.2, fallback_off=0.3)
    store_thresholds(path, tm)
    store_thresholds(path, tm)  # replacing works
    with RecordingFile(path) as r:
        back = r.read_thresholds()
    np.testing.assert_array_equal(back.c_on, tm.c_on)
    assert (back.fallback_on, back.fallback_off) == (0.2, 0.3)
    a = reconstruct(path, "akf", times_us=[4_000], mode="causal")
    b = reconstruct(rec, "akf", times_us=[4_000], mode="causal", thresholds=tm)
    c = reconstruct(rec, "akf", times_us=[4_000], mode="causal")
    np.testing.assert_array_equal(a.frames, b.frames)
    assert not np.array_equal(a.frames, c.frames)
    assert a.info["thresholds"].startswith("per-pixel map")
    with pytest.raises(ValueError, match="shape"):
        store_thresholds(path, ThresholdMap(c_on=np.ones((2, 2)), c_off=np.ones((2, 2)), fallback_on=1.0,
                                            fallback_off=1.0))


def test_a_recordings_declared_profile_is_used_from_a_path_too(tmp_path):
    """A camera profile in the metadata (e.g. an AKF .mat file's f_Q) applies whether the
    recording is passed in memory or as a file path."""
    import dataclasses
    from hybridhdr.camera import default_profile
    from hybridhdr.formats.container import write_recording
    from hybridhdr.model import Metadata
    prof = dataclasses.replace(default_profile(8, encoding="gamma"), extra={}, name="declared")  # a measured one
    rec = _rec()
    rec = Recording(rec.events, rec.sensor_size, rec.frames,
                    metadata=Metadata(provenance={"camera_profile": prof.to_dict()}))
    path = write_recording(rec, tmp_path / "r.h5")
    t = [30_000]
    a = reconstruct(path, "akf", times_us=t, mode="causal")
    b = reconstruct(rec, "akf", times_us=t, mode="causal")
    c = reconstruct(rec, "akf", times_us=t, mode="causal", profile=prof)
    d = reconstruct(rec, "akf", times_us=t, mode="causal", profile=default_profile(8))
    np.testing.assert_array_equal(a.frames, c.frames)
    np.testing.assert_array_equal(b.frames, c.frames)
    assert not np.array_equal(a.frames, d.frames)
