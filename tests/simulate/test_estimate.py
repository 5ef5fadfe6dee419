"""The run-time estimate: renders predicted from the sampler's own rule at probe times."""

from __future__ import annotations

import time

import pytest

from hybridhdr.simulate import SamplingParams, simulate
from hybridhdr.simulate.camera import FrameCameraParams
from hybridhdr.simulate.estimate import RunEstimate, predict_renders
from hybridhdr.simulate.pipeline import planned_mandatory_times
from hybridhdr.simulate.sensor import sensor_preset

from ._sources import BlobSource, SwitchSource


@pytest.mark.parametrize("make", [
    lambda: BlobSource(duration_us=300_000, speed_px_s=400.0),                      # motion rule
    lambda: BlobSource(duration_us=300_000, speed_px_s=0.0, flicker_hz=4.0, flicker_depth=0.8),  # brightness rule
])
def test_predicted_renders_match_the_run(make):
    """Predicted within the 30 % the estimate is held to (the probes sample the flicker's density at
    8 phases; mandatory cuts and the step growth between probes are the rest)."""
    sen = sensor_preset("ideal")
    cam = FrameCameraParams(frame_rate_hz=20, exposure_us=5000)
    src = make()
    pred = predict_renders(src, SamplingParams(), contrast_threshold=sen.contrast_threshold, log_eps=sen.log_eps,
                           n_mandatory=0, mandatory_us=planned_mandatory_times(cam, src.duration_us))
    res = simulate(make(), sensor=sen, camera=cam, progress=False)
    assert 0 < pred["probe_renders"] <= 10 * 14
    assert abs(pred["renders"] / res.renders - 1) <= 0.30, (pred, res.renders)


def test_fixed_rate_is_counted_exactly():
    src = SwitchSource()
    pred = predict_renders(src, SamplingParams(mode="fixed", fixed_rate_hz=1000), contrast_threshold=0.2,
                           log_eps=1e-3, n_mandatory=0)
    res = simulate(SwitchSource(), sensor="ideal", camera=None, sampling=SamplingParams(mode="fixed", fixed_rate_hz=1000),
                   progress=False)
    assert round(pred["renders"]) == res.renders == 101


def test_run_estimate_prints_once_after_timed_renders():
    lines = []
    src = BlobSource()
    t0 = time.perf_counter()
    est = RunEstimate(src, 100, t0, after=10, skip=2, printer=lines.append).install()
    for k in range(30):
        src.render(k * 1000)
    assert len(lines) == 1 and lines[0].startswith("estimate: about 100 renders")
    assert est.predicted_s is not None and est.predicted_s >= 0


class _BlinkSource:
    """A static pattern on a monitor blinking on/off (a scene declaring its blink, as the built-in
    checkerboard does): the renders cost is the bisections at each edge, not the quiet time."""

    def __init__(self, period_us=100_000, duration_us=1_000_000, phase_us=0):
        import types

        import numpy as np

        from hybridhdr.events import SensorSize
        from hybridhdr.simulate.scene import Blink
        self.blink = Blink(period_us=period_us, duty=0.5, off_scale=0.0, phase_us=phase_us)
        self.scene = types.SimpleNamespace(objects=(), emitters=(types.SimpleNamespace(blink=self.blink),))
        self.duration_us = duration_us
        self.sensor_size = SensorSize(16, 20)
        yy, xx = np.mgrid[0:16, 0:20]
        self._img = np.where((yy // 4 + xx // 4) % 2 == 0, 50.0, 0.0).astype(np.float32) + np.float32(0.05)

    def render(self, t_us):
        return self._img * self.blink.scale(t_us) + 0.05

    def max_image_speed_px_per_s(self, t0_us, t1_us):
        return 0.0

    def describe(self):
        return {"kind": "blink"}


@pytest.mark.parametrize("period_us,phase_us", [(100_000, 0), (100_000, 17_000), (30_000, 0), (400_000, 123_000)])
def test_blink_edges_are_counted(period_us, phase_us):
    """Edges every 15-200 ms, at and off the frame timing: the declared edges' bursts are counted
    (probes at a fixed phase of a 50 ms blink overestimated such a run 3x, every probe in a burst)."""
    from hybridhdr.simulate.estimate import switch_times_us
    sen = sensor_preset("clean")
    cam = FrameCameraParams(frame_rate_hz=20, exposure_us=10_000)
    src = _BlinkSource(period_us, phase_us=phase_us)
    assert switch_times_us(src)[:2] == sorted(t for t in (phase_us, phase_us + period_us // 2, phase_us + period_us)
                                              if t > 0)[:2]
    pred = predict_renders(src, SamplingParams(), contrast_threshold=sen.contrast_threshold, log_eps=sen.log_eps,
                           n_mandatory=0, mandatory_us=planned_mandatory_times(cam, src.duration_us))
    res = simulate(_BlinkSource(period_us, phase_us=phase_us), sensor=sen, camera=cam, progress=False)
    assert abs(pred["renders"] / res.renders - 1) <= 0.30, (pred, res.renders)
    assert pred["probe_renders"] < res.renders
