"""The AKF measures the frames' noise and drift on its input when asked (``AKFParams.noise_from_frames``)."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.calibrate.frame_noise import estimate_frame_noise
from hybridhdr.camera.profile import load_profile, profile_for_frames
from hybridhdr.events import make_events
from hybridhdr.model import Frames, Recording
from hybridhdr.reconstruct import AKFParams, reconstruct
from hybridhdr.reconstruct.api import source_profile

PERIOD_US = 40_000


@pytest.fixture(scope="module")
def noisy_static():
    """A static scene seen by 12 frames of 8-bit codes with temporal noise (2 codes), thresholds
    declared (no self-calibration), and events only at pixel (0, 0)."""
    rng = np.random.default_rng(1)
    h, w, k = 24, 32, 12
    scene = rng.uniform(60, 200, (h, w))
    imgs = np.clip(np.rint(scene + rng.normal(0, 2.0, (k, h, w))), 0, 255).astype(np.uint8)
    t = (np.arange(k, dtype=np.int64) + 1) * PERIOD_US
    frames = Frames(images=imgs, t_start_us=t - 250, t_end_us=t + 250)
    ev = make_events(np.array([0, (k + 1) * PERIOD_US]), np.zeros(2), np.zeros(2), np.ones(2))
    return Recording(ev, (h, w), frames), scene / 255.0


ON = AKFParams(noise_from_frames=True)


def _run(rec, params=ON, mode="causal"):
    t = np.array([int(rec.frames.t_mid_us[-1]) + PERIOD_US // 2], np.int64)
    return reconstruct(rec, "akf", params, times_us=t, mode=mode, thresholds="params")


def test_measures_and_records(noisy_static):
    rec, _ = noisy_static
    v = _run(rec)
    got = v.info["frame_noise"]
    assert got["identifiable"]
    p = ON
    prof = profile_for_frames(load_profile(source_profile(rec)), rec.frames)
    want = estimate_frame_noise(rec.frames, rec.events["t"], rec.events["x"], rec.events["y"], prof,
                                p.intensity_offset)
    assert got["variance_scale"] == pytest.approx(want["variance_scale"], rel=1e-12)
    # 2 codes of noise is far above the paper's DAVIS240C precision (about 0.3 codes at mid-grey)
    assert got["variance_scale"] > 10


def test_default_and_presets_keep_their_values(noisy_static):
    rec, _ = noisy_static
    for p in (None, AKFParams(), AKFParams.paper(), AKFParams.reference_code(), AKFParams.paper(noise_from_frames=False)):
        assert "frame_noise" not in _run(rec, p).info


def test_averaging_the_frames_lowers_the_error(noisy_static):
    """A static scene: the measured model averages the noisy frames, the opt-out restarts from
    the last one (error about 2 codes)."""
    rec, scene = noisy_static
    err = {}
    for label, p in (("measured", ON), ("given", AKFParams())):
        out = _run(rec, p).frames[0]
        err[label] = float(np.sqrt(np.mean((out - scene) ** 2)) * 255)
    assert err["given"] > 1.5  # one frame's noise (2 codes)
    assert err["measured"] < 0.75 * err["given"], err


def test_two_sided_fusion_keeps_its_carried_rate():
    p = AKFParams()
    q = p.replace(process_noise_per_s=1e-3, fusion_carried_rate_per_s=p.process_noise_per_s)
    assert q.carried_variance() == p.carried_variance()
    assert AKFParams(fusion_carried_rate_per_s=None).carried_variance()[1] == p.process_noise_per_s
    with pytest.raises(ValueError, match="fusion_carried_rate_per_s"):
        AKFParams(fusion_carried_rate_per_s=-1.0)


def test_stated_values_win(noisy_static):
    rec, _ = noisy_static
    info = _run(rec).info["frame_noise"]
    assert info["applied"] == ["frame_precision_scale", "fusion_carried_rate_per_s", "process_noise_per_s"]
    info = _run(rec, ON.replace(process_noise_per_s=0.02)).info["frame_noise"]
    assert info["applied"] == ["frame_precision_scale"]
    info = _run(rec, ON.replace(frame_precision_scale=1e5)).info["frame_noise"]
    assert info["applied"] == ["fusion_carried_rate_per_s", "process_noise_per_s"]
    info = _run(rec, ON.replace(process_noise_per_s=0.02, frame_precision_scale=1e5)).info["frame_noise"]
    assert info["applied"] == []
