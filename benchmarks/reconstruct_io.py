"""End-to-end ``hybridhdr reconstruct`` wall time with its outputs, before and after the streaming writer.

Usage: ``python benchmarks/reconstruct_io.py [--quick] [--old-commit REV] [--repeats N]``. Prints
progress, then ONE JSON object on the last line.

Runs ``hybridhdr reconstruct ../shared/data/ecd_slider_depth --fps 300 --out ...`` (1,001 outputs
of 240x180) as a child process:

* **before**: the commit before the streaming writer (default: the parent of the commit that
  introduced ``VideoWriter``), checked out with ``git worktree add --detach`` under /tmp (the main
  working tree is not touched);
* **after**: HEAD, also in a worktree, so other people's uncommitted edits do not enter the figures.

Each configuration is run ``--repeats`` times, interleaved, and the best wall time is reported
(the 2-core VMs are shared: medians and the load average are printed too). Configurations: EXR
(default compression), ``--png``, ``--no-exr``; after only: every ``--exr-compression`` (bytes on
disk, lossless or not), ``--writers 0`` (the serial path; its files are compared byte for byte with
the pool's) and ``--mp4``. Without ``--quick`` also the peak RSS of 10,000 outputs at 240x180
(``--fps 3000``) for ``--mode forward`` and the default two-sided offline mode.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED_DATA, git, loadavg, worktree  # noqa: E402,F401

REPO = Path(__file__).resolve().parents[1]
DATA = SHARED_DATA / "ecd_slider_depth"





def run_cli(wt: Path, args: list[str], out: Path) -> tuple[float, int, int]:
    """(wall s, peak RSS kB of the process tree's largest process, exit status) of one reconstruct."""
    if out.exists():
        shutil.rmtree(out)
    env = dict(os.environ, PYTHONPATH=str(wt), NUMBA_CACHE_DIR=str(wt / ".numba-cache"))
    cmd = [sys.executable, "-m", "hybridhdr", "reconstruct", str(DATA), "--fps", "300", "--out", str(out),
           "--no-progress", *args]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=str(wt))
    err = p.stderr.read()
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise RuntimeError(f"{cmd} failed ({p.returncode}): {err.decode()[-2000:]}")
    return wall, int(ru.ru_maxrss), p.returncode


def _digest(d: Path, pattern: str) -> str:
    """sha256 of the files' names and contents; of an EXR its decoded pixels (the two trees may
    compress differently: the default went from zip to none)."""
    h = hashlib.sha256()
    for p in sorted(d.glob(pattern)):
        h.update(p.name.encode())
        if p.suffix == ".exr":
            from hybridhdr.formats.images import read_exr
            h.update(read_exr(p).tobytes())
        else:
            h.update(p.read_bytes())
    return h.hexdigest()


def _bytes(d: Path, pattern: str) -> int:
    return sum(p.stat().st_size for p in d.glob(pattern))


