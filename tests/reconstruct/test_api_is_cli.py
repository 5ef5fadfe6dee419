"""The API is the command line: ``reconstruct(rec, "akf")`` with no parameters runs the calibrated
model, output span and defaults of ``hybridhdr reconstruct REC --method akf``; explicit parameters
still win; the docs' example gives the command line's frames."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

import hybridhdr
from hybridhdr.cli import main
from hybridhdr.formats import images as IM
from hybridhdr.formats.container import write_recording
from hybridhdr.model import Recording
from hybridhdr.reconstruct import AKFParams, reconstruct

from ..conftest import shared_file

DOCS = Path(__file__).resolve().parents[2] / "docs" / "reconstruct.md"


def _cli_frames(tmp_path, rec_path, *extra, name="cli"):
    out = tmp_path / name
    assert main(["reconstruct", str(rec_path), "--method", "akf", "--out", str(out), "--no-progress", "-q",
                 *extra]) == 0
    rows = [ln.split() for ln in (out / "timestamps.txt").read_text().splitlines() if not ln.startswith("#")]
    t = np.array([int(r[0]) for r in rows], np.int64)
    frames = np.stack([IM.read_exr(out / r[1]) for r in rows])
    return t, frames, json.loads((out / "run.json").read_text())


@pytest.fixture(scope="module")
def undeclared(tmp_path_factory):
    """A procedural recording (30x40, 0.3 s, 25 Hz frames, c = 0.15) that declares no thresholds,
    written to a container: the command line's default self-calibrates it."""
    from hybridhdr.simulate.procedural import procedural_recording
    r, _ = procedural_recording((30, 40), 300_000, contrast_threshold=0.15, frame_rate_hz=25.0, step_us=500)
    rec = Recording(r.events, r.sensor_size, r.frames)
    path = tmp_path_factory.mktemp("undeclared") / "rec.h5"
    write_recording(rec, path)
    return path, hybridhdr.read(path)


@pytest.mark.parametrize("extra", [(), ("--fps", "300"), ("--mode", "causal", "--fps", "200")])
def test_api_without_parameters_gives_the_command_lines_frames(tmp_path, undeclared, extra):
    path, rec = undeclared
    t_cli, f_cli, run = _cli_frames(tmp_path, path, *extra)
    kw = {}
    if "--fps" in extra:
        kw["fps"] = float(extra[extra.index("--fps") + 1])
    if "--mode" in extra:
        kw["mode"] = extra[extra.index("--mode") + 1]
    for src in (rec, path):  # in memory and from the file
        v = reconstruct(src, "akf", **kw)
        np.testing.assert_array_equal(v.t_us, t_cli)
        np.testing.assert_array_equal(v.frames, f_cli)  # EXR float32, the API's frames float32
    assert "self_calibration" in run and isinstance(v.info["self_calibration"], dict)
    assert v.info.get("frame_time_offset_us", 0) == run["self_calibration"]["time_offset_us"]
    assert v.params["intensity_offset"] == run["self_calibration"]["intensity_offset"]


def test_explicit_parameters_and_words_still_win(undeclared):
    path, rec = undeclared
    d = reconstruct(rec, "akf", fps=300)
    assert isinstance(d.info["self_calibration"], dict)
    p = reconstruct(rec, "akf", AKFParams(), fps=300)  # an instance states its thresholds: no calibration
    assert "self_calibration" not in p.info and p.params["contrast_threshold_on"] in (None, 0.1)
    assert p.params["intensity_offset"] == AKFParams().intensity_offset
    q = reconstruct(rec, "akf", {"contrast_threshold": 0.2}, fps=300)
    assert "self_calibration" not in q.info and q.params["contrast_threshold"] == 0.2
    i = reconstruct(rec, "akf", fps=300, thresholds="input")  # the recording declares none: the defaults
    assert "self_calibration" not in i.info
    np.testing.assert_array_equal(i.frames, p.frames)
    # the span: --fps outputs stop at the last event, as the command line's --until events
    last = int(rec.events["t"][-1])
    assert d.t_us[-1] <= last < d.t_us[-1] + int(1e6 / 300) + 1
    np.testing.assert_array_equal(i.t_us, p.t_us)


def test_a_recording_that_declares_thresholds_keeps_them(undeclared):
    from hybridhdr.model import CameraInfo, Metadata
    _, rec = undeclared
    ss = rec.sensor_size
    md = Metadata(CameraInfo(ss, contrast_threshold_on=0.15, contrast_threshold_off=0.17), CameraInfo(ss))
    v = reconstruct(Recording(rec.events, ss, rec.frames, metadata=md), "akf", fps=100)
    assert "self_calibration" not in v.info and "declared" in v.info["thresholds"]
    assert (v.params["contrast_threshold_on"], v.params["contrast_threshold_off"]) == (0.15, 0.17)


# ECD frames do not bound the log offset I0: self-calibration warns that it lies on its grid's
# upper edge (the calibration is told apart in tests/calibrate); this test is about what follows
@pytest.mark.filterwarnings("ignore::hybridhdr.calibrate.camera_model.GridEdgeWarning")
@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::hybridhdr.calibrate.camera_model.GridEdgeWarning")  # ECD: I0 unbounded (test_ecd_profile)
def test_docs_example_gives_the_command_lines_frames(tmp_path):
    """The first example of docs/reconstruct.md, run on ecd_slider_depth, equals ``hybridhdr
    reconstruct ecd_slider_depth --method akf --fps 300``."""
    ecd = shared_file("ecd_slider_depth")
    text = DOCS.read_text()
    line = next(ln for ln in text.splitlines() if ln.startswith("video = reconstruct(rec"))
    call = re.match(r"video = (reconstruct\(rec, [^#]*\))", line).group(1).strip()
    assert call == 'reconstruct(rec, "akf", fps=300)', call  # the example states no parameters
    rec = hybridhdr.read(ecd)
    video = eval(call, {"reconstruct": reconstruct, "rec": rec})  # noqa: S307 - the docs' own line
    t, f, run = _cli_frames(tmp_path, ecd, "--fps", "300")
    np.testing.assert_array_equal(video.t_us, t)
    np.testing.assert_array_equal(video.frames, f)
    assert video.info["self_calibration"]["c_on"] == run["self_calibration"]["c_on"]
