"""Benchmark the evaluation metrics and the benchmark runner.

Usage: ``python benchmarks/evaluate.py [--quick]``. Prints progress to stderr, then ONE JSON
object on the last stdout line.

- SSIM (Gaussian σ = 1.5, data range 1): ours (``hybridhdr.evaluate.metrics.ssim``) against the
  peer scikit-image ``structural_similarity(gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1)`` on the same frames, best of 3; ratio and the
  largest absolute difference.
- PU21 encoding throughput (Mpixel/s) and ``score_video`` per frame.
- The runner: the bundled ``tiny`` bench in this process, with 2 local processes and, if Dask is
  installed, on an in-process ``LocalCluster``; wall times and whether the metric columns agree.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def best(fn, repeat=3):
    b = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        b = min(b, time.perf_counter() - t0)
    return b


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller images and fewer frames (< 60 s)")
    args = ap.parse_args()
    from skimage.metrics import structural_similarity

    from hybridhdr.evaluate import bench as B
    from hybridhdr.evaluate import metrics as M

    res = {"loadavg_1min": os.getloadavg()[0], "quick": args.quick}
    k, h, w = (8, 260, 346) if args.quick else (20, 480, 640)
    rng = np.random.default_rng(0)
    ref = rng.random((k, h, w))
    test = np.clip(ref + 0.05 * rng.standard_normal((k, h, w)), 0, 1)
    log(f"SSIM on {k} frames of {w}x{h}")
    ours = best(lambda: M.ssim(test, ref, 1.0))
    peer = best(lambda: [structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                               data_range=1.0) for a, b in zip(test, ref)])
    diff = max(abs(M.ssim(a, b, 1.0) - structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                                                               use_sample_covariance=False, data_range=1.0))
               for a, b in zip(test[:3], ref[:3]))
    res.update(ssim_ours_ms_per_frame=1e3 * ours / k, ssim_skimage_ms_per_frame=1e3 * peer / k,
               ssim_speed_ratio_ours_over_skimage=peer / ours, ssim_max_abs_diff=diff)
    pu = best(lambda: M.pu21_encode(ref * 4000))
    res["pu21_mpix_per_s"] = ref.size / pu / 1e6
    sv = best(lambda: M.score_video(test, ref, normalise="scale"), 2)
    res["score_video_ms_per_frame"] = 1e3 * sv / k

    bench = B.load_bench("tiny")
    log("runner: bundled 'tiny' bench in-process, 2 local processes, Dask LocalCluster")
    t0 = time.perf_counter()
    r0 = B.run_bench(bench, workers=0, progress=False)
    res["tiny_bench_in_process_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    r2 = B.run_bench(bench, workers=2, progress=False)
    res["tiny_bench_2_processes_s"] = time.perf_counter() - t0
    skip = set(B.TIMING_COLUMNS) | {"_strip"}
    same = lambda a, b: [{k2: v for k2, v in r.items() if k2 not in skip} for r in a] == \
        [{k2: v for k2, v in r.items() if k2 not in skip} for r in b]  # noqa: E731
    res["local_processes_equal_in_process"] = same(r0, r2)
    try:
        from dask.distributed import LocalCluster
        with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=":0") as cl:
            t0 = time.perf_counter()
            rd = B.run_bench(bench, scheduler=cl.scheduler_address, progress=False)
            res["tiny_bench_dask_localcluster_s"] = time.perf_counter() - t0
        res["dask_equal_local"] = same(r0, rd)
    except ImportError:
        res["dask_equal_local"] = None
    res["tiny_bench_runs"] = len(r0)
    for key, v in res.items():
        log(f"  {key}: {v}")
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
