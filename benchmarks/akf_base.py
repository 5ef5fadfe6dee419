"""The AKF kernel and end-to-end speed of this tree against an earlier commit, in one run.

Usage: ``python benchmarks/akf_base.py [--quick] [--base REV]`` (default REV: the commit before the
accuracy model of this round, ``a1cab8f``). Prints a table, then ONE JSON object on the last line.

* **Kernel**: the earlier commit's ``_kernels.py`` is loaded as a separate module (a git worktree
  of REV) and both ``akf_events`` kernels filter the same synthetic events (``akf.py``'s 60
  drifting blobs at 346×260) on the same state, interleaved, best of N, in this process. The
  current kernel runs the new code paths' cheapest settings that match the old semantics (no
  censoring, no per-pixel thresholds): what every caller pays for the new branches.
* **End to end**: ``reconstruct(container, "akf", fps=300)`` of both trees, each in its own
  child process, interleaved, best of N: the one-pass forward filter without augmentation
  (the old tree's ``augment=False`` offline; this tree's ``mode="forward"``), and this tree's
  default two-sided filter beside it.

The machine's cores are shared and swing by tens of percent; the load average is printed.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import akf as B  # noqa: E402  (synth_events, synth_frames)
from _common import loadavg, worktree  # noqa: E402

DEFAULT_BASE = "a1cab8f"



def _load_kernels(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # Numba's cache finds the module again by name
    spec.loader.exec_module(mod)
    return mod


def _kernel_run(K, t, x, y, p, new: bool):
    n = t.shape[0]
    S = K.aligned_state(B.H * B.W, K.AKF_FIELDS)
    rng = np.random.default_rng(0)
    S[:, K.A_L] = rng.normal(-1.0, 0.3, S.shape[0])
    S[:, K.A_P] = 0.01
    S[:, K.A_LA] = S[:, K.A_L]
    S[:, K.A_RINV] = 1e4
    S[:, K.A_TU] = float(t[0])
    if new:  # as the engine runs it: int32 last-event times relative to the start (te_base)
        te = K.padded_te(B.H, B.W, 0, np.int32)
        te_args = [te, np.int64(t[0])]
    else:
        te_args = [K.padded_te(B.H, B.W, int(t[0]))]
    args = [t, x, y, p, 0, n, 0, B.H, B.W, B.H, S, *te_args, False, float(t[0]), 0.0, 0.1, 0.1, 5e-4, 0.03,
            0.01, np.int64(10_000), 0]
    if new:
        args += [np.empty(0), np.empty(0)]
    t0 = time.perf_counter()
    K.akf_events(*args)
    return time.perf_counter() - t0


_E2E = textwrap.dedent("""
    import sys, time, json
    sys.path.insert(0, {root!r})
    from hybridhdr.formats.container import RecordingFile
    from hybridhdr.reconstruct import reconstruct
    kw = json.loads({kw!r})
    with RecordingFile({path!r}) as f:
        reconstruct(f, "akf", fps=300, chunk_events=1 << 21, **kw, thresholds="input")  # compile / warm the caches
    best = float("inf")
    for _ in range({reps}):
        with RecordingFile({path!r}) as f:
            t0 = time.perf_counter()
            v = reconstruct(f, "akf", fps=300, chunk_events=1 << 21, **kw, thresholds="input")
            best = min(best, time.perf_counter() - t0)
    print(json.dumps({{"s": best, "frames": len(v)}}))
