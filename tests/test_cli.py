"""The command line: help, info on the sample files, convert, demo."""

import json

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.cli import main
from hybridhdr.formats.container import RecordingFile, write_recording
from hybridhdr.simulate.procedural import procedural_recording


def run_cli(capsys, *argv):
    rc = main(list(argv))
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_help_lists_subcommands(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for cmd in ("capture", "calibrate", "simulate", "reconstruct", "evaluate", "info", "convert", "demo"):
        assert cmd in out


# facts from ../shared/reference/formats.md and ../shared/data/README.md
SAMPLES = [
    ("prophesee/sparklers_gen3_evt2.raw", "evt2", 521_252, (95_000, 97_000), 0),
    ("prophesee/evt2_sample.raw", "evt2", 539_481, (49_000, 51_000), 0),
    ("prophesee/evt3_sample.raw", "evt3", 219_596, (8_300, 9_300), 0),
    ("aedat4/sample.aedat4", "aedat4", 111_954, (585_000, 595_000), 0),
    ("ecd_slider_depth", "ecd", 50_000, (170_345, 170_345), 87),
]


@pytest.mark.parametrize("rel,fmt,n,span,frames", SAMPLES, ids=[s[0] for s in SAMPLES])
def test_info_on_sample_files(capsys, shared_data, rel, fmt, n, span, frames):
    path = shared_data(rel)
    rc, out, _ = run_cli(capsys, "info", str(path), "--json")
    assert rc == 0
    info = json.loads(out)
    assert info["format"] == fmt
    assert info["events"] == n
    assert span[0] <= info["span_us"] <= span[1]
    assert info["frames"] == frames
    rc, table, _ = run_cli(capsys, "info", str(path))
    assert rc == 0 and f"{n:,}" in table


def test_info_ecd_details(capsys, shared_data):
    rc, out, _ = run_cli(capsys, "info", str(shared_data("ecd_slider_depth")), "--json")
    info = json.loads(out)
    assert info["t_first_us"] == 3811 and info["t_last_us"] == 174156
    assert info["sensor"] == "240x180"
    assert abs(info["on_fraction"] - 0.42) < 0.01


def test_convert_container_window_and_formats(tmp_path, capsys):
    rec, _ = procedural_recording((30, 40), 200_000, seed=1)
    src = write_recording(rec, tmp_path / "src.h5")
    out = tmp_path / "win.h5"
    rc, stdout, _ = run_cli(capsys, "convert", str(src), str(out), "--start-us", "50000", "--end-us",
                            "150000", "--no-progress")
    assert rc == 0 and "wrote" in stdout
    with RecordingFile(out) as r:
        assert np.array_equal(r.events(), hh.slice_time(rec.events, 50_000, 150_000))
        assert len(r.read_frames()) == len(rec.frames.slice_time(50_000, 150_000))
        assert len(r.read_hdr()) == len(rec.hdr)
    for to, name in (("evt2", "o.raw"), ("evt3", "o3.raw"), ("dat", "o.dat"), ("akf_mat", "o.mat"), ("ecd", "o_ecd")):
        rc, _, err = run_cli(capsys, "convert", str(src), str(tmp_path / name), "--to", to, "--no-progress")
        assert rc == 0, err
        assert np.array_equal(hh.read(tmp_path / name).events, rec.events), to
        if to in ("evt2", "evt3", "dat"):
            assert "cannot hold" in err and "frames" in err  # dropped parts are reported, never silent


def test_cli_errors_are_clear(tmp_path, capsys):
    rc, _, err = run_cli(capsys, "info", str(tmp_path / "missing.raw"))
    assert rc == 1 and "no such file" in err
    (tmp_path / "junk.bin").write_bytes(b"\x00\x01garbage" * 10)
    rc, _, err = run_cli(capsys, "info", str(tmp_path / "junk.bin"))
    assert rc == 1 and "could not detect" in err
    rc, _, err = run_cli(capsys, "info", str(tmp_path / "junk.bin"), "--from", "nosuch")
    assert rc == 1 and "unknown format" in err
    rec, _ = procedural_recording((10, 10), 20_000, seed=0)
    src = write_recording(rec, tmp_path / "s.h5")
    rc, _, err = run_cli(capsys, "convert", str(src), str(tmp_path / "o.h5"), "--start-us", "5", "--end-us", "5")
    assert rc == 2 and "--end-us" in err and not (tmp_path / "o.h5").exists()


def test_demo_runs(demo_run):
    """``hybridhdr demo`` (the run shared with its --help example's test: tests/conftest.py)."""
    rc, out, err, folder = demo_run
    assert rc == 0, err
    assert "identical events" in out and "EVENTS DIFFER" not in out
    assert (folder / "demo_out" / "procedural.h5").exists()  # the default --out


def test_demo_passes_learned_weights_to_table_1(tmp_path, capsys, monkeypatch):
    """demo --weights-e2vid/--weights-firenet: a missing file fails before any work; given files
    reach the paper table (run_paper's ``weights``), where they add the learned columns."""
    rc, out, err = run_cli(capsys, "demo", "--out", str(tmp_path / "d"), "--weights-e2vid", str(tmp_path / "no.pth"))
    assert rc == 1 and "--weights-e2vid" in err and "never downloads" in err
    assert not (tmp_path / "d").exists()
    from hybridhdr.evaluate import bench as B
    from hybridhdr.evaluate import paper as P
    seen = {}
    monkeypatch.setattr(P, "run_paper", lambda out, **kw: seen.update(kw) or "table 1")
    real_load = B.load_bench
    monkeypatch.setattr(B, "load_bench", lambda name, **kw: real_load("tiny"))  # the bench step, small
    w = tmp_path / "e2vid.pth.tar"
    w.write_bytes(b"x")
    text = P.demo_evaluate(tmp_path / "ev", progress=False, weights={"e2vid": w, "firenet": None})
    # Table 1 (then the demo's headline figures)
    assert "\ntable 1\n" in "\n" + text + "\n" and seen["weights"] == {"e2vid": w, "firenet": None}


def test_command_logging_is_undone_after_each_call(capsys):
    # a second main() in one process (a test, a notebook) must not inherit the first call's -q
    # (root at ERROR) nor its handler on a stream that may be closed since
    import logging

    from hybridhdr.cli import _command_logging
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    root.handlers[:] = []
    try:
        with _command_logging(logging.ERROR):
            logging.getLogger("hybridhdr.x").warning("hidden by -q")
        with _command_logging(logging.WARNING):
            logging.getLogger("hybridhdr.x").warning("shown")
        assert root.handlers == [] and root.level == saved[1]
    finally:
        root.handlers[:], _ = saved[0], root.setLevel(saved[1])
    err = capsys.readouterr().err
    assert "hybridhdr.x: shown" in err and "hidden by -q" not in err
