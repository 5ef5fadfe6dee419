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
from tests.conftest import sigint_default

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
    kw.setdefault("stdout", subprocess.PIPE)
    kw.setdefault("stderr", subprocess.PIPE)
    kw.setdefault("preexec_fn", sigint_default)  # the SIGINT tests need it not ignored
    return subprocess.Popen([sys.executable, "-c", code, *map(str, args)], cwd=REPO, env=env, text=True, **kw)


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
    assert rc == 2 and "--overwrite" in err and prof.read_text() == "{\"mine\": 1}\n"


def test_convert_refuses_an_existing_output_without_overwrite(tmp_path, capsys):
    p = _rec(tmp_path / "r.h5")
    out = tmp_path / "o.h5"
    out.write_bytes(b"a long simulation")
    rc, _, err = _run(["convert", p, out], capsys)
    assert rc == 2 and "--overwrite" in err and out.read_bytes() == b"a long simulation"
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


# -- the bench: one --out, orphans, --resume, tampered run files, the headline ---------------------
_BENCH = """[bench]
name = "t"
jod = false
warmup = false
strips = 2

[[datasets]]
kind = "procedural"
width = 32
height = 24
duration_us = 60000
grid = { noise_rate_hz = [SEEDS] }

[[methods]]
method = "highpass"
"""


def _bench_file(d, seeds=(0,)):
    b = d / "b.toml"
    b.write_text(_BENCH.replace("SEEDS", ", ".join(f"{float(s):.1f}" for s in seeds)))
    return b


def test_two_benches_on_one_out_are_refused(tmp_path, capsys):
    from hybridhdr.evaluate.bench import claim_bench_out
    out = tmp_path / "o"
    argv = ["evaluate", "bench", _bench_file(tmp_path, (0, 1)), "--out", out, "--workers", "0", "--no-progress"]
    assert _run(argv, capsys)[0] == 0
    first = sorted(p.name for p in (out / "strips").iterdir())
    assert len(first) == 2
    rc, _, err = _run(argv, capsys)  # a second bench on the same non-empty --out
    assert rc == 2 and "--overwrite" in err
    # a bench running there now (it holds the lock): refused even with --overwrite
    fd = claim_bench_out(tmp_path / "busy")
    try:
        rc, _, err = _run([*argv[:4], tmp_path / "busy", *argv[5:], "--overwrite"], capsys)
        assert rc == 1 and "another running bench" in err
    finally:
        os.close(fd)
    # --overwrite with another bench: its report, and no strip of the first beside it
    argv2 = ["evaluate", "bench", _bench_file(tmp_path, (5,)), "--out", out, "--workers", "0", "--no-progress",
             "--overwrite"]
    assert _run(argv2, capsys)[0] == 0
    assert len(list((out / "strips").iterdir())) == 1


def test_resume_digests_the_data_not_the_path(tmp_path):
    from hybridhdr.evaluate import bench as B
    p = _rec(tmp_path / "d.h5", seed=1)
    task = ("d", {"kind": "file", "path": str(p)}, {}, [])
    k1 = B._task_key(task, {"seed": 0})
    _rec(tmp_path / "d.h5", seed=2)  # same name, other data
    assert B._task_key(task, {"seed": 0}) != k1


def _load_in_thread(fn, *args, timeout=10.0):
    import threading
    box = {}
    t = threading.Thread(target=lambda: box.setdefault("v", fn(*args)), daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), "hung"
    return box.get("v", "raised")


@pytest.mark.parametrize("tamper", ["made_up_values", "fifo", "dev_zero", "deep_json", "list_value", "npz_fifo"])
def test_tampered_run_files_are_run_again(tmp_path, tamper):
    from hybridhdr.evaluate import bench as B
    rows = [{"dataset": "d", "status": "ok", "mse": 0.01, "ssim": 0.9, "_strip": {"a": np.zeros((4, 4))}}]
    B._save_task(tmp_path, 0, "k", rows)
    f = tmp_path / "task_00000.json"
    if tamper == "made_up_values":
        f.write_text(json.dumps({"key": "k", "task": 0, "rows": [{"dataset": "d", "status": "ok", "mse": -5.0,
                                                                 "ssim": 7.0}]}))
    elif tamper == "fifo":
        f.unlink()
        os.mkfifo(f)
    elif tamper == "dev_zero":
        f.unlink()
        os.symlink("/dev/zero", f)
    elif tamper == "deep_json":
        f.write_text('{"key": "k", "rows": ' + "[" * 5000 + "]" * 5000 + "}")
    elif tamper == "list_value":
        f.write_text(json.dumps({"key": "k", "rows": [{"dataset": "d", "status": "ok", "mse": [1] * 10}]}))
    elif tamper == "npz_fifo":
        z = tmp_path / "task_00000.npz"
        z.unlink()
        os.mkfifo(z)
    assert _load_in_thread(B._load_task, tmp_path, 0, "k") is None


