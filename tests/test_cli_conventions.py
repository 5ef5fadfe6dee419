"""One CLI style across the verbs (conventions in hybridhdr/_util/cliargs.py)."""

import argparse
import json
import re

import pytest

from hybridhdr.cli import build_parser, main


def run_cli(capsys, *argv):
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def leaves(parser, path=()):
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
        return
    for a in subs:
        for name, child in a.choices.items():
            if child is not parser and name not in [p for p in path]:
                yield from leaves(child, path + (name,))


def all_leaves():
    seen = {}
    for path, p in leaves(build_parser()):
        seen.setdefault(id(p), (path, p))
    return list(seen.values())


def test_every_command_has_the_common_options_and_no_abbreviations():
    found = all_leaves()
    names = {" ".join(p) for p, _ in found}
    assert {"info", "convert", "demo", "view", "reconstruct", "simulate", "calibrate crf", "calibrate hdr-reference",
            "calibrate rig", "calibrate thresholds", "capture recover", "capture devices", "evaluate paper",
            "evaluate metrics"} <= names
    for path, p in found:
        opts = p._option_string_actions
        for o in ("--debug", "--no-progress", "-q", "--quiet", "-v", "--verbose"):
            assert o in opts, (path, o)
        assert p.allow_abbrev is False and p.prog == "hybridhdr " + " ".join(path)


def test_help_prints_defaults_once_and_none_for_required():
    for path, p in all_leaves():
        text = p.format_help()
        assert "(default: None)" not in text, path
        for act in p._actions:
            h = p._get_formatter()._get_help_string(act) or ""
            if act.required and act.option_strings:
                assert "(default:" not in h, (path, act.option_strings)
        # rendered help: no option shows two "(default: ...)"
        blocks = re.split(r"\n  (?=-)", text)
        assert not [b for b in blocks if b.count("(default:") > 1], path


def test_no_abbreviation_and_full_error_prefix(tmp_path, capsys):
    rc, _, err = run_cli(capsys, "reconstruct", tmp_path / "x.h5", "--out", tmp_path / "o", "--fp", "300")
    assert rc == 2 and "hybridhdr reconstruct: error: unrecognized arguments: --fp 300" in err
    rc, _, err = run_cli(capsys, "calibrate", "crf", tmp_path / "nothing", "--out", tmp_path / "crf")
    assert rc == 1 and err.startswith("hybridhdr calibrate crf: error:"), err
    rc, _, err = run_cli(capsys, "calibrate", "crf", tmp_path / "nothing", "--out", tmp_path / "crf", "--bogus")
    assert rc == 2 and "hybridhdr calibrate crf: error: unrecognized arguments: --bogus" in err
    rc, _, err = run_cli(capsys, "capture", "recover", tmp_path / "none.h5", "--no-progress")
    assert rc == 1 and err.startswith("hybridhdr capture recover: error:"), err


def test_hints_in_cli_wording(tmp_path, capsys):
    from hybridhdr._util.cliargs import cli_wording
    assert cli_wording("needs frames (use method='highpass' for events only)") == \
        "needs frames (use --method highpass for events only)"
    assert cli_wording("x=3, fps=30") == "x=3, --fps 30"
    import hybridhdr as hh
    from hybridhdr.formats.container import write_recording
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording((20, 30), 50_000, seed=0)
    write_recording(hh.Recording(events=rec.events, sensor_size=rec.sensor_size), tmp_path / "ev.h5")
    rc, _, err = run_cli(capsys, "reconstruct", tmp_path / "ev.h5", "--method", "akf", "--out", tmp_path / "o",
                         "--no-progress")
    assert rc != 0 and "--method highpass" in err and "method='" not in err, err


def test_quiet_and_json(tmp_path, capsys):
    from hybridhdr.formats.container import write_recording
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording((20, 30), 50_000, seed=0)
    src = write_recording(rec, tmp_path / "s.h5")
    rc, out, err = run_cli(capsys, "convert", src, tmp_path / "o.dat", "-q")
    assert rc == 0 and err == "" and "wrote" in out  # the note about dropped frames is silenced
    rc, out, err = run_cli(capsys, "info", src, "--json")
    assert json.loads(out)["events"] == len(rec.events)
    with pytest.raises(SystemExit):  # commands without a JSON result do not offer --json
        build_parser().parse_args(["demo", "--out", "o", "--json"])


def test_capture_devices_json_prints_empty_list(capsys, monkeypatch):
    import hybridhdr.capture.devices as d
    monkeypatch.setattr(d, "list_devices", lambda include_unknown=False: [])
    rc, out, err = run_cli(capsys, "capture", "devices", "--json")
    assert rc == 0 and json.loads(out) == []
    rc, out, err = run_cli(capsys, "capture", "devices")
    assert rc == 1 and "no device found" in err


def test_one_name_per_rate():
    p = build_parser()
    a = p.parse_args(["simulate", "builtin:slow_static", "--out", "x.h5", "--fps", "25", "--gt-fps", "100"])
    b = p.parse_args(["simulate", "builtin:slow_static", "--out", "x.h5", "--frame-rate-hz", "25", "--gt-rate-hz",
                      "100"])
    assert a.frame_rate_hz == b.frame_rate_hz == 25 and a.gt_rate_hz == b.gt_rate_hz == 100
    r = p.parse_args(["reconstruct", "x.h5", "--out", "o", "--fps", "300", "--playback-fps", "24"])
    v = p.parse_args(["view", "x.h5", "--out", "o.mp4", "--fps", "300", "--playback-fps", "24"])
    assert r.fps == v.fps == 300 and r.playback_fps == v.playback_fps == 24


def test_simulate_sensor_flags_and_board_poses():
    from hybridhdr.simulate.cli import load_any_scene, sensor_params
    p = build_parser()
    a = p.parse_args(["simulate", "builtin:blinking_checkerboard", "--out", "x.h5", "--preset", "clean",
                      "--pos-thres", "0.3", "--neg-thres", "0.25", "--sigma-thres", "0.05", "--cutoff-hz", "200",
                      "--leak-rate-hz", "0.1", "--shot-noise-rate-hz", "2", "--refractory-period-us", "100",
                      "--poses", "4"])
    s = sensor_params(a)
    assert (s.contrast_threshold_on, s.contrast_threshold_off, s.threshold_mismatch_sigma, s.photoreceptor_cutoff_hz,
            s.leak_rate_hz, s.shot_noise_rate_hz, s.refractory_period_us) == (0.3, 0.25, 0.05, 200, 0.1, 2, 100)
    clean = sensor_params(p.parse_args(["simulate", "builtin:slow_static", "--out", "x.h5"]))
    assert clean.refractory_period_us == 500 and clean.contrast_threshold_on == 0.2  # the preset untouched
    scene = load_any_scene(a.scene, board_options={"poses": a.poses})
    assert len(scene.info["camera_pose_change_times_us"]) == 6  # start and end of the 3 moves
    with pytest.raises(ValueError, match="blinking_checkerboard"):
        load_any_scene("builtin:slow_static", board_options={"poses": 4})
    for bad in (["--pos-thres", "0"], ["--refractory-period-us", "-1"], ["--poses", "0"], ["--fps", "0"]):
        with pytest.raises(SystemExit):
            p.parse_args(["simulate", "builtin:slow_static", "--out", "x.h5", *bad])
