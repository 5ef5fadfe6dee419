"""``hybridhdr capture ...`` through hybridhdr.cli.main (no hardware: device commands exit 1)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hybridhdr import make_triggers
from hybridhdr.capture.recorder import Recorder, journal_path
from hybridhdr.capture.sources import SyntheticEventSource
from hybridhdr.cli import main
from hybridhdr.formats.container import read_recording, write_recording
from hybridhdr.model import Frames, Recording


@pytest.mark.parametrize("argv", [
    ["capture", "devices"],
    ["capture", "brackets", "--device", "oak", "--exposures-us", "1000", "4000", "--out", "OUT"],
    ["capture", "record", "--events", "synthetic:1000", "--frames", "oak", "--out", "OUT", "--duration-s", "1"],
    ["capture", "record", "--events", "prophesee", "--out", "OUT", "--duration-s", "1"],
    ["capture", "record", "--camera", "davis", "--out", "OUT", "--duration-s", "1"],
    ["capture", "brackets", "--device", "pylon", "--exposures-us", "1000", "4000", "--out", "OUT"],
])
def test_device_commands_without_hardware(argv, tmp_path, capsys):
    argv = [str(tmp_path / "o") if a == "OUT" else a for a in argv]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "no device found" in err and "Traceback" not in err
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_record_replay(procedural_rec_file, tmp_path, capsys):
    src, rec = procedural_rec_file
    out = tmp_path / "r.h5"
    assert main(["capture", "record", "--events", str(src), "--frames", str(src), "--out", str(out),
                 "--pace", "fast", "--no-progress", "--flush-interval-s", "0.05"]) == 0
    assert f"{len(rec.events):,} events" in capsys.readouterr().out
    back = read_recording(out)
    np.testing.assert_array_equal(back.events, rec.events)
    np.testing.assert_array_equal(back.frames.images, rec.frames.images)


def test_recover_cli(tmp_path, capsys):
    src = SyntheticEventSource(1e5, sensor_size=(8, 8), chunk_us=1_000, duration_s=0.005, pace="fast")
    r = Recorder(tmp_path / "c.h5", src)
    r.start()
    r.wait()
    r.stop()
    r._jw.close()  # as if killed after the last flush
    assert main(["capture", "recover", str(tmp_path / "c.h5")]) == 0
    assert "recovered" in capsys.readouterr().out
    assert len(read_recording(tmp_path / "c.h5").events) == 500
    assert not journal_path(tmp_path / "c.h5").exists()
    assert main(["capture", "recover", str(tmp_path / "c.h5")]) == 1  # no journal any more
    assert "no journal" in capsys.readouterr().err


def test_sync_cli(tmp_path, capsys):
    n, period = 60, 20_000
    fs = 500_000 + period * np.arange(n, dtype=np.int64)
    frames = Frames(np.zeros((n, 3, 3), np.uint8), fs, fs + 4_000, encoding="raw")
    a, drift = 7_000.0, 50e-6
    ts = np.rint(a + (1 + drift) * fs).astype(np.int64)
    te = np.rint(a + (1 + drift) * (fs + 4_000)).astype(np.int64)
    t = np.sort(np.concatenate([ts, te]))
    trig = make_triggers(t, 3, np.tile([1, -1], n))
    ev = SyntheticEventSource(1e4, sensor_size=(3, 3), chunk_us=100_000, pace="fast").base
    write_recording(Recording(ev, (3, 3), frames, trig), tmp_path / "s.h5")
    out = tmp_path / "s2.h5"
    assert main(["capture", "sync", str(tmp_path / "s.h5"), "--trigger-channel", "3", "--out", str(out),
                 "--report", str(tmp_path / "rep.json"), "--plot", str(tmp_path / "res.png")]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert abs(last["drift_ppm"] - 50) < 1 and last["n_pairs"] == n  # 1.2 s span, 0.29 µs rounding
    np.testing.assert_array_equal(read_recording(out).frames.t_start_us, ts)
    assert json.loads((tmp_path / "rep.json").read_text())["n_pairs"] == n
    assert (tmp_path / "res.png").stat().st_size > 1000


def test_brackets_from_folder(shared_data, capsys):
    folder = shared_data("brackets/memorial")
    assert main(["capture", "brackets", str(folder), "--json"]) == 0
    info = json.loads(capsys.readouterr().out.splitlines()[0])
    assert info["images"] == 16 and info["shape"] == [768, 512, 3]
    # 32 s ... 1/1024 s in one-stop steps (README of the sample)
    assert max(info["exposures_s"]) == pytest.approx(32) and min(info["exposures_s"]) == pytest.approx(1 / 1024)


def test_brackets_list_file_rewrite_and_plot(tmp_path, capsys):
    import imageio.v3 as iio
    src = tmp_path / "jpgs"
    src.mkdir()
    for i, v in enumerate((20, 80, 240)):
        iio.imwrite(src / f"im{i}.png", np.full((6, 8), v, np.uint8))
    (src / "exposures.txt").write_text("im0.png 1/1000\nim1.png 1/250\nim2.png 0.016\n")
    assert main(["capture", "brackets", str(src), "--out", str(tmp_path / "bs"), "--plot",
                 str(tmp_path / "sheet.png")]) == 0
    meta = json.loads((tmp_path / "bs" / "brackets.json").read_text())
    assert [im["exposure_s"] for im in meta["images"]] == pytest.approx([0.001, 0.004, 0.016])
    assert (tmp_path / "sheet.png").stat().st_size > 1000


def test_session_cli(procedural_rec_file, tmp_path, capsys):
    src, _ = procedural_rec_file
    assert main(["capture", "session", str(tmp_path / "seq"), "--recording", str(src)]) == 0
    assert main(["capture", "session", "--verify", str(tmp_path / "seq")]) == 0
    assert capsys.readouterr().out.strip().endswith("OK")
    (tmp_path / "seq" / "recording.h5").write_bytes(b"x")
    assert main(["capture", "session", "--verify", str(tmp_path / "seq")]) == 1
    assert "FAILED" in capsys.readouterr().out
    assert main(["capture", "session", str(tmp_path / "x")]) == 1  # --recording missing: clear error
    assert "--recording" in capsys.readouterr().err


def test_help_texts(capsys):
    for step in ("devices", "record", "brackets", "sync", "recover", "session"):
        with pytest.raises(SystemExit) as e:
            main(["capture", step, "--help"])
        assert e.value.code == 0
    assert "µs" in capsys.readouterr().out
