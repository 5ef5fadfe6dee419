"""ColorVideoVDP: 10 JOD for identical inputs, monotone decrease with noise, display model stated."""

from __future__ import annotations

import numpy as np
import pytest

cv = pytest.importorskip("hybridhdr.evaluate.cvvdp_metric")
if not cv.cvvdp_available():
    pytest.skip("cvvdp (ColorVideoVDP) or PyTorch not installed: pip install 'hybridhdr[evaluate]'",
                allow_module_level=True)


def _hdr_scene(k=3, h=64, w=96):
    yy, xx = np.mgrid[0:h, 0:w]
    base = 0.01 + np.exp(3 * np.sin(xx / 9.0) * np.cos(yy / 13.0)) / 20.0   # ~4 decades
    return np.stack([base * (1 + 0.02 * i) for i in range(k)]).astype(np.float32)


def test_identical_is_10_and_display_is_stated():
    ref = _hdr_scene()
    for fps in (0.0, 30.0):
        r = cv.cvvdp_jod(ref, ref, fps=fps)
        assert r.jod == pytest.approx(10.0, abs=1e-4)
    assert r.display == "standard_hdr_linear" and "HDR" in r.display_description
    assert r.viewing_distance_m == pytest.approx(0.7472) and r.peak_luminance_cd_m2 == 1500
    line = r.display_line()
    assert "standard_hdr_linear" in line and "0.7472 m" in line and "JOD" in line
    assert r.to_dict()["n_frames"] == 3


def test_jod_decreases_monotonically_with_noise():
    ref = _hdr_scene()
    rng = np.random.default_rng(0)
    z = rng.standard_normal(ref.shape)
    jods = [cv.cvvdp_jod(ref * np.exp(s * z), ref, fps=30.0).jod for s in (0.0, 0.02, 0.06, 0.2, 0.5)]
    assert jods[0] == pytest.approx(10.0, abs=1e-4)
    assert all(a > b for a, b in zip(jods, jods[1:])), jods
    assert jods[-1] < 9.0


def test_scale_invariance_and_errors():
    ref = _hdr_scene(k=1)[0]
    noisy = ref * 1.1
    a = cv.cvvdp_jod(noisy, ref).jod
    b = cv.cvvdp_jod(7.0 * noisy, 7.0 * ref).jod   # test and reference scaled together
    assert a == pytest.approx(b, abs=1e-3) and a < 10
    with pytest.raises(ValueError):
        cv.cvvdp_jod(ref, ref[:-1])
    with pytest.raises(ValueError):
        cv.cvvdp_jod(ref, ref, anchor="median")
    with pytest.raises(ValueError):
        cv.cvvdp_jod(np.full_like(ref, np.nan), ref)


def test_gaussian_blur_stand_in_matches_the_separable_gaussian():
    import torch
    G = cv._gaussian_blur_class(torch)(13, 3.0)
    x = torch.from_numpy(np.random.default_rng(1).random((2, 3, 20, 24)).astype(np.float32))
    y = G(x).numpy()
    # same kernel: sampled Gaussian over ±6 taps, normalised, reflect (no edge repeat) padding
    k = np.exp(-0.5 * (np.arange(-6, 7) / 3.0) ** 2)
    k /= k.sum()
    ref = x.numpy()
    for ax in (-2, -1):
        pad = [(0, 0)] * 4
        pad[ax] = (6, 6)
        p = np.pad(ref, pad, mode="reflect")
        ref = np.apply_along_axis(lambda v: np.convolve(v, k, mode="valid"), ax, p)
    np.testing.assert_allclose(y, ref, atol=1e-5)
