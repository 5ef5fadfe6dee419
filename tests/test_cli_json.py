"""``--json`` on every command with a result: exactly one JSON object on stdout, nothing else."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from hybridhdr.cli import build_parser, main

#: commands without a result to report (a guided tour that prints as it goes)
NO_JSON = {"demo"}


def _leaves(p, name=()):
    subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield " ".join(name), p
    for a in subs:
        for k, c in a.choices.items():
            yield from _leaves(c, name + (k,))


def test_every_command_with_a_result_offers_json():
    leaves = dict(_leaves(build_parser()))
    assert {"calibrate crf", "calibrate rig", "capture sync", "evaluate bench", "evaluate paper"} <= set(leaves)
    missing = [n for n, p in leaves.items() if n not in NO_JSON and "--json" not in p._option_string_actions]
    assert not missing, f"commands without --json: {missing}"
    for n in NO_JSON:
        assert "--json" not in leaves[n]._option_string_actions


def _run_json(capsys, *argv, rc=0):
    code = main([str(a) for a in argv] + ["--json"])
    cap = capsys.readouterr()
    assert code == rc, cap.err
    text = cap.out
    assert text.endswith("\n") and text.count("\n") == 1, f"more than one line on stdout: {text!r}"
    obj = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert isinstance(obj, dict)
    return obj, cap.err


# -- capture ------------------------------------------------------------------------------------

def test_capture_record_recover_session_json(procedural_rec_file, tmp_path, capsys):
    from hybridhdr.capture.recorder import Recorder, journal_path
    from hybridhdr.capture.sources import SyntheticEventSource
    src, rec = procedural_rec_file
    out = tmp_path / "r.h5"
    res, err = _run_json(capsys, "capture", "record", "--events", src, "--frames", src, "--out", out,
                         "--pace", "fast", "--no-progress")
    assert res["events_written"] == len(rec.events) and res["frames_written"] == len(rec.frames)
    assert res["out"] == str(out) and res["dropped_anything"] is False
    assert "recording to" in err  # the notes go to stderr
    # recover after a "crash"
    s = SyntheticEventSource(1e5, sensor_size=(8, 8), chunk_us=1_000, duration_s=0.005, pace="fast")
    r = Recorder(tmp_path / "c.h5", s)
    r.start()
    r.wait()
    r.stop()
    r._jw.close()
    res, err = _run_json(capsys, "capture", "recover", tmp_path / "c.h5")
    assert res["events"] == 500 and res["output"] == str(tmp_path / "c.h5") and res["journal_kept"] is False
    assert not journal_path(tmp_path / "c.h5").exists()
    # session: create, verify OK, verify FAILED (rc 1, still one JSON object)
    res, _ = _run_json(capsys, "capture", "session", tmp_path / "seq", "--recording", src)
    assert res["session"] == str(tmp_path / "seq") and (tmp_path / "seq" / "manifest.json").is_file()
    res, _ = _run_json(capsys, "capture", "session", "--verify", tmp_path / "seq")
    assert res["ok"] is True and res["missing"] == []
    (tmp_path / "seq" / "recording.h5").write_bytes(b"x")
    res, _ = _run_json(capsys, "capture", "session", "--verify", tmp_path / "seq", rc=1)
    assert res["ok"] is False and res["changed"]


def test_capture_sync_json(tmp_path, capsys):
    from hybridhdr import make_triggers
    from hybridhdr.capture.sources import SyntheticEventSource
    from hybridhdr.container import write_recording
    from hybridhdr.model import Frames, Recording
    n, period = 30, 20_000
    fs = 500_000 + period * np.arange(n, dtype=np.int64)
    frames = Frames(np.zeros((n, 3, 3), np.uint8), fs, fs + 4_000, encoding="raw")
    ts = np.rint(7_000.0 + (1 + 50e-6) * fs).astype(np.int64)
    te = np.rint(7_000.0 + (1 + 50e-6) * (fs + 4_000)).astype(np.int64)
    trig = make_triggers(np.sort(np.concatenate([ts, te])), 3, np.tile([1, -1], n))
    ev = SyntheticEventSource(1e4, sensor_size=(3, 3), chunk_us=100_000, pace="fast").base
    write_recording(Recording(ev, (3, 3), frames, trig), tmp_path / "s.h5")
    res, err = _run_json(capsys, "capture", "sync", tmp_path / "s.h5", "--trigger-channel", "3", "--out",
                         tmp_path / "s2.h5")
    assert res["n_pairs"] == n and abs(res["drift_ppm"] - 50) < 2 and res["out"] == str(tmp_path / "s2.h5")
    assert "wrote" in err


def test_capture_brackets_json_with_out(tmp_path, capsys):
    import imageio.v3 as iio
    src = tmp_path / "pngs"
    src.mkdir()
    for i, v in enumerate((20, 80, 240)):
        iio.imwrite(src / f"im{i}.png", np.full((6, 8), v, np.uint8))
    (src / "exposures.txt").write_text("im0.png 1/1000\nim1.png 1/250\nim2.png 0.016\n")
    res, _ = _run_json(capsys, "capture", "brackets", src, "--out", tmp_path / "bs")
    assert res["images"] == 3 and res["out"] == str(tmp_path / "bs")


# -- calibrate ----------------------------------------------------------------------------------

def test_calibrate_crf_and_hdr_reference_json(tmp_path, capsys):
    from hybridhdr.simulate.procedural import hdr_scene, render_frame
    from hybridhdr.formats.brackets import write_bracket_set
    rng = np.random.default_rng(4)
    E = hdr_scene(60, 80, seed=2)
    ex = [0.05, 0.2, 0.8, 3.2]
    br = write_bracket_set(tmp_path / "br", [render_frame(E, np.eye(3), t, rng) for t in ex], ex, encoding="gamma",
                           camera={"name": "synthetic"})
    res, err = _run_json(capsys, "calibrate", "crf", br, "--out", tmp_path / "cal", "--no-progress")
    assert res["n_images"] == 4 and res["sigma2_im"] > 0 and res["out"] == str(tmp_path / "cal")
    assert json.loads((tmp_path / "cal" / "report.json").read_text())["sigma2_im"] == res["sigma2_im"]
    assert "crf (debevec)" in err  # the human summary moved to stderr
    res, _ = _run_json(capsys, "calibrate", "hdr-reference", br, "--out", tmp_path / "ref.exr", "--crf",
                       tmp_path / "cal" / "crf.json", "--no-progress")
    assert res["reference"] == str(tmp_path / "ref.exr") and res["shape"][:2] == [60, 80]
    assert (tmp_path / "ref.exr").is_file()


def test_calibrate_rig_json(shared_data, tmp_path, capsys):
    d = shared_data("checkerboard/opencv_stereo")
    left = sorted(d.glob("left*.jpg"))[:5]
    right = sorted(d.glob("right*.jpg"))[:5]
    res, err = _run_json(capsys, "calibrate", "rig", "--left", *left, "--right", *right, "--board", "9x6",
                         "--square-mm", "25", "--detector-frames", "classic", "--detector-events", "classic",
                         "--prune-factor", "0", "--out", tmp_path / "lr", "--no-progress")
    assert res["board_found"] == {"left": 5, "right": 5} and res["stereo"]["baseline_m"] > 0
    assert "calibration.json" in res["written"] and "stereo:" in err


# -- evaluate -----------------------------------------------------------------------------------

TINY = """
[bench]
name = "cli"
seed = 1
warmup = false
jod = false
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
method = "cf"
"""


def test_evaluate_bench_json(tmp_path, capsys):
    toml = tmp_path / "b.toml"
    toml.write_text(TINY)
    res, err = _run_json(capsys, "evaluate", "bench", toml, "--out", tmp_path / "o", "--workers", "0",
                         "--no-progress")
    assert res["bench"] == "cli" and res["runs"] == 2 and res["failed"] == 0
    assert [s["method"] for s in res["summary"]] == ["akf", "cf"] and 0 < res["summary"][0]["ssim"] <= 1
    assert res["akf_vs_cf"]["datasets"] == ["p"]
    assert res["written"]["report_html"] == str(tmp_path / "o" / "report.html")
    assert "| p | akf |" in err


def test_evaluate_paper_json(tmp_path, capsys, monkeypatch):
    """The paper command's JSON (on a tiny stand-in of the paper's bench: the real one takes a minute)."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib

    from hybridhdr.evaluate import paper
    tiny = tomllib.loads(TINY)

    def small(quick, **kw):
        b = {k: v for k, v in tiny.items()}
        b["datasets"] = [dict(tiny["datasets"][0], name=n) for n in ("HDR:p", "AHDR:p")]
        return b
    monkeypatch.setattr(paper, "paper_bench", small)
    res, err = _run_json(capsys, "evaluate", "paper", "--quick", "--out", tmp_path / "pp", "--workers", "0",
                         "--no-progress", "--no-jod")
    assert res["runs"] == 4 and res["failed"] == 0 and res["quick"] is True
    assert set(res["table"]["cells"]) >= {"akf|HDR", "cf|HDR", "akf|AHDR", "cf|AHDR"}
    assert res["written"]["table1_md"] == str(tmp_path / "pp" / "table1.md")
    assert "Table 1" in err
