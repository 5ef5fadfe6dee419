"""Run the same reconstructions with two commits of hybridhdr and compare every output bit for bit.

Usage: ``python tools/compare_commits.py A B [--out DIR] [--quick] [--no-cudasim] [--no-cli]``

Each commit is exported with ``git archive`` into a temporary folder and imported from there in
its own Python process (the interpreter running this script), so neither the working tree nor
the installed package is used. Both processes run the same cases:

* every method and mode (``offline``, ``causal``, ``forward``) on the edge-sweep recording
  (:func:`hybridhdr.simulate.procedural.edge_sweep_recording`, seed 0, as the accuracy suite
  makes it) and on ``ecd_slider_depth`` (``$HYBRIDHDR_SHARED_DATA``, default
  ``../shared/data`` of the repository; skipped with a note when absent);
* the API's options that take other paths through the driver: frame augmentation, workers,
  fps outputs, a time window, a per-pixel threshold map, a frame time offset, parameters with
  and without thresholds (the recording's declared ones), a colour recording, a streamed
  container file;
* the ``hybridhdr reconstruct`` command on ``ecd_slider_depth`` with each ``--thresholds`` word
  (``selfcal`` is the default there), comparing the EXR files' bytes and ``run.json`` (without the
  command line and paths);
* the CUDA path (``device="cuda"``) under Numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``) on
  a small edge sweep, in a process of its own.

A case that raises records its error message, which must then be the same. ``info`` dictionaries
are compared too, without wall-clock entries. Prints one JSON object last:
``{"cases", "identical", "different": [...], "only_in_a"/"only_in_b": [...]}``; exit status 1
when anything differs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

RUNNER = r'''
import json, os, sys, traceback
from pathlib import Path
import numpy as np

out = Path(sys.argv[1]); which = sys.argv[2]; quick = sys.argv[3] == "1"; data = Path(sys.argv[4])
out.mkdir(parents=True, exist_ok=True)
from hybridhdr.reconstruct import reconstruct
from hybridhdr.simulate.procedural import edge_sweep_recording
from hybridhdr.events import SensorSize

def clean(o):
    if isinstance(o, dict):
        return {str(k): clean(v) for k, v in o.items()
                if not any(s in str(k) for s in ("wall", "seconds", "_s_", "time_s", "elapsed"))
                and not str(k).endswith("_s")}
    if isinstance(o, (list, tuple)):
        return [clean(v) for v in o]
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return {"ndarray": o.dtype.str, "shape": list(o.shape), "bytes": o.tobytes().hex()[:4096]}
    return o if isinstance(o, (int, float, str, bool, type(None))) else repr(o)

def run(name, src, method, params=None, **kw):
    try:
        v = reconstruct(src, method, params, **kw)
        np.savez(out / f"{name}.npz", frames=v.frames, t_us=v.t_us)
        res = {"info": clean(v.info), "params": clean(v.params), "method": v.method}
    except Exception as e:
        res = {"error": f"{type(e).__name__}: {e}"}
    (out / f"{name}.json").write_text(json.dumps(res, sort_keys=True, default=str))

METHODS = ["akf", "cf", "highpass", "direct", "frames_zoh", "frames_linear", "edi", "e2vid", "firenet"]
MODES = ["offline", "causal", "forward"]

if which == "cudasim":
    small, _ = edge_sweep_recording(0, sensor_size=SensorSize(8, 12), duration_us=120_000)
    for m in ["akf", "cf", "direct", "highpass"]:
        for mode in MODES:
            run(f"cudasim_{m}_{mode}", small, m, mode=mode, device="cuda")
    run("cudasim_akf_offline_aug", small, "akf", augment=True, device="cuda")
    sys.exit(0)

edge, _ = edge_sweep_recording(0, duration_us=300_000 if quick else 800_000)
sources = {"edge": edge}
ecd_dir = data / "ecd_slider_depth"
if ecd_dir.exists():
    from hybridhdr.formats import read
    sources["ecd"] = read(ecd_dir)
for sname, src in sources.items():
    for m in METHODS:
        for mode in MODES:
            run(f"{sname}_{m}_{mode}", src, m, mode=mode)
    run(f"{sname}_akf_offline_aug", src, "akf", augment=True)
    run(f"{sname}_akf_forward_aug", src, "akf", mode="forward", augment={"deblur": False})
    run(f"{sname}_akf_offline_w2", src, "akf", n_workers=2)
    run(f"{sname}_cf_forward_w2", src, "cf", mode="forward", n_workers=2)
    t0 = int(src.frames.t_mid_us[1]); t1 = int(src.frames.t_mid_us[-2])
    run(f"{sname}_akf_offline_fps", src, "akf", fps=120.0, t_start_us=t0, t_end_us=t1)
    run(f"{sname}_highpass_fps", src, "highpass", fps=90.0)
    run(f"{sname}_akf_causal_window", src, "akf", mode="causal", t_start_us=t0, t_end_us=t1)
    h, w = src.sensor_size.shape
    rng = np.random.default_rng(1)
    tmap = (rng.uniform(0.08, 0.2, (h, w)), rng.uniform(0.08, 0.2, (h, w)))
    run(f"{sname}_akf_offline_map", src, "akf", thresholds=tmap)
    run(f"{sname}_cf_causal_map", src, "cf", mode="causal", thresholds=tmap)
    run(f"{sname}_akf_offline_dt", src, "akf", frame_time_offset_us=3000)
    run(f"{sname}_direct_forward_dt", src, "direct", mode="forward", frame_time_offset_us=-2500)
    run(f"{sname}_akf_params_dict", src, "akf", {"process_noise_per_s": 1e-3})
    run(f"{sname}_akf_params_thr", src, "akf", {"contrast_threshold": 0.13})
    run(f"{sname}_cf_params_on_off", src, "cf", {"contrast_threshold_on": 0.12, "contrast_threshold_off": 0.09})
    run(f"{sname}_akf_times", src, "akf", mode="forward", times_us=np.array([t0, t0 + 777, t1], np.int64))
    run(f"{sname}_bad_mode", src, "akf", mode="sideways")
    run(f"{sname}_bad_workers", src, "akf", n_workers=0)
if not quick:
    from hybridhdr.simulate.procedural import colour_edge_sweep_recording
    col, _ = colour_edge_sweep_recording(0, duration_us=300_000)
    for m in ["akf", "cf", "frames_linear"]:
        run(f"colour_{m}_offline", col, m)
    run("colour_akf_none", col, "akf", cfa="none")
import tempfile
from hybridhdr.formats import write
with tempfile.TemporaryDirectory() as td:
    p = Path(td) / "edge.h5"
    write(edge, p)
    run("edge_file_akf_offline", str(p), "akf")
    run("edge_file_akf_aug", str(p), "akf", augment=True)
    run("edge_file_cf_causal", str(p), "cf", mode="causal", chunk_events=5000)
    if "ecd" in sources:
        run("ecd_dir_akf_offline", str(ecd_dir), "akf")
'''

CLI_RUNS = {
    "cli_default": [],
    "cli_input": ["--thresholds", "input"],
    "cli_params": ["--thresholds", "params"],
    "cli_auto": ["--contrast-threshold", "auto"],
    "cli_selfcal_cf": ["--method", "cf", "--thresholds", "selfcal", "--mode", "causal"],
    "cli_c013": ["--contrast-threshold", "0.13", "--mode", "forward"],
}


def _export(commit: str, dest: Path) -> None:
    dest.mkdir(parents=True)
    arch = dest.parent / f"{dest.name}.tar"
    subprocess.run(["git", "-C", str(REPO), "archive", "--format=tar", "-o", str(arch), commit], check=True)
    with tarfile.open(arch) as tf:
        tf.extractall(dest, filter="data")
    arch.unlink()


def _run(tree: Path, out: Path, which: str, quick: bool, data: Path, env_extra=None) -> None:
    env = dict(os.environ, PYTHONPATH=str(tree), **(env_extra or {}))
    out.parent.mkdir(parents=True, exist_ok=True)
    script = out.parent / f"runner_{out.name}.py"
    script.write_text(RUNNER)
    r = subprocess.run([sys.executable, str(script), str(out), which, "1" if quick else "0", str(data)], cwd=tree,
                       env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{which} run in {tree} failed:\n{r.stderr[-4000:]}")


def _run_cli(tree: Path, out: Path, data: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(tree))
    rec = data / "ecd_slider_depth"
    out.mkdir(parents=True, exist_ok=True)
    for name, extra in CLI_RUNS.items():
        dest = out / name
        r = subprocess.run([sys.executable, "-m", "hybridhdr", "reconstruct", str(rec), "--out", str(dest),
                            "--no-progress", "--end", "1.5s", *extra], cwd=tree, env=env, capture_output=True,
                           text=True)
        (out / f"{name}.log").write_text(f"rc {r.returncode}\n{r.stdout}\n{r.stderr}")


def _strip_run_json(path: Path) -> dict:
    d = json.loads(path.read_text())
    for k in ("command", "hybridhdr_version"):
        d.pop(k, None)
    d.get("info", {}).pop("two_sided", None) if isinstance(d.get("info"), dict) else None

    def clean(o):
        if isinstance(o, dict):
            return {k: clean(v) for k, v in o.items() if not str(k).endswith("_s") and "wall" not in str(k)}
        if isinstance(o, list):
            return [clean(v) for v in o]
        return o
    return clean(d)


def _compare(a: Path, b: Path) -> tuple[list, list, list, int]:
    import numpy as np
    files_a = {p.relative_to(a) for p in a.rglob("*") if p.is_file()}
    files_b = {p.relative_to(b) for p in b.rglob("*") if p.is_file()}
    diff, n = [], 0
    for rel in sorted(files_a & files_b):
        n += 1
        pa, pb = a / rel, b / rel
        if rel.suffix == ".npz":
            za, zb = np.load(pa), np.load(pb)
            same = (sorted(za.files) == sorted(zb.files)
                    and all(za[k].dtype == zb[k].dtype and za[k].shape == zb[k].shape
                            and za[k].tobytes() == zb[k].tobytes() for k in za.files))
        elif rel.name == "run.json":
            same = _strip_run_json(pa) == _strip_run_json(pb)
        elif rel.suffix == ".log":
            la, lb = pa.read_text().splitlines(), pb.read_text().splitlines()
            same = la[:1] == lb[:1]  # the exit status; the messages are in run.json and below
            same = same and [s for s in la if not s.startswith(("/", "ecd", "akf:", "cf:", "{"))] == \
                [s for s in lb if not s.startswith(("/", "ecd", "akf:", "cf:", "{"))]
        else:
            same = pa.read_bytes() == pb.read_bytes()
        if not same:
            diff.append(str(rel))
    return diff, sorted(map(str, files_a - files_b)), sorted(map(str, files_b - files_a)), n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", help="first commit (e.g. main)")
    ap.add_argument("b", help="second commit (e.g. HEAD)")
    ap.add_argument("--out", type=Path, default=None, help="keep the outputs here (default: a temporary folder)")
    ap.add_argument("--quick", action="store_true", help="shorter edge sweep, no colour cases")
    ap.add_argument("--no-cudasim", action="store_true", help="skip the CUDA-simulator cases")
    ap.add_argument("--no-cli", action="store_true", help="skip the command-line cases")
    args = ap.parse_args(argv)
    data = Path(os.environ.get("HYBRIDHDR_SHARED_DATA", REPO.parent / "shared" / "data"))
    with tempfile.TemporaryDirectory(prefix="compare_commits_") as td:
        root = args.out or Path(td)
        outs = {}
        for tag, commit in (("a", args.a), ("b", args.b)):
            tree = Path(td) / f"tree_{tag}"
            _export(commit, tree)
            out = root / f"out_{tag}"
            print(f"running {commit} ({tag}) ...", file=sys.stderr)
            _run(tree, out / "api", "api", args.quick, data)
            if not args.no_cudasim:
                _run(tree, out / "cudasim", "cudasim", args.quick, data, {"NUMBA_ENABLE_CUDASIM": "1"})
            if not args.no_cli and (data / "ecd_slider_depth").exists():
                _run_cli(tree, out / "cli", data)
            outs[tag] = out
        diff, only_a, only_b, n = _compare(outs["a"], outs["b"])
        errors = sum(1 for p in outs["a"].rglob("*.json") if p.parent.name in ("api", "cudasim")
                     and "error" in json.loads(p.read_text()))
    res = {"a": args.a, "b": args.b, "files_compared": n, "identical": n - len(diff), "different": diff,
           "only_in_a": only_a, "only_in_b": only_b, "cases_raising_an_error_in_a": errors,
           "ecd_slider_depth": (data / "ecd_slider_depth").exists()}
    print(json.dumps(res))
    return 1 if diff or only_a or only_b else 0


if __name__ == "__main__":
    raise SystemExit(main())
