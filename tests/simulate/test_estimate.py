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
