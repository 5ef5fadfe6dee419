"""Interrupted simulations keep a resumable partial; --resume finishes bit-identical; outputs are never
overwritten without --overwrite; --json puts only the JSON object on stdout."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hybridhdr.cli import main
from hybridhdr.simulate.camera import FrameCameraParams
from hybridhdr.simulate.cli import run_simulation
from hybridhdr.simulate.resume import RenderCache, partial_path
from hybridhdr.simulate.sampling import SamplingParams
from hybridhdr.simulate.sensor import sensor_preset

from ._sources import BlobSource

ROOT = Path(__file__).resolve().parents[2]


class _Interrupting(BlobSource):
    """A blob source whose ``stop_at``-th render raises KeyboardInterrupt (Ctrl-C mid-run)."""

    def __init__(self, stop_at=None, **kw):
        super().__init__(**kw)
        self.stop_at = stop_at

    def render(self, t_us):
        if self.stop_at is not None and self.renders + 1 == self.stop_at:
            raise KeyboardInterrupt
        return super().render(t_us)


def _run(src, out, resume=False):
    return run_simulation(src, out, partial_path(out), resume=resume, sensor=sensor_preset("noisy"),
                          camera=FrameCameraParams(frame_rate_hz=50, exposure_us=5000),
                          sampling=SamplingParams(), gt_times_us=None, seed=7, progress=False,
                          say=lambda s: None, estimate=False)


def test_interrupt_then_resume_is_bit_identical(tmp_path):
    kw = dict(duration_us=150_000, flicker_hz=10, flicker_depth=0.5)
    a = tmp_path / "a.h5"
    _, sa = _run(_Interrupting(**kw), a)
    assert not partial_path(a).exists()  # a finished run leaves no partial
    b = tmp_path / "b.h5"
    with pytest.raises(KeyboardInterrupt):
        _run(_Interrupting(stop_at=sa["renders"] // 2, **kw), b)
    assert not b.exists() and partial_path(b).exists()
    src = _Interrupting(**kw)
    _, sb = _run(src, b, resume=True)
    assert not partial_path(b).exists()
    # the resumed run took the first half from the partial and rendered only the rest
    assert 0 < sb["renders_reused"] < sb["renders"] and src.renders < sa["renders"]
    assert sb["events"] == sa["events"] > 0 and sb["renders"] == sa["renders"]
    assert a.read_bytes() == b.read_bytes()


def test_resume_refuses_another_source(tmp_path):
    b = tmp_path / "b.h5"
    with pytest.raises(KeyboardInterrupt):
        _run(_Interrupting(stop_at=20, duration_us=100_000), b)
    with pytest.raises(ValueError, match="another source"):
        _run(_Interrupting(duration_us=100_000, speed_px_s=80.0), b, resume=True)
    with pytest.raises(ValueError, match="--resume to finish"):  # a fresh run does not clobber it either
        RenderCache(_Interrupting(duration_us=100_000), partial_path(b))


_SCENE = ["simulate", "builtin:slow_static", "--width", "40", "--height", "30", "--spp", "1", "--duration-s", "0.4",
          "--fixed-rate-hz", "1500", "--preset", "clean", "--seed", "3", "--no-progress"]


def _cli(args, **kw):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "hybridhdr", *args], cwd=str(ROOT), env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The scene simulated by the command line without interruption: the file both signals' resumed
    runs must equal, simulated once for both (they only read it)."""
    pytest.importorskip("mitsuba")
    a = tmp_path_factory.mktemp("uninterrupted") / "a.h5"
    p = _cli(_SCENE + ["--out", str(a)])
    _, err = p.communicate(timeout=600)
    assert p.returncode == 0, err
    return a


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_cli_signal_keeps_partial_and_resume_matches(tmp_path, sig, uninterrupted):
    pytest.importorskip("mitsuba")
    a, b = uninterrupted, tmp_path / "b.h5"
    p = _cli(_SCENE + ["--out", str(b)])
    part = partial_path(b)
    t0 = time.time()
    # wait for some renders on disk (40x30 float32 = 4.8 kB each), then interrupt
    while p.poll() is None and not (part.exists() and part.stat().st_size > 150_000) and time.time() - t0 < 300:
        time.sleep(0.05)
    assert p.poll() is None, "the run ended before it could be interrupted"
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    rc = p.returncode
    assert rc == 128 + sig or (sig == signal.SIGINT and rc == 130), err
    assert part.exists() and not b.exists()
    assert "--resume" in err
    p = _cli(_SCENE + ["--out", str(b), "--resume", "--json"])
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err
    summary = json.loads(out)  # --json: stdout is the JSON object alone
    assert summary["renders_reused"] > 0
    assert a.read_bytes() == b.read_bytes()
    assert not part.exists()


def _tiny(out):
    return ["simulate", "builtin:slow_static", "--width", "16", "--height", "12", "--spp", "1", "--duration-s", "0.02",
            "--fixed-rate-hz", "500", "--no-frames", "--no-progress", "--out", str(out)]


def test_overwrite_refused_and_json_convention(tmp_path, capsys):
    pytest.importorskip("mitsuba")
    out = tmp_path / "sim.h5"
    assert main(_tiny(out)) == 0
    o = capsys.readouterr()
    assert o.out.startswith("wrote ") and "{" not in o.out  # no JSON without --json
    assert "variant" in o.err  # the variant line (and why) on stderr
    before = out.read_bytes()
    assert main(_tiny(out) + ["--json"]) != 0  # refused: the file stays
    err = capsys.readouterr().err
    assert "exists" in err and "--overwrite" in err
    assert out.read_bytes() == before
    assert main(_tiny(out) + ["--json", "--overwrite", "--seed", "1"]) == 0
    o = capsys.readouterr()
    summary = json.loads(o.out)  # only the JSON object on stdout
    assert summary["out"] == str(out) and "wrote " in o.err
    # a partial left by an interrupted run is not clobbered by a fresh run either
    partial_path(out).write_bytes(b"x")
    assert main(_tiny(out) + ["--overwrite"]) == 0  # --overwrite starts again (replaces the partial)
    partial_path(out).write_bytes(b"x")
    out.unlink()
    assert main(_tiny(out)) != 0
    assert "--resume" in capsys.readouterr().err
    assert main(_tiny(out) + ["--resume"]) != 0
    assert "partial" in capsys.readouterr().err
