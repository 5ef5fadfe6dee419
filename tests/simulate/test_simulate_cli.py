"""``hybridhdr simulate`` end to end: builtin scene -> recording -> ``hybridhdr reconstruct``."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from hybridhdr.cli import main  # noqa: E402
from hybridhdr.simulate.builtin import BUILTIN_SCENES  # noqa: E402


def test_list(capsys):
    assert main(["simulate", "--list"]) == 0
    out = capsys.readouterr().out
    for n in BUILTIN_SCENES:
        assert f"builtin:{n}" in out


def test_end_to_end_reconstruct(tmp_path, capsys):
    from hybridhdr.formats.container import read_recording
    rec_path = tmp_path / "rec.h5"
    # a 64x48 blinking checkerboard for 120 ms: the board switches off at 50 ms and on at 100 ms
    rc = main(["simulate", "builtin:blinking_checkerboard", "--width", "64", "--height", "48", "--duration-s", "0.12",
               "--spp", "1", "--preset", "ideal", "--out", str(rec_path), "--frame-rate-hz", "25",
               "--exposure-us", "5000", "--no-progress", "--json"])
    assert rc == 0
    o = capsys.readouterr()
    summary = json.loads(o.out)  # --json: the JSON object alone on stdout, the human lines on stderr
    assert summary["variant"] in ("llvm_ad_mono", "scalar_rgb") and f"variant {summary['variant']}" in o.err
    assert rec_path.exists() and not (tmp_path / "rec.h5.partial").exists()
    rec = read_recording(rec_path)
    assert rec.sensor_size.width == 64 and rec.sensor_size.height == 48
    assert summary["events"] == len(rec.events) > 0
    # the blink edges produce OFF events at 50 ms and ON events at 100 ms
    t, p = rec.events["t"], rec.events["p"]
    assert np.all(p[(t > 45_000) & (t <= 55_000)] == -1) and np.any((t > 45_000) & (t <= 55_000))
    assert np.all(p[(t > 95_000) & (t <= 105_000)] == 1) and np.any((t > 95_000) & (t <= 105_000))
    assert len(rec.frames) == summary["frames"] >= 2
    assert rec.hdr is not None and rec.hdr.images.dtype == np.float32
    prov = json.dumps(rec.metadata.provenance)
    assert "blinking_checkerboard" in prov and summary["variant"] in prov
    out_dir = tmp_path / "akf"
    assert main(["reconstruct", str(rec_path), "--method", "akf", "--out", str(out_dir), "--no-progress"]) == 0
    assert (out_dir / "timestamps.txt").exists()
    assert len(list(out_dir.glob("*.exr"))) == len(rec.frames)


def test_fixed_rate_and_preview(tmp_path, capsys):
    rec_path = tmp_path / "fixed.h5"
    assert main(["simulate", "builtin:slow_static", "--width", "32", "--height", "24", "--duration-s", "0.02",
                 "--spp", "1", "--fixed-rate-hz", "500", "--no-frames", "--out", str(rec_path), "--no-progress",
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["renders"] == 11  # 0, 2, ..., 20 ms
    png = tmp_path / "strip.png"
    assert main(["simulate", "builtin:slow_static", "--width", "32", "--height", "24", "--preview", str(png),
                 "--preview-frames", "2"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_toml_scene(tmp_path):
    from hybridhdr.simulate.builtin import builtin_scene
    from hybridhdr.simulate.scene import save_scene
    p = save_scene(builtin_scene("slow_static", width=32, height=24, duration_s=0.02, spp=1), tmp_path / "s.toml")
    assert main(["simulate", str(p), "--out", str(tmp_path / "r.h5"), "--no-frames", "--no-progress"]) == 0
    assert (tmp_path / "r.h5").exists()


@pytest.mark.parametrize("argv, needle", [
    (["simulate", "builtin:teapot", "--out", "x.h5"], "unknown built-in scene"),
    (["simulate", "builtin:slow_static"], "--out"),
    (["simulate"], "--list"),
    (["simulate", "builtin:slow_static", "--width", "32", "--out", "x.h5"], "--height"),
    (["simulate", "nope.toml", "--out", "x.h5"], "not found"),
])
def test_errors(tmp_path, monkeypatch, capsys, argv, needle):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 1
    assert needle in capsys.readouterr().err


def test_failures_leave_no_partial(tmp_path, monkeypatch):
    # an exception during the run (here: the third render), and a writer that fails creating its file:
    # no half-written REC.h5.partial, only the renders made so far in the resumable REC.h5.resume
    from hybridhdr.simulate import render as R
    out = tmp_path / "rec.h5"
    calls = {"n": 0}
    real = R.MitsubaSource.render

    def flaky(self, t_us):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("renderer failed")
        return real(self, t_us)

    monkeypatch.setattr(R.MitsubaSource, "render", flaky)
    args = ["simulate", "builtin:slow_static", "--width", "32", "--height", "24", "--duration-s", "0.05",
            "--spp", "1", "--out", str(out), "--no-progress"]
    with pytest.raises(RuntimeError, match="renderer failed"):
        main(args)
    assert calls["n"] == 3 and [p.name for p in tmp_path.iterdir()] == ["rec.h5.resume"]
    (tmp_path / "rec.h5.resume").unlink()
    monkeypatch.setattr(R.MitsubaSource, "render", real)

    import hybridhdr.formats.container as C

    def bad_open(self):
        open(self.tmp_path, "wb").close()
        raise OSError("disk full")

    monkeypatch.setattr(C.RecordingWriter, "_open", bad_open)
    assert main(args) != 0  # reported as "hybridhdr simulate: error: disk full"
    assert [p.name for p in tmp_path.iterdir()] == ["rec.h5.resume"]


@pytest.mark.slow
def test_sigterm_leaves_no_partial(tmp_path):
    # a run ended by SIGTERM removes its REC.h5.partial (SystemExit through the writer's abort) and
    # keeps its renders in REC.h5.resume
    import signal
    import subprocess
    import sys
    import time
    out = tmp_path / "rec.h5"
    partial = tmp_path / "rec.h5.partial"
    with subprocess.Popen([sys.executable, "-m", "hybridhdr", "simulate", "builtin:night_drive_sign", "--width", "32",
                           "--height", "24", "--duration-s", "30", "--spp", "1", "--fixed-rate-hz", "2000",
                           "--out", str(out), "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          text=True) as p:
        try:
            t_end = time.monotonic() + 120
            while not partial.exists() and p.poll() is None and time.monotonic() < t_end:
                time.sleep(0.05)
            assert partial.exists(), p.communicate(timeout=60)[1]
            time.sleep(0.3)
            p.send_signal(signal.SIGTERM)
            err = p.communicate(timeout=60)[1]
        finally:
            if p.poll() is None:
                p.kill()
    assert p.returncode == 128 + signal.SIGTERM, err
    assert not partial.exists() and not out.exists() and (tmp_path / "rec.h5.resume").exists()
