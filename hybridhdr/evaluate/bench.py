"""Benchmark runner: methods × datasets × parameter grids from a TOML bench file.

See ``docs/evaluate.md`` for the file format. Each *task* is one dataset variant (one point of
its grid) and runs every method variant on it in a worker process (local processes by default,
a Dask cluster with ``scheduler=ADDRESS``); each *run* yields one CSV row: quality metrics
(:func:`hybridhdr.evaluate.metrics.score_video`), wall time, time per second of data, events per
second and the worker's peak RSS during the run (Linux ``VmHWM``, reset before each run through
``/proc/self/clear_refs``; NaN elsewhere). Results are ordered by (task, method variant) whatever
the scheduler, and every random choice is seeded from the bench file, so local and Dask runs give
identical metric columns (tested).
"""

from __future__ import annotations

import copy
import csv
import itertools
import json
import math
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._util.atomic import atomic_outputs, atomic_path, remap_paths
from .._util.confine import confine
from .._util.toml import load_toml, loads_toml
from ..reconstruct.api import reconstruct, resolve_method
from ..simulate.procedural import procedural_recording
from .datasets import DATASET_KINDS, load_dataset
from .metrics import default_normalise, match_frames, score_video
from .report import write_report

__all__ = ["Bench", "RunSpec", "load_bench", "parse_bench", "expand", "run_bench", "run_task", "write_results",
           "TIMING_COLUMNS", "METRIC_COLUMNS", "bundled_bench", "BUNDLED"]

TIMING_COLUMNS = ("wall_s", "time_per_data_s", "events_per_s", "peak_rss_mb", "dataset_load_s",
                  "dataset_time_per_data_s", "jod_seconds")
METRIC_COLUMNS = ("mse", "psnr_db", "ssim", "global_ssim", "log_mse", "log_ssim", "pu_psnr_db", "pu_ssim", "jod", "q")
BUNDLED = ("demo", "speed_accuracy", "stability", "tiny")

_BENCH_KEYS = {"name", "seed", "tolerance_us", "peak_luminance_cd_m2", "hdrvdp_dir", "strips",
               "warmup", "cache_dir", "jod", "jod_frames", "jod_display", "weights"}
#: Methods whose ``params.weights`` a ``[bench] weights = { e2vid = PATH, firenet = PATH }`` table fills.
LEARNED = ("e2vid", "firenet")
_CHART_KEYS = {"speed_accuracy", "sampling", "stability"}
_METHOD_KEYS = {"name", "method", "params", "augment", "mode", "normalise", "threshold_factor", "grid"}


@dataclass(frozen=True)
class Bench:
    """A parsed bench file (see docs/evaluate.md)."""

    name: str
    seed: int
    tolerance_us: int
    peak_luminance_cd_m2: float
    datasets: list
    methods: list
    charts: dict = field(default_factory=dict)
    hdrvdp_dir: str | None = None
    strips: int = 4
    warmup: bool = True
    source: str = ""
    cache_dir: str | None = None
    jod: bool = True              # ColorVideoVDP JOD of every run (needs cvvdp; else "n/a")
    jod_frames: int = 8           # at most this many evenly spaced matched frames per run
    jod_display: str | None = None  # cvvdp display model (default standard_hdr_linear)
    weights: dict = field(default_factory=dict)  # learned method -> checkpoint path


@dataclass(frozen=True)
class RunSpec:
    """One method variant: label, method name and the resolved settings."""

    label: str
    name: str
    method: str
    params: dict
    augment: object
    mode: str
    normalise: str | None
    threshold_factor: float
    grid_values: dict


def _check_grid(grid, where: str) -> None:
    """A grid's shape (a table of non-empty lists), checked without expanding it."""
    if grid is None:
        return
    if not isinstance(grid, dict):
        raise TypeError(f"{where}.grid must be a table of name = [values], got {type(grid).__name__}")
    for n in grid:
        if not isinstance(grid[n], list) or not grid[n]:
            raise ValueError(f"{where}.grid.{n} must be a non-empty list, got {grid[n]!r}")


def _grid(grid: dict, where: str):
    if grid is None:
        return [{}]
    _check_grid(grid, where)
    names = list(grid)
    return [dict(zip(names, vals)) for vals in itertools.product(*(grid[n] for n in names))]


def _set_dotted(d: dict, key: str, value):
    parts = key.split(".")
    cur = d
    for p in parts[:-1]:
        cur = cur.setdefault(p, {})
        if not isinstance(cur, dict):
            raise ValueError(f"grid key {key!r}: {p!r} is not a table")
    cur[parts[-1]] = value


#: Dataset keys that name files a bench file reads (confined to its folder, ``docs/security.md``).
_DATASET_PATH_KEYS = ("path", "profile", "image")


def _confine_grid_params(grid, where: str, base: Path, source: str, allow_outside) -> None:
    """Grids may not set what the method table itself may not: ``allow_pickle`` is refused in any
    spelling (``params.allow_pickle``, a whole ``params`` table), and checkpoint ``weights`` set
    by a grid are confined to the bench file's folder like ``params.weights``."""
    if not isinstance(grid, dict):
        return
    for key, values in grid.items():
        leaf = str(key).split(".")[-1]
        if not isinstance(values, list):
            continue
        tables = [v for v in values if isinstance(v, dict)]
        if leaf == "allow_pickle" or any(_mentions(t, "allow_pickle") for t in tables):
            raise ValueError(f"{source}: {where}.{key} may not set allow_pickle in a bench file (it lets a checkpoint "
                             f"run Python code); load such weights from Python yourself (docs/security.md)")
        if leaf == "weights":
            grid[key] = [str(confine(v, base, allow_outside, what=f"{where}.{key}", source=source))
                         if isinstance(v, str) else v for v in values]
        for t in tables:
            if isinstance(t.get("weights"), str):
                t["weights"] = str(confine(t["weights"], base, allow_outside, what=f"{where}.{key}.weights",
                                           source=source))