def test_results_csv_quotes_cells_a_spreadsheet_would_run(tmp_path):
    from hybridhdr.evaluate import bench as B
    rows = [{"task": 0, "run": 0, "dataset": "=cmd|' /C calc'!A0", "status": "ok", "mse": -0.0,
             "ds.=HYPERLINK(\"x\")": "@SUM(1)", "method_label": "+1"}]
    B.write_results(rows, tmp_path, None, charts=False)
    import csv
    with open(tmp_path / "results.csv", newline="", encoding="utf-8") as fh:
        cells = [c for line in csv.reader(fh) for c in line]
    assert not any(c[:1] in ("=", "+", "@") for c in cells), cells
    assert "-0.0" in cells  # numbers stay numbers


def test_stability_headline_is_not_carried_by_blown_up_runs():
    from hybridhdr.evaluate.report import akf_vs_cf, akf_vs_cf_text, summary_table
    rows = []
    for ds, (akf, cf) in {"a": (0.010, 0.020), "b": (0.002, 0.004), "c": (0.05, 0.1)}.items():
        for k in range(3):
            rows.append({"dataset": ds, "method_label": "akf", "status": "ok", "mse": akf, "ssim": 0.8,
                         "log_mse": akf, "log_ssim": 0.8, "pu_ssim": 0.8, "n_nonfinite": 0})
            rows.append({"dataset": ds, "method_label": "cf", "status": "ok", "mse": cf, "ssim": 0.7,
                         "log_mse": cf, "log_ssim": 0.7, "pu_ssim": 0.7, "n_nonfinite": 0})
    rows.append({"dataset": "a", "method_label": "akf", "status": "ok", "mse": 1.4e29, "ssim": 0.0,
                 "log_mse": 50.0, "log_ssim": 0.0, "pu_ssim": 0.0, "n_nonfinite": 0})  # diverged, finite
    c = akf_vs_cf(rows)
    assert c["mse_reduction_pct"] == pytest.approx(50.0)  # AKF half of CF on every dataset
    assert c["akf_failed"] == 1 and c["akf_runs"] == 10 and c["cf_failed"] == 0
    assert "higher" not in akf_vs_cf_text(c) and "1/10" in akf_vs_cf_text(c)
    a = {s["dataset"]: s for s in summary_table(rows) if s["method"] == "akf"}
    assert a["a"]["blown_up"] == 1 and a["a"]["mse"] == pytest.approx(0.01) and a["a"]["ok"] == 3


_BENCH_KILL = r"""
import sys
from hybridhdr.cli import main
sys.exit(main(["evaluate", "bench", sys.argv[1], "--out", sys.argv[2], "--workers", "2", "--no-progress"]))
"""


def _descendants(pid):
    kids = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        for c in kids.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def _alive(pid):
    try:
        st = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        return st != "Z"
    except OSError:
        return False


