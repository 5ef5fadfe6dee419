"""Metrics against literal reference values (scikit-image SSIM, PU21 formula, hand MSE)."""

import math

import numpy as np
import pytest

from hybridhdr.evaluate import metrics as M


def _fixed_pair():
    # the images of the literal below
    rng = np.random.default_rng(1234)
    a = rng.random((24, 32))
    b = np.clip(a + 0.1 * rng.standard_normal((24, 32)), 0, 1)
    return a, b


def test_mse_psnr_by_hand():
    a = np.array([[0.0, 0.5], [1.0, 0.25]])
    b = np.array([[0.1, 0.5], [0.8, 0.25]])
    # (0.01 + 0 + 0.04 + 0) / 4 = 0.0125
    assert M.mse(a, b) == pytest.approx(0.0125, rel=1e-15)
    assert M.psnr(a, b, 1.0) == pytest.approx(10 * math.log10(1 / 0.0125), rel=1e-15)
    assert M.psnr(a, a) == math.inf
    with pytest.raises(ValueError, match="same shape"):
        M.mse(a, b[:1])
    with pytest.raises(ValueError, match="data_range"):
        M.psnr(a, b, 0)


def test_ssim_literal_skimage_values():
    # literals from scikit-image 0.26.0:
    #   structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
    #                         use_sample_covariance=False, data_range=1.0)
    a, b = _fixed_pair()
    assert M.ssim(a, b, 1.0) == pytest.approx(0.9484061208205754, abs=1e-12)
    x = np.arange(400, dtype=float).reshape(20, 20) / 400
    assert M.ssim(x, x ** 2, 1.0) == pytest.approx(0.751572787302188, abs=1e-12)
    assert M.ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_ssim_equals_skimage_within_1e6():
    skm = pytest.importorskip("skimage.metrics")
    rng = np.random.default_rng(7)
    for shape, dr in (((16, 16), 1.0), ((31, 45), 255.0), ((12, 70), 4.0)):
        a = rng.random(shape) * dr
        b = np.clip(a + 0.2 * dr * rng.standard_normal(shape), 0, dr)
        ref = skm.structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                        data_range=dr)
        assert M.ssim(a, b, dr) == pytest.approx(ref, abs=1e-6)


def test_ssim_stack_is_frame_mean_and_too_small_raises():
    a, b = _fixed_pair()
    st = M.ssim(np.stack([a, a]), np.stack([b, a]))
    assert st == pytest.approx((0.9484061208205754 + 1.0) / 2, abs=1e-12)
    with pytest.raises(ValueError, match="at least 11x11"):
        M.ssim(np.zeros((8, 8)), np.zeros((8, 8)))


def test_global_ssim_variants():
    a, b = _fixed_pair()
    # standard: one window, by hand
    mx, my = a.mean(), b.mean()
    vx, vy, vxy = a.var(), b.var(), np.mean((a - mx) * (b - my))
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    want = (2 * mx * my + c1) * (2 * vxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2))
    assert M.global_ssim(a, b, 1.0, variant="standard") == pytest.approx(want, rel=1e-12)
    # EAF variant on a constant-column image: every column mean equal, so the least-squares ratio
    # is the plain scalar SSIM with sample covariance
    x = np.tile(np.array([[10.0], [20.0], [30.0]]), (1, 4))
    y = x + np.array([[1.0], [0.0], [-1.0]])
    cov = np.cov(x.ravel(), y.ravel())
    C1, C2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    want = (2 * 20 * 20 + C1) * (2 * cov[0, 1] + C2) / ((20 ** 2 + 20 ** 2 + C1) * (cov[0, 0] + cov[1, 1] + C2))
    assert M.global_ssim(x, y, 255.0) == pytest.approx(want, rel=1e-12)
    assert M.global_ssim(a * 255, a * 255) == pytest.approx(1.0, abs=1e-12)


def test_pu21_literals_from_formula():
    # V = p6*(((p0 + p1*Y**p3)/(1 + p2*Y**p3))**p4 - p5), banding_glare p from calibration.md,
    # evaluated with Python floats: Y=1 -> 36.5439111394192, Y=100 -> 256.3838973127039,
    # Y=10000 -> 595.393920020095, Y=0.005 -> 5.47e-10
    v = M.pu21_encode(np.array([1.0, 100.0, 10000.0, 0.005, 1e-9, 1e9]))
    np.testing.assert_allclose(v[:3], [36.5439111394192, 256.3838973127039, 595.393920020095], rtol=1e-13)
    assert abs(v[3]) < 1e-8
    assert v[4] == v[3] and v[5] == v[2]  # clipped to [0.005, 10000] cd/m²
    assert np.all(np.diff(M.pu21_encode(np.logspace(-2, 4, 50))) > 0)