""")


def _e2e(root: Path, path: Path, kw: dict, reps: int) -> float:
    code = _E2E.format(root=str(root), kw=json.dumps(kw), path=str(path), reps=reps)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(root))
    if out.returncode != 0:
        raise RuntimeError(f"end-to-end run in {root} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])["s"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer events and repeats (well under 60 s)")
    ap.add_argument("--base", default=DEFAULT_BASE, help="the earlier commit to compare with")
    args = ap.parse_args(argv)
    n = 2_000_000 if args.quick else 10_000_000
    reps = 3 if args.quick else 7
    base = worktree(args.base)
    # a copy of its own (with its own Numba cache): the base tree's cache stays that of its package
    kdir = Path(tempfile.gettempdir()) / f"hybridhdr-base-kernels-{args.base}"
    kdir.mkdir(exist_ok=True)
    kfile = kdir / "hybridhdr_base_kernels.py"
    kfile.write_bytes((base / "hybridhdr" / "reconstruct" / "_kernels.py").read_bytes())
    K_old = _load_kernels(kfile, "hybridhdr_base_kernels")
    from hybridhdr.reconstruct import _kernels as K_new
    t, x, y, p, dur = B.synth_events(n)
    res = {"base": args.base, "n_events": n, "loadavg_start": loadavg()}
    _kernel_run(K_old, t, x, y, p, False)  # compile
    _kernel_run(K_new, t, x, y, p, True)
    old, new = [], []
    for _ in range(reps):
        old.append(_kernel_run(K_old, t, x, y, p, False))
        new.append(_kernel_run(K_new, t, x, y, p, True))
    res["kernel_base_mev_s"] = round(n / min(old) / 1e6, 2)
    res["kernel_mev_s"] = round(n / min(new) / 1e6, 2)
    res["kernel_ratio"] = round(min(old) / min(new), 3)
    print(f"AKF kernel: {args.base} {res['kernel_base_mev_s']} Mev/s, this tree {res['kernel_mev_s']} Mev/s "
          f"(ratio {res['kernel_ratio']}, best of {reps})", file=sys.stderr)

    from hybridhdr import Recording, SensorSize, make_events
    from hybridhdr.formats.container import write_recording
    frames = B.synth_frames(dur)
    with tempfile.TemporaryDirectory() as d:
        # the older container format is written by the older tree; each tree reads its own file
        path_new = Path(d) / "new.h5"
        write_recording(Recording(make_events(t, x, y, p), SensorSize(B.H, B.W), frames), path_new)
        path_old = Path(d) / "old.h5"
        np.savez(Path(d) / "ev.npz", t=t, x=x, y=y, p=p, ft=frames.t_start_us, fe=frames.t_end_us, im=frames.images)
        subprocess.run([sys.executable, "-c", textwrap.dedent(f"""
            import sys; sys.path.insert(0, {str(base)!r})
            import numpy as np
            from hybridhdr import Recording, SensorSize, make_events, Frames
            from hybridhdr.formats.container import write_recording
            z = np.load({str(Path(d) / 'ev.npz')!r})
            fr = Frames(z['im'], z['ft'], z['fe'], encoding='raw')
            write_recording(Recording(make_events(z['t'], z['x'], z['y'], z['p']), SensorSize({B.H}, {B.W}), fr),
                            {str(path_old)!r})
        """)], check=True, capture_output=True, cwd=str(base))
        e_old, e_new, e_two = [], [], []
        r = 2 if args.quick else 3
        for _ in range(2):
            e_old.append(_e2e(base, path_old, {"augment": False}, r))
            e_new.append(_e2e(ROOT, path_new, {"mode": "forward"}, r))
            e_two.append(_e2e(ROOT, path_new, {}, r))
    res["end_to_end_base_forward_mev_s"] = round(n / min(e_old) / 1e6, 2)
    res["end_to_end_forward_mev_s"] = round(n / min(e_new) / 1e6, 2)
    res["end_to_end_ratio"] = round(min(e_old) / min(e_new), 3)
    res["end_to_end_two_sided_mev_s"] = round(n / min(e_two) / 1e6, 2)
    res["two_sided_over_forward"] = round(min(e_new) / min(e_two), 3)
    res["loadavg_end"] = loadavg()
    print(f"end to end (forward, 300 Hz outputs): {args.base} {res['end_to_end_base_forward_mev_s']} Mev/s, this "
          f"tree {res['end_to_end_forward_mev_s']} Mev/s (ratio {res['end_to_end_ratio']}); two-sided (default) "
          f"{res['end_to_end_two_sided_mev_s']} Mev/s = {res['two_sided_over_forward']} x forward", file=sys.stderr)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