def _mentions(d, key: str) -> bool:
    return isinstance(d, dict) and (key in d or any(_mentions(v, key) for v in d.values()))


def _grid_size(grid) -> int:
    n = 1
    if isinstance(grid, dict):
        for v in grid.values():
            n *= len(v) if isinstance(v, list) else 1
    return n


def _count_runs(ds: list, ms: list) -> int:
    """Runs a bench expands to (methods x method grids x dataset grids x method_grid), without expanding."""
    per_method = {m.get("name", m["method"]): _grid_size(m.get("grid")) for m in ms}
    total = 0
    for x in ds:
        names = x.get("methods") if isinstance(x.get("methods"), list) else list(per_method)
        runs = sum(per_method.get(n, 0) for n in names)
        total += runs * _grid_size(x.get("method_grid")) * _grid_size(x.get("grid"))
    return total


#: numbers of a dataset (or its grid) bounded before anything is built (docs/security.md)
_DATASET_BOUNDS = {"width": ("max_side", 1, True), "height": ("max_side", 1, True),
                   "duration_us": ("max_duration_us", 1, True)}


def _check_dataset_numbers(i: int, x: dict) -> None:
    from .._util.limits import check_number
    for key, (limit, lo, integer) in _DATASET_BOUNDS.items():
        values = [x[key]] if key in x else []
        grid = x.get("grid")
        if isinstance(grid, dict) and isinstance(grid.get(key), list):
            values += grid[key]
        for v in values:
            check_number(v, f"datasets[{i}].{key}", lo=lo, limit=limit, integer=integer)


def _check_runs(bench: "Bench", base: Path, allow_outside) -> None:
    """The expanded runs of a bench file: none may unpickle, every checkpoint inside the allowed folders."""
    for _, _, _, runs in expand(bench):
        for r in runs:
            if r.params.get("allow_pickle"):
                raise ValueError(f"{bench.source}: run {r.label!r} sets allow_pickle, which a bench file may not "
                                 f"(docs/security.md)")
            w = r.params.get("weights")
            if w is not None:
                real = confine(w, base, allow_outside, what=f"run {r.label!r} weights", source=bench.source)
                if not Path(os.fspath(w)).is_absolute() or os.path.realpath(os.fspath(w)) != str(real):
                    raise ValueError(f"{bench.source}: run {r.label!r}: weights {w!r} set in a way the bench "
                                     f"loader cannot confine; give it as params.weights or [bench].weights")


def _confine_bench_file(d: dict, base: Path, source: str, allow_outside, out_dir) -> None:
    """A bench loaded from a file reads and writes only inside its folder (and ``out_dir`` for its
    cache) unless ``allow_outside`` folders are given; it never names code to run (HDR-VDP's
    folder, unpickling checkpoints): those come from the command line or the environment."""
    b = d.get("bench", {})
    if b.get("hdrvdp_dir") is not None:
        raise ValueError(f"{source}: [bench].hdrvdp_dir is not accepted in a bench file (HDR-VDP runs the .m files of "
                         f"that folder); give it on the command line (--hdrvdp-dir) or in $HYBRIDHDR_HDRVDP_DIR "
                         f"(docs/security.md)")
    for i, m in enumerate(d.get("methods", [])):
        params = m.get("params") if isinstance(m, dict) else None
        if isinstance(params, dict) and params.get("allow_pickle"):
            raise ValueError(f"{source}: methods[{i}].params.allow_pickle is not accepted in a bench file (it lets a "
                             f"checkpoint run Python code); load such weights from Python yourself (docs/security.md)")
        if isinstance(m, dict):
            _confine_grid_params(m.get("grid"), f"methods[{i}].grid", base, source, allow_outside)
    for i, x in enumerate(d.get("datasets", [])):
        if isinstance(x, dict):
            _confine_grid_params(x.get("method_grid"), f"datasets[{i}].method_grid", base, source, allow_outside)
    for i, x in enumerate(d.get("datasets", [])):
        if not isinstance(x, dict):
            continue
        for key in _DATASET_PATH_KEYS:
            v = x.get(key)
            if isinstance(v, str) and not (key == "image" and v.startswith("procedural")):
                x[key] = str(confine(v, base, allow_outside, what=f"datasets[{i}].{key}", source=source))
        grid = x.get("grid")
        if isinstance(grid, dict):
            for key in _DATASET_PATH_KEYS:
                if isinstance(grid.get(key), list):
                    grid[key] = [str(confine(v, base, allow_outside, what=f"datasets[{i}].grid.{key}", source=source))
                                 if isinstance(v, str) and not v.startswith("procedural") else v for v in grid[key]]
    if isinstance(b.get("cache_dir"), str):
        roots = tuple(allow_outside or ()) + ((out_dir,) if out_dir is not None else ())
        b["cache_dir"] = str(confine(b["cache_dir"], base, roots, what="[bench].cache_dir", source=source))


