"""Reproducers of a hostile-input attack on the output rules, the bench, the readers and the
simulator, each turned into a test: nothing is lost, overwritten, hung or reported wrong.

Each test runs the command (through ``hybridhdr.cli.main`` or a child process where a signal or a
kill is involved) and checks the files afterwards, not only the exit status.
"""

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

import hybridhdr as hh
from hybridhdr.cli import main

REPO = Path(__file__).resolve().parents[2]


def _rec(path, n=2000, ss=(24, 32), frames=None, seed=0):
    from hybridhdr.formats.container import write_recording
    rng = np.random.default_rng(seed)
    ev = hh.make_events(np.sort(rng.integers(0, 200_000, n)), rng.integers(0, ss[1], n), rng.integers(0, ss[0], n),
                        rng.choice([-1, 1], n))
    return write_recording(hh.Recording(ev, ss, frames), path)


def _frames(k=6, ss=(24, 32), dtype=np.uint8, value=100, t_start=None, t_end=None):
    t_start = np.arange(k) * 30_000 if t_start is None else np.asarray(t_start)
    t_end = t_start + 5_000 if t_end is None else np.asarray(t_end)
    return hh.Frames(np.full((k, *ss), value, dtype), t_start, t_end)


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def _child(code: str, *args, **kw):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, "-c", code, *map(str, args)], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


# -- data loss and inputs overwritten --------------------------------------------------------------
def test_recover_refuses_a_journal_a_live_recorder_holds(tmp_path):
    from hybridhdr.capture.recorder import Recorder, journal_path, recover
    from hybridhdr.capture.sources import SyntheticEventSource
    out = tmp_path / "rec.h5"
    src = SyntheticEventSource(2e5, sensor_size=(30, 40), chunk_us=10_000, pace="realtime", seed=1)
    rec = Recorder(out, src, flush_interval_s=0.05, compression=None).start()
    try:
        time.sleep(0.3)
        assert journal_path(out).exists()
        with pytest.raises(FileExistsError, match="running recorder"):
            recover(out)
        assert not out.exists() and journal_path(out).exists()
    finally:
        stats = rec.finish()
    assert out.is_file() and not journal_path(out).exists() and stats.events_written > 0


def test_recover_cli_refuses_a_live_journal(tmp_path, capsys):
    from hybridhdr.capture.recorder import Recorder, journal_path
    from hybridhdr.capture.sources import SyntheticEventSource
    out = tmp_path / "rec.h5"
    rec = Recorder(out, SyntheticEventSource(2e5, sensor_size=(30, 40), pace="realtime"), compression=None).start()
    try:
        time.sleep(0.2)
        rc, _, err = _run(["capture", "recover", out], capsys)
        assert rc == 1 and "running recorder" in err and journal_path(out).exists()
    finally:
        rec.finish()
    assert out.is_file()


@pytest.mark.parametrize("flag", ["--out", "--report", "--plot"])
def test_capture_sync_refuses_an_output_that_is_the_input(tmp_path, capsys, flag):
    p = _rec(tmp_path / "r.h5")
    before = p.read_bytes()
    rc, _, err = _run(["capture", "sync", p, flag, p], capsys)
    assert rc == 1 and "input" in err and p.read_bytes() == before


def test_capture_sync_refuses_two_outputs_on_one_file(tmp_path, capsys):
    p = _rec(tmp_path / "r.h5")
    rc, _, err = _run(["capture", "sync", p, "--out", tmp_path / "o.h5", "--report", tmp_path / "o.h5"], capsys)
    assert rc == 1 and "two outputs" in err and not (tmp_path / "o.h5").exists()


def test_calibrate_sensor_refuses_out_that_is_the_recording(tmp_path, capsys):
    p = _rec(tmp_path / "r.h5", frames=_frames())
    before = p.read_bytes()
    rc, _, err = _run(["calibrate", "sensor", p, "--out", p], capsys)
    assert rc == 1 and "input" in err and p.read_bytes() == before


