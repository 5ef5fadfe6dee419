"""One overwrite rule for the verbs that write an output folder: ``calibrate crf``, ``calibrate
thresholds``, ``calibrate rig`` and ``capture brackets`` refuse an existing non-empty output without
``--overwrite`` (as ``reconstruct``, ``convert`` and ``calibrate sensor`` do), and refuse an output
that is one of their inputs even with it. Every refusal comes before any work and changes nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.cli import main
from hybridhdr.formats.brackets import read_bracket_set, write_bracket_set


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def _brackets(folder, exposures=(1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4)):
    """A bracket set of a smooth scene through a gamma curve (5 exposures, 2 stops apart)."""
    yy, xx = np.mgrid[0:24, 0:32]
    radiance = np.exp(-5.0 + 7.0 * xx / 31 + 0.3 * np.sin(yy / 4.0))
    imgs = [np.clip(np.round(255 * np.clip(radiance * t, 0, 1) ** (1 / 2.2)), 0, 255).astype(np.uint8)
            for t in exposures]
    return write_bracket_set(folder, imgs, list(exposures), encoding="gamma")


def _users_folder(path):
    path.mkdir()
    (path / "notes.txt").write_text("mine")
    return path


def _untouched(path):
    return sorted(p.name for p in path.iterdir()) == ["notes.txt"] and (path / "notes.txt").read_text() == "mine"


def _recording(path):
    from hybridhdr.formats.container import write_recording
    rng = np.random.default_rng(0)
    n = 500
    ev = hh.make_events(np.sort(rng.integers(0, 100_000, n)), rng.integers(0, 32, n), rng.integers(0, 24, n),
                        rng.choice([-1, 1], n))
    frames = hh.Frames(np.full((4, 24, 32), 100, np.uint8), np.arange(4) * 30_000, np.arange(4) * 30_000 + 5_000)
    return write_recording(hh.Recording(ev, (24, 32), frames), path)


# -- calibrate crf ------------------------------------------------------------------------------


def test_calibrate_crf_refuses_a_non_empty_out_then_replaces_its_own_files(tmp_path, capsys):
    bs = _brackets(tmp_path / "bs")
    out = _users_folder(tmp_path / "out")
    rc, _, err = _run(["calibrate", "crf", bs, "--out", out, "--no-progress"], capsys)
    assert rc != 0 and "--overwrite" in err and _untouched(out)
    rc, _, err = _run(["calibrate", "crf", bs, "--out", out, "--no-progress", "--overwrite"], capsys)
    assert rc == 0, err
    assert {"crf.json", "camera_profile.json", "report.json", "notes.txt"} <= {p.name for p in out.iterdir()}
    assert (out / "notes.txt").read_text() == "mine"  # what crf does not write is left alone


def test_calibrate_crf_refuses_out_that_is_its_brackets(tmp_path, capsys):
    bs = _brackets(tmp_path / "bs")
    before = sorted(p.name for p in bs.iterdir())
    rc, _, err = _run(["calibrate", "crf", bs, "--out", bs, "--overwrite", "--no-progress"], capsys)
    assert rc != 0 and "input" in err and sorted(p.name for p in bs.iterdir()) == before


# -- calibrate thresholds ------------------------------------------------------------------------


def test_calibrate_thresholds_refuses_a_non_empty_out(tmp_path, capsys):
    rec = _recording(tmp_path / "r.h5")
    out = _users_folder(tmp_path / "out")
    rc, _, err = _run(["calibrate", "thresholds", rec, "--out", out], capsys)
    assert rc != 0 and "--overwrite" in err and _untouched(out)


def test_calibrate_thresholds_refuses_out_that_is_the_recording(tmp_path, capsys):
    rec = _recording(tmp_path / "r.h5")
    before = rec.read_bytes()
    rc, _, err = _run(["calibrate", "thresholds", rec, "--out", rec, "--overwrite"], capsys)
    assert rc != 0 and "input" in err and rec.read_bytes() == before


# -- calibrate rig -------------------------------------------------------------------------------


def _rig_argv(left, right, out):
    return ["calibrate", "rig", "--left", left, "--right", right, "--board", "9x6", "--square-mm", "20",
            "--out", out, "--no-progress"]


def test_calibrate_rig_refuses_a_non_empty_out(tmp_path, capsys):
    left, right = _users_folder(tmp_path / "left"), _users_folder(tmp_path / "right")
    out = _users_folder(tmp_path / "out")
    rc, _, err = _run(_rig_argv(left, right, out), capsys)
    assert rc != 0 and "--overwrite" in err and _untouched(out)


def test_calibrate_rig_refuses_out_that_is_an_input(tmp_path, capsys):
    left, right = _users_folder(tmp_path / "left"), _users_folder(tmp_path / "right")
    rc, _, err = _run(_rig_argv(left, right, left) + ["--overwrite"], capsys)
    assert rc != 0 and "input" in err and _untouched(left)


# -- capture brackets ----------------------------------------------------------------------------


def test_capture_brackets_refuses_a_non_empty_out_then_replaces_the_set(tmp_path, capsys):
    src = _brackets(tmp_path / "src")
    out = _brackets(tmp_path / "out", exposures=(0.5, 1.0))  # an older set, with fewer images
    (out / "notes.txt").write_text("mine")
    old = json.loads((out / "brackets.json").read_text())
    rc, _, err = _run(["capture", "brackets", src, "--out", out], capsys)
    assert rc != 0 and "--overwrite" in err and json.loads((out / "brackets.json").read_text()) == old
    rc, _, err = _run(["capture", "brackets", src, "--out", out, "--overwrite"], capsys)
    assert rc == 0, err
    got, want = read_bracket_set(out), read_bracket_set(src)
    assert got.exposures_s.tolist() == pytest.approx(want.exposures_s.tolist())
    assert all(np.array_equal(a, b) for a, b in zip(got.images, want.images))
    assert (out / "notes.txt").read_text() == "mine"
    assert not [p for p in out.iterdir() if p.name.startswith(".hybridhdr-staging")]


def test_capture_brackets_refuses_a_plot_that_exists(tmp_path, capsys):
    src = _brackets(tmp_path / "src")
    sheet = tmp_path / "sheet.png"
    sheet.write_bytes(b"my picture")
    rc, _, err = _run(["capture", "brackets", src, "--plot", sheet], capsys)
    assert rc != 0 and "--overwrite" in err and sheet.read_bytes() == b"my picture"


@pytest.mark.parametrize("target", ["folder", "image"])
def test_capture_brackets_refuses_an_output_that_is_an_input(tmp_path, capsys, target):
    src = _brackets(tmp_path / "src")
    before = {p.name: p.read_bytes() for p in src.iterdir()}
    argv = (["--out", src] if target == "folder" else ["--plot", src / "exp_000.png"])
    rc, _, err = _run(["capture", "brackets", src, *argv, "--overwrite"], capsys)
    assert rc != 0 and "input" in err and {p.name: p.read_bytes() for p in src.iterdir()} == before