def parse_bench(d: dict, source: str = "", *, allow_outside=(), out_dir=None) -> Bench:
    """Validate a bench dict (as loaded from TOML).

    When ``source`` is a bench file on disk, the files it names (dataset ``path``/``profile``/
    ``image``, checkpoints, ``cache_dir``) resolve relative to its folder and must lie inside it
    (``cache_dir`` also inside ``out_dir``) or an ``allow_outside`` folder, and it may not set
    ``hdrvdp_dir`` or ``allow_pickle`` (``docs/security.md``). A dict from Python is trusted."""
    if not isinstance(d, dict):
        raise TypeError(f"a bench must be a dict, got {type(d).__name__}")
    unknown = sorted(set(d) - {"bench", "datasets", "methods", "charts"})
    if unknown:
        raise ValueError(f"{source or 'bench'}: unknown top-level key(s) {unknown}; expected bench, datasets, "
                         f"methods, charts")
    b = d.get("bench", {})
    bad = sorted(set(b) - _BENCH_KEYS)
    if bad:
        raise ValueError(f"[bench]: unknown key(s) {bad}; expected some of {sorted(_BENCH_KEYS)}")
    ds, ms = d.get("datasets"), d.get("methods")
    if not isinstance(ds, list) or not ds:
        raise ValueError(f"{source or 'bench'}: needs at least one [[datasets]] entry")
    if not isinstance(ms, list) or not ms:
        raise ValueError(f"{source or 'bench'}: needs at least one [[methods]] entry")
    names = set()
    for i, x in enumerate(ds):
        if not isinstance(x, dict) or x.get("kind") not in DATASET_KINDS:
            raise ValueError(f"datasets[{i}]: 'kind' must be one of {DATASET_KINDS}, got {x.get('kind')!r}")
        x.setdefault("name", f"{x['kind']}{i}")
        if x["name"] in names:
            raise ValueError(f"datasets[{i}]: duplicate name {x['name']!r}")
        names.add(x["name"])
        _check_grid(x.get("grid"), f"datasets[{i}]")
        _check_grid(x.get("method_grid"), f"datasets[{i}].method_grid")
    labels = set()
    for i, m in enumerate(ms):
        if not isinstance(m, dict) or "method" not in m:
            raise ValueError(f"methods[{i}]: needs 'method'")
        bad = sorted(set(m) - _METHOD_KEYS)
        if bad:
            raise ValueError(f"methods[{i}]: unknown key(s) {bad}; expected some of {sorted(_METHOD_KEYS)}")
        resolve_method(m["method"])
        m.setdefault("name", m["method"])
        if m["name"] in labels:
            raise ValueError(f"methods[{i}]: duplicate name {m['name']!r}")
        labels.add(m["name"])
        _check_grid(m.get("grid"), f"methods[{i}]")
    charts = d.get("charts", {})
    if not isinstance(charts, dict) or sorted(set(charts) - _CHART_KEYS):
        raise ValueError(f"{source or 'bench'}: unknown [charts] table(s) "
                         f"{sorted(set(charts) - _CHART_KEYS) if isinstance(charts, dict) else charts!r}; "
                         f"expected some of {sorted(_CHART_KEYS)}")
    for i, x in enumerate(ds):
        _check_dataset_numbers(i, x)
    from .._util.limits import LIMITS, LimitExceeded, OVERRIDE_HINT, huge_allowed
    n_runs = _count_runs(ds, ms)
    if n_runs > LIMITS["max_runs"] and not huge_allowed():
        raise LimitExceeded(source or None, f"the bench expands to {n_runs:,} runs (methods x grids x datasets), "
                                            f"above the limit of {LIMITS['max_runs']:,}; {OVERRIDE_HINT}")
    tol = b.get("tolerance_us", 1000)
    if isinstance(tol, bool) or not isinstance(tol, int) or tol < 0:
        raise ValueError(f"[bench].tolerance_us must be an int >= 0 (µs), got {tol!r}")
    jod = b.get("jod", True)
    if not isinstance(jod, bool):
        raise ValueError(f"[bench].jod must be true or false, got {jod!r}")
    jf = b.get("jod_frames", 8)
    if isinstance(jf, bool) or not isinstance(jf, int) or jf < 1:
        raise ValueError(f"[bench].jod_frames must be an int >= 1, got {jf!r}")
    jd = b.get("jod_display")
    if jd is not None and not isinstance(jd, str):
        raise ValueError(f"[bench].jod_display must be a cvvdp display name, got {jd!r}")
    weights = b.get("weights") or {}
    if not isinstance(weights, dict) or not all(k in LEARNED and isinstance(v, str) for k, v in weights.items()):
        raise ValueError(f"[bench].weights must be a table {{ e2vid = PATH, firenet = PATH }}, got {weights!r}")
    base = Path(source).resolve().parent if source and Path(source).is_file() else None
    if base is not None:
        _confine_bench_file(d, base, str(source), allow_outside, out_dir)

    def _path(v):  # relative checkpoint paths are relative to the bench file, and stay inside its folder
        if base is None:
            return v
        return str(confine(v, base, allow_outside, what="checkpoint (weights)", source=str(source)))
    weights = {k: _path(v) for k, v in weights.items()}
    for m in ms:
        if resolve_method(m["method"]) in LEARNED:
            params = m.setdefault("params", {})
            if params.get("weights"):
                params["weights"] = _path(params["weights"])
            elif resolve_method(m["method"]) in weights:
                params["weights"] = weights[resolve_method(m["method"])]
    bench = Bench(name=str(b.get("name", Path(source).stem if source else "bench")), seed=int(b.get("seed", 0)),
                 tolerance_us=tol, peak_luminance_cd_m2=float(b.get("peak_luminance_cd_m2", 4000.0)),
                 datasets=ds, methods=ms, charts=d.get("charts", {}), hdrvdp_dir=b.get("hdrvdp_dir"),
                 strips=int(b.get("strips", 4)), warmup=bool(b.get("warmup", True)),
                 source=str(source), cache_dir=b.get("cache_dir"), jod=jod, jod_frames=jf, jod_display=jd,
                 weights=weights)
    if base is not None:
        _check_runs(bench, base, allow_outside)
    return bench


