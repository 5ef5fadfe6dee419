"""Real-data scoring without ground truth (hybridhdr.evaluate.realdata) and `evaluate holdout`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hybridhdr.camera.encoding import well_exposed_range
from hybridhdr.evaluate import realdata as RD

from tests.conftest import SHARED_DATA

ECD = SHARED_DATA / "ecd_slider_depth"  # HYBRIDHDR_SHARED_DATA, else ../shared/data


@pytest.fixture(scope="module")
def rec():
    from hybridhdr.simulate.procedural import procedural_recording
    r, _ = procedural_recording((30, 40), 300_000, contrast_threshold=0.15, frame_rate_hz=25.0, step_us=500)
    return r


def test_well_exposed_range():
    assert well_exposed_range(255) == (20, 235)
    assert well_exposed_range(1023) == (81, 942)  # 80.2 rounded up, 942.7 rounded down
    assert well_exposed_range(65535) == (5140, 60395)


def test_holdout_inputs(rec):
    held = RD.default_held_frames(rec)
    n = len(rec.frames)
    assert held == list(range(1, n - 1))
    k = held[1]
    tk = int(rec.frames.t_mid_us[k])
    loo, t = RD.holdout_input(rec, k, "leave_one_out")
    assert t == tk and len(loo.frames) == n - 1 and tk not in loo.frames.t_mid_us
    assert len(loo.events) == len(rec.events)
    nf, t = RD.holdout_input(rec, k, "next_frame")
    assert t == tk - 1 and len(nf.frames) == k
    assert nf.events["t"].max() < tk - 1 and len(nf.events) == int(np.sum(rec.events["t"] < tk - 1))
    with pytest.raises(ValueError, match="task"):
        RD.holdout_input(rec, k, "both")


def test_score_frame_closed_form():
    rng = np.random.default_rng(0)
    r = rng.uniform(0.1, 0.9, (20, 24))
    v = np.ones(r.shape, bool)
    v[:, :4] = False
    s = RD.score_frame(r, r, v)
    assert s["mse"] == 0 and s["psnr_db"] == np.inf and s["ssim"] == pytest.approx(1.0)
    x = r + 0.1
    x[:, :4] = 5.0  # outside the valid pixels: not scored (nor is the clip to [0, 1] seen there)
    s = RD.score_frame(x, r, v)
    assert s["mse"] == pytest.approx(0.01) and s["psnr_db"] == pytest.approx(20.0) and s["n_valid"] == 20 * 20
    x[0, 10] = np.nan
    assert RD.score_frame(x, r, v)["n_nonfinite"] == 1


def test_evaluate_holdout_baselines_and_causality(rec):
    specs = [RD.HoldoutSpec("akf", "akf", "offline", {"contrast_threshold": 0.15}),
             RD.HoldoutSpec("akf_causal", "akf", "causal", {"contrast_threshold": 0.15})]
    res = RD.evaluate_holdout(rec, specs)
    held = res["held"]
    loo, nf = res["leave_one_out"]["methods"], res["next_frame"]["methods"]
    assert all(r["status"] == "ok" for r in loo.values())
    assert nf["akf"]["status"].startswith("skipped")
    # hold-previous is frame k-1 itself: its score by hand
    ref, valid, _ = RD.reference_frames(rec, held)
    prev, _, _ = RD.reference_frames(rec, [k - 1 for k in held])
    m = res["reference_max"]
    by_hand = [RD.score_frame(p / m, r / m, v)["mse"] for p, r, v in zip(prev, ref, valid)]
    got = [p["mse"] for p in loo["hold_previous"]["per_frame"]]
    np.testing.assert_allclose(got, by_hand, rtol=1e-5)
    assert [p["frame"] for p in loo["hold_previous"]["per_frame"]] == held
    # a causal method sees nothing after tau_k in either task: 1 µs apart, the same prediction
    a = [p["mse"] for p in loo["akf_causal"]["per_frame"]]
    b = [p["mse"] for p in nf["akf_causal"]["per_frame"]]
    np.testing.assert_allclose(a, b, rtol=1e-3)
    # baselines are the same in both tasks; linear interpolation is marked non-causal there
    assert nf["hold_previous"]["mean"] == loo["hold_previous"]["mean"]
    assert "non-causal" in nf["linear_interpolation"]["role"]
    text = RD.format_holdout(res)
    assert "leave-one-frame-out" in text and "next-frame" in text and "hold_previous" in text


def test_cli_json_and_errors(rec, tmp_path, capsys):
    from hybridhdr.cli import main
    from hybridhdr.formats.container import write_recording
    p = tmp_path / "rec.h5"
    write_recording(rec, p)
    assert main(["evaluate", "holdout", str(p), "--method", "akf,cf", "--mode", "causal",
                 "--contrast-threshold", "0.15", "--frames", "2,3", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["held"] == [2, 3]
    for task in ("leave_one_out", "next_frame"):
        rows = res[task]["methods"]
        assert set(rows) == {"akf_causal", "cf_causal", "hold_previous", "linear_interpolation"}
        assert [q["frame"] for q in rows["akf_causal"]["per_frame"]] == [2, 3]
        assert {"mse", "psnr_db", "ssim", "n_valid", "t_us"} <= set(rows["cf_causal"]["per_frame"][0])
    assert main(["evaluate", "holdout", str(p), "--task", "next-frame"]) == 1
    assert "causal" in capsys.readouterr().err
    assert main(["evaluate", "holdout", str(p), "--method", "frames_zoh", "--contrast-threshold", "0.1"]) == 1


@pytest.mark.skipif(not ECD.exists(), reason=f"sample data {ECD} not present")
def test_ecd_slider_depth_akf_beats_hold_previous():
    import hybridhdr
    r = hybridhdr.read(ECD)
    # no parameters and no thresholds: the API's default is the command line's (self-calibration here),
    # one calibration without any held frame
    res = RD.evaluate_holdout(r, [RD.HoldoutSpec("akf", "akf")], tasks=("leave_one_out",), calibration_holdout="scored")
    assert res["thresholds"] == "selfcal"
    m = res["leave_one_out"]["methods"]
    assert res["held"] == [1, 2, 3]
    assert m["akf"]["mean"]["mse"] < m["hold_previous"]["mean"]["mse"]
    assert m["akf"]["mean"]["ssim"] > m["hold_previous"]["mean"]["ssim"]


def test_input_thresholds_recover_the_sensor_and_never_see_frame_k(rec):
    """Pooled thresholds estimated on the leave-one-out input, in the AKF's log model, recover the
    simulated sensor's c = 0.15 (the frames are exact, events ideal: error from the residual of
    each interval, below one threshold, averaged over ~1000 pixel-intervals: 5 %)."""
    k = RD.default_held_frames(rec)[2]
    loo, _ = RD.holdout_input(rec, k, "leave_one_out")
    p, used = RD.input_thresholds(loo, "akf", None)
    assert used["source"] == "auto"
    assert p.c_on == pytest.approx(0.15, rel=0.05) and p.c_off == pytest.approx(0.15, rel=0.05)
    # CF's log(I + 1) model gives its own (smaller) numbers: each method in its own model
    q, used_cf = RD.input_thresholds(loo, "cf", None)
    assert used_cf["intensity_offset"] == 1.0 and q.c_on < 0.8 * p.c_on
    # frames-only and high-pass methods keep their parameters
    assert RD.input_thresholds(loo, "frames_zoh", None) == (None, None)
    assert RD.input_thresholds(loo, "highpass", None) == (None, None)
    # one frame: nothing to calibrate against, the method's own thresholds are kept and said so
    one, _ = RD.holdout_input(rec, 1, "next_frame")
    p1, u1 = RD.input_thresholds(one, "akf", {"contrast_threshold": 0.3})
    assert u1["source"] == "params" and p1.c_on == 0.3 and "two frames" in u1["why"]
    # in next-frame prediction the numbers come from the recording without frame k (never from it)
    res = RD.holdout_reconstructions(rec, [RD.HoldoutSpec("akf_causal", "akf", "causal")], task="next_frame",
                                     held=[k], thresholds="auto")
    assert res["akf_causal"]["thresholds"][0] == used
    with pytest.raises(ValueError, match="thresholds must be one of"):
        RD.holdout_reconstructions(rec, [], task="next_frame", held=[k], thresholds="estimated")


def test_cli_thresholds_default_follows_the_arguments(rec, tmp_path, capsys):
    from hybridhdr.cli import main
    from hybridhdr.container import write_recording
    p = tmp_path / "rec.h5"
    write_recording(rec, p)
    from hybridhdr.calibrate.resolve import DEFAULT_THRESHOLDS
    assert main(["evaluate", "holdout", str(p), "--method", "akf", "--frames", "2", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # a recording that declares no thresholds: the one default (DEFAULT_THRESHOLDS, selfcal, as
    # reconstruct's) self-calibrates it, leave-one-out
    assert res["thresholds"] == "selfcal"
    used = res["leave_one_out"]["methods"]["akf"]["thresholds"][0]
    assert used["source"] in ("selfcal", "params"), used  # params: the input cannot tell (recorded why)
    assert used["source"] == "selfcal" or used["why"]
    assert main(["evaluate", "holdout", str(p), "--method", "akf", "--frames", "2", "--thresholds", "auto",
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["thresholds"] == "auto"
    assert res["leave_one_out"]["methods"]["akf"]["thresholds"][0]["source"] == "auto"
    assert main(["evaluate", "holdout", str(p), "--method", "akf", "--frames", "2", "--thresholds", "input",
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    used = res["leave_one_out"]["methods"]["akf"]["thresholds"][0]
    assert used["source"] == "input" and "declares none" in used["used"]  # procedural: none declared
    import dataclasses

    import hybridhdr
    ec = dataclasses.replace(rec.metadata.event_camera, contrast_threshold_on=0.15, contrast_threshold_off=0.14)
    declared = hybridhdr.Recording(rec.events, rec.sensor_size, rec.frames, rec.triggers, rec.hdr,
                                   dataclasses.replace(rec.metadata, event_camera=ec))
    write_recording(declared, tmp_path / "declared.h5")
    assert main(["evaluate", "holdout", str(tmp_path / "declared.h5"), "--method", "akf", "--frames", "2",
                 "--thresholds", "input", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    used = res["leave_one_out"]["methods"]["akf"]["thresholds"][0]
    assert used["source"] == "input" and used["used"].startswith("declared by the recording: ON 0.15, OFF 0.14")
    assert main(["evaluate", "holdout", str(p), "--method", "akf", "--frames", "2", "--contrast-threshold", "0.15",
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["thresholds"] == "params" and "thresholds" not in res["leave_one_out"]["methods"]["akf"]


def test_one_calibration_without_every_held_out_frame(rec, monkeypatch):
    """``calibration_holdout="scored"``: one threshold estimate, on the input without every held-out
    frame, shared by them and by the methods of one log model; bad values are named."""
    held = RD.default_held_frames(rec)[1:4]
    fr = RD._trimmed_frames(rec)
    seen = []
    real = RD.resolve_thresholds

    def spy(r, *a, **kw):
        seen.append(set(r.frames.t_mid_us.tolist()))
        return real(r, *a, **kw)

    monkeypatch.setattr(RD, "resolve_thresholds", spy)
    specs = [RD.HoldoutSpec("akf", "akf", "offline"), RD.HoldoutSpec("akf_causal", "akf", "causal")]
    res = RD.holdout_reconstructions(rec, specs, task="leave_one_out", held=held, thresholds="auto",
                                     calibration_holdout="scored")
    assert seen == [set(fr.t_mid_us.tolist()) - {int(fr.t_mid_us[k]) for k in held}]
    used = res["akf"]["thresholds"]
    assert len(used) == len(held) and all(u == used[0] and u["source"] == "auto" for u in used)
    with pytest.raises(ValueError, match="calibration_holdout must be one of"):
        RD.holdout_reconstructions(rec, specs, task="leave_one_out", held=held, calibration_holdout="all")


def test_default_thresholds_are_the_command_lines(rec):
    """With no thresholds given, the API picks what ``evaluate holdout``/``overexpose`` pick: explicit
    parameters win; otherwise the recording's declared thresholds, else the self-calibration."""
    with_params = [RD.HoldoutSpec("akf", "akf", "offline", {"contrast_threshold": 0.15})]
    bare = [RD.HoldoutSpec("akf", "akf")]
    assert RD.default_thresholds_for(rec, with_params) == "params"
    assert RD.default_thresholds_for(rec, bare) == RD.default_threshold_source(rec)
    assert RD.default_thresholds_for(rec, with_params + bare) == "params"
