"""The frames' noise and drift measured on a recording (calibrate.frame_noise), against a known truth."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.calibrate.frame_noise import MAX_TRIPLES, estimate_frame_noise
from hybridhdr.camera.profile import default_profile
from hybridhdr.model import Frames

I0 = 0.25
PERIOD_US = 40_000


def _local_level(rho, q_per_s, *, k=40, h=64, w=64, seed=0):
    """Frames of the local level model on a linear 8-bit camera: a random walk of rate ``q_per_s``
    in ln(I + I0) observed in white noise of ``rho`` times the profile's eq. 9 variance, as float
    codes (no quantisation), and events only at pixel (0, 0) before the first and after the last
    frame (every other pixel is event-free over the whole span)."""
    rng = np.random.default_rng(seed)
    prof = default_profile(8)
    inten = rng.uniform(0.2, 0.8, (h, w))  # inside the well-exposed plateau (f_w = 1)
    x = np.log(inten + I0)
    dt = PERIOD_US * 1e-6
    imgs = np.empty((k, h, w))
    for j in range(k):
        if j:
            x = x + rng.normal(0.0, np.sqrt(q_per_s * dt), x.shape)
        i_true = np.exp(x) - I0
        r = prof.variance(i_true * 255.0) / (i_true + I0) ** 2  # eq. 9 at the true code
        obs = x + rng.normal(0.0, 1.0, x.shape) * np.sqrt(rho * r)
        imgs[j] = np.clip((np.exp(obs) - I0) * 255.0, 0.0, 255.0)
    t = (np.arange(k, dtype=np.int64) + 1) * PERIOD_US
    frames = Frames(images=imgs, t_start_us=t - 250, t_end_us=t + 250)
    te = np.array([0, (k + 2) * PERIOD_US], np.int64)
    z = np.zeros(2, np.uint16)
    return frames, te, z, z, prof


@pytest.mark.parametrize("rho,q", [(20.0, 1e-3), (100.0, 0.02)])
def test_recovers_the_noise_scale_and_the_drift(rho, q):
    frames, t, x, y, prof = _local_level(rho, q)
    got = estimate_frame_noise(frames, t, x, y, prof, I0)
    assert got["identifiable"], got
    assert got["triples"] == min(len(frames) - 2, MAX_TRIPLES)
    # 32 triples x 4095 pixels: the scale's standard error is about 1 %; 5 % and 3 se hold it
    assert abs(got["variance_scale"] / rho - 1) < max(0.05, 3 * got["variance_scale_se"] / rho)
    assert got["frame_precision_scale"] == pytest.approx(prof.frame_precision_scale / got["variance_scale"])
    # q's sampling error is larger where the frame noise dominates (q dt / R about 0.3 and 1.5 here)
    assert got["process_noise_per_s"] == pytest.approx(q, rel=0.15)


def test_noise_free_static_frames_are_not_identified():
    frames, t, x, y, prof = _local_level(0.0, 0.0)
    got = estimate_frame_noise(frames, t, x, y, prof, I0)
    assert not got["identifiable"]
    assert "lag-one covariance" in got["reason"]


def test_too_little_data_says_why():
    frames, t, x, y, prof = _local_level(20.0, 1e-3, k=2)
    got = estimate_frame_noise(frames, t, x, y, prof, I0)
    assert not got["identifiable"] and "3 frames" in got["reason"]
    frames, t, x, y, prof = _local_level(20.0, 1e-3, k=5, h=8, w=8)
    got = estimate_frame_noise(frames, t, x, y, prof, I0)
    assert not got["identifiable"] and "fewer than" in got["reason"]


def test_pixels_with_events_are_left_out():
    frames, t, x, y, prof = _local_level(20.0, 1e-3, k=5, h=16, w=16)
    # one event per frame interval at every pixel of the left half: only the right half counts
    tt = (np.arange(1, 5) * PERIOD_US + PERIOD_US // 2).astype(np.int64)
    yy, xx = np.mgrid[0:16, 0:8]
    ev_t = np.concatenate([t[:1], np.repeat(tt, yy.size), t[1:]])
    ev_x = np.concatenate([[0], np.tile(xx.ravel(), len(tt)), [0]]).astype(np.uint16)
    ev_y = np.concatenate([[0], np.tile(yy.ravel(), len(tt)), [0]]).astype(np.uint16)
    got = estimate_frame_noise(frames, ev_t, ev_x, ev_y, prof, I0, min_samples=1)
    assert got["samples"] == 3 * 16 * 8  # three triples, the right half


def test_bad_input_is_named():
    frames, t, x, y, prof = _local_level(20.0, 1e-3, k=3, h=4, w=4)
    with pytest.raises(ValueError, match="intensity_offset"):
        estimate_frame_noise(frames, t, x, y, prof, 0.0)
    with pytest.raises(TypeError, match="Frames"):
        estimate_frame_noise(frames.images, t, x, y, prof, I0)