def test_kill9_of_a_bench_with_workers_leaves_no_process(tmp_path):
    proc = _child(_BENCH_KILL, _bench_file(tmp_path, tuple(range(8))), tmp_path / "o",
                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    helpers = []
    t_end = time.monotonic() + 120
    while time.monotonic() < t_end:  # the forkserver, the resource tracker and two workers
        helpers = _descendants(proc.pid)
        if len(helpers) >= 4:
            break
        time.sleep(0.2)
    assert len(helpers) >= 4, helpers
    time.sleep(1.0)
    helpers = _descendants(proc.pid)
    proc.kill()
    proc.wait()
    t_end = time.monotonic() + 20
    while time.monotonic() < t_end and any(_alive(p) for p in helpers):
        time.sleep(0.2)
    left = [p for p in helpers if _alive(p)]
    for p in left:  # never leave them to the next test
        os.kill(p, signal.SIGKILL)
    assert not left, f"left running after kill -9: {left}"


# -- sensor profiles: physics bounds, an event budget, signals honoured -----------------------------
def _profile(path, **params):
    d = {"format": "hybridhdr-sensor-profile", "version": 1, "name": "x", "sensor": {}, "simulator_params": params,
         "estimates": {}, "provenance": {}}
    path.write_text(json.dumps(d))
    return path


@pytest.mark.parametrize("params", [{"photoreceptor_cutoff_hz": 1e308},
                                    {"contrast_threshold_on": 1e-300, "contrast_threshold_off": 1e-300,
                                     "refractory_period_us": 0},
                                    {"shot_noise_rate_hz": 1e300}, {"refractory_period_us": 10**30}])
def test_sensor_profile_values_are_bounded_by_physics(tmp_path, params):
    from hybridhdr.formats.sensor_profile import SensorProfileError, load_sensor_profile
    from hybridhdr.simulate.sensor import EventSensorParams
    with pytest.raises(SensorProfileError, match="physical range"):
        load_sensor_profile(_profile(tmp_path / "p.json", **params))
    with pytest.raises(ValueError, match="physical range"):
        EventSensorParams(**{"min_threshold": 1e-300, **params})


def test_simulator_event_budget_is_checked_before_the_kernel(monkeypatch):
    from hybridhdr._util import limits
    from hybridhdr.simulate.sensor import EventSensor, EventSensorParams
    s = EventSensor((8, 8), EventSensorParams(contrast_threshold_on=1e-4, contrast_threshold_off=1e-4,
                                              min_threshold=1e-4), seed=0)
    s.start(0, np.full((8, 8), 1e-3))
    monkeypatch.setitem(limits.LIMITS, "max_events", 100_000)
    t0 = time.perf_counter()
    with pytest.raises(limits.LimitExceeded, match="budget"):
        s.step(1000, np.full((8, 8), 1e3))  # 13.8 log units / 1e-4 = 138,000 crossings a pixel
    assert time.perf_counter() - t0 < 5
    with limits.allow_huge():  # lifted: it runs, and the events are all there
        ev = s.step(1000, np.full((8, 8), 1e3))
    assert len(ev) == 64 * int(np.log((1e3 + 1e-3) / (1e-3 + 1e-3)) / 1e-4)


_SIM_SIGTERM = r"""
import sys, numpy as np
from hybridhdr._util.limits import allow_huge
from hybridhdr._util.procs import signals_exit
from hybridhdr.simulate.sensor import EventSensor, EventSensorParams
s = EventSensor((8, 8), EventSensorParams(contrast_threshold_on=1e-4, contrast_threshold_off=1e-4,
                                          min_threshold=1e-4), seed=0)
s.start(0, np.full((8, 8), 1e-3))
print("start", flush=True)
with signals_exit(), allow_huge():
    for k in range(1, 100000):  # about 9e6 crossings a step, for minutes
        s.step(k * 1000, np.full((8, 8), 1e3 if k % 2 else 1e-3))
"""


def test_a_step_with_many_crossings_is_split_so_signals_act(monkeypatch):
    """A compiled kernel cannot take a signal: no call may walk more than MAX_CROSSINGS_PER_CALL."""
    from hybridhdr.simulate import _kernels as K
    from hybridhdr.simulate import sensor as S
    from hybridhdr.simulate.sensor import EventSensor, EventSensorParams
    monkeypatch.setattr(S, "MAX_CROSSINGS_PER_CALL", 1 << 16, raising=False)
    calls = []
    real = K.crossings

    def counting(*a):
        if not a[13]:  # the counting pass of each call
            calls.append(1)
        return real(*a)
    monkeypatch.setattr(K, "crossings", counting)
    s = EventSensor((4, 4), EventSensorParams(contrast_threshold_on=1e-4, contrast_threshold_off=1e-4,
                                              min_threshold=1e-4), seed=0)
    s.start(0, np.full((4, 4), 1e-3))
    ev = s.step(1000, np.full((4, 4), 1e3))  # 16 x 138,000 crossings
    assert len(ev) > 2_000_000 and len(calls) >= len(ev) // (1 << 16)
    assert np.all(np.diff(ev["t"]) >= 0)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_crossing_kernel_honours_sigterm_and_sigint(sig):
    proc = _child(_SIM_SIGTERM)
    assert proc.stdout.readline().strip() == "start"
    time.sleep(3.0)  # inside the kernel by now
    t0 = time.monotonic()
    proc.send_signal(sig)
    try:
        proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"{signal.Signals(sig).name} ignored for 30 s")
    assert proc.returncode != 0 and time.monotonic() - t0 < 30