def bundled_bench(name: str) -> str:
    """Text of a bench file bundled in ``hybridhdr/evaluate/benches/NAME.toml``."""
    from importlib import resources
    f = resources.files("hybridhdr.evaluate").joinpath("benches", f"{name}.toml")
    if not f.is_file():
        raise FileNotFoundError(f"no bundled bench {name!r}; bundled: {list(BUNDLED)}")
    return f.read_text(encoding="utf-8")


def load_bench(path_or_name, *, allow_outside=(), out_dir=None) -> Bench:
    """Load a bench file, or a bundled one by name (``demo``, ``speed_accuracy``, ``stability``, ``tiny``).

    A bench file is confined to its folder (and ``out_dir`` for its cache) unless
    ``allow_outside`` folders are given (:func:`parse_bench`)."""
    p = Path(path_or_name)
    if p.is_file():
        return parse_bench(load_toml(p), str(p), allow_outside=allow_outside, out_dir=out_dir)
    if str(path_or_name) in BUNDLED:
        return parse_bench(loads_toml(bundled_bench(str(path_or_name))), f"<bundled {path_or_name}>")
    raise FileNotFoundError(f"bench file {path_or_name} not found (bundled benches: {list(BUNDLED)})")


def expand(bench: Bench):
    """The task list: ``[(dataset_name, dataset_spec, dataset_grid_values, [RunSpec ...]), ...]``."""
    runs = []
    for m in bench.methods:
        for gv in _grid(m.get("grid"), f"methods[{m['name']}]"):
            mm = copy.deepcopy({k: v for k, v in m.items() if k != "grid"})
            for k, v in gv.items():
                _set_dotted(mm, k, v)
            label = m["name"] + ("" if not gv else " [" + ", ".join(f"{k}={v}" for k, v in gv.items()) + "]")
            method = resolve_method(mm["method"])
            runs.append(RunSpec(label, m["name"], method, dict(mm.get("params", {})), mm.get("augment"),
                                mm.get("mode", "offline"), mm.get("normalise") or default_normalise(method),
                                float(mm.get("threshold_factor", 1.0)), gv))
    tasks = []
    for x in bench.datasets:
        ds_runs = runs
        if x.get("methods") is not None:
            want = x["methods"]
            missing = sorted(set(want) - {r.name for r in runs})
            if missing:
                raise ValueError(f"datasets[{x['name']}].methods names unknown method(s) {missing}")
            ds_runs = [r for r in runs if r.name in want]
        if x.get("method_grid"):
            # a per-dataset grid over method settings (e.g. threshold_factor for the misestimate sweep)
            base, ds_runs = ds_runs, []
            for r in base:
                for gv in _grid(x["method_grid"], f"datasets[{x['name']}].method_grid"):
                    params, aug, tf = dict(r.params), r.augment, r.threshold_factor
                    for k, v in gv.items():
                        if k == "threshold_factor":
                            tf = float(v)
                        elif k == "augment":
                            aug = v
                        elif k.startswith("params."):
                            params[k[7:]] = v
                        else:
                            raise ValueError(f"datasets[{x['name']}].method_grid: key {k!r} must be threshold_factor, "
                                             f"augment or params.NAME")
                    label = r.label + " [" + ", ".join(f"{k}={v}" for k, v in gv.items()) + "]"
                    ds_runs.append(RunSpec(label, r.name, r.method, params, aug, r.mode, r.normalise, tf,
                                           {**r.grid_values, **gv}))
        for gv in _grid(x.get("grid"), f"datasets[{x['name']}]"):
            spec = {k: v for k, v in x.items() if k not in ("grid", "method_grid", "methods")}
            spec.update(gv)
            tasks.append((x["name"], spec, gv, ds_runs))
    return tasks


# -- worker side --------------------------------------------------------------------------------

def _peak_rss_reset() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


_WARM: set = set()


def _method_params(run: RunSpec, c_sensor):
    p = dict(run.params)
    if run.method in ("akf", "cf", "highpass", "direct", "edi") and c_sensor is not None:
        # the method's threshold: the sensor's nominal one times threshold_factor, unless given
        if not any(k.startswith("contrast_threshold") for k in p) and run.method != "edi":
            p["contrast_threshold"] = float(c_sensor) * run.threshold_factor
    if run.method == "edi" and c_sensor is not None and "contrast_threshold" not in p:
        p["contrast_threshold"] = float(c_sensor) * run.threshold_factor
    return p


def _warmup(run: RunSpec, profile=None):
    """JIT-load each method's kernels once per worker so that timings exclude compilation: the
    warm-up call is the timed call's kind (output times between the frames, the dataset's camera
    profile), so no kernel meets a new signature inside the timed region (a kernel compiled there
    made plain "akf" look slower than "akf augmented" in the speed-accuracy chart)."""
    key = (run.method, json.dumps(run.augment, sort_keys=True, default=str), run.mode,
           None if profile is None else getattr(profile, "name", type(profile).__name__))
    if key in _WARM:
        return
    rec, _ = procedural_recording((16, 16), 120_000, seed=0, frame_rate_hz=20.0)
    times = np.arange(int(rec.frames.t_mid_us[0]), int(rec.frames.t_mid_us[-1]), 10_000, dtype=np.int64)
    try:
        reconstruct(rec, run.method, _method_params(run, 0.2), times_us=times, mode=run.mode, augment=run.augment,
                    profile=profile, thresholds="input")
    except Exception:  # the real run reports the error
        pass
    _WARM.add(key)


