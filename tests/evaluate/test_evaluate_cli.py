"""``hybridhdr evaluate metrics / bench`` end to end, the paper table, simulator-backed datasets."""

import json
import math

import numpy as np
import pytest

from hybridhdr.cli import main
from hybridhdr.formats.container import write_recording
from hybridhdr.evaluate import metrics as M
from hybridhdr.evaluate.paper import paper_table
from hybridhdr.simulate.procedural import procedural_recording


@pytest.fixture(scope="module")
def rec_path(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    rec, _ = procedural_recording((24, 32), 200_000, seed=1, hdr_rate_hz=50.0)
    p = d / "rec.h5"
    write_recording(rec, p)
    return p, rec


def test_metrics_command_matches_library(rec_path, tmp_path, capsys):
    path, rec = rec_path
    out = tmp_path / "recon"
    assert main(["reconstruct", str(path), "--method", "cf", "--out", str(out), "--fps", "200",
                 "--contrast-threshold", "0.2"]) == 0
    capsys.readouterr()
    assert main(["evaluate", "metrics", str(out), "--reference", str(path), "--tolerance-us", "0", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    # library path on the same data: 200 fps outputs every 5000 µs from the first frame time, the
    # 50 Hz references every 20000 µs -> exact matches only (tolerance 0)
    from hybridhdr.formats.images import read_exr
    lines = [ln.split() for ln in (out / "timestamps.txt").read_text().splitlines() if not ln.startswith("#")]
    t = np.array([int(a) for a, _ in lines])
    vi, ri = M.match_frames(t, rec.hdr.t_us, 0)
    assert res["matched"] == len(vi) > 3
    frames = np.stack([read_exr(out / lines[i][1]) for i in vi])
    want = M.score_video(frames, rec.hdr.images[ri], normalise="none")
    for k in ("mse", "ssim", "log_ssim", "pu_ssim", "gain"):
        assert res[k] == pytest.approx(want[k], rel=1e-12)
    # unaltered by default (the paper's scoring), for every method
    assert res["method"] == "cf" and res["normalise"] == "none" and res["gain"] == 1.0
    assert res["q"] is None and "HDR-VDP" in res["q_note"]
    # the gain fit by name
    assert main(["evaluate", "metrics", str(out), "--reference", str(path), "--tolerance-us", "0", "--json",
                 "--normalise", "scale"]) == 0
    res_s = json.loads(capsys.readouterr().out)
    want_s = M.score_video(frames, rec.hdr.images[ri], normalise="scale")
    assert res_s["normalise"] == "scale" and res_s["mse"] == pytest.approx(want_s["mse"], rel=1e-12)
    assert res_s["gain"] == pytest.approx(want_s["gain"], rel=1e-12) and res_s["gain"] != 1.0
    # human-readable output
    assert main(["evaluate", "metrics", str(out), "--reference", str(path)]) == 0
    text = capsys.readouterr().out
    assert "SSIM (Gaussian σ=1.5, range 1)" in text and "HDR-VDP Q" in text and "n/a" in text


def test_metrics_command_errors(rec_path, tmp_path, capsys):
    path, _ = rec_path
    assert main(["evaluate", "metrics", str(tmp_path), "--reference", str(path)]) == 1
    assert "timestamps.txt" in capsys.readouterr().err
    (tmp_path / "timestamps.txt").write_text("# t_us filename\n99999999 frame_000000.exr\n")
    assert main(["evaluate", "metrics", str(tmp_path), "--reference", str(path)]) == 1
    assert "no reconstructed frame within 1000 µs" in capsys.readouterr().err
    (tmp_path / "timestamps.txt").write_text("abc frame.exr\n")
    assert main(["evaluate", "metrics", str(tmp_path), "--reference", str(path)]) == 1
    assert "must be an integer" in capsys.readouterr().err


def test_bench_command(tmp_path, capsys):
    toml = tmp_path / "b.toml"
    toml.write_text("""
[bench]
name = "cli"
seed = 1
warmup = false
[[datasets]]
name = "p"
kind = "procedural"
width = 24
height = 16
duration_us = 120000
[[methods]]
method = "akf"
augment = false
[[methods]]
method = "frames"
""")
    assert main(["evaluate", "bench", str(toml), "--out", str(tmp_path / "o"), "--workers", "0",
                 "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "| p | akf |" in out and "results.csv" in out
    assert (tmp_path / "o" / "speed_accuracy.png").is_file() and (tmp_path / "o" / "report.html").is_file()
    assert main(["evaluate", "bench", str(tmp_path / "missing.toml"), "--out", str(tmp_path)]) == 1
    assert "bundled" in capsys.readouterr().err


def test_paper_table_shape_and_reductions():
    rows = []
    for ds in ("HDR:a", "HDR:b", "AHDR:c"):
        rows.append({"dataset": ds, "method_label": "akf", "status": "ok", "mse": 0.01, "ssim": 0.9, "q": math.nan,
                     "log_mse": 0.02, "log_ssim": 0.8})
        rows.append({"dataset": ds, "method_label": "cf", "status": "ok", "mse": 0.02, "ssim": 0.75, "q": math.nan,
                     "log_mse": 0.04, "log_ssim": 0.4})
    text, nums = paper_table(rows)
    lines = text.splitlines()
    # the table says how it was scored (rows without a normalise column: the default, unaltered)
    assert lines[0].startswith("Scoring: unaltered reconstructions (normalise=none")
    lines = lines[2:]
    # methods as columns (Table 1's order, then the paper's AKF); MSE, SSIM, JOD rows per set
    assert lines[0] == "| set | metric | CF | AKF | *paper: AKF* |"
    assert lines[2] == "| HDR | MSE | 2.000e-02 | 1.000e-02 | 1.710e-02 |"
    assert lines[3] == "| HDR | SSIM | 0.750 | 0.900 | 0.89 |"
    assert lines[4] == "| HDR | JOD (ColorVideoVDP) | skipped (--no-jod) | skipped (--no-jod) | — |"
    assert lines[5].startswith("| AHDR | MSE |")
    assert "Q (HDR-VDP 3) not computed" in text and "| Q (HDR-VDP 3) |" not in text
    # JOD and Q values; n/a note when cvvdp is missing; learned columns marked as gain-fitted
    more = [{**r, "jod": 7.5, "q": 5.0} for r in rows] + [
        {"dataset": ds, "method_label": "e2vid", "status": "ok", "mse": 0.05, "ssim": 0.5, "q": math.nan,
         "jod": math.nan, "jod_note": "n/a (install hybridhdr[evaluate])", "normalise": "scale",
         "log_mse": 0.1, "log_ssim": 0.3} for ds in ("HDR:a", "AHDR:c")]
    t2 = paper_table(more)[0].splitlines()
    assert t2[2] == "| set | metric | E2VID† | CF | AKF | *paper: AKF* |"
    assert "| HDR | JOD (ColorVideoVDP) | n/a (install hybridhdr[evaluate]) | 7.50 | 7.50 | — |" in t2
    assert "| HDR | Q (HDR-VDP 3) | n/a | 5.00 | 5.00 | 4.83 |" in t2
    assert any(x.startswith("† events-only output") for x in t2)
    fitted = [{**r, "normalise": "scale"} for r in rows]
    assert paper_table(fitted)[0].splitlines()[0] == ("Scoring: reconstructions fitted to the reference per run "
                                                       "by least squares (normalise=scale).")
    assert nums["mse_reduction_pct"] == pytest.approx(50.0) and nums["ssim_improvement_pct"] == pytest.approx(20.0)
    assert "AKF MSE 50.0% lower (paper: 48% lower)" in text


def test_simulated_dataset_and_cache(tmp_path):
    pytest.importorskip("hybridhdr.simulate.pipeline")
    from hybridhdr.evaluate.datasets import load_dataset
    spec = {"kind": "sim_procedural", "width": 24, "height": 16, "duration_us": 100_000, "hdr_rate_hz": 50.0,
            "sampling": {"mode": "fixed", "fixed_rate_hz": 500.0}, "sensor.shot_noise_rate_hz": 2.0,
            "camera": {"code_clip": [100, 160]}}
    a = load_dataset(spec, seed=2, cache_dir=tmp_path)
    b = load_dataset(spec, seed=2, cache_dir=tmp_path)  # read back from the cache
    assert len(list(tmp_path.glob("sim_procedural_*.h5"))) == 1
    np.testing.assert_array_equal(a.recording.events, b.recording.events)
    np.testing.assert_array_equal(a.recording.hdr.images, b.recording.hdr.images)
    assert a.contrast_threshold == pytest.approx(0.2) and len(a.recording.events) > 0
    assert set(range(0, 100_001, 20_000)) <= set(a.recording.hdr.t_us.tolist())
    im = a.recording.frames.images
    assert im.min() >= 100 and im.max() <= 160  # the AHDR clipped camera
    with pytest.raises(ValueError, match="prefix"):
        load_dataset({**spec, "lens.f": 1}, seed=2)
    with pytest.raises(ValueError, match="unknown sensor parameter"):
        load_dataset({**spec, "sensor.bogus": 1}, seed=2)


def test_real_data_holdout_frame_prediction(shared_data):
    """ecd_slider_depth (real DAVIS240C): frame 2 held out of the input and used as the reference.

    Measured (this data, c = 0.1) with the gain fit (``normalise = "scale"``, this test's
    original scoring, kept by name): AKF (with frame augmentation) MSE 0.0110 vs frames only
    (zero-order hold of frame 1) 0.0212; the events must carry the image from frame 1 towards
    frame 2 (requiring 25 % less leaves room for parameter changes in reconstruct, not for an
    AKF that ignores its events). Unaltered (the default scoring, the reference is frame 2 in
    the same profile units) the AKF must still beat the hold.
    """
    from hybridhdr.evaluate import bench as B
    path = shared_data("ecd_slider_depth")
    b = B.parse_bench({"bench": {"warmup": False},
                       "datasets": [{"name": "ecd", "kind": "file", "path": str(path), "contrast_threshold": 0.1,
                                     "holdout_frames": [2]}],
                       "methods": [{"method": "akf", "normalise": "scale"}, {"method": "frames", "normalise": "scale"},
                                   {"name": "akf_unaltered", "method": "akf"},
                                   {"name": "frames_unaltered", "method": "frames"}]})
    rows = B.run_bench(b, workers=0, progress=False)
    assert [r["status"] for r in rows] == ["ok"] * 4
    akf, zoh, akf_u, zoh_u = rows
    assert akf["n_frames"] == 1 and akf["n_nonfinite"] == 0
    assert akf["mse"] < 0.75 * zoh["mse"]
    assert akf_u["normalise"] == "none" and akf_u["gain"] == 1.0
    assert akf_u["mse"] < zoh_u["mse"]


def test_ahdr_dataset_and_clipped_camera_profile():
    pytest.importorskip("hybridhdr.simulate.ahdr")
    from hybridhdr.simulate.datasets import camera_profile
    from hybridhdr.evaluate.datasets import load_dataset
    from hybridhdr.simulate.camera import FrameCameraParams, crf_inverse_table
    cam = FrameCameraParams(crf="gamma", code_clip=(100, 160))
    prof = camera_profile(cam)
    inv = crf_inverse_table(cam)
    np.testing.assert_allclose(prof.inverse_crf, inv / inv[-1], rtol=1e-12)
    assert np.all(prof.weighting[:101] == 0) and np.all(prof.weighting[160:] == 0)
    assert prof.weighting[130] > 0
    assert camera_profile(FrameCameraParams(crf="gamma")) is None
    d = load_dataset({"kind": "ahdr", "image": "procedural:3", "width": 24, "height": 16, "duration_us": 150_000,
                      "sampling": {"mode": "fixed", "fixed_rate_hz": 500.0}, "motion": {"pan_x_px": 10.0}}, seed=0)
    im = d.recording.frames.images
    assert im.min() >= 100 and im.max() <= 160 and len(d.recording.events) > 0
    assert d.contrast_threshold == pytest.approx(0.2)  # from the recording's provenance (clean preset)
    assert d.profile is not None and d.profile.weighting[100] == 0


def test_paper_table_labels_the_stress_set():
    # HDR set v2 ("HDR:"), the former scenes as "HDR-stress:", AHDR: three labelled sets; the
    # stress set has no paper column value and its own reductions in the numbers
    rows = []
    for ds, (a, c, f) in (("HDR:w", (0.01, 0.04, 0.05)), ("HDR-stress:d", (0.03, 0.03, 0.03)),
                          ("AHDR:c", (0.01, 0.02, 0.02))):
        for lab, m in (("akf", a), ("cf", c), ("frames", f)):
            rows.append({"dataset": ds, "method_label": lab, "status": "ok", "mse": m, "ssim": 0.9 if lab == "akf"
                         else 0.6, "q": math.nan, "log_mse": m, "log_ssim": 0.5})
    text, nums = paper_table(rows)
    assert "| HDR-stress | MSE | 3.000e-02 | 3.000e-02 | — |" in text
    assert "| HDR | MSE | 4.000e-02 | 1.000e-02 | 1.710e-02 |" in text
    assert nums["mse_reduction_pct"] == pytest.approx(75.0) and nums["stress_mse_reduction_pct"] == pytest.approx(0.0)
    assert nums["mse_reduction_vs_frames_pct"] == pytest.approx(80.0)
    assert nums["ssim_improvement_vs_frames_pct"] == pytest.approx(50.0)
    assert "on the HDR-stress set" in text and "on the HDR set (v2)" in text
