"""Benchmark the blinking-board event images and the corner detectors of ``calibrate rig``.

Usage: ``python benchmarks/calibrate_rig.py [--quick]``. Prints progress to stderr, then ONE JSON
object on the last stdout line.

A synthetic blinking stream is generated with a seeded generator: a 9x6 checkerboard (white
squares and margin) on a Prophesee Gen4 sized sensor (1280x720; 640x480 with ``--quick``) blinks
at 10 Hz for 12 periods (6 with ``--quick``); every white pixel fires 3-8 ON events after each rising edge and as many OFF events
after each falling edge (latency jitter 50-600 µs), plus 0.1 Hz/pixel background noise. Measured:

* ``event_images`` end to end (period from the event rate, window statistics, pose image) and
  the Numba window kernel alone, in Mev/s;
* a NumPy baseline of the same window classification (``np.bincount`` per window), and the
  kernel / NumPy speed ratio (no peer library implements blinking-board frames in Python; the
  Metavision SDK is not pip-installable);
* ``findChessboardCornersSB`` (``sb``) and ``sb+subpix`` time per event image.
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


def board_mask(h, w, cols=9, rows=6):
    sq = min(w // (cols + 3), h // (rows + 3))
    x0 = (w - (cols + 3) * sq) // 2
    y0 = (h - (rows + 3) * sq) // 2
    yy, xx = np.mgrid[0:h, 0:w]
    i = (xx - x0) // sq - 1
    j = (yy - y0) // sq - 1
    inside = (i >= -1) & (i <= cols + 1) & (j >= -1) & (j <= rows + 1)
    squares = (i >= 0) & (i <= cols) & (j >= 0) & (j <= rows)
    return inside & np.where(squares, (i + j) % 2 == 0, True)


def blink_stream(h, w, periods, period_us=100_000, seed=0):
    from hybridhdr.events import EVENT_DTYPE
    rng = np.random.default_rng(seed)
    m = board_mask(h, w)
    ys, xs = np.nonzero(m)
    k = rng.integers(3, 9, ys.size)
    ts, xl, yl, pl = [], [], [], []
    for n in range(periods):
        for edge, pol in ((0, 1), (period_us // 2, -1)):
            rep = np.repeat(np.arange(ys.size), k)
            t0 = 1_000_000 + n * period_us + edge
            ts.append(t0 + rng.integers(50, 600, rep.size))
            xl.append(xs[rep])
            yl.append(ys[rep])
            pl.append(np.full(rep.size, pol))
    dur = periods * period_us
    nn = rng.poisson(0.1 * h * w * dur * 1e-6)
    ts.append(1_000_000 + rng.integers(0, dur, nn))
    xl.append(rng.integers(0, w, nn))
    yl.append(rng.integers(0, h, nn))
    pl.append(rng.choice([-1, 1], nn))
    t = np.concatenate(ts)
    o = np.argsort(t, kind="stable")
    ev = np.empty(t.size, EVENT_DTYPE)
    ev["t"] = t[o]
    ev["x"] = np.concatenate(xl)[o]
    ev["y"] = np.concatenate(yl)[o]
    ev["p"] = np.concatenate(pl)[o]
    return ev


def numpy_window_stats(ev, h, w, w0, w1):
    t = ev["t"]
    idx = ev["y"].astype(np.int64) * w + ev["x"]
    out = []
    for a, b in zip(np.searchsorted(t, w0), np.searchsorted(t, w1)):
        pi, pp = idx[a:b], ev["p"][a:b]
        on = np.bincount(pi[pp > 0], minlength=h * w)
        off = np.bincount(pi[pp < 0], minlength=h * w)
        out.append(((on > 0) & (off > 0)).sum())
    return np.array(out)


def best_of(f, n=2):
    best, r = float("inf"), None
    for _ in range(n):
        t0 = time.perf_counter()
        r = f()
        best = min(best, time.perf_counter() - t0)
    return best, r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="640x480, 6 periods (under 60 s)")
    args = ap.parse_args()
    from hybridhdr.calibrate import _kernels as K
    from hybridhdr.calibrate.event_images import event_images, windows_from_period, blink_period_from_events
    from hybridhdr.calibrate.rig import Board, find_corners
    from hybridhdr.events import SensorSize

    h, w = (480, 640) if args.quick else (720, 1280)
    periods = 6 if args.quick else 12
    load0 = os.getloadavg()
    log(f"generating {periods} blink periods at {w}x{h} ...")
    ev = blink_stream(h, w, periods)
    n = ev.size
    size = SensorSize(h, w)
    log(f"{n} events; warming up the kernels")
    event_images(blink_stream(96, 128, 3), SensorSize(96, 128))
    t_end, res = best_of(lambda: event_images(ev, size))
    log(f"event_images: {t_end:.3f} s, {len(res.poses)} pose(s), period {res.period.period_us:.1f} µs")
    per = blink_period_from_events(ev)
    w0, w1 = windows_from_period(per, int(ev["t"][0]), int(ev["t"][-1]))
    cols = [np.ascontiguousarray(ev[f]) for f in ("x", "y", "p")]
    i0 = np.searchsorted(ev["t"], w0).astype(np.int64)
    i1 = np.searchsorted(ev["t"], w1).astype(np.int64)

    def kern():
        st = np.zeros((len(w0), K.N_STATS), np.int64)
        img = np.zeros(h * w)
        K.blink_window_stats(*cols, i0, i1, w, h * w, np.ones(len(w0), np.bool_), 1, False, img, st)
        return st

    t_k, st = best_of(kern)
    t_np, both_np = best_of(lambda: numpy_window_stats(ev, h, w, w0, w1), 1)
    if not np.array_equal(both_np, st[:, K.S_BOTH]):
        raise SystemExit("NumPy baseline and kernel disagree on the both-polarity counts")
    log(f"kernel {t_k:.3f} s, numpy {t_np:.3f} s")
    img = res.poses[0].image
    board = Board(9, 6, 30.0)
    t_sb, c = best_of(lambda: find_corners(img, board, detector="sb"))
    t_sp, c2 = best_of(lambda: find_corners(img, board, detector="sb+subpix"))
    load1 = os.getloadavg()
    out = {
        "benchmark": "calibrate_rig", "quick": args.quick, "sensor": f"{w}x{h}", "events": int(n),
        "blink_periods": periods, "period_found_us": round(res.period.period_us, 2),
        "event_images_s": round(t_end, 4), "event_images_mev_s": round(n / t_end / 1e6, 2),
        "kernel_s": round(t_k, 4), "kernel_mev_s": round(n / t_k / 1e6, 2),
        "numpy_baseline_s": round(t_np, 4), "kernel_vs_numpy": round(t_np / t_k, 2),
        "board_found": c is not None, "sb_ms_per_image": round(1e3 * t_sb, 1),
        "sb_subpix_ms_per_image": round(1e3 * t_sp, 1), "board_found_subpix": c2 is not None,
        "loadavg_before": [round(v, 2) for v in load0], "loadavg_after": [round(v, 2) for v in load1],
        "cpus": os.cpu_count(),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