def _strip_frame(video_frames, vi, ri, ref_images, frames, ref_t):
    """Middle matched frame of a run: (reconstruction, reference, LDR input) images."""
    k = len(ri) // 2
    rec_img = video_frames[vi[k]]
    ref_img = ref_images[ri[k]]
    ldr = None
    if frames is not None and len(frames):
        j = int(np.argmin(np.abs(frames.t_mid_us - ref_t[ri[k]])))
        ldr = np.asarray(frames.images[j])
    return rec_img, ref_img, ldr


def run_task(task, bench_opts: dict) -> list[dict]:
    """Run every method variant of one dataset variant; returns one row dict per run."""
    ds_name, spec, ds_gv, runs = task
    seed = int(bench_opts["seed"])
    rows = []
    t_load = time.perf_counter()
    try:
        data = load_dataset(spec, seed=seed, cache_dir=bench_opts.get("cache_dir"))
        err = None
    except Exception as e:  # reported per run
        data, err = None, f"{type(e).__name__}: {e}"
    t_load = time.perf_counter() - t_load
    strip = {}
    for run in runs:
        variant = ds_name + ("" if not ds_gv else " [" + ", ".join(f"{k}={v}" for k, v in ds_gv.items()) + "]")
        row = {"dataset": ds_name, "dataset_variant": variant, "kind": spec["kind"],
               **{f"ds.{k}": v for k, v in ds_gv.items()},
               "method_label": run.label, "method_name": run.name, "method": run.method, **{f"m.{k}": v for k, v in run.grid_values.items()},
               "augment": json.dumps(run.augment, sort_keys=True) if run.augment is not None else "",
               "mode": run.mode, "normalise": run.normalise, "threshold_factor": run.threshold_factor,
               "dataset_seconds": float("nan"), "dataset_load_s": t_load}
        if data is None:
            row.update(status="error: " + err)
            rows.append(row)
            continue
        rec = data.recording
        hdr = rec.hdr
        ref = hdr.images if hdr.images.ndim == 3 else hdr.images.mean(axis=3)
        row["dataset_seconds"] = data.duration_us * 1e-6
        row["n_events"] = int(len(rec.events))
        try:
            if bench_opts.get("warmup", True):
                _warmup(run, data.profile)
            params = _method_params(run, data.contrast_threshold)
            first = int(rec.frames.t_mid_us.min()) if rec.frames is not None and len(rec.frames) else None
            times = hdr.t_us if first is None else hdr.t_us[hdr.t_us >= first]
            if run.method == "highpass":
                times = times[times > int(rec.events["t"][0])] if len(rec.events) else times
            _peak_rss_reset()
            t0 = time.perf_counter()
            v = reconstruct(rec, run.method, params, times_us=times, mode=run.mode, augment=run.augment,
                            profile=data.profile, thresholds="input")
            wall = time.perf_counter() - t0
            row["peak_rss_mb"] = _peak_rss_mb()
            vi, ri = match_frames(v.t_us, hdr.t_us, int(bench_opts["tolerance_us"]))
            if len(vi) == 0:
                raise ValueError("no reconstructed frame within tolerance_us of any reference")
            hv = None
            if bench_opts.get("hdrvdp_dir"):
                hv = {"hdrvdp_dir": bench_opts["hdrvdp_dir"]}
            jod = None
            if bench_opts.get("jod", True):
                jod = {"max_frames": int(bench_opts.get("jod_frames", 8)), "display": bench_opts.get("jod_display")}
            sc = score_video(v.frames[vi], ref[ri], normalise=run.normalise,
                             peak_luminance_cd_m2=float(bench_opts["peak_luminance_cd_m2"]), hdrvdp=hv, jod=jod)
            row.update(sc)
            row.update(wall_s=wall, time_per_data_s=wall / max(data.duration_us * 1e-6, 1e-12),
                       dataset_time_per_data_s=t_load / max(data.duration_us * 1e-6, 1e-12),
                       events_per_s=(v.info.get("n_events_used", len(rec.events)) / wall if wall > 0 else float("nan")),
                       status="ok")
            r_img, ref_img, ldr = _strip_frame(v.frames, vi, ri, ref, rec.frames, hdr.t_us)
            from .metrics import apply_normalisation
            t01 = apply_normalisation(r_img, sc["gain"], sc["exponent"] if run.normalise == "affine" else sc["offset"],
                                      run.normalise)
            strip[run.label] = t01.astype(np.float32)
            strip.setdefault("__reference__", ref_img.astype(np.float32))
            if ldr is not None:
                strip.setdefault("__ldr__", ldr)
        except Exception as e:
            row.update(status=f"error: {type(e).__name__}: {e}")
        rows.append(row)
    if rows:
        rows[0]["_strip"] = strip
    return rows


# -- driver -------------------------------------------------------------------------------------

def _bench_opts(bench: Bench) -> dict:
    return {"seed": bench.seed, "tolerance_us": bench.tolerance_us, "peak_luminance_cd_m2": bench.peak_luminance_cd_m2,
            "hdrvdp_dir": bench.hdrvdp_dir, "warmup": bench.warmup, "cache_dir": bench.cache_dir,
            "jod": bench.jod, "jod_frames": bench.jod_frames, "jod_display": bench.jod_display}


def _bench_worker_init(bench_pid: int | None = None):
    from .._util.procs import die_with_parent, die_with_process
    die_with_parent()  # its parent (the forkserver) gone: end
    if bench_pid is not None:
        # the forkserver outlives a kill -9 of the bench: watch the bench itself, so that the
        # workers end, and with them the forkserver's and the resource tracker's last clients
        die_with_process(bench_pid)


