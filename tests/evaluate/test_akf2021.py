"""The AKF authors' protocol (``--protocol akf2021``): unaltered reconstruction against the
reference's channel mean / 255, reference-0 pixels masked, MSE, PSNR, SSIM and HDR-VDP 3 Q
(luminance, 21-inch 640x480 at 1 m)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridhdr.evaluate import metrics as M


def _hdr(k=3, h=24, w=32, seed=0):
    rng = np.random.default_rng(seed)
    ref = rng.random((k, h, w, 3)) * 300.0 + 5.0         # code units, above 255 = beyond the frames' range
    ref[:, :4] = 0.0                                      # unregistered rows
    ref[:, :, :3] = 0.0                                   # and columns
    return ref, rng


def test_scores_in_frame_units_with_unregistered_pixels_masked():
    ref, rng = _hdr()
    y = ref.mean(axis=3) / 255.0
    mask = y != 0
    recon = y * (1 + 0.1 * rng.standard_normal(y.shape))
    recon[~mask] = 50.0                                   # anything where the reference is unregistered
    s = M.score_akf2021(recon, ref)
    want = np.mean((recon[mask] - y[mask]) ** 2)
    assert s["mse"] == pytest.approx(want, rel=1e-12)
    assert s["psnr_db"] == pytest.approx(10 * math.log10(1 / want))
    assert s["n_masked"] == int((~mask).sum()) and s["n_valid"] == int(mask.sum())
    # masked SSIM: the map's mean over unmasked pixels inside the border, per frame, averaged
    smap, r = M.ssim_map(recon, y, 1.0)
    inner = np.zeros_like(mask)
    inner[:, r:-r, r:-r] = True
    want_ssim = np.mean([smap[k][(mask & inner)[k]].mean() for k in range(3)])
    assert s["ssim"] == pytest.approx(want_ssim, rel=1e-12)
    # unaltered: no gain fit, no clipping (a recon x2 is worse, the exact reference is perfect)
    assert M.score_akf2021(y, ref)["mse"] == 0.0 and M.score_akf2021(y, ref)["ssim"] == pytest.approx(1.0)
    assert M.score_akf2021(2 * y, ref)["mse"] == pytest.approx(np.mean(y[mask] ** 2))
    # grey references are used as they are
    assert M.score_akf2021(recon, ref.mean(axis=3))["mse"] == pytest.approx(want)
    with pytest.raises(ValueError, match="unregistered"):
        M.score_akf2021(recon, np.zeros_like(ref))


def test_q_settings_are_the_authors(monkeypatch):
    ref, rng = _hdr()
    y = ref.mean(axis=3) / 255.0
    recon = y * 1.1
    recon[y == 0] = 7.0
    seen = {}

    def fake(test, reference, **kw):
        seen.update(kw, test=test, reference=reference)
        return M.HDRVDPResult(6.5, "3.0.6", kw["task"], kw["color_encoding"], kw["pixels_per_degree"],
                              kw["luminance_scale_cd_m2"], "octave")
    monkeypatch.setattr(M, "hdrvdp_q", fake)
    s = M.score_akf2021(recon, ref, hdrvdp={"hdrvdp_dir": "/x"})
    assert s["q"] == 6.5 and s["q_color_encoding"] == "luminance" and s["q_task"] == "side-by-side"
    assert seen["pixels_per_degree"] == pytest.approx(M.pixels_per_degree(21.0, (640, 480), 1.0))
    assert seen["luminance_scale_cd_m2"] == 255.0 and seen["hdrvdp_dir"] == "/x"
    # masked pixels carry no difference into HDR-VDP
    np.testing.assert_array_equal(seen["test"][y == 0], 0.0)
    np.testing.assert_allclose(seen["test"][y != 0], recon[y != 0])