def test_pu_psnr_ssim():
    lt = np.full((16, 16), 100.0)
    lr = np.full((16, 16), 1.0)
    d = 256.3838973127039 - 36.5439111394192
    assert M.pu_psnr(lt, lr) == pytest.approx(10 * math.log10(256.0 ** 2 / d ** 2), rel=1e-12)
    assert M.pu_psnr(lt, lr, peak="pu_max") == pytest.approx(20 * math.log10(595.393920020095 / d), rel=1e-12)
    a, b = _fixed_pair()
    assert M.pu_ssim(a * 1000, b * 1000) == pytest.approx(
        M.ssim(M.pu21_encode(a * 1000), M.pu21_encode(b * 1000), 256.0), rel=1e-15)


def test_match_frames():
    v = np.array([0, 1000, 2000, 3000], np.int64)
    r = np.array([-600, 490, 510, 1500, 2999, 9000], np.int64)
    vi, ri = M.match_frames(v, r, 500)
    # -600: 600 away -> dropped; 490 -> 0; 510 -> 1000; 1500: tie -> earlier (1000); 2999 -> 3000
    assert vi.tolist() == [0, 1, 1, 3]
    assert ri.tolist() == [1, 2, 3, 4]
    vi, ri = M.match_frames(v, r, 0)
    assert vi.size == 0
    with pytest.raises(ValueError, match="non-decreasing"):
        M.match_frames(v[::-1], r, 5)
    with pytest.raises(ValueError, match="tolerance_us"):
        M.match_frames(v, r, -1)
    with pytest.raises(TypeError, match="integer"):
        M.match_frames(v.astype(float), r, 5)


def test_normalisation_policy():
    rng = np.random.default_rng(3)
    r = rng.random((2, 12, 12)) * 50 + 1
    # "scale" (log fit) recovers a pure gain exactly; "affine" (log-affine) a gain and a power
    g, o = M.fit_normalisation(r / 2.5, r, "scale")
    assert (g, o) == (pytest.approx(2.5, rel=1e-12), 0.0)
    g, e = M.fit_normalisation(0.2 * r ** 0.5, r, "affine")  # r = 25 x^2
    assert g == pytest.approx(25, rel=1e-10) and e == pytest.approx(2, rel=1e-12)
    t01, r01, info = M.normalise_pair(0.2 * r ** 0.5, r, "affine")
    assert info["exponent"] == pytest.approx(2) and info["reference_max"] == pytest.approx(r.max())
    np.testing.assert_allclose(t01, r01, atol=1e-12)
    # the linear variants: least squares on intensity
    g, o = M.fit_normalisation(0.1 * r + 3, r, "affine_linear")
    assert g == pytest.approx(10, rel=1e-10) and o == pytest.approx(-30, rel=1e-9)
    g, o = M.fit_normalisation(r / 4, r, "scale_linear")
    assert (g, o) == (pytest.approx(4, rel=1e-12), 0.0)
    # the log fit ignores non-positive pixels; a linear fit of an HDR pair is led by the brightest
    x = np.array([[1e-3, 1e-3, 1.0, 1.0]])
    ref = np.array([[2e-3, 2e-3, 1000.0, 1000.0]])  # dim part x2, bright part x1000 (a saturated frame)
    assert M.fit_normalisation(x, ref, "scale")[0] == pytest.approx(math.sqrt(2 * 1000), rel=1e-12)
    assert M.fit_normalisation(x, ref, "scale_linear")[0] == pytest.approx(1000, rel=1e-5)
    # symmetric by default (the AKF authors' anal_hdr_results.m scores the raw output): an
    # overshoot is kept, and costs as much as the same undershoot
    t01, r01, info = M.normalise_pair(r * 10, r, "none")
    assert info["clip"] == "none" and t01.max() == pytest.approx(10.0, rel=1e-12)
    over = M.score_video(r * 1.5, r, pu21=False)["mse"]
    under = M.score_video(r * 0.5, r, pu21=False)["mse"]
    assert over == pytest.approx(under, rel=1e-12) and over > 0
    # the former policy by name: clipped at the reference maximum, where overshoot is cheaper
    t01, _, info = M.normalise_pair(r * 10, r, "none", clip="reference_max")
    assert t01.max() == 1.0 and info["clip"] == "reference_max"
    assert M.score_video(r * 1.5, r, pu21=False, clip="reference_max")["mse"] < over
    with pytest.raises(ValueError, match="clip"):
        M.normalise_pair(r, r, "none", clip="max")
    with pytest.raises(ValueError, match="normalise"):
        M.fit_normalisation(r, r, "log")
    # unaltered scoring by default (the paper's Table 1), for every method
    for m in ("akf", "cf", "highpass", "frames_zoh", "edi", ""):
        assert M.default_normalise(m) == "none"
    # except the learned events-only methods, whose output is a relative intensity: a gain fit
    assert M.default_normalise("e2vid") == M.default_normalise("firenet") == "scale"
    # the default keeps the reconstruction's units: a recon at half the reference scores as such
    d = M.score_video(r / 2, r, pu21=False)
    assert d["normalise"] == "none" and d["gain"] == 1.0
    assert d["mse"] == pytest.approx(np.mean((r / 2 / r.max() - r / r.max()) ** 2), rel=1e-12)
    assert M.score_video(r / 2, r, normalise="scale", pu21=False)["mse"] == pytest.approx(0.0, abs=1e-20)


