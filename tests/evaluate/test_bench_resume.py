"""Long benches survive an interruption: each finished task is written as it finishes and
``--resume`` runs only the others, with the same results (no hours of work lost to Ctrl-C)."""

from __future__ import annotations

import csv

import pytest

from hybridhdr.cli import main
from hybridhdr.evaluate import bench as B

#: Columns that measure the machine, not the result (they differ between any two runs).
_MACHINE = set(B.TIMING_COLUMNS) | {"dataset_load_s", "dataset_time_per_data_s", "peak_rss_mb", "wall_s",
                                  "time_per_data_s", "events_per_s", "jod_seconds"}


def _results(path):
    with open(path, newline="", encoding="utf-8") as f:
        return [{k: v for k, v in r.items() if k not in _MACHINE} for r in csv.DictReader(f)]


@pytest.mark.slow
def test_interrupted_bench_resumes_to_the_same_results(tmp_path, capsys, monkeypatch):
    argv = ["evaluate", "bench", "tiny", "--workers", "0", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "full")]) == 0
    capsys.readouterr()

    real = B.run_task
    calls = []

    def interrupted(task, opts):  # the second task is interrupted (Ctrl-C) after the first finished
        calls.append(task[0])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(task, opts)
    monkeypatch.setattr(B, "run_task", interrupted)
    out = tmp_path / "cut"
    assert main([*argv, "--out", str(out)]) == 130
    capsys.readouterr()
    assert sorted(p.name for p in (out / B.RUNS_DIR).iterdir()) == ["task_00000.json", "task_00000.npz"]
    assert not (out / "results.csv").exists()

    monkeypatch.setattr(B, "run_task", real)
    ran = []
    monkeypatch.setattr(B, "run_task", lambda task, opts: ran.append(task) or real(task, opts))
    assert main([*argv, "--out", str(out), "--resume"]) == 0
    err = capsys.readouterr().err
    assert "1 of 2 tasks already finished" in err
    assert len(ran) == 1  # only the unfinished task ran again
    full, resumed = _results(tmp_path / "full" / "results.csv"), _results(out / "results.csv")
    assert len(full) == 8 and full == resumed
    assert sorted(p.name for p in (out / "strips").iterdir()) == sorted(p.name for p in (tmp_path / "full" /
                                                                                          "strips").iterdir())


def test_run_file_of_another_bench_is_not_reused(tmp_path):
    """A task file whose key differs (other bench or options) is ignored by --resume."""
    rows = [{"dataset": "d", "status": "ok", "mse": 0.5, "_strip": {}}]
    got = B._save_task(tmp_path, 0, "k1", rows)
    assert got == [{"dataset": "d", "status": "ok", "mse": 0.5}]
    assert B._load_task(tmp_path, 0, "k1") == got and B._load_task(tmp_path, 0, "k2") is None
    assert B._load_task(tmp_path, 1, "k1") is None
