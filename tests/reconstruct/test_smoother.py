"""Two-sided offline AKF (hybridhdr.reconstruct.smoother): reversal, fusion, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.events import EVENT_DTYPE, SensorSize
from hybridhdr.model import Frames, Recording
from hybridhdr.reconstruct import AKFParams, reconstruct
from hybridhdr.reconstruct.edi import EventArrays
from hybridhdr.reconstruct.smoother import fuse, output_times, reverse_events, reverse_frames


def _rec(seed=0, h=5, w=7, k=6):
    rng = np.random.default_rng(seed)
    ts = np.arange(k, dtype=np.int64) * 40_000 + 1_000
    img = rng.integers(20, 230, (k, h, w)).astype(np.uint8)
    frames = Frames(img, ts, ts + 3_001, encoding="linear")  # odd exposure: mid rounding matters
    n = 3000
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, int(ts[-1]) + 10_000, n))
    ev["x"], ev["y"] = rng.integers(0, w, n), rng.integers(0, h, n)
    ev["p"] = rng.choice([-1, 1], n)
    return Recording(ev, SensorSize(h, w), frames)


def test_fuse_is_inverse_covariance_weighting():
    l, p = fuse([0.0, 1.0], [1.0, 3.0], [2.0, 1.0], [3.0, 1e-12])
    assert l == pytest.approx([0.5, 1.0]) and p == pytest.approx([0.75, 1e-12], rel=1e-6)


def test_reversal_is_an_involution_and_keeps_mid_exposure_times():
    rec = _rec()
    ev = EventArrays.from_structured(rec.events, rec.sensor_size.shape)
    m = 123_457
    back = reverse_events(reverse_events(ev, m), m)
    for a in "txyp":
        assert np.array_equal(getattr(back, a), getattr(ev, a))
    r = reverse_events(ev, m)
    assert np.all(np.diff(r.t) >= 0) and np.array_equal(r.p, -ev.p[::-1])
    fr = reverse_frames(rec.frames, m)
    assert np.array_equal(fr.t_mid_us, (m - 1) - rec.frames.t_mid_us[::-1])
    assert np.array_equal(fr.exposure_us, rec.frames.exposure_us[::-1])
    assert np.array_equal(reverse_frames(fr, m).t_mid_us, rec.frames.t_mid_us)


def test_static_scene_without_events_gives_the_frames():
    rec = _rec()
    still = Frames(np.repeat(rec.frames.images[:1], len(rec.frames), 0), rec.frames.t_start_us,
                   rec.frames.t_end_us, encoding="linear")
    r = Recording(np.zeros(0, EVENT_DTYPE), rec.sensor_size, still)
    v = reconstruct(r, "akf", AKFParams(bias_correction=False), fps=100.0)
    want = still.images[0] / 255.0
    assert np.allclose(v.frames, want, rtol=2e-6), np.abs(v.frames - want).max()
    assert v.info["two_sided"]["outputs_fused"] > 0


def test_two_sided_uses_the_future_frame():
    """A pixel steps up between frames k and k+1 with no events: at τ_{k+1} - 1 µs the forward
    filter still says frame k, the two-sided one leans towards frame k+1."""
    rec = _rec()
    k = len(rec.frames)
    img = np.full((k, 5, 7), 50, np.uint8)
    img[3:] = 200
    fr = Frames(img, rec.frames.t_start_us, rec.frames.t_end_us, encoding="linear")
    r = Recording(np.zeros(0, EVENT_DTYPE), rec.sensor_size, fr)
    t = int(fr.t_mid_us[3]) - 1
    fwd = reconstruct(r, "akf", times_us=[t], mode="causal").frames[0, 0, 0]
    two = reconstruct(r, "akf", times_us=[t]).frames[0, 0, 0]
    assert fwd == pytest.approx(50 / 255, rel=1e-3)
    assert two > 100 / 255


def test_two_sided_is_deterministic_and_bit_identical_across_workers():
    rec = _rec(3, h=40, w=9)
    a = reconstruct(rec, "akf", fps=250.0, n_workers=1)
    b = reconstruct(rec, "akf", fps=250.0, n_workers=2)
    c = reconstruct(rec, "akf", fps=250.0, n_workers=1)
    assert np.array_equal(a.frames, b.frames) and np.array_equal(a.frames, c.frames)
    assert np.array_equal(a.t_us, b.t_us)


def test_output_times_match_the_forward_driver():
    rec = _rec()
    fwd = reconstruct(rec, "akf", fps=300.0, mode="forward")
    t = output_times(rec.frames.t_mid_us, int(rec.events["t"][-1]), fps=300.0)
    assert np.array_equal(t, fwd.t_us)
    two = reconstruct(rec, "akf", fps=300.0)
    assert np.array_equal(two.t_us, fwd.t_us)