def test_ssim_map_matches_ssim_and_masks():
    rng = np.random.default_rng(5)
    a, b = rng.random((2, 20, 24)), rng.random((2, 20, 24))
    m, r = M.ssim_map(a, b)
    assert m.shape == a.shape and r == 5
    assert M.ssim(a[0], b[0]) == pytest.approx(m[0, r:-r, r:-r].mean(), rel=1e-12)
    assert M.ssim(a, b) == pytest.approx(np.mean([x[r:-r, r:-r].mean() for x in m]), rel=1e-12)


def test_log_pair_by_hand():
    ref = np.array([[1.0, 0.01], [0.1, 1e-6]])
    test = np.array([[1.0, 0.1], [np.nan, 2.0]])
    t, r = M.log_pair(test, ref, 1e-4)
    # the reference log range is [log 1e-4, 0] (floored), so v = 1 + log10(I)/4
    np.testing.assert_allclose(r, [[1.0, 0.5], [0.75, 0.0]], atol=1e-15)
    assert t[0, 0] == pytest.approx(1.0) and t[0, 1] == pytest.approx(0.75) and np.isnan(t[1, 0])
    assert t[1, 1] == pytest.approx(1 + math.log10(2) / 4)  # symmetric: above the reference max kept
    t, _ = M.log_pair(test, ref, 1e-4, clip="reference_max")
    assert t[1, 1] == 1.0  # the former policy: clipped


def test_score_video_perfect_and_nan():
    rng = np.random.default_rng(4)
    r = rng.random((3, 16, 16)) + 0.1
    s = M.score_video(r * 0.4, r, normalise="scale")  # the gain fit, by name
    assert s["mse"] == pytest.approx(0, abs=1e-25) and s["ssim"] == pytest.approx(1, abs=1e-12)
    assert s["n_nonfinite"] == 0 and s["gain"] == pytest.approx(2.5)
    s = M.score_video(r, r)  # the default scores the reconstruction unaltered
    assert s["normalise"] == "none" and s["gain"] == 1.0
    assert s["mse"] == 0 and s["ssim"] == pytest.approx(1, abs=1e-12)
    assert M.score_video(r * 0.4, r)["mse"] > 1e-3
    bad = r.copy()
    bad[1, 2, 3] = np.nan
    s = M.score_video(bad, r)
    assert s["n_nonfinite"] == 1 and math.isnan(s["mse"]) and math.isnan(s["ssim"])


def test_pixels_per_degree():
    # 21" 4:3 -> height 0.32004 m; 480 / (2 atan(0.16002) in degrees) = 26.3986
    assert M.pixels_per_degree() == pytest.approx(480 / math.degrees(2 * math.atan(0.16002)), rel=1e-9)
    assert M.pixels_per_degree() == pytest.approx(26.3986, abs=1e-4)
