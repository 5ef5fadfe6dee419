"""Simulation pipeline: recording contents, ground truth, determinism, streaming file output."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.formats.container import read_recording
from hybridhdr.simulate import FrameCameraParams, SamplingParams, simulate, simulate_to_file

from ._sources import BlobSource

CAM = FrameCameraParams(frame_rate_hz=50, exposure_us=5000, shot_noise=True, read_noise_e=3.0, crf="gamma")


def fields_equal(a, b):
    return all(np.array_equal(a[f], b[f]) for f in a.dtype.names)


def test_simulate_produces_events_frames_and_ground_truth():
    src = BlobSource(duration_us=100_000)
    res = simulate(src, sensor="clean", camera=CAM, gt_times_us=[1234, 50_000], progress=False)
    rec = res.recording
    assert rec.n_events > 100 and np.all(np.diff(rec.events["t"]) >= 0)
    assert rec.events["t"].min() > 0 and rec.events["t"].max() <= 100_000
    # frames at 0, 20, 40, 60, 80 ms (the one at 100 ms would end after the duration)
    np.testing.assert_array_equal(rec.frames.t_start_us, [0, 20_000, 40_000, 60_000, 80_000])
    np.testing.assert_array_equal(rec.frames.exposure_us, 5000)
    assert rec.frames.encoding == "gamma" and rec.frames.images.dtype == np.uint8
    # ground truth: every frame's mid-exposure plus the requested times, exact renders
    expected_t = sorted(set(rec.frames.t_mid_us.tolist()) | {1234, 50_000})
    np.testing.assert_array_equal(rec.hdr.t_us, expected_t)
    for t, im in zip(rec.hdr.t_us, rec.hdr.images):
        np.testing.assert_array_equal(im, BlobSource(duration_us=100_000).render(int(t)))
    prov = rec.metadata.provenance
    assert prov["renders"] == res.renders == src.renders == res.stats["renders"]
    assert prov["source"] == src.describe() and prov["seed"] == 0
    assert prov["sensor"]["refractory_period_us"] == 500 and prov["sampling"]["mode"] == "adaptive"
    assert len(prov["camera"]["inverse_crf"]) == 256 and "hybridhdr_version" in prov
    assert res.stats["n_events"] == rec.n_events and res.stats["n_frames"] == 5


def test_same_seed_same_bits_other_seed_differs():
    kw = dict(sensor="noisy", camera=CAM, progress=False)
    a = simulate(BlobSource(duration_us=60_000), seed=3, **kw).recording
    b = simulate(BlobSource(duration_us=60_000), seed=3, **kw).recording
    c = simulate(BlobSource(duration_us=60_000), seed=4, **kw).recording
    assert fields_equal(a.events, b.events)
    np.testing.assert_array_equal(a.frames.images, b.frames.images)
    assert not (len(a.events) == len(c.events) and fields_equal(a.events, c.events))
    assert not np.array_equal(a.frames.images, c.frames.images)


def test_frame_is_the_blurred_capture_of_the_renders():
    # noiseless linear camera: a frame equals capture(mean of the renders over its exposure)
    cam = FrameCameraParams(frame_rate_hz=50, exposure_us=8000, bit_depth=12)
    res = simulate(BlobSource(duration_us=40_000, speed_px_s=300), sensor="ideal", camera=cam,
                   sampling=SamplingParams(mode="fixed", fixed_rate_hz=2000), progress=False)
    from hybridhdr.simulate import FrameCamera
    src = BlobSource(duration_us=40_000, speed_px_s=300)
    fc = FrameCamera(cam, src.sensor_size)
    samples = [(t, src.render(t).astype(np.float64)) for t in range(20_000, 28_001, 500)]
    expected = fc.capture(fc.integrate(samples, 20_000, 28_000), 8000)
    np.testing.assert_array_equal(res.recording.frames.images[1], expected)


def test_simulate_to_file_matches_memory_and_is_atomic(tmp_path):
    kw = dict(sensor="noisy", camera=CAM, gt_times_us=[7000], seed=9, progress=False)
    mem = simulate(BlobSource(duration_us=60_000), **kw)
    path = tmp_path / "sim.h5"
    res = simulate_to_file(BlobSource(duration_us=60_000), path, **kw)
    assert res.path == path and path.exists() and not (tmp_path / "sim.h5.partial").exists()
    rec = read_recording(path)
    assert fields_equal(rec.events, mem.recording.events)
    np.testing.assert_array_equal(rec.frames.images, mem.recording.frames.images)
    np.testing.assert_array_equal(rec.frames.t_end_us, mem.recording.frames.t_end_us)
    np.testing.assert_array_equal(rec.hdr.images, mem.recording.hdr.images)
    np.testing.assert_array_equal(rec.hdr.t_us, mem.recording.hdr.t_us)
    assert rec.metadata.provenance["renders"] == res.renders == mem.renders
    assert rec.frames.encoding == "gamma" and rec.sensor_size == mem.recording.sensor_size

    class Broken(BlobSource):
        def render(self, t_us):
            if t_us > 30_000:
                raise RuntimeError("renderer crashed")
            return super().render(t_us)

    bad = tmp_path / "bad.h5"
    with pytest.raises(RuntimeError, match="renderer crashed"):
        simulate_to_file(Broken(duration_us=60_000), bad, progress=False)
    assert not bad.exists() and not (tmp_path / "bad.h5.partial").exists()


def test_validation_errors():
    src = BlobSource(duration_us=10_000)
    with pytest.raises(ValueError, match=r"gt_times_us must lie in \[0, 10000\]"):
        simulate(src, gt_times_us=[20_000], progress=False)
    with pytest.raises(TypeError, match="sensor must be"):
        simulate(src, sensor=3, progress=False)
    with pytest.raises(TypeError, match="RadianceSource"):
        simulate(object(), progress=False)
    with pytest.raises(ValueError, match="unknown event-sensor preset"):
        simulate(src, sensor="loud", progress=False)
