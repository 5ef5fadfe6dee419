"""Small things a new user trips on: each a check that failed before it was fixed."""

from __future__ import annotations

import ast
import json
import re

import numpy as np
import pytest

from hybridhdr.cli import main


def test_format_hint_python_half_is_valid_python(tmp_path, capsys):
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"\x01\x02 no events here " * 8)
    assert main(["info", str(junk)]) == 1
    err = capsys.readouterr().err
    assert "--format NAME on the command line" in err and "--from NAME in Python" not in err
    py = re.search(r"line, (.*) in Python\)", err).group(1)
    ast.parse(py)  # hybridhdr.read(path, format='NAME')
    assert "format=" in py


@pytest.fixture
def plain_h5(tmp_path):
    import h5py
    p = tmp_path / "plain.h5"
    with h5py.File(p, "w") as f:
        g = f.create_group("events")
        n = 100
        g["t"] = np.arange(n, dtype=np.int64) * 10
        g["x"] = np.arange(n, dtype=np.uint16) % 30
        g["y"] = np.arange(n, dtype=np.uint16) % 20
        g["p"] = (np.arange(n) % 2).astype(np.uint8)
        f.attrs["height"], f.attrs["width"] = 20, 30
    return p


def test_plain_hdf5_events_error_lists_groups_and_suggests_dsec(plain_h5, capsys):
    assert main(["info", str(plain_h5)]) == 1
    err = capsys.readouterr().err
    assert "/events" in err and "p, t, x, y" in err and "--format dsec" in err
    assert main(["info", str(plain_h5), "--format", "dsec", "--json"]) == 0  # and the hint works
    info = json.loads(capsys.readouterr().out)
    assert info["events"] == 100 and info["sensor"] == "30x20"


def test_write_picks_evt3_by_name(tmp_path):
    import hybridhdr as hh
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording((20, 30), 50_000, seed=0)
    ev_only = hh.Recording(events=rec.events, sensor_size=rec.sensor_size)
    for name, fmt in (("x_evt3.raw", "evt3"), ("plain.raw", "evt2"), ("x_evt2.raw", "evt2")):
        p = hh.write(ev_only, tmp_path / name)
        assert hh.detect_format(p) == fmt, name
        np.testing.assert_array_equal(hh.read(p).events, rec.events)
    with pytest.raises(hh.UnknownFormatError, match="'evt21' can be read but not written"):  # says so
        hh.write(ev_only, tmp_path / "rec_evt21.raw")


@pytest.mark.parametrize("gain", ["0.5", "1", "1,4"])
def test_overexpose_gain_must_exceed_one(gain, tmp_path, capsys):
    rc = main(["evaluate", "overexpose", str(tmp_path / "r.h5"), "--gain", gain, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "> 1" in err, err


def test_overexpose_api_gain_must_exceed_one():
    from hybridhdr.evaluate.overexpose import evaluate_overexpose
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording((20, 30), 200_000, seed=0)
    with pytest.raises(ValueError, match="> 1"):
        evaluate_overexpose(rec, [1.0])


def test_rig_few_views_advice_stays_within_poses_range(shared_data, tmp_path, capsys):
    from hybridhdr._util.cliargs import BLINKING_BOARD_MAX_POSES
    from hybridhdr.simulate.builtin import builtin_scene
    board = shared_data("checkerboard/opencv_stereo")
    rc = main(["calibrate", "rig", "--left", str(board / "left0[1-5].jpg"), "--right", str(board / "right0[1-5].jpg"),
               "--board", "9x6", "--square-mm", "25", "--out", str(tmp_path / "rig"), "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    warnings = json.loads((tmp_path / "rig" / "report.json").read_text())["warnings"]
    assert warnings
    for w in warnings:  # advice a user can follow: a --poses value the simulator accepts
        assert re.search(r"--poses \d+", w), w
        for n in re.findall(r"--poses (\d+)", w):
            assert 1 <= int(n) <= BLINKING_BOARD_MAX_POSES, w
    builtin_scene("builtin:blinking_checkerboard", poses=BLINKING_BOARD_MAX_POSES, duration_s=0.1)
    with pytest.raises(ValueError, match=f"1..{BLINKING_BOARD_MAX_POSES}"):
        builtin_scene("builtin:blinking_checkerboard", poses=BLINKING_BOARD_MAX_POSES + 1, duration_s=0.1)


def test_reconstruct_refuses_a_non_empty_out_before_self_calibrating(tmp_path, capsys, monkeypatch):
    import hybridhdr.calibrate.selfcal as selfcal
    from hybridhdr.formats.container import write_recording
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording((20, 30), 200_000, seed=0)  # declares no thresholds: self-calibrated
    src = write_recording(rec, tmp_path / "r.h5")
    calls = []
    monkeypatch.setattr(selfcal, "self_calibration", lambda *a, **k: calls.append(1) or 1 / 0)
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    rc = main(["reconstruct", str(src), "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "not empty" in err and not calls, err
    assert (out / "mine.txt").read_text() == "keep"


def test_calibrate_crf_prints_width_x_height(shared_data, tmp_path, capsys):
    src = shared_data("brackets/memorial")
    assert main(["calibrate", "crf", str(src), "--out", str(tmp_path / "crf"), "--ignore-colour", "0,0,255",
                 "--no-progress"]) == 0
    err = capsys.readouterr().err
    from hybridhdr.formats.brackets import read_bracket_set
    h, w = read_bracket_set(src).shape[:2]
    assert f"images {w}x{h} RGB" in err and f"({h}, {w}" not in err, err

