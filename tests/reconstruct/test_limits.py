"""reconstruct checks what it is asked for before any work (docs/security.md)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from hybridhdr._limits import LimitExceeded, allow_huge
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
