"""Reliability checks that need processes, signals or injected failures (the file-
and option-shaped ones are cases in ``tests/hostile/cases.py``): partial files locked and
exclusive, SIGTERM like Ctrl-C, no orphans after ``kill -9``, ffmpeg's exit status, full disks
(an ``OSError(ENOSPC)`` injected in the writer) leaving nothing at the final names."""

from __future__ import annotations

import errno
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

REPO = Path(__file__).resolve().parents[2]


def _env():
    return {**os.environ, "PYTHONPATH": str(REPO)}


def _recording(path, n=2000, frames=True, ss=(48, 64), span_us=1_000_000):
    import hybridhdr as hh
    from hybridhdr.formats.container import write_recording
    rng = np.random.default_rng(0)
    ev = hh.make_events(np.sort(rng.integers(0, span_us, n)), rng.integers(0, ss[1], n), rng.integers(0, ss[0], n),
                        rng.choice([-1, 1], n))
    fr = None
    if frames:
        k = 6
        t = np.linspace(0, span_us - 10_000, k).astype(np.int64)
        fr = hh.Frames((rng.random((k, *ss)) * 200 + 20).astype(np.uint8), t, t + 5000)
    return write_recording(hh.Recording(ev, ss, fr), path)


def _descendants(pid: int) -> set[int]:
    """Every process whose parent chain reaches ``pid`` (read from /proc)."""
    parent = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    parent[int(d)] = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                pass
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for c, pp in parent.items():
            if pp == p and c not in out:
                out.add(c)
                todo.append(c)
    return out