def _stop_pool(ex) -> None:
    """Cancel queued tasks and end the worker processes (SIGTERM, then SIGKILL after 5 s)."""
    procs = list((getattr(ex, "_processes", None) or {}).values())
    ex.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        try:
            p.terminate()
        except Exception:
            pass
    for p in procs:
        try:
            p.join(5)
            if p.is_alive():
                p.kill()
                p.join(1)
        except Exception:
            pass


def _pool_context():
    import multiprocessing as mp
    try:
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(["hybridhdr.evaluate.bench"])
        return ctx
    except ValueError:  # pragma: no cover - platforms without forkserver
        return mp.get_context("spawn")


# -- runs that survive an interruption (Ctrl-C, a killed job): one file per finished task, --resume

#: Folder under ``--out`` holding one ``task_NNNNN.json`` (its rows) and ``.npz`` (its strip
#: images) per finished task (a dataset variant with its method runs), each written atomically
#: as the task finishes.
RUNS_DIR = "runs"


def _file_digest(path: Path, cache: dict) -> str:
    """SHA-256 of a file's bytes (a folder: of its files' relative names and bytes, in order)."""
    import hashlib
    key = os.path.realpath(path)
    if key in cache:
        return cache[key]
    h = hashlib.sha256()
    p = Path(key)
    if p.is_file():
        files = [p]
    else:  # a dataset folder (ECD, brackets): its files, up to a bound that no dataset reaches
        files = []
        for q in p.rglob("*"):
            if q.is_file() and not q.is_symlink():
                files.append(q)
                if len(files) > 100_000:
                    raise ValueError(f"{p} holds more than 100,000 files; not a dataset folder")
        files.sort()
    for q in files:
        h.update(str(q.relative_to(p) if q != p else q.name).encode() + b"\0")
        with open(q, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    cache[key] = h.hexdigest()
    return cache[key]


def _data_digests(obj, cache: dict, out: dict) -> dict:
    """Digest of every file or folder that a task's spec, grid values or runs name (dataset
    recordings, profiles, weights, thresholds maps): ``--resume`` must see a changed file."""
    if isinstance(obj, dict):
        for v in obj.values():
            _data_digests(v, cache, out)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            _data_digests(v, cache, out)
    elif isinstance(obj, (str, Path)) and str(obj) and len(str(obj)) < 4096:
        p = Path(obj)
        try:
            if (p.is_file() or p.is_dir()) and (p.is_absolute() or os.sep in str(obj) or p.suffix):
                out[str(obj)] = _file_digest(p, cache)
        except (OSError, ValueError) as e:
            out[str(obj)] = f"unreadable: {e}"
    return out


def _task_key(task, opts: dict, cache: dict | None = None) -> str:
    """A digest of everything a task's rows depend on (dataset, grid values, runs, bench options,
    and the bytes of every file they name), so that ``--resume`` reuses a finished task only for
    the same bench on the same data."""
    import dataclasses
    import hashlib
    ds_name, spec, ds_gv, runs = task
    run_dicts = [dataclasses.asdict(r) for r in runs]
    data = _data_digests([spec, ds_gv, run_dicts], {} if cache is None else cache, {})
    blob = json.dumps([ds_name, spec, ds_gv, run_dicts,
                       {k: v for k, v in opts.items() if k != "warmup"}, data], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


def _plain(v):
    if isinstance(v, np.generic):
        return v.item()
    raise TypeError(f"cannot store {type(v).__name__} in a run file")


def _save_task(runs_dir: Path, i: int, key: str, rows: list[dict]) -> list[dict]:
    """Write task ``i``'s rows (and strip images) atomically; returns the rows as read back, so
    that a resumed and an uninterrupted bench report the same values (JSON round trip)."""
    strip = rows[0].get("_strip", {}) if rows else {}
    plain = [{k: v for k, v in r.items() if k != "_strip"} for r in rows]
    text = json.dumps({"key": key, "task": i, "rows": plain}, default=_plain)
    if strip:
        with atomic_path(runs_dir / f"task_{i:05d}.npz", ".npz") as tmp:
            np.savez(tmp, **{f"s{j}": np.asarray(v) for j, v in enumerate(strip.values())},
                     names=np.array(list(strip.keys()), dtype=str))
    with atomic_path(runs_dir / f"task_{i:05d}.json") as tmp:  # last: the task counts as finished
        Path(tmp).write_text(text, encoding="utf-8")
    return _load_task(runs_dir, i, key)


#: Bounds on a run file read back by ``--resume`` (a task's rows are a few kB; its strip a few MB).
_RUN_FILE_BYTES = 16 << 20
_STRIP_FILE_BYTES = 256 << 20

#: Ranges a measured value can take (anything else in a run file is made up: the task runs again).
_ROW_RANGES = {"mse": (0.0, math.inf), "log_mse": (0.0, math.inf), "ssim": (-1.0, 1.0), "global_ssim": (-1.0, 1.0),
               "log_ssim": (-1.0, 1.0), "pu_ssim": (-1.0, 1.0), "psnr_db": (-math.inf, math.inf),
               "pu_psnr_db": (-math.inf, math.inf), "jod": (-math.inf, 10.0), "q": (-math.inf, math.inf),
               "n_frames": (0, math.inf), "n_nonfinite": (0, math.inf), "n_events": (0, math.inf)}


def _run_file(path: Path, limit: int) -> bytes | None:
    """The bytes of a run file: a regular file (never through a link, never a FIFO or a device)
    of at most ``limit`` bytes, else None (the task is run again)."""
    import stat
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size > limit:
            return None
        with os.fdopen(os.dup(fd), "rb") as f:
            data = f.read(limit + 1)
        return data if len(data) <= limit else None
    finally:
        os.close(fd)


_COLUMN_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.\-]{0,199}")


def _row_ok(r) -> bool:
    """A run-file row holds column names of the kind a run writes (words, dotted grid keys) and
    values of the right kind and range."""
    if not isinstance(r, dict):
        return False
    for k, v in r.items():
        if not isinstance(k, str) or not _COLUMN_NAME.fullmatch(k):
            return False
        if v is None or isinstance(v, (bool, str)):
            if isinstance(v, str) and len(v) > 100_000:
                return False
            continue
        if not isinstance(v, (int, float)):
            return False  # a list or a table where a run writes a number or a word
        if k in _ROW_RANGES:
            lo, hi = _ROW_RANGES[k]
            if not (math.isnan(v) or lo <= v <= hi):
                return False
    return True


def _load_task(runs_dir: Path, i: int, key: str) -> list[dict] | None:
    """Task ``i``'s rows from a run file written for the same ``key``, else None.

    A run file is data anyone with write access to ``OUT`` controls: it is read only when it is a
    regular file within a size bound, parsed with the nesting bounded, and its rows are taken only
    when every column is one a run writes and every measured value lies in its range; anything
    else makes the task run again."""
    data = _run_file(runs_dir / f"task_{i:05d}.json", _RUN_FILE_BYTES)
    if data is None:
        return None
    try:
        d = json.loads(data.decode("utf-8"))
    except (ValueError, RecursionError):
        return None
    if not isinstance(d, dict) or d.get("key") != key or not isinstance(d.get("rows"), list):
        return None
    rows = d["rows"]
    if not all(_row_ok(r) for r in rows):
        return None
    z = runs_dir / f"task_{i:05d}.npz"
    if rows and (z.exists() or z.is_symlink()):
        strip = _load_strip(z)
        if strip is None:
            return None
        rows[0]["_strip"] = strip
    return rows


def _load_strip(z: Path) -> dict | None:
    """A task's strip images from its ``.npz``: a regular file within bounds, every array 2-D or
    3-D with sides within the frame limits (checked from the headers, before any allocation)."""
    import io
    import zipfile
    from .._util.limits import LIMITS
    data = _run_file(z, _STRIP_FILE_BYTES)
    if data is None:
        return None
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            if sum(m.file_size for m in zf.infolist()) > 4 * _STRIP_FILE_BYTES:
                return None
        with np.load(io.BytesIO(data), allow_pickle=False) as a:
            names = [str(n) for n in a["names"]]
            out = {}
            for j, n in enumerate(names):
                im = a[f"s{j}"]
                if im.ndim not in (2, 3) or max(im.shape[:2]) > LIMITS["max_side"] or im.dtype.kind not in "uif":
                    return None
                out[n] = im
            return out
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, RecursionError):
        return None