def encode_speeds(frames, compressions, n: int) -> dict:
    """ms per frame and kB per frame of write_exr alone (in this process, best of 2), lossless or not."""
    from hybridhdr.formats.images import read_exr, write_exr
    res = {}
    with tempfile.TemporaryDirectory() as td:
        for c in compressions:
            best = float("inf")
            for _ in range(2):
                size = 0
                t0 = time.perf_counter()
                for i in range(n):
                    p = Path(td) / f"{i % 4}.exr"
                    write_exr(p, frames[i], compression=c)
                    size += p.stat().st_size
                best = min(best, time.perf_counter() - t0)
            lossless = bool((read_exr(p) == frames[n - 1]).all())
            res[c] = {"ms_per_frame": round(best / n * 1e3, 3), "kB_per_frame": round(size / n / 1e3, 1),
                      "lossless": lossless}
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer configurations, one repeat (< 60 s)")
    ap.add_argument("--old-commit", default=None, help="the 'before' revision (default: before VideoWriter)")
    ap.add_argument("--repeats", type=int, default=None)
    args = ap.parse_args(argv)
    if not DATA.exists():
        print(json.dumps({"skipped": f"{DATA} not found"}))
        return 0
    t_start = time.perf_counter()
    repeats = args.repeats or (1 if args.quick else 3)
    old_rev = args.old_commit
    if old_rev is None:
        intro = git("log", "--format=%H", "-S", "class VideoWriter", "--", "hybridhdr/reconstruct/output.py")
        old_rev = intro.splitlines()[-1] + "~1"
    old, new = worktree(old_rev), worktree("HEAD")
    res = {"quick": args.quick, "repeats": repeats, "recording": "ecd_slider_depth", "fps": 300,
           "old_commit": git("rev-parse", "--short", old_rev), "new_commit": git("rev-parse", "--short", "HEAD"),
           "loadavg_start": loadavg()}
    sys.path.insert(0, str(new))
    from hybridhdr.formats.images import DEFAULT_EXR_COMPRESSION, exr_compressions
    comps = exr_compressions()
    res["default_compression"] = DEFAULT_EXR_COMPRESSION
    tmp = Path(tempfile.mkdtemp(prefix="hybridhdr-bench-io-"))
    try:
        for wt in (old, new):  # warm-up: numba caches of each worktree
            run_cli(wt, ["--no-exr"], tmp / "warm")
        configs = [("before", old, "exr", []), ("after", new, "exr", []),
                   ("before", old, "exr+png", ["--png"]), ("after", new, "exr+png", ["--png"]),
                   ("after", new, "exr_serial", ["--writers", "0"])]
        if not args.quick:
            configs += [("before", old, "no_exr", ["--no-exr"]), ("after", new, "no_exr", ["--no-exr"]),
                        ("after", new, "exr+png+mp4", ["--png", "--mp4"]),
                        ("after", new, "exr+png_serial", ["--png", "--writers", "0"])]
            configs += [("after", new, f"exr_{c}", ["--exr-compression", c]) for c in comps
                        if c != DEFAULT_EXR_COMPRESSION]
        walls: dict[str, list[float]] = {}
        rss: dict[str, int] = {}
        for r in range(repeats):
            for side, wt, name, extra in configs:
                key = f"{side}_{name}"
                out = tmp / key
                # the after tree stops --fps outputs at the last event unless told (909f94c); the
                # recording's 50,000 events end at 0.17 s, its frames at 3.33 s: --until last gives
                # the before tree's 1,001 outputs
                w, m, _ = run_cli(wt, extra + (["--until", "last"] if side == "after" else []), out)
                walls.setdefault(key, []).append(w)
                rss[key] = max(rss.get(key, 0), m)
                print(f"{key:28s} {w:6.2f} s  peak RSS {m / 1024:6.0f} MB", file=sys.stderr)
                if r == 0 and name.startswith("exr"):
                    comp = name[4:] if name.startswith("exr_") and name[4:] in comps else "default"
                    res.setdefault("exr_bytes", {})[f"{side}_{comp}"] = _bytes(out, "frame_*.exr")
                    res.setdefault("exr_files", {})[f"{side}_{comp}"] = len(list(out.glob("frame_*.exr")))
        res["wall_s_best"] = {k: round(min(v), 3) for k, v in walls.items()}
        res["wall_s_median"] = {k: round(statistics.median(v), 3) for k, v in walls.items()}
        res["peak_rss_MB"] = {k: round(v / 1024) for k, v in rss.items()}
        b = res["wall_s_best"]
        res["speedup_before_over_after"] = {n: round(b[f"before_{n}"] / b[f"after_{n}"], 2)
                                            for n in ("exr", "exr+png", "no_exr") if f"after_{n}" in b}
        # the pipeline changes no result: pool vs serial path of the same commit, and vs the old commit
        same = {}
        for a, s in (("after_exr", "after_exr_serial"), ("after_exr+png", "after_exr+png_serial")):
            if (tmp / s).exists():
                same[f"{a}_vs_serial"] = all(_digest(tmp / a, p) == _digest(tmp / s, p)
                                             for p in ("frame_*.exr", "timestamps.txt", "previews/*.png"))
        # False since the accuracy model changed the filter (not the writer's doing)
        same["after_vs_before_exr"] = _digest(tmp / "after_exr", "frame_*.exr") == _digest(tmp / "before_exr",
                                                                                           "frame_*.exr")
        res["bit_identical"] = same
        # per-frame encode cost of each compression on these very frames
        from hybridhdr.formats.images import read_exr
        import numpy as np
        names = sorted((tmp / "after_exr").glob("frame_*.exr"))[:: max(1, 1001 // (60 if args.quick else 300))]
        frames = np.stack([read_exr(p) for p in names])
        res["exr_encode"] = encode_speeds(frames, comps, len(frames))
        for c, v in res["exr_encode"].items():
            print(f"EXR {c:6s} {v['ms_per_frame']:6.2f} ms/frame {v['kB_per_frame']:7.1f} kB/frame "
                  f"lossless={v['lossless']}", file=sys.stderr)
        if not args.quick:
            for mode in ("forward", "offline"):
                env_out = tmp / f"rss_{mode}"
                cmd_extra = ["--mode", mode]
                # 10,000 outputs: --fps 3000 over the recording's 3.33 s
                if env_out.exists():
                    shutil.rmtree(env_out)
                env = dict(os.environ, PYTHONPATH=str(new), NUMBA_CACHE_DIR=str(new / ".numba-cache"))
                t0 = time.perf_counter()
                p = subprocess.Popen([sys.executable, "-m", "hybridhdr", "reconstruct", str(DATA), "--fps", "3000",
                                      "--until", "last", "--out", str(env_out), "--no-progress", *cmd_extra], env=env,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=str(new))
                _, status, ru = os.wait4(p.pid, 0)
                n = len(list(env_out.glob("frame_*.exr")))
                res[f"rss_10k_{mode}"] = {"frames": n, "peak_rss_MB": round(ru.ru_maxrss / 1024),
                                          "wall_s": round(time.perf_counter() - t0, 1),
                                          "exit": os.waitstatus_to_exitcode(status)}
                print(f"10k outputs, {mode}: {res[f'rss_10k_{mode}']}", file=sys.stderr)
                shutil.rmtree(env_out, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    res["loadavg_end"] = loadavg()
    res["elapsed_s"] = round(time.perf_counter() - t_start, 1)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