# -- unbounded reads, deep JSON, thresholds maps -----------------------------------------------------
@pytest.mark.parametrize("kind", ["fifo", "dev_zero", "deep", "big"])
def test_sensor_profile_read_is_bounded(tmp_path, kind):
    from hybridhdr.formats.sensor_profile import SensorProfileError, load_sensor_profile
    p = tmp_path / "p.json"
    if kind == "fifo":
        os.mkfifo(p)
    elif kind == "dev_zero":
        os.symlink("/dev/zero", p)
    elif kind == "deep":
        p.write_text("[" * 5000 + "]" * 5000)
    else:
        p.write_text(" " * (2 << 20) + "{}")
    assert _load_in_thread(_raises(load_sensor_profile, SensorProfileError), p) == "refused"


def _raises(fn, exc):
    def call(*a):
        try:
            return fn(*a)
        except exc:
            return "refused"
    return call


def _npz_declaring(path, shape):
    import io
    import zipfile
    hdr = io.BytesIO()
    np.lib.format.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False, "shape": shape})
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("c_on.npy", "w", force_zip64=True) as f:
            f.write(hdr.getvalue())
            f.write(b"\0" * (7 << 20))  # 7 MB of zeros: deflates to a few kB
    return path


@pytest.mark.parametrize("kind", ["30000_square", "zip_magic_only", "fifo", "c_1e308", "c_1e-300"])
def test_thresholds_npz_is_checked_before_allocation(tmp_path, kind):
    from hybridhdr.formats.thresholds import load_thresholds
    p = tmp_path / "t.npz"
    if kind == "30000_square":
        _npz_declaring(p, (30000, 30000))
    elif kind == "zip_magic_only":
        p.write_bytes(b"PK\x03\x04" + os.urandom(200))
    elif kind == "fifo":
        os.mkfifo(p)
    else:
        c = 1e308 if kind == "c_1e308" else 1e-300
        np.savez(p, format=np.array("hybridhdr-thresholds"), version=np.array(1), c_on=np.full((24, 32), c),
                 c_off=np.full((24, 32), 0.2), fallback_on=np.array(0.2), fallback_off=np.array(0.2))
    import resource
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    why = {}

    def load(path):
        try:
            return load_thresholds(path)
        except ValueError as e:
            why["message"] = str(e)
            return "refused"
    assert _load_in_thread(load, p) == "refused"
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - r0 < 500_000  # kB: never the 6.7 GB it declares
    if kind == "30000_square":  # refused from the header, before the 6.7 GB are asked for
        assert "30000x30000" in why["message"] and "limit" in why["message"], why


def test_reconstruct_with_huge_threshold_map_writes_no_inf_frame(tmp_path, capsys):
    p = _rec(tmp_path / "r.h5", frames=_frames())
    t = tmp_path / "t.npz"
    np.savez(t, format=np.array("hybridhdr-thresholds"), version=np.array(1), c_on=np.full((24, 32), 1e308),
             c_off=np.full((24, 32), 1e308), fallback_on=np.array(0.2), fallback_off=np.array(0.2))
    rc, _, err = _run(["reconstruct", p, "--out", tmp_path / "o", "--fps", "20", "--thresholds", t, "--no-progress"],
                      capsys)
    assert rc != 0 and "contrast threshold" in err and not (tmp_path / "o").exists()


def test_16bit_frames_without_a_profile_are_refused_by_reconstruct(tmp_path, capsys):
    p = _rec(tmp_path / "r.h5", frames=_frames(dtype=np.uint16, value=40000))
    rc, _, err = _run(["reconstruct", p, "--out", tmp_path / "o", "--fps", "20", "--no-progress"], capsys)
    assert rc != 0 and "frame codes reach 40000" in err and not (tmp_path / "o").exists()