def run_bench(bench: Bench, *, workers: int | None = None, scheduler: str | None = None,
              progress: bool = True, out_dir=None, resume: bool = False) -> list[dict]:
    """Run all tasks; returns rows in (task, method) order.

    With ``out_dir``, each task's rows are written to ``out_dir/runs/task_NNNNN.json`` (and its
    strip images to ``.npz``) atomically as soon as it finishes, so an interrupted bench keeps
    every finished task; ``resume=True`` reads those back and runs only the others (a file
    written for another bench, or other options, is run again). Without ``resume`` earlier run
    files are replaced.

    Parameters
    ----------
    workers : int, optional
        Local worker processes (default ``min(2, cpu_count)``); 0 runs in this process.
    scheduler : str, optional
        Dask scheduler address (``tcp://host:8786``) or a ``dask.distributed`` Client/cluster;
        the tasks are submitted in order and gathered in order.
    """
    tasks = expand(bench)
    opts = _bench_opts(bench)
    bar = None
    results: list = [None] * len(tasks)
    digests: dict = {}
    keys = [_task_key(t, opts, digests) for t in tasks]
    runs_dir = None
    if out_dir is not None:
        runs_dir = Path(out_dir) / RUNS_DIR
        runs_dir.mkdir(parents=True, exist_ok=True)
        if resume:
            for i in range(len(tasks)):
                results[i] = _load_task(runs_dir, i, keys[i])
        else:
            old = list(runs_dir.glob("task_*.json"))
            if old:
                print(f"note: bench {bench.name}: replacing the {len(old)} finished task(s) in {runs_dir} "
                      f"(--resume reuses them)", file=sys.stderr)
            for f in old + list(runs_dir.glob("task_*.npz")):
                f.unlink()
    todo = [i for i in range(len(tasks)) if results[i] is None]
    if resume and out_dir is not None:
        print(f"bench {bench.name}: resuming, {len(tasks) - len(todo)} of {len(tasks)} tasks already finished "
              f"in {runs_dir}", file=sys.stderr)

    def done(i, rows):
        results[i] = rows if runs_dir is None else _save_task(runs_dir, i, keys[i], rows)
        if bar is not None:
            bar.update(1)

    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(tasks), initial=len(tasks) - len(todo), desc=f"bench {bench.name}", unit="task",
                   file=sys.stderr, dynamic_ncols=True)
    try:
        if scheduler is not None:
            try:
                from dask.distributed import Client, as_completed
            except ImportError as e:
                raise ImportError("--scheduler needs dask[distributed] (pip install 'hybridhdr[evaluate]')") from e
            own = isinstance(scheduler, str)
            client = Client(scheduler) if own else (scheduler if hasattr(scheduler, "submit") else Client(scheduler))
            try:
                import uuid
                tag = uuid.uuid4().hex[:12]  # fresh keys: a reused Client must not return old results
                futs = [client.submit(run_task, tasks[i], opts, key=f"hybridhdr-bench-{bench.name}-{tag}-{i}",
                                      pure=False) for i in todo]
                index = {f.key: i for f, i in zip(futs, todo)}
                for f in as_completed(futs):
                    done(index[f.key], f.result())
            finally:
                if own or not hasattr(scheduler, "submit"):
                    client.close()
        else:
            n = min(2, os.cpu_count() or 1) if workers is None else int(workers)
            if n < 0:
                raise ValueError(f"workers must be >= 0, got {n}")
            if n == 0:
                for i in todo:
                    done(i, run_task(tasks[i], opts))
            elif todo:
                from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor
                from concurrent.futures import wait as cf_wait
                ex = ProcessPoolExecutor(max_workers=n, mp_context=_pool_context(), initializer=_bench_worker_init,
                                         initargs=(os.getpid(),))
                try:
                    futs = {ex.submit(run_task, tasks[i], opts): i for i in todo}
                    pending = set(futs)
                    while pending:
                        # short waits: the main thread wakes to take a Ctrl-C even when the signal
                        # went to another thread, instead of at the next finished task
                        fin, pending = cf_wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                        for f in sorted(fin, key=lambda f: futs[f]):
                            done(futs[f], f.result())
                except BaseException:
                    # SIGTERM, Ctrl-C, an error: end the workers now and leave none behind (a worker
                    # that got the SIGINT too would only fail its task and go on with the queue); the
                    # finished tasks are already in OUT/runs/ for --resume
                    _stop_pool(ex)
                    raise
                ex.shutdown(wait=True)
    finally:
        if bar is not None:
            bar.close()
    rows = []
    for i, rs in enumerate(results):
        for j, r in enumerate(rs):
            r["task"] = i
            r["run"] = j
            rows.append(r)
    return rows