def _alive(pids) -> set[int]:
    alive = set()
    for p in pids:
        try:
            with open(f"/proc/{p}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] != "Z":
                    alive.add(p)
        except OSError:
            pass
    return alive


def _wait_gone(pids, timeout=15.0) -> set[int]:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        left = _alive(pids)
        if not left:
            return set()
        time.sleep(0.1)
    return _alive(pids)


# -- partial outputs --------------------------------------------------------------------------
def test_partial_claim_is_exclusive_locked_and_never_follows_links(tmp_path):
    from hybridhdr._util.atomic import PartialInUse, claim_partial, release_partial
    p = tmp_path / "out.h5.partial"
    fd = claim_partial(p)
    with pytest.raises(PartialInUse, match="another running"):
        claim_partial(p)  # a second writer (another open file description) is refused while the first lives
    release_partial(fd)
    fd = claim_partial(p)  # the lock is free: a stale partial of ours is removed and claimed again
    release_partial(fd)
    os.unlink(p)
    victim = tmp_path / "victim"
    victim.write_text("keep")
    os.symlink(victim, p)
    with pytest.raises(PartialInUse, match="symbolic link"):
        claim_partial(p)
    assert victim.read_text() == "keep"
    os.unlink(p)
    p.mkdir()
    (p / "mine").write_text("keep")
    with pytest.raises(PartialInUse, match="never deleted"):
        claim_partial(p)
    with pytest.raises(PartialInUse, match="never deleted"):
        claim_partial(p, directory=True)  # a folder without our marker is the user's
    assert (p / "mine").read_text() == "keep"


def test_concurrent_converts_to_one_output_never_corrupt_it(tmp_path):
    import hybridhdr as hh
    src = _recording(tmp_path / "r.h5", n=400_000, frames=False)
    out = tmp_path / "same.h5"
    cmd = [sys.executable, "-m", "hybridhdr", "convert", str(src), str(out), "--no-progress"]
    procs = [subprocess.Popen(cmd, cwd=REPO, env=_env(), stderr=subprocess.PIPE, text=True) for _ in range(3)]
    results = [(p.communicate(timeout=300)[1], p.returncode)[::-1] for p in procs]
    assert any(rc == 0 for rc, _ in results), results
    for rc, err in results:
        assert "Traceback" not in err, err
        if rc != 0:  # the loser: one error line naming the other run
            assert rc == 1 and len([ln for ln in err.splitlines() if "error:" in ln]) == 1, err
            assert "another" in err or "exists" in err, err
    assert len(hh.read(out).events) == 400_000  # readable, complete
    assert not list(tmp_path.glob("*.partial*"))


def _start_and_wait(cmd, ready, timeout=120):
    p = subprocess.Popen(cmd, cwd=REPO, env=_env(), stderr=subprocess.PIPE, text=True)
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end and p.poll() is None and not ready():
        time.sleep(0.02)
    if p.poll() is not None:
        err = p.communicate()[1]
        pytest.skip(f"the run ended before it could be interrupted (rc {p.returncode}): {err[-300:]}")
    return p


def test_sigterm_convert_removes_its_partial_file(tmp_path):
    src = _recording(tmp_path / "r.h5", n=1_500_000, frames=False)
    out = tmp_path / "out"
    part = tmp_path / "out.partial"
    p = _start_and_wait([sys.executable, "-m", "hybridhdr", "convert", str(src), str(out), "--to", "ecd",
                         "--no-progress"], lambda: part.is_dir())
    time.sleep(0.2)
    p.send_signal(signal.SIGTERM)
    err = p.communicate(timeout=60)[1]
    assert p.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert sorted(x.name for x in tmp_path.iterdir()) == ["r.h5"]


def test_sigterm_view_removes_its_temporary_mp4(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    src = _recording(tmp_path / "r.h5", n=20_000)
    p = _start_and_wait([sys.executable, "-m", "hybridhdr", "view", str(src), "--out", str(tmp_path / "v.mp4"),
                         "--fps", "3000", "--no-progress"], lambda: bool(list(tmp_path.glob(".v.mp4.*partial*"))))
    time.sleep(0.3)
    p.send_signal(signal.SIGTERM)
    err = p.communicate(timeout=60)[1]
    assert p.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert sorted(x.name for x in tmp_path.iterdir()) == ["r.h5"]


def test_kill9_reconstruct_leaves_no_writers_and_a_rerun_cleans_the_stale_folder(tmp_path):
    src = _recording(tmp_path / "r.h5", n=20_000, span_us=2_000_000)
    out = tmp_path / "o"
    part = tmp_path / "o.partial"
    cmd = [sys.executable, "-m", "hybridhdr", "reconstruct", str(src), "--out", str(out), "--fps", "3000",
           "--png", "--writers", "2", "--no-progress"]
    p = _start_and_wait(cmd, lambda: part.is_dir() and len(list(part.glob("frame_*.exr"))) > 30)
    kids = _descendants(p.pid)
    assert kids, "the writer pool was expected to run in processes"
    p.kill()
    p.communicate(timeout=30)
    assert not _wait_gone(kids), "writer processes outlived a kill -9 of reconstruct"
    assert part.is_dir()  # left by the killed run ...
    r = subprocess.run(cmd[:-4] + ["--fps", "50", "--no-progress"], cwd=REPO, env=_env(), capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]  # ... and cleaned by the rerun, which says so
    assert "removed" in r.stderr and "interrupted" in r.stderr
    assert (out / "run.json").is_file() and not part.exists()


_BENCH = """[bench]
name = "t"
jod = false
warmup = false
{datasets}
[[methods]]
method = "akf"
grid = {{ threshold_factor = [0.8, 1.0, 1.2, 1.4] }}
"""


def test_bench_sigterm_leaves_no_forkserver_or_workers(tmp_path):
    ds = "".join(f"\n[[datasets]]\nkind = \"procedural\"\nname = \"d{i}\"\nwidth = 64\nheight = 48\n"
                 f"duration_us = 400000\n" for i in range(6))
    (tmp_path / "b.toml").write_text(_BENCH.format(datasets=ds))
    proc = subprocess.Popen([sys.executable, "-m", "hybridhdr", "evaluate", "bench", str(tmp_path / "b.toml"),
                             "--out", str(tmp_path / "o"), "--workers", "2", "--no-progress"],
                            cwd=REPO, env=_env(), stderr=subprocess.PIPE, text=True)
    t_end = time.monotonic() + 120
    kids: set[int] = set()
    while time.monotonic() < t_end and proc.poll() is None:
        kids |= _descendants(proc.pid)
        if len(kids) >= 3:  # forkserver (+ resource tracker) and workers
            break
        time.sleep(0.05)
    if proc.poll() is not None:
        proc.communicate()
        pytest.skip("the bench ended before it could be interrupted")
    time.sleep(1.0)
    kids |= _descendants(proc.pid)
    proc.send_signal(signal.SIGTERM)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert not _wait_gone(kids), "bench helper processes outlived SIGTERM"
    assert not (tmp_path / "o" / "results.csv").exists()



# -- ffmpeg's exit status ---------------------------------------------------------------------
@pytest.fixture
def failing_ffmpeg(tmp_path, monkeypatch):
    """An ffmpeg that reads its input, says the disk is full and exits 1 (as on a full disk)."""
    pytest.importorskip("imageio_ffmpeg")
    import imageio_ffmpeg
    exe = tmp_path / "ffmpeg"
    exe.write_text("#!/bin/sh\ncat > /dev/null\necho 'Error writing trailer: No space left on device' >&2\nexit 1\n")
    exe.chmod(0o755)
    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", lambda: str(exe))
    import imageio_ffmpeg._io as io_mod
    monkeypatch.setattr(io_mod, "get_ffmpeg_exe", lambda: str(exe))
    return exe


def _one_error_line(err):
    return len([ln for ln in err.splitlines() if "error:" in ln]) == 1 and "Traceback" not in err


def test_view_ffmpeg_failure_exit_1_nothing_written(tmp_path, failing_ffmpeg, capfd):
    src = _recording(tmp_path / "r.h5")
    rc = main(["view", str(src), "--out", str(tmp_path / "v.mp4"), "--still", str(tmp_path / "s.png"),
               "--no-progress"])
    err = capfd.readouterr().err
    assert rc == 1 and _one_error_line(err), err
    assert "ffmpeg failed" in err and "No space left" in err
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != "ffmpeg") == ["r.h5"]


def test_reconstruct_mp4_ffmpeg_failure_exit_1_nothing_written(tmp_path, failing_ffmpeg, capfd):
    src = _recording(tmp_path / "r.h5")
    rc = main(["reconstruct", str(src), "--out", str(tmp_path / "o"), "--fps", "20", "--mp4", "--writers", "0",
               "--no-progress"])
    err = capfd.readouterr().err
    assert rc == 1 and _one_error_line(err), err
    assert not (tmp_path / "o").exists() and not (tmp_path / "o.partial").exists()


# -- full disks: multi-file outputs all or none -----------------------------------------------
def _enospc(*a, **k):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_view_still_full_disk_keeps_no_mp4(tmp_path, monkeypatch, capfd):
    pytest.importorskip("imageio_ffmpeg")
    import hybridhdr.formats.images as images
    src = _recording(tmp_path / "r.h5")
    monkeypatch.setattr(images, "write_png", _enospc)
    rc = main(["view", str(src), "--out", str(tmp_path / "v.mp4"), "--still", str(tmp_path / "s.png"),
               "--no-progress"])
    err = capfd.readouterr().err
    assert rc == 1 and _one_error_line(err) and "No space left" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.h5"]


def _brackets(tmp_path):
    from hybridhdr.formats.brackets import write_bracket_set
    from hybridhdr.simulate.procedural import hdr_scene, render_frame
    rng = np.random.default_rng(4)
    E = hdr_scene(60, 80, seed=2)
    ex = [0.05, 0.2, 0.8, 3.2]
    return write_bracket_set(tmp_path / "br", [render_frame(E, np.eye(3), t, rng) for t in ex], ex,
                             encoding="gamma", camera={"name": "synthetic"})


@pytest.mark.parametrize("error", [OSError(errno.ENOSPC, "No space left on device"),
                                   RuntimeError("libpng error: Write Error")])
def test_hdr_reference_full_disk_writes_none_of_exr_json_png(tmp_path, monkeypatch, capfd, error):
    from hybridhdr.calibrate import _cli_photometric as photo
    br = _brackets(tmp_path)

    def fail(*a, **k):
        raise error
    monkeypatch.setattr(photo, "_plot_reference", fail)  # the last of the three files
    rc = main(["calibrate", "hdr-reference", str(br), "--out", str(tmp_path / "ref.exr")])
    err = capfd.readouterr().err
    assert rc == 1 and _one_error_line(err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["br"]


def test_crf_full_disk_writes_none_of_its_files(tmp_path, monkeypatch, capfd):
    import importlib
    npf = importlib.import_module("hybridhdr.calibrate.noise_profile")  # the module (the package exports a function)
    br = _brackets(tmp_path)
    monkeypatch.setattr(npf, "plot_profile", _enospc)
    rc = main(["calibrate", "crf", str(br), "--out", str(tmp_path / "cal"), "--no-progress"])
    err = capfd.readouterr().err
    assert rc == 1 and _one_error_line(err), err
    assert not (tmp_path / "cal").exists() or not any((tmp_path / "cal").iterdir())


def test_bench_full_disk_writes_no_csv_without_its_report(tmp_path, monkeypatch, capfd):
    import hybridhdr.evaluate.report as report
    ds = "\n[[datasets]]\nkind = \"procedural\"\nwidth = 32\nheight = 24\nduration_us = 60000\n"
    (tmp_path / "b.toml").write_text(_BENCH.format(datasets=ds).replace("[0.8, 1.0, 1.2, 1.4]", "[1.0]"))
    real = report.write_text_atomic

    def fail_on_report(path, text, **k):
        if Path(path).name == "report.html":
            _enospc()
        return real(path, text, **k)
    monkeypatch.setattr(report, "write_text_atomic", fail_on_report)
    rc = main(["evaluate", "bench", str(tmp_path / "b.toml"), "--out", str(tmp_path / "o"), "--workers", "0",
               "--no-progress"])
    err = capfd.readouterr().err
    assert rc == 1 and _one_error_line(err), err
    left = sorted(str(p.relative_to(tmp_path / "o")) for p in (tmp_path / "o").rglob("*")) \
        if (tmp_path / "o").exists() else []
    # nothing of the bench's outputs; only the finished runs kept for --resume (OUT/runs/, each
    # written atomically: docs/evaluate.md) and the lock a bench holds in its OUT (left in place,
    # never counted as content)
    from hybridhdr.evaluate.bench import BENCH_LOCK
    assert all(p in ("runs", BENCH_LOCK) or p.startswith("runs/task_") for p in left), left
    assert not any(p.endswith((".csv", ".html", ".png")) for p in left), left


def test_refuse_overwriting_inputs_follows_links(tmp_path):
    from hybridhdr._util.atomic import refuse_overwriting_inputs
    a = tmp_path / "a.h5"
    a.write_bytes(b"x")
    os.symlink(a, tmp_path / "link.h5")
    with pytest.raises(ValueError, match="refusing to overwrite an input"):
        refuse_overwriting_inputs({"--out": tmp_path / "link.h5"}, [a])
    os.link(a, tmp_path / "hard.h5")
    with pytest.raises(ValueError, match="refusing to overwrite an input"):
        refuse_overwriting_inputs([tmp_path / "hard.h5"], [a])
    refuse_overwriting_inputs({"--out": tmp_path / "b.h5", "--still": None}, [a, None])


def test_bench_json_reports_failure_when_every_run_fails(tmp_path, capfd):
    (tmp_path / "bad.pth").write_bytes(b"not a checkpoint")
    ds = "\n[[datasets]]\nkind = \"procedural\"\nwidth = 32\nheight = 24\nduration_us = 60000\n"
    (tmp_path / "b.toml").write_text(_BENCH.format(datasets=ds).replace(
        'method = "akf"\ngrid = { threshold_factor = [0.8, 1.0, 1.2, 1.4] }', 'method = "e2vid"\n'
        'params = { weights = "bad.pth" }'))
    rc = main(["evaluate", "bench", str(tmp_path / "b.toml"), "--out", str(tmp_path / "o"), "--workers", "0",
               "--no-progress", "--json"])
    cap = capfd.readouterr()
    assert rc == 1 and "every run failed" in cap.err
    assert json.loads(cap.out.strip().splitlines()[-1])["failed"] == 1