def test_reconstruct_quiet_still_prints_its_error(tmp_path):
    p = _rec(tmp_path / "r.h5")  # no frames: the AKF needs them
    env = dict(os.environ, PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-m", "hybridhdr", "reconstruct", str(p), "--out", str(tmp_path / "o"),
                        "--fps", "10", "-q"], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "error:" in r.stderr and "needs frames" in r.stderr, r.stderr


# -- frame times the model accepts -------------------------------------------------------------------
def test_sorted_starts_with_unsorted_mid_exposures_reconstruct(tmp_path, capsys):
    ts = np.array([0, 30_000, 40_000, 90_000, 120_000, 150_000])
    te = ts + 5_000
    te[1] = 80_000  # a long exposure: its mid (55 ms) comes after the next frame's (42.5 ms)
    p = _rec(tmp_path / "r.h5", n=3000, frames=_frames(t_start=ts, t_end=te))
    # the thresholds the recording declares: these random events on flat frames give self-calibration
    # nothing to fit, and the frame order, not the calibration, is what this case checks
    rc, out, err = _run(["reconstruct", p, "--out", tmp_path / "o", "--fps", "50", "--thresholds", "input",
                         "--no-progress"], capsys)
    assert rc == 0, err
    assert (tmp_path / "o" / "run.json").is_file()


def test_overexpose_refuses_frames_at_one_instant(tmp_path, capsys):
    ts = np.zeros(6, np.int64)
    p = _rec(tmp_path / "r.h5", n=3000, frames=_frames(t_start=ts, t_end=ts + 5000))
    rc, _, err = _run(["evaluate", "overexpose", p, "--gain", "4", "--method", "akf", "--out", tmp_path / "e",
                       "--no-progress", "--no-figures"], capsys)
    assert rc == 1 and "mid-exposure time" in err and not (tmp_path / "e").exists()


# -- view --recon ---------------------------------------------------------------------------------------
def _recon_of(tmp_path, capsys, ss, name):
    p = _rec(tmp_path / f"{name}.h5", ss=ss)
    rc, _, err = _run(["reconstruct", p, "--out", tmp_path / name, "--fps", "20", "--method", "highpass",
                       "--no-progress"], capsys)
    assert rc == 0, err
    return p, tmp_path / name


def test_view_recon_of_another_size_is_refused(tmp_path, capsys):
    p, _ = _recon_of(tmp_path, capsys, (24, 32), "a")
    _, other = _recon_of(tmp_path, capsys, (30, 40), "b")
    rc, _, err = _run(["view", p, "--recon", other, "--out", tmp_path / "v.mp4", "--no-progress"], capsys)
    assert rc == 1 and "40x30" in err and "32x24" in err and not (tmp_path / "v.mp4").exists()


@pytest.mark.parametrize("kind", ["fifo", "dev_zero", "deep"])
def test_view_recon_run_json_read_is_bounded(tmp_path, capsys, kind):
    p, rec = _recon_of(tmp_path, capsys, (24, 32), "a")
    run = rec / "run.json"
    run.unlink()
    if kind == "fifo":
        os.mkfifo(run)
    elif kind == "dev_zero":
        os.symlink("/dev/zero", run)
    else:
        run.write_text("[" * 5000 + "]" * 5000)
    res = _load_in_thread(lambda: _run(["view", p, "--recon", rec, "--out", tmp_path / "v.mp4", "--no-progress"],
                                       capsys))
    assert res[0] == 1 and "run.json" in res[2]


@pytest.mark.parametrize("kind", ["fifo", "dev_zero", "deep"])
def test_brackets_json_read_is_bounded(tmp_path, kind):
    from hybridhdr.errors import FormatError
    from hybridhdr.formats.brackets import read_bracket_set, write_bracket_set
    b = tmp_path / "br"
    write_bracket_set(b, [np.full((8, 8), 60, np.uint8), np.full((8, 8), 120, np.uint8)], [0.01, 0.02],
                      encoding="linear")
    meta = b / "brackets.json"
    meta.unlink()
    if kind == "fifo":
        os.mkfifo(meta)
    elif kind == "dev_zero":
        os.symlink("/dev/zero", meta)
    else:
        meta.write_text('{"a": ' + "[" * 5000 + "]" * 5000 + "}")
    assert _load_in_thread(_raises(read_bracket_set, FormatError), b) == "refused"
