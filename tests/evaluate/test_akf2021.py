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


def test_cli_protocol_akf2021_on_a_file_with_the_authors_layout(tmp_path, capsys):
    """``hybridhdr evaluate metrics RECON --reference seq.mat --protocol akf2021`` on a small MAT
    v7.3 file written here with the layout of the authors' HDR sequences."""
    import json

    h5py = pytest.importorskip("h5py")
    import hybridhdr as hh
    from hybridhdr.formats.akf_mat import matlab_v73_header
    from hybridhdr.cli import main
    from hybridhdr.formats.images import write_exr, write_timestamps
    k, h, w = 4, 20, 28
    ref, rng = _hdr(k, h, w, seed=1)                        # HDR_mat in code units, 0 = unregistered
    t_mid = np.array([10_000, 60_000, 110_000, 160_000])
    ev = hh.make_events(np.sort(rng.integers(0, 170_000, 300)), rng.integers(0, w, 300), rng.integers(0, h, 300),
                        rng.integers(0, 2, 300))
    frames = np.clip(ref.mean(axis=3), 0, 255).astype(np.uint8)
    mat = tmp_path / "seq.mat"
    with h5py.File(mat, "w", userblock_size=512) as f:       # MATLAB v7.3: axes reversed in HDF5
        f["events"] = np.stack([ev["t"].astype(float), ev["x"] + 1.0, ev["y"] + 1.0, (ev["p"] > 0) * 1.0])
        f["image"] = np.transpose(frames, (0, 2, 1))
        f["time_image"] = t_mid.astype(float)[:, None]
        f["exposure"] = np.full((k, 1), 5000.0)
        f["f_Q"] = np.full((1, 256), 7e5)
        f["HDR_mat"] = np.transpose(ref, (0, 3, 2, 1))
    with open(mat, "r+b") as fh:
        fh.write(matlab_v73_header())
    # a reconstruction in frame units at the reference times (+ 300 µs: matched within 1 ms)
    y = ref.mean(axis=3) / 255.0
    recon = (y * (1 + 0.1 * rng.standard_normal(y.shape))).astype(np.float32)
    recon[y == 0] = 3.0                                     # must not count
    d = tmp_path / "recon"
    d.mkdir()
    names = [f"frame_{i:06d}.exr" for i in range(k)]
    for n, img in zip(names, recon):
        write_exr(d / n, img)
    write_timestamps(t_mid + 300, names, d / "timestamps.txt")
    assert main(["evaluate", "metrics", str(d), "--reference", str(mat), "--protocol", "akf2021", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    want = M.score_akf2021(recon, ref)
    assert res["protocol"] == "akf2021" and res["matched"] == 4
    assert res["mse"] == pytest.approx(want["mse"], rel=1e-6) and res["ssim"] == pytest.approx(want["ssim"], rel=1e-6)
    assert res["n_masked"] == int((y == 0).sum()) and "jod" not in res
    assert res["q"] is None and "HDR-VDP" in res["q_note"]
    assert main(["evaluate", "metrics", str(d), "--reference", str(mat), "--protocol", "akf2021"]) == 0
    out = capsys.readouterr().out
    assert "protocol akf2021" in out and "masked" in out and "MSE (frame units)" in out
    # the default protocol on the same files scores differently (reference max, clipping)
    assert main(["evaluate", "metrics", str(d), "--reference", str(mat), "--metric", "none", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["mse"] != pytest.approx(want["mse"])
