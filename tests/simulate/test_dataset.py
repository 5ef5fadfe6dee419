"""``hybridhdr simulate dataset``: scenes x seeds in one command, interrupted and resumed to the same
files as an uninterrupted run, locally and on a Dask cluster."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hybridhdr.simulate.dataset_run import load_spec, plan_jobs
from tests.conftest import sigint_default

ROOT = Path(__file__).resolve().parents[2]

SPEC = """
scenes = ["builtin:slow_static", "builtin:blinking_checkerboard"]
seeds = [0, 1]
profiles = ["clean"]
[options]
width = 40
height = 30
spp = 1
duration_s = 0.3
fixed_rate_hz = 800
"""


def _cli(args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "hybridhdr", *args], cwd=str(cwd), env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=sigint_default)


def _files(d: Path) -> dict:
    return {p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_spec_checks(tmp_path):
    s = tmp_path / "s.toml"
    s.write_text('scenes = ["builtin:slow_static"]\nseeds = [0, 0]\n')
    with pytest.raises(ValueError, match="duplicates"):
        load_spec(s)
    s.write_text('scenes = ["builtin:slow_static"]\nseeds = [1]\nprofile = ["clean"]\n')
    with pytest.raises(ValueError, match="unknown keys"):
        load_spec(s)
    s.write_text('scenes = ["builtin:slow_static"]\nseeds = [1]\n[options]\nseed = 3\n')
    with pytest.raises(ValueError, match="set by the dataset"):
        plan_jobs(load_spec(s), tmp_path)
    s.write_text('scenes = ["builtin:slow_static", "a.toml"]\nseeds = [4]\nprofiles = ["noisy", "p.json"]\n'
                 '[options]\nno_frames = true\nwidth = 8\n')
    jobs = plan_jobs(load_spec(s), tmp_path)
    assert len(jobs) == 4
    j = jobs[0]
    assert j["argv"] == ["simulate", "builtin:slow_static", "--out", "recordings/slow_static__noisy__seed4.h5",
                         "--seed", "4", "--preset", "noisy", "--no-frames", "--width", "8"]
    assert jobs[1]["argv"][6:8] == ["--sensor", str((tmp_path / "p.json").resolve())]


@pytest.fixture(scope="module")
def dataset_a(tmp_path_factory):
    """``(folder, JSON summary)``: ``spec.toml`` in the folder and the uninterrupted local run of it
    (``A``), made once for the two tests below, which compare their own runs (other output folders
    beside it, from the same spec file) with it and only read it."""
    pytest.importorskip("mitsuba")
    d = tmp_path_factory.mktemp("dataset")
    (d / "spec.toml").write_text(SPEC)
    p = _cli(["simulate", "dataset", "spec.toml", "--out", "A", "--jobs", "2", "--no-progress", "--json"], d)
    out, err = p.communicate(timeout=900)
    assert p.returncode == 0, err
    return d, json.loads(out)


@pytest.mark.slow
def test_dataset_interrupt_resume_identical(dataset_a):
    tmp_path, summary = dataset_a
    assert summary["recordings"] == 4 == summary["ran"]
    m = json.loads((tmp_path / "A" / "manifest.json").read_text())
    assert all(r["done"] and r["events"] > 0 and len(r["sha256"]) == 64 for r in m["recordings"])
    assert {(r["scene"], r["seed"]) for r in m["recordings"]} == {
        (s, k) for s in ("builtin:slow_static", "builtin:blinking_checkerboard") for k in (0, 1)}

    # interrupt B once a recording has renders on disk, then resume
    p = _cli(["simulate", "dataset", "spec.toml", "--out", "B", "--jobs", "2", "--no-progress"], tmp_path)
    rec = tmp_path / "B" / "recordings"
    t0 = time.time()
    while p.poll() is None and time.time() - t0 < 600:
        parts = list(rec.glob("*.resume")) if rec.exists() else []
        if any(q.stat().st_size > 100_000 for q in parts if q.exists()):
            break
        time.sleep(0.05)
    assert p.poll() is None, "the dataset finished before it could be interrupted"
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=300)
    assert p.returncode == 130, err
    assert "--resume" in err
    assert list(rec.glob("*.resume"))  # the stopped recordings kept their partials
    m = json.loads((tmp_path / "B" / "manifest.json").read_text())
    assert not all(r["done"] for r in m["recordings"])
    # without --resume the folder is refused, not overwritten
    p = _cli(["simulate", "dataset", "spec.toml", "--out", "B", "--no-progress"], tmp_path)
    _, err = p.communicate(timeout=300)
    assert p.returncode != 0 and "--overwrite" in err
    p = _cli(["simulate", "dataset", "spec.toml", "--out", "B", "--jobs", "2", "--resume", "--no-progress"], tmp_path)
    _, err = p.communicate(timeout=900)
    assert p.returncode == 0, err
    assert _files(tmp_path / "A") == _files(tmp_path / "B")  # recordings and manifest, byte for byte


@pytest.mark.slow
def test_dataset_on_local_dask_cluster(dataset_a):
    distributed = pytest.importorskip("distributed")
    tmp_path = dataset_a[0]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp",
                                   dashboard_address=None) as cl:
        p = _cli(["simulate", "dataset", "spec.toml", "--out", "D", "--scheduler", cl.scheduler_address,
                  "--no-progress"], tmp_path)
        _, err = p.communicate(timeout=900)
    assert p.returncode == 0, err
    assert "Dask scheduler" in err
    assert _files(tmp_path / "A") == _files(tmp_path / "D")
