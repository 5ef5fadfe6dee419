"""Camera profiles: the built-in profile follows ``Frames.encoding`` (gamma frames read correctly)."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr import Frames, Recording, SensorSize, make_events
from hybridhdr.camera import CameraProfile, default_profile
from hybridhdr.reconstruct import FrameMeasurements, reconstruct
from hybridhdr.camera.profile import profile_for_frames, weighting_from_inverse_crf


def _static_gamma_recording(linear, encoding="gamma", n_frames=4, period_us=50_000):
    """A static scene of linear intensities ``linear`` (H, W), 8-bit gamma-2.2 frames, no events."""
    code = np.round(255.0 * np.clip(linear, 0, 1) ** (1 / 2.2)).astype(np.uint8)
    imgs = np.repeat(code[None], n_frames, axis=0)
    t = 1_000 + period_us * np.arange(n_frames, dtype=np.int64)
    ev = make_events(np.zeros(0, np.int64), [], [], [])
    return Recording(ev, SensorSize(*linear.shape), Frames(imgs, t, t, encoding=encoding)), code


@pytest.mark.parametrize("method", ["akf", "cf", "frames"])
def test_gamma_static_scene_converges_to_linear_intensity(method):
    lin = np.array([[0.01, 0.05, 0.2], [0.4, 0.7, 0.95]])
    rec, code = _static_gamma_recording(lin)
    v = reconstruct(rec, method, times_us=[1_000, 60_000, 151_000])
    truth = (code / 255.0) ** 2.2  # the quantised scene, linear
    # eq. 8's bias correction shifts exp(L) by about R/2 (I + I0) < 1e-5
    np.testing.assert_allclose(v.frames[-1], truth, rtol=1e-4, atol=2e-5)
    # and not the gamma codes read as linear values (the old behaviour)
    assert np.all(np.abs(v.frames[-1] - code / 255.0) > 0.02)


def test_linear_frames_keep_the_linear_profile():
    lin = np.array([[0.1, 0.5, 0.9]])
    code = np.round(255 * lin).astype(np.uint8)
    t = np.array([0, 10_000], np.int64)
    for enc in ("raw", "linear", "unknown"):
        fr = Frames(np.repeat(code[None], 2, 0), t, t, encoding=enc)
        m = FrameMeasurements(fr, (1, 3), default_profile(), intensity_offset=1.0)
        assert m.profile.inverse_crf is None
        np.testing.assert_allclose(m.segment(0).intensity, code.ravel() / 255.0)


def test_profile_for_frames_swaps_only_builtin_profiles():
    fr = Frames(np.zeros((1, 2, 2), np.uint8), [0], [0], encoding="gamma")
    g = profile_for_frames(default_profile(8, 7e7), fr)
    assert g.extra["encoding"] == "gamma" and g.frame_precision_scale == 7e7
    np.testing.assert_allclose(g.intensity([0, 51, 255]), [0.0, 0.2 ** 2.2, 1.0])
    measured = CameraProfile(weighting=np.ones(256), name="measured")
    assert profile_for_frames(measured, fr) is measured
    assert profile_for_frames(g, fr) is g
    # a built-in profile survives a JSON round trip and is still adapted
    d = CameraProfile.from_dict(default_profile().to_dict())
    assert profile_for_frames(d, fr).extra["encoding"] == "gamma"


def test_gamma_weighting_follows_eqs_4_5(tmp_path):
    g = default_profile(encoding="gamma")
    w = g.weighting
    assert w.shape == (256,) and w.min() >= 0 and w.max() == pytest.approx(1.0)
    assert w[0] == 0.0 and w[255] == 0.0  # clipped ends
    # over the well-exposed codes f_w ∝ dCRF/dI at CRF⁻¹(code) = (1/γ) v^(1-γ): check ratios
    v = np.arange(256) / 255.0
    for a, b in ((40, 80), (60, 200), (100, 180)):
        assert w[a] / w[b] == pytest.approx((v[a] / v[b]) ** (1 - 2.2), rel=2e-2)
    # linear LUT: the certainty is constant, the weighting is the trapezoid
    np.testing.assert_allclose(weighting_from_inverse_crf(np.arange(256) / 255.0), default_profile().weighting,
                               atol=1e-12)
    p = g.save(tmp_path / "g.json")
    g2 = CameraProfile.load(p)
    np.testing.assert_array_equal(g2.weighting, g.weighting)
    np.testing.assert_array_equal(g2.inverse_crf, g.inverse_crf)


@pytest.mark.parametrize("kw", [dict(encoding="srgb"), dict(encoding="gamma", gamma=0), dict(encoding="gamma", gamma=True),
                                dict(bit_depth=0)])
def test_default_profile_rejects_bad_arguments(kw):
    with pytest.raises(ValueError):
        default_profile(**kw)


def test_flat_inverse_crf_is_rejected():
    with pytest.raises(ValueError, match="flat"):
        weighting_from_inverse_crf(np.zeros(16))


def test_measurements_reject_non_profile():
    fr = Frames(np.zeros((1, 2, 2), np.uint8), [0], [0], encoding="gamma")
    with pytest.raises(TypeError, match="CameraProfile"):
        FrameMeasurements(fr, (2, 2), "not a profile", intensity_offset=1.0)
