"""Benchmark the simulator: renderer variants, the run-time estimate, adaptive sampling, event generation.

Usage: ``python benchmarks/simulate.py [--quick]``. Prints progress on stderr, then ONE JSON object
on the last stdout line.

Renderer and estimate (``llvm_vs_scalar``, ``estimate_table``):

- the LLVM renderer (``llvm_ad_mono`` with the libLLVM the simulator chose: a system libLLVM 17-19 or
  the karellen-llvm-core wheel; the line says which) against ``scalar_rgb`` in the same process, on
  the same scene, size, spp and render times: renders/s of each, their ratio (target >= 3x at
  346x260), and the events each gives from the same sensor and seed;
- the time estimate 'simulate' prints after its first renders against the run's measured wall time
  on every built-in scene (full mode: each at its default size and duration, in a fresh process as a
  user runs it; target within +-30 %); ``--quick`` runs the same comparison in this process on two
  scenes (blinking_checkerboard: periodic switches, 0.3 s; slow_static, its 1 s) at 64x48, and the renderer comparison on 5 render times (same scene, size and times for both);
- full mode also times the README's simulate example end to end (target <= 3 min on 2 cores).

Adaptive sampling and event generation:

- adaptive sampling reaches the event fidelity of a dense fixed-rate reference (per-pixel event
  count error <= 5 %, timestamp RMSE printed) with >= 3x fewer renders, on built-in scenes;
- render ms per frame and renders per second at 320x240 for the variant in use (``cuda_ad_mono``
  on an NVIDIA GPU; scalar_rgb too for comparison);
- event generation >= 20 M events/s (the sensor model's Numba kernel through ``EventSensor.step``);
- a 1 s built-in scene at 346x260 simulates in < 60 s on 2 cores with LLVM (full mode only).

The fidelity comparison uses the ``ideal`` sensor (no noise), so both runs see the same radiance
function and differ only in their render times, against a dense fixed-rate reference. Two adaptive
settings run: the sampler defaults (``robust_quantile=0.99``: the brightness rule ignores the 1 %
of pixels with the largest change) and ``robust_quantile=0.999``, which shows why: anti-aliasing
samples crossing a 10^4-contrast edge jump by several log units whatever the step, and with the
0.999 quantile they force bisection to the maximum rate)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import loadavg  # noqa: E402



def log(*a):
    print(*a, file=sys.stderr, flush=True)


class _Window:
    """A time window [t_start, t_start + duration] of a source, re-based to start at 0 (keeps the
    scene's real speeds, unlike shortening the scene, which stretches its trajectories)."""

    def __init__(self, src, t_start_us, duration_us):
        self.src, self.t0 = src, int(t_start_us)
        self.sensor_size = src.sensor_size
        self.duration_us = int(min(duration_us, src.duration_us - self.t0))
        self.renders = 0

    def render(self, t_us):
        self.renders += 1
        return self.src.render(self.t0 + int(t_us))

    def max_image_speed_px_per_s(self, t0_us, t1_us):
        return self.src.max_image_speed_px_per_s(self.t0 + int(t0_us), self.t0 + int(t1_us))

    def describe(self):
        return {**self.src.describe(), "window_us": [self.t0, self.t0 + self.duration_us]}


def fidelity_case(name, w, h, t_start_s, dur_s, ref_hz, spp):
    from hybridhdr.simulate import MitsubaSource, SamplingParams, builtin_scene, event_fidelity, simulate
    sc = builtin_scene(name, width=w, height=h, spp=spp)
    out = {"scene": name, "size": f"{w}x{h}", "window_s": [t_start_s, t_start_s + dur_s], "reference_rate_hz": ref_hz}
    runs = {}
    configs = (("reference", SamplingParams(mode="fixed", fixed_rate_hz=ref_hz)),
               ("adaptive", SamplingParams(mode="adaptive")),
               ("adaptive_q0999", SamplingParams(mode="adaptive", robust_quantile=0.999)))
    for label, sp in configs:
        msrc = MitsubaSource(sc)
        msrc.render(0)  # JIT warm-up outside the timing
        src = _Window(msrc, int(t_start_s * 1e6), int(dur_s * 1e6))
        t0 = time.perf_counter()
        res = simulate(src, sensor="ideal", camera=None, sampling=sp, seed=0, progress=False)
        wall = time.perf_counter() - t0
        runs[label] = res.recording.events
        out[label] = {"renders": int(res.renders), "events": int(len(res.recording.events)),
                      "wall_s": round(wall, 2), "render_s": round(float(res.stats.get("render_s", np.nan)), 2)}
        if label != "reference":
            fid = event_fidelity(res.recording.events, runs["reference"], src.sensor_size)
            out[label].update({
                "count_error": round(fid["count_error"], 4),
                "timestamp_rmse_us": round(fid["timestamp_rmse_us"], 1) if np.isfinite(fid["timestamp_rmse_us"]) else None,
                "render_ratio": round(out["reference"]["renders"] / max(1, res.renders), 2)})
            out[label]["met"] = out[label]["count_error"] <= 0.05 and out[label]["render_ratio"] >= 3
            log(f"  {name} {label}: {res.renders} renders ({out[label]['render_ratio']}x fewer), "
                f"{len(res.recording.events)} events, count error {fid['count_error']:.2%}, "
                f"timestamp RMSE {fid['timestamp_rmse_us']:.0f} µs, {wall:.1f} s")
        else:
            log(f"  {name} {label}: {res.renders} renders, {len(res.recording.events)} events, {wall:.1f} s")
    out["variant"] = msrc.variant
    return out


def render_speed(variant, w=320, h=240, n=20, scene="night_drive_sign"):
    from hybridhdr.simulate import MitsubaSource, builtin_scene
    src = MitsubaSource(builtin_scene(scene, width=w, height=h, spp=4), variant=variant)
    ts = np.linspace(0, src.duration_us, n + 2).astype(np.int64)
    src.render(int(ts[0]))
    src.render(int(ts[1]))  # JIT / first BVH
    best = np.inf
    t0 = time.perf_counter()
    for t in ts[2:]:
        t1 = time.perf_counter()
        src.render(int(t))
        best = min(best, time.perf_counter() - t1)
    mean = (time.perf_counter() - t0) / n
    return {"variant": src.variant, "scene": scene, "size": f"{w}x{h}", "spp": 4,
            "ms_per_frame_mean": round(mean * 1e3, 1), "ms_per_frame_best": round(best * 1e3, 1),
            "renders_per_s": round(1.0 / mean, 2)}


def event_rate(n_pairs=30, w=346, h=260):
    """Mev/s of the sensor model on synthetic radiance with many crossings per step."""
    from hybridhdr.events import SensorSize
    from hybridhdr.simulate import EventSensor
    rng = np.random.default_rng(0)
    base = rng.uniform(0.05, 1.0, (h, w)).astype(np.float32)
    # alternating +-1.5 log units: ~7 events per pixel per step at C = 0.2
    imgs = [base * np.float32(np.exp(1.5 * (k % 2))) for k in range(n_pairs + 1)]
    s = EventSensor(SensorSize(h, w), "ideal", seed=0)
    s.start(0, imgs[0])
    s.step(1000, imgs[1])  # compile / load cache
    n = 0
    t0 = time.perf_counter()
    for k in range(2, n_pairs + 1):
        n += len(s.step(1000 * k, imgs[k]))
    el = time.perf_counter() - t0
    return {"events": n, "seconds": round(el, 3), "mev_s": round(n / el / 1e6, 2), "size": f"{w}x{h}"}


def end_to_end_1s(name="dark_room_window", extra=(), timeout_s=300):
    """`hybridhdr simulate builtin:NAME` for 1 s at 346x260 in a fresh process (includes start-up)."""
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "rec.h5"
        cmd = [sys.executable, "-m", "hybridhdr", "simulate", f"builtin:{name}", "--duration-s", "1",
               "--out", str(out), "--no-progress", "--json", *extra]
        t0 = time.perf_counter()
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, cwd=str(Path(__file__).resolve().parents[1]),
                               timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return {"scene": name, "options": list(extra), "error": f"not finished in {timeout_s} s"}
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            return {"scene": name, "options": list(extra), "error": r.stderr.strip().splitlines()[-1:]}
        summary = json.loads(r.stdout.strip().splitlines()[-1])
        summary.update({"scene": name, "options": list(extra), "size": "346x260", "duration_s": 1.0,
                        "process_wall_s": round(wall, 1), "goal_s": 180})
        return summary


def llvm_vs_scalar(scene="window_scenery", w=346, h=260, window_s=(0.3, 0.012), rate_hz=1000):
    """Both variants on the same renders: a ``window_s`` (start, length) window of ``scene`` at a fixed
    render rate, the clean sensor with seed 0, no frame camera."""
    from hybridhdr.simulate import MitsubaSource, SamplingParams, builtin_scene, simulate
    from hybridhdr.simulate.render import llvm_source, select_variant, variant_reason
    auto = select_variant()
    out = {"scene": scene, "size": f"{w}x{h}", "window_s": list(window_s), "fixed_rate_hz": rate_hz,
           "auto_variant": variant_reason(auto), "libllvm": llvm_source()}
    runs = {}
    for variant in ("llvm_ad_mono", "scalar_rgb"):
        if variant == "llvm_ad_mono" and auto not in ("llvm_ad_mono", "cuda_ad_mono"):
            out[variant] = {"error": "not usable here: " + variant_reason(auto)}
            continue
        src = MitsubaSource(builtin_scene(scene, width=w, height=h), variant=variant)
        src.render(0)  # JIT / scene load outside the timing
        win = _Window(src, int(window_s[0] * 1e6), int(window_s[1] * 1e6))
        r0 = src.render_time_s
        t0 = time.perf_counter()
        res = simulate(win, sensor="clean", camera=None, sampling=SamplingParams(mode="fixed", fixed_rate_hz=rate_hz),
                       seed=0, progress=False)
        wall = time.perf_counter() - t0
        rt = src.render_time_s - r0
        runs[variant] = res.recording.events
        out[variant] = {"renders": res.renders, "render_s": round(rt, 2), "renders_per_s": round(res.renders / rt, 2),
                        "wall_s": round(wall, 2), "events": int(len(res.recording.events))}
        log(f"  {variant}: {res.renders} renders at {w}x{h}, {out[variant]['renders_per_s']} renders/s, "
            f"{len(res.recording.events)} events")
    if "renders_per_s" in out.get("llvm_ad_mono", {}):
        out["speedup"] = round(out["llvm_ad_mono"]["renders_per_s"] / out["scalar_rgb"]["renders_per_s"], 2)
        out["speedup_goal"] = 3.0
        from hybridhdr.simulate import event_fidelity
        fid = event_fidelity(runs["llvm_ad_mono"], runs["scalar_rgb"], (h, w))
        out["event_count_error_llvm_vs_scalar"] = round(fid["count_error"], 4)
    return out


def estimate_case(name, w=None, h=None, duration_s=None, timeout_s=900):
    """'hybridhdr simulate builtin:NAME' in a fresh process: its printed estimate against its wall time."""
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "rec.h5"
        cmd = [sys.executable, "-m", "hybridhdr", "simulate", f"builtin:{name}", "--out", str(out), "--no-progress",
               "--json"]
        if w:
            cmd += ["--width", str(w), "--height", str(h)]
        if duration_s:
            cmd += ["--duration-s", str(duration_s)]
        t0 = time.perf_counter()
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, cwd=str(Path(__file__).resolve().parents[1]),
                               timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return {"scene": name, "error": f"not finished in {timeout_s} s"}
        proc = time.perf_counter() - t0
    if r.returncode != 0:
        return {"scene": name, "error": (r.stderr.strip().splitlines() or ["?"])[-1]}
    s = json.loads(r.stdout)
    est, wall = s.get("estimate_s"), s["wall_s"]
    row = {"scene": name, "size": f"{w}x{h}" if w else "default", "renders": s["renders"],
           "estimate_renders": s["estimate_renders"], "variant": s["variant"],
           "estimate_s": est, "wall_s": wall, "process_wall_s": round(proc, 1),
           "estimate_error": None if est is None else round(est / wall - 1, 3), "loadavg": loadavg()}
    row["within_30pct"] = est is not None and abs(est / wall - 1) <= 0.30
    log(f"  {name}: estimate {est} s, took {wall} s ({row['estimate_error']}), {s['renders']} renders")
    return row


def estimate_case_inprocess(name, w, h, duration_s=None):
    """The same comparison as :func:`estimate_case`, in this process (no interpreter start-up): the
    command's own run (``run_simulation``: probes, estimate after the first renders, the run)."""
    import tempfile

    from hybridhdr.simulate import MitsubaSource, builtin_scene
    from hybridhdr.simulate.camera import FrameCameraParams
    from hybridhdr.simulate.resume import partial_path
    from hybridhdr.simulate.runner import run_simulation
    from hybridhdr.simulate.sampling import SamplingParams
    from hybridhdr.simulate.sensor import sensor_preset
    src = MitsubaSource(builtin_scene(name, width=w, height=h, duration_s=duration_s))
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "rec.h5"
        _, s = run_simulation(src, out, partial_path(out), resume=False, sensor=sensor_preset("clean"),
                              camera=FrameCameraParams(frame_rate_hz=20.0, exposure_us=10_000),
                              sampling=SamplingParams(), gt_times_us=None, seed=0, progress=False, say=lambda m: None)
    est, wall = s["estimate_s"], s["wall_s"]
    row = {"scene": name, "size": f"{w}x{h}", "duration_s": src.duration_us / 1e6, "renders": s["renders"],
           "estimate_renders": s["estimate_renders"], "variant": s["variant"], "estimate_s": est, "wall_s": wall,
           "estimate_error": None if est is None else round(est / wall - 1, 3), "loadavg": loadavg()}
    row["within_30pct"] = est is not None and abs(est / wall - 1) <= 0.30
    log(f"  {name}: estimate {est} s ({s['estimate_renders']} renders), took {wall} s ({s['renders']} renders): "
        f"{row['estimate_error']}")
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="few renders per comparison, 2 small short scenes in the estimate table (under 60 s)")
    args = ap.parse_args(argv)
    from hybridhdr.simulate import select_variant
    res: dict = {"quick": bool(args.quick), "cpu_count": os.cpu_count(), "loadavg_start": loadavg()}
    t_all = time.perf_counter()
    variant = select_variant()
    res["variant"] = variant
    log(f"variant {variant}")

    log("LLVM against scalar_rgb at 346x260 (same scene, renders, sensor and seed) ...")
    res["llvm_vs_scalar"] = llvm_vs_scalar(window_s=(0.3, 0.004 if args.quick else 0.03))
    from hybridhdr.simulate.builtin import BUILTIN_SCENES
    log("estimate against the measured time, every built-in scene ...")
    if args.quick:  # a periodic-switch scene and a static one, small and short (the full table: full mode)
        # (long enough for the estimate: it is printed after the 40th render)
        res["estimate_table"] = [estimate_case_inprocess(n, 64, 48, duration_s=d)
                                 for n, d in (("blinking_checkerboard", 0.3), ("slow_static", None))]
    else:
        res["estimate_table"] = [estimate_case(n) for n in BUILTIN_SCENES]
    res["estimate_all_within_30pct"] = all(r.get("within_30pct") for r in res["estimate_table"])

    if args.quick:
        cases = [("dark_room_window", 64, 48, 0.4, 0.01, 10_000, 2)]
    else:
        cases = [("dark_room_window", 173, 130, 0.4, 0.1, 20_000, 4), ("night_drive_sign", 173, 130, 0.2, 0.1, 20_000, 4),
                 ("slow_static", 173, 130, 0.0, 0.2, 20_000, 4),
                 ("blinking_checkerboard", 173, 130, 0.0, 0.2, 20_000, 4)]
    res["fidelity"] = [fidelity_case(*c) for c in cases]
    res["fidelity_goal"] = {"count_error_max": 0.05, "render_ratio_min": 3.0}
    for k in ("adaptive", "adaptive_q0999"):
        res[f"fidelity_met_{k}"] = all(c[k]["met"] for c in res["fidelity"])

    if not args.quick:  # (quick: llvm_vs_scalar above measures the renderers)
        log("render speed at 320x240 ...")
        res["render"] = [render_speed(variant, n=30)]
        if variant != "scalar_rgb":
            res["render"].append(render_speed("scalar_rgb", n=10))
        for r in res["render"]:
            log(f"  {r['variant']}: {r['ms_per_frame_mean']} ms/frame mean, {r['ms_per_frame_best']} best, "
                f"{r['renders_per_s']} renders/s")
        res["renders_per_s"] = res["render"][0]["renders_per_s"]  # the variant in use (cuda_ad_mono on a GPU)

    log("event generation ...")
    res["event_generation"] = event_rate(n_pairs=8 if args.quick else 40)
    res["event_generation"]["goal_mev_s"] = 20
    log(f"  {res['event_generation']['mev_s']} Mev/s")

    if not args.quick:
        log("1 s built-in scene at 346x260 end to end (window_scenery: the README's example) ...")
        res["end_to_end_1s"] = []
        for name, extra in (("window_scenery", ()), ("slow_static", ()), ("dark_room_window", ())):
            res["end_to_end_1s"].append(end_to_end_1s(name, extra))
            log(f"  {res['end_to_end_1s'][-1]}")
    res["loadavg_end"] = loadavg()
    res["total_s"] = round(time.perf_counter() - t_all, 1)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
