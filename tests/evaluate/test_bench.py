"""Benchmark runner: parsing, determinism, local processes vs Dask, CSV/report outputs."""

import csv
import math

import numpy as np
import pytest

from hybridhdr.evaluate import bench as B
from hybridhdr.evaluate.datasets import load_dataset, requantise, add_noise_events
from hybridhdr.events import EVENT_DTYPE

MICRO = {
    "bench": {"name": "micro", "seed": 3, "tolerance_us": 1000, "warmup": False, "strips": 1},
    "datasets": [{"name": "d", "kind": "procedural", "width": 24, "height": 16, "duration_us": 150_000,
                  "disc_radius_px": 4.0, "grid": {"noise_rate_hz": [0.0, 30.0]}}],
    "methods": [{"name": "akf", "method": "akf", "augment": False}, {"name": "cf", "method": "cf"},
                {"name": "hpf", "method": "hpf"}],
    "charts": {"speed_accuracy": {"metrics": ["mse", "ssim"]},
               "stability": [{"dataset": "d", "axis": "noise_rate_hz", "metric": "ssim", "bound": 0.2}]},
}


def _bench():
    import copy
    return B.parse_bench(copy.deepcopy(MICRO), "micro")


def _metric_rows(rows):
    skip = set(B.TIMING_COLUMNS) | {"dataset_load_s", "_strip"}
    return [{k: v for k, v in r.items() if k not in skip} for r in rows]


def test_parse_errors():
    with pytest.raises(ValueError, match="at least one"):
        B.parse_bench({"bench": {}, "methods": [{"method": "akf"}]})
    with pytest.raises(ValueError, match="kind"):
        B.parse_bench({"datasets": [{"kind": "nope"}], "methods": [{"method": "akf"}]})
    with pytest.raises(ValueError, match="unknown method"):
        B.parse_bench({"datasets": [{"kind": "procedural"}], "methods": [{"method": "xx"}]})
    with pytest.raises(ValueError, match="non-empty list"):
        B.parse_bench({"datasets": [{"kind": "procedural", "grid": {"noise_rate_hz": 3}}],
                       "methods": [{"method": "akf"}]})
    with pytest.raises(ValueError, match="unknown key"):
        B.parse_bench({"bench": {"sed": 1}, "datasets": [{"kind": "procedural"}], "methods": [{"method": "akf"}]})


def test_expand_grid_and_dotted_keys():
    b = B.parse_bench({"datasets": [{"kind": "procedural", "name": "p", "grid": {"a": [1, 2], "b": [3]}}],
                       "methods": [{"name": "akf", "method": "akf",
                                    "grid": {"params.frame_precision_scale": [1e5, 1e6], "augment": [True, False]}}]})
    tasks = B.expand(b)
    assert [t[2] for t in tasks] == [{"a": 1, "b": 3}, {"a": 2, "b": 3}]
    runs = tasks[0][3]
    assert len(runs) == 4
    assert runs[0].params == {"frame_precision_scale": 1e5} and runs[0].augment is True
    assert runs[3].label == "akf [params.frame_precision_scale=1000000.0, augment=False]"
    assert runs[0].normalise == "none"  # unaltered by default (the paper's scoring)


def test_requantise_kernel_matches_py_func_and_model():
    from hybridhdr.evaluate._kernels import requantise_events
    rng = np.random.default_rng(0)
    n = 400
    t = np.sort(rng.integers(0, 10_000, n)).astype(np.int64)
    x = rng.integers(0, 3, n).astype(np.uint16)
    y = rng.integers(0, 2, n).astype(np.uint16)
    p = np.where(rng.random(n) < 0.6, 1, -1).astype(np.int8)
    c_on = rng.uniform(0.05, 0.2, 6)
    c_off = rng.uniform(0.05, 0.2, 6)
    for refr in (0, 500):
        outs = []
        for fn in (requantise_events, requantise_events.py_func):
            o = (np.empty(4 * n, np.int64), np.empty(4 * n, np.uint16), np.empty(4 * n, np.uint16),
                 np.empty(4 * n, np.int8))
            k, ovf = fn(t, x, y, p, 3, 0.05, c_on, c_off, refr, *o)
            assert not ovf
            outs.append([a[:k].copy() for a in o])
        for a, b in zip(*outs):
            np.testing.assert_array_equal(a, b)
    # identity: thresholds equal to c_fine, no refractory -> the events come back unchanged
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = t, x, y, p
    back = requantise(ev, (2, 3), 0.05, np.full((2, 3), 0.05), np.full((2, 3), 0.05), 0)
    np.testing.assert_array_equal(back, ev)
    # a threshold of 2 c_fine halves a run of same-polarity steps
    run = np.zeros(10, EVENT_DTYPE)
    run["t"] = np.arange(10) * 100
    run["p"] = 1
    out = requantise(run, (1, 1), 0.05, np.full((1, 1), 0.1), np.full((1, 1), 0.1), 0)
    assert out["t"].tolist() == [100, 300, 500, 700, 900]
    # refractory 250 µs, threshold c_fine: 0 fires; 100 and 200 are blocked (backlog 2 steps);
    # 300 fires once and drops the backlog; 400, 500 blocked; 600 fires; ...
    out = requantise(run, (1, 1), 0.05, np.full((1, 1), 0.05), np.full((1, 1), 0.05), 250)
    assert out["t"].tolist() == [0, 300, 600, 900]  # one event per refractory period, backlog lost