def test_calibrate_sensor_refuses_an_existing_profile(tmp_path, capsys):
    p = _rec(tmp_path / "r.h5", frames=_frames())
    prof = tmp_path / "s.json"
    prof.write_text("{\"mine\": 1}\n")
    rc, _, err = _run(["calibrate", "sensor", p, "--out", prof], capsys)
    assert rc == 1 and "--overwrite" in err and prof.read_text() == "{\"mine\": 1}\n"


def test_convert_refuses_an_existing_output_without_overwrite(tmp_path, capsys):
    p = _rec(tmp_path / "r.h5")
    out = tmp_path / "o.h5"
    out.write_bytes(b"a long simulation")
    rc, _, err = _run(["convert", p, out], capsys)
    assert rc == 1 and "--overwrite" in err and out.read_bytes() == b"a long simulation"
    rc, _, _ = _run(["convert", p, out, "--overwrite"], capsys)
    assert rc == 0 and len(hh.read(out).events) == 2000


def test_folder_and_file_refusals_share_one_wording(tmp_path):
    from hybridhdr._util.atomic import AtomicFolder, refuse_existing_output
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "x").write_text("x")
    with pytest.raises(ValueError) as folder:
        AtomicFolder(tmp_path / "o", outputs=("frame_*.exr",), command="reconstruct")
    with pytest.raises(ValueError) as file:
        refuse_existing_output(tmp_path / "o" / "x", overwrite=False, command="reconstruct")
    tail = "choose another name or pass --overwrite (replaces what a reconstruct run writes)"
    assert str(folder.value).endswith(tail) and str(file.value).endswith(tail)


def test_a_users_file_named_partial_is_never_deleted(tmp_path, capsys):
    p = _rec(tmp_path / "r.h5")
    user = tmp_path / "o.h5.partial"
    user.write_text("my notes")
    rc, _, err = _run(["convert", p, tmp_path / "o.h5"], capsys)
    assert rc == 1 and "not made by hybridhdr" in err and user.read_text() == "my notes"


def test_a_killed_writers_partial_is_marked_and_removed(tmp_path):
    """The partial a writer leaves when killed carries the mark; the finished file does not."""
    from hybridhdr._util.atomic import claim_partial, release_partial
    fd = claim_partial(tmp_path / "o.h5.partial")
    assert "user.hybridhdr.partial" in os.listxattr(tmp_path / "o.h5.partial")
    os.write(fd, b"half")
    release_partial(fd)  # as a kill -9 drops it
    release_partial(claim_partial(tmp_path / "o.h5.partial"))  # stale and ours: replaced
    p = _rec(tmp_path / "r.h5")
    assert "user.hybridhdr.partial" not in os.listxattr(p)


_COMMIT_UNDER_SIGTERM = r"""
import os, signal, sys, time
from pathlib import Path
from hybridhdr._util import atomic
from hybridhdr._util.procs import signals_exit
out = Path(sys.argv[1])
slow_replace = os.replace
def replace(a, b):  # a slow disk: each move takes a while; the parent sends SIGTERM in the middle
    slow_replace(a, b)
    if Path(b).parent == out:
        print("moved", flush=True)
        time.sleep(0.05)
atomic.os.replace = replace
with signals_exit():
    f = atomic.AtomicFolder(out, outputs=("frame_*.txt", "timestamps.txt"), command="reconstruct", overwrite=True)
    for i in range(20):
        (f.path / f"frame_{i:02d}.txt").write_text("new")
    (f.path / "timestamps.txt").write_text("new")
    (f.path / "run.json").write_text("new")
    try:
        f.commit()
    except SystemExit:
        print("exit after commit", flush=True)
        raise
"""


def test_overwrite_commit_is_all_or_nothing_under_sigterm(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    for i in range(20):
        (out / f"frame_{i:02d}.txt").write_text("old")
    (out / "timestamps.txt").write_text("old")
    (out / "run.json").write_text("old")
    (out / "notes.md").write_text("mine")
    proc = _child(_COMMIT_UNDER_SIGTERM, out)
    assert proc.stdout.readline().strip() == "moved"
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([f"frame_{i:02d}.txt" for i in range(20)] + ["timestamps.txt", "run.json", "notes.md"])
    assert all((out / n).read_text() == ("mine" if n == "notes.md" else "new") for n in names)
    assert not (tmp_path / "o.partial").exists()