#: The lock file a running bench holds in its ``--out`` (left in place; never counted as content).
BENCH_LOCK = ".hybridhdr-bench.lock"


def claim_bench_out(out, *, overwrite: bool = False, resume: bool = False) -> int:
    """Take ``out`` for one bench run: created if absent, refused while another bench holds its
    lock, refused when it holds anything (other than the lock) unless ``overwrite`` or ``resume``.
    Returns the locked descriptor (close it when the bench is done)."""
    from .._util.atomic import try_lock, refuse_existing_output
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out / BENCH_LOCK, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666)
    try:
        if not try_lock(fd):
            raise ValueError(f"--out {out} is being written by another running bench; wait for it or choose "
                             f"another folder")
        if not resume and any(p.name != BENCH_LOCK for p in out.iterdir()):
            refuse_existing_output(out, overwrite=overwrite, flag="--out", command="evaluate bench")
    except BaseException:
        os.close(fd)
        raise
    return fd


def remove_stale_outputs(out, written: dict) -> None:
    """After a report is written: remove the strips an earlier run left in ``out/strips`` that
    this report does not show (its charts are replaced by name)."""
    keep = {Path(p).name for p in written.get("strips", [])}
    d = Path(out) / "strips"
    if d.is_dir():
        for p in d.glob("strip_*.png"):
            if p.name not in keep and (p.is_file() or p.is_symlink()):
                p.unlink()


def _columns(rows):
    first = ["task", "run", "dataset", "dataset_variant", "kind"]
    ds = sorted({k for r in rows for k in r if k.startswith("ds.")})
    mid = ["method_label", "method_name", "method"]
    mg = sorted({k for r in rows for k in r if k.startswith("m.")})
    rest = ["augment", "mode", "normalise", "threshold_factor", "status", "n_frames", *METRIC_COLUMNS,
            "n_nonfinite", "gain", "offset", "exponent", "reference_max", "peak_luminance_cd_m2", "dataset_seconds",
            "n_events", *TIMING_COLUMNS, "dataset_load_s", "dataset_time_per_data_s"]
    extra = sorted({k for r in rows for k in r} - set(first + ds + mid + mg + rest) - {"_strip"})
    return list(dict.fromkeys(first + ds + mid + mg + rest + extra))  # unique, first place kept


def _cell(text: str) -> str:
    """A text cell a spreadsheet would run as a formula (``=``, ``+``, ``-``, ``@``, a tab or a
    carriage return first) is quoted with a leading apostrophe; numbers are written as numbers."""
    return "'" + text if text[:1] in ("=", "+", "-", "@", "\t", "\r") else text


def _fmt(v):
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, (bool, int, np.integer, np.floating)):
        return str(v)
    return "" if v is None else _cell(str(v))


def write_results(rows, out_dir, bench: Bench | None = None, *, charts: bool = True) -> dict:
    """Write ``results.csv``, ``strips/*.png``, charts and ``report.md`` / ``report.html``.

    Returns the paths written (name -> Path).
    """
    out = Path(out_dir)
    # all or none (a full disk leaves no CSV and charts without their report): staged, then renamed in
    with atomic_outputs(out, last=("results.csv", "report.html", "report.md")) as stage:
        cols = _columns(rows)
        path = stage / "results.csv"
        with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow([_cell(c) for c in cols])
            for r in rows:
                w.writerow([_fmt(r.get(c)) for c in cols])
        written = {"csv": path}
        written.update(write_report(rows, stage, bench, charts=charts))
    return remap_paths(written, stage, out)


def read_results(path) -> list[dict]:
    """Read ``results.csv`` back (numbers as float where they parse)."""
    rows = []
    with open(path, newline="", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            d = {}
            for k, v in r.items():
                try:
                    d[k] = float(v) if v not in ("",) and k not in ("dataset", "dataset_variant", "kind", "method_label", "method_name", "method",
                                                                     "augment", "mode", "normalise", "status",
                                                                     "jod_display", "jod_display_line", "jod_note") else v
                except ValueError:
                    d[k] = v
            rows.append(d)
    return rows
