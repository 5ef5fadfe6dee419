"""Per-frame scores: ``score_video/score_akf2021(per_frame=True)`` and ``evaluate metrics --json`` /
``--csv FILE``."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from hybridhdr.cli import main
from hybridhdr.evaluate import metrics as M


def _pair(k=4, h=20, w=28, seed=0):
    rng = np.random.default_rng(seed)
    ref = np.exp(rng.normal(0, 1.2, (k, h, w)))
    test = ref * np.exp(rng.normal(0, 0.05 * (1 + np.arange(k))[:, None, None], (k, h, w)))  # worse frame by frame
    return test, ref


def test_score_video_per_frame_is_consistent_with_the_aggregates():
    test, ref = _pair()
    test[3, 0, 0] = np.nan
    res = M.score_video(test, ref, normalise="scale", per_frame=True)
    fr = res["frames"]
    assert [f["index"] for f in fr] == [0, 1, 2, 3]
    assert [f["n_nonfinite"] for f in fr] == [0, 0, 0, 1]
    ok = fr[:3]
    # the same normalised pair as the aggregate (one gain for the sequence): frame k alone by hand
    t01, r01, _ = M.normalise_pair(test, ref, "scale")
    for k, f in enumerate(ok):
        assert f["mse"] == pytest.approx(np.mean((t01[k] - r01[k]) ** 2), rel=1e-12)
        assert f["ssim"] == pytest.approx(M.ssim(t01[k], r01[k]), rel=1e-12)
        assert f["psnr_db"] == pytest.approx(10 * math.log10(1 / f["mse"]), rel=1e-12)
        assert math.isfinite(f["pu_ssim"]) and math.isfinite(f["log_ssim"])
    # the noise grows frame by frame: so does the error
    assert ok[0]["mse"] < ok[1]["mse"] < ok[2]["mse"]
    assert math.isnan(fr[3]["mse"]) and math.isnan(fr[3]["pu_ssim"])
    # without NaN the means of the per-frame MSE and SSIM are the aggregates
    res = M.score_video(*_pair(), per_frame=True)
    assert np.mean([f["mse"] for f in res["frames"]]) == pytest.approx(res["mse"], rel=1e-12)
    assert np.mean([f["ssim"] for f in res["frames"]]) == pytest.approx(res["ssim"], rel=1e-12)
    assert np.mean([f["log_mse"] for f in res["frames"]]) == pytest.approx(res["log_mse"], rel=1e-12)
    assert "frames" not in M.score_video(*_pair())


def test_score_akf2021_per_frame():
    test, ref = _pair()
    ref = ref * 100
    ref[:, :3] = 0.0
    res = M.score_akf2021(test, ref, per_frame=True)
    mask = ref != 0
    for k, f in enumerate(res["frames"]):
        want = np.mean((test[k][mask[k]] - ref[k][mask[k]] / 255.0) ** 2)
        assert f["mse"] == pytest.approx(want, rel=1e-12) and f["n_valid"] == int(mask[k].sum())
    assert np.mean([f["ssim"] for f in res["frames"]]) == pytest.approx(res["ssim"], rel=1e-12)


def test_cli_metrics_json_and_csv_per_frame(tmp_path, capsys):
    from hybridhdr.container import write_recording
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording((24, 32), 200_000, seed=1, hdr_rate_hz=50.0)
    path = write_recording(rec, tmp_path / "rec.h5")
    out = tmp_path / "recon"
    assert main(["reconstruct", str(path), "--method", "cf", "--out", str(out), "--fps", "200",
                 "--contrast-threshold", "0.2", "--no-progress"]) == 0
    capsys.readouterr()
    csv_path = tmp_path / "frames.csv"
    assert main(["evaluate", "metrics", str(out), "--reference", str(path), "--tolerance-us", "0", "--json",
                 "--metric", "none", "--csv", str(csv_path)]) == 0
    text = capsys.readouterr().out
    res = json.loads(text)  # one strict JSON object: NaN/inf as null
    assert "NaN" not in text and "Infinity" not in text
    fr = res["frames"]
    assert len(fr) == res["matched"] > 3
    assert all(f["t_us"] == f["reference_t_us"] for f in fr)  # tolerance 0
    assert [f["reference_t_us"] for f in fr] == [int(rec.hdr.t_us[f["reference_index"]]) for f in fr]
    assert all(f["file"].endswith(".exr") and (out / f["file"]).is_file() for f in fr)
    assert np.mean([f["ssim"] for f in fr]) == pytest.approx(res["ssim"], rel=1e-12)
    with open(csv_path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(fr)
    assert list(rows[0])[:5] == ["file", "t_us", "reference_index", "reference_t_us", "index"]
    for r, f in zip(rows, fr):
        assert r["file"] == f["file"] and int(r["t_us"]) == f["t_us"]
        assert float(r["mse"]) == f["mse"] and float(r["ssim"]) == f["ssim"]  # repr: exact round trip
    # text mode with --csv: the table, then where the rows went
    csv2 = tmp_path / "frames2.csv"
    assert main(["evaluate", "metrics", str(out), "--reference", str(path), "--tolerance-us", "0",
                 "--metric", "none", "--csv", str(csv2)]) == 0
    assert f"per-frame rows to {csv2}" in capsys.readouterr().out and csv2.read_text() == csv_path.read_text()
    # a missing folder is an error before any scoring
    assert main(["evaluate", "metrics", str(out), "--reference", str(path), "--csv",
                 str(tmp_path / "nope" / "f.csv")]) == 1
    assert "does not exist" in capsys.readouterr().err
