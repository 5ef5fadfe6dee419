"""Time windows on the command line (hybridhdr._util.timearg): units, relative to the recording's first
timestamp, --absolute, deprecated --start-us/--end-us, empty windows are errors naming the span."""

import json

import numpy as np
import pytest

from hybridhdr._util.timearg import parse_time_us
from hybridhdr.cli import main
from hybridhdr.formats.container import RecordingFile, write_recording
from hybridhdr.simulate.procedural import procedural_recording


def run_cli(capsys, *argv):
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.mark.parametrize("text,us", [("2.5s", 2_500_000), ("1500ms", 1_500_000), ("913716224us", 913_716_224),
                                     ("7µs", 7), ("0", 0), ("1", 1_000_000), ("0.5", 500_000), ("1e-3s", 1000),
                                     ("2min", 120_000_000), (" 3 ms ", 3000)])
def test_parse_time(text, us):
    assert parse_time_us(text) == us


@pytest.mark.parametrize("text", ["", "s", "2x", "1.2.3s", "nan", "inf s", "--1s"])
def test_parse_time_rejects(text):
    with pytest.raises(ValueError):
        parse_time_us(text)


def test_readme_example_on_sparklers(tmp_path, capsys, shared_data):
    raw = shared_data("prophesee/sparklers_gen3_evt2.raw")
    rc, out, err = run_cli(capsys, "convert", raw, tmp_path / "a.h5", "--start", "0", "--end", "1s", "--json",
                           "--no-progress")
    assert rc == 0, err
    assert json.loads(out)["events"] == 521_252
    rc, out, _ = run_cli(capsys, "convert", raw, tmp_path / "b.h5", "--start", "50ms", "--end", "60ms", "--json",
                         "--no-progress")
    res = json.loads(out)
    assert res["window_us"] == [913_716_224 + 50_000, 913_716_224 + 60_000] and 0 < res["events"] < 521_252
    # the old absolute-µs spelling still works, and the same window in sensor time gives the same events
    rc, out2, err = run_cli(capsys, "convert", raw, tmp_path / "c.h5", "--start-us", 913_766_224, "--end-us",
                            913_776_224, "--json", "--no-progress")
    assert rc == 0 and "deprecated" in err and json.loads(out2)["events"] == res["events"]
    rc, out3, _ = run_cli(capsys, "convert", raw, tmp_path / "d.h5", "--start", "913766224us", "--end",
                          "913776224us", "--absolute", "--json", "--no-progress")
    assert json.loads(out3)["events"] == res["events"]
    # a window outside the recording's span: absolute 0..1 s is empty -> rc 1, the span named, no output left
    rc, _, err = run_cli(capsys, "convert", raw, tmp_path / "e.h5", "--start-us", 0, "--end-us", 1_000_000,
                         "--no-progress")
    assert rc == 1 and "913,716,224" in err and "0.095871 s" in err and not (tmp_path / "e.h5").exists()
    rc, _, err = run_cli(capsys, "convert", raw, tmp_path / "e.h5", "--start", "2s", "--no-progress")
    assert rc == 1 and "nothing in the time window" in err and not (tmp_path / "e.h5").exists()


def test_window_errors_before_work(tmp_path, capsys):
    rec, _ = procedural_recording((10, 10), 20_000, seed=0)
    src = write_recording(rec, tmp_path / "s.h5")
    for args, msg in ((("--start", "2s", "--end", "1s"), "must be after"),
                      (("--start=-1s",), "before the recording's first timestamp"),
                      (("--start", "1s", "--start-us", "5"), "not both")):
        rc, _, err = run_cli(capsys, "convert", src, tmp_path / "o.h5", *args)
        assert rc == 2 and msg in err and "hybridhdr convert: error:" in err, err
        assert not (tmp_path / "o.h5").exists()
    assert main(["convert", str(src), str(tmp_path / "o.h5"), "--start", "soon"]) == 2
    assert "expected a time" in capsys.readouterr().err


def test_relative_window_on_container(tmp_path, capsys):
    rec, _ = procedural_recording((30, 40), 200_000, seed=1)
    src = write_recording(rec, tmp_path / "src.h5")
    with RecordingFile(src) as r:
        t_ev = int(r.events()["t"][0])
    t0 = min(t_ev, int(rec.frames.t_start_us[0]))
    rc, _, err = run_cli(capsys, "convert", src, tmp_path / "w.h5", "--start", "50ms", "--end", "0.15",
                         "--no-progress")
    assert rc == 0, err
    with RecordingFile(tmp_path / "w.h5") as r:
        ev = r.events()
    sel = rec.events[(rec.events["t"] >= t0 + 50_000) & (rec.events["t"] < t0 + 150_000)]
    assert np.array_equal(ev, sel)


def test_reconstruct_windows_and_until(tmp_path, capsys, shared_data):
    ecd = shared_data("ecd_slider_depth")
    # numeric arguments are checked before any work: no progress bar, no output folder
    for args in (("--fps", "0"), ("--fps", "-5"), ("--start", "500ms", "--end", "100ms"), ("--fp", "300"),
                 ("--workers", "0"), ("--until", "frames")):
        rc, _, err = run_cli(capsys, "reconstruct", ecd, "--out", tmp_path / "bad", *args)
        assert rc == 2 and "hybridhdr reconstruct: error:" in err and "ev/s" not in err and "kev" not in err, args
        assert not (tmp_path / "bad").exists() and not (tmp_path / "bad.partial").exists()
    rc, _, err = run_cli(capsys, "reconstruct", ecd, "--out", tmp_path / "bad", "--start", "5s", "--no-progress")
    assert rc == 1 and "3.33382 s" in err and "0.174156 s" in err and not (tmp_path / "bad").exists()
    # --fps stops at the last event (0.174 s), saying so; --until last runs on to the last frame (3.33 s)
    # (--thresholds params: the frames' own times; self-calibration would move them 7.75 ms)
    rc, out, err = run_cli(capsys, "reconstruct", ecd, "--method", "direct", "--out", tmp_path / "a", "--fps", "300",
                           "--no-exr", "--no-progress", "--json", "--thresholds", "params")
    assert rc == 0, err
    res = json.loads(out)
    assert res["t_last_us"] <= 174_156 and res["frames"] == 53 and "outputs stop at the last event" in err
    rc, out, err = run_cli(capsys, "reconstruct", ecd, "--method", "direct", "--out", tmp_path / "b", "--fps", "300",
                           "--until", "last", "--no-exr", "--no-progress", "--json", "--thresholds", "params")
    res = json.loads(out)
    assert rc == 0 and res["t_last_us"] > 3_300_000 and res["frames"] == 1001 and "outputs stop" not in err
    # relative window: 50 ms .. 100 ms after the first timestamp (t = 0 here: the first frame)
    rc, out, err = run_cli(capsys, "reconstruct", ecd, "--method", "direct", "--out", tmp_path / "c", "--fps", "100",
                           "--start", "50ms", "--end", "100ms", "--no-exr", "--no-progress", "--json", "--thresholds", "params")
    res = json.loads(out)
    assert rc == 0 and res["t_first_us"] == 50_000 and res["t_last_us"] == 90_000