def test_noise_events_rate_and_seed():
    ev = np.zeros(0, EVENT_DTYPE)
    a = add_noise_events(ev, (10, 20), 50.0, 0, 1_000_000, np.random.default_rng(1))
    b = add_noise_events(ev, (10, 20), 50.0, 0, 1_000_000, np.random.default_rng(1))
    np.testing.assert_array_equal(a, b)
    # 200 px · 50 Hz · 1 s = 10000 expected; Poisson sd 100 -> 5 sd = 500
    assert abs(len(a) - 10_000) < 500
    assert np.all(np.diff(a["t"]) >= 0)


def test_dataset_same_seed_same_bits():
    s = {"kind": "procedural", "width": 24, "height": 16, "duration_us": 100_000, "noise_rate_hz": 10.0,
         "threshold_mismatch_sigma": 0.1, "exposure_scale": 0.5}
    a, b = load_dataset(s, seed=5), load_dataset(s, seed=5)
    np.testing.assert_array_equal(a.recording.events, b.recording.events)
    np.testing.assert_array_equal(a.recording.frames.images, b.recording.frames.images)
    c = load_dataset(s, seed=6)
    assert not np.array_equal(a.recording.events, c.recording.events)
    with pytest.raises(ValueError, match="unknown 'procedural' dataset key"):
        load_dataset({"kind": "procedural", "noise": 1})


@pytest.mark.slow
def test_local_processes_equal_dask_and_in_process(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    b = _bench()
    local = B.run_bench(b, workers=2, progress=False)
    inproc = B.run_bench(b, workers=0, progress=False)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=":0") as cl:
        with distributed.Client(cl) as client:
            dask_rows = B.run_bench(b, scheduler=cl.scheduler_address, progress=False)
            assert client.status == "running"
    assert len(local) == 6
    assert all(r["status"] == "ok" for r in local)
    assert _metric_rows(local) == _metric_rows(dask_rows) == _metric_rows(inproc)
    # the CSV files agree outside the timing columns
    w1 = B.write_results(local, tmp_path / "local", b, charts=False)
    w2 = B.write_results(dask_rows, tmp_path / "dask", b, charts=False)
    def load(p):
        with open(p, newline="") as f:
            rows = list(csv.DictReader(f))
        return [{k: v for k, v in r.items() if k not in B.TIMING_COLUMNS + ("dataset_load_s",)} for r in rows]
    assert load(w1["csv"]) == load(w2["csv"])
    r0 = local[0]
    assert r0["method"] == "akf" and r0["ds.noise_rate_hz"] == 0.0
    assert r0["n_events"] > 0 and r0["time_per_data_s"] > 0 and r0["events_per_s"] > 0
    assert 0 < r0["ssim"] <= 1 and 0 <= r0["mse"] < 1
    assert math.isfinite(r0["peak_rss_mb"]) and r0["peak_rss_mb"] > 10  # a Python worker is > 10 MB


def test_write_results_report_and_strip(tmp_path):
    b = _bench()
    rows = B.run_bench(b, workers=0, progress=False)
    w = B.write_results(rows, tmp_path, b)
    md = w["report_md"].read_text()
    assert "| d | akf |" in md and "AKF vs CF" in md and "Numerical failures" in md
    assert (tmp_path / "report.html").read_text().startswith("<!DOCTYPE html>")
    for k in ("speed_accuracy", "stability"):
        assert w[k].stat().st_size > 10_000
    assert len(w["strips"]) == 1 and w["strips"][0].stat().st_size > 2_000
    back = B.read_results(w["csv"])
    assert len(back) == len(rows) and back[1]["method"] == "cf"
    assert back[1]["mse"] == pytest.approx(rows[1]["mse"], rel=1e-15)
    assert not list(tmp_path.glob("*.partial*"))


def test_bundled_benches_parse():
    for name in B.BUNDLED:
        b = B.load_bench(name)
        assert B.expand(b)
    with pytest.raises(FileNotFoundError, match="bundled"):
        B.load_bench("no_such_bench")
