"""Run one benchmark of two commits, interleaved, and print each figure's ratio.

Usage: ``python tools/bench_commits.py A B [--bench benchmarks/akf.py] [--rounds 2] [--args "--quick"]``

Both commits are exported with ``git archive`` into temporary folders; the benchmark of each
commit's own tree runs in turn (A, B, A, B, ...), so the machine's drift from minute to minute
falls on both alike. For every numeric figure whose name ends in ``mev_s`` (a throughput: higher
is better) the best of the rounds of each commit is compared: ``ratio = B / A``. Prints one
JSON object last: ``{"a", "b", "rounds", "figures": {name: {"a", "b", "ratio"}}, "worst_ratio"}``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _export(commit: str, dest: Path) -> None:
    dest.mkdir(parents=True)
    arch = dest.parent / f"{dest.name}.tar"
    subprocess.run(["git", "-C", str(REPO), "archive", "--format=tar", "-o", str(arch), commit], check=True)
    with tarfile.open(arch) as tf:
        tf.extractall(dest, filter="data")
    arch.unlink()


def _figures(obj, prefix="") -> dict:
    out = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(_figures(v, f"{prefix}{k}." if isinstance(v, dict) else f"{prefix}{k}"))
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool) and prefix.endswith("mev_s"):
        out[prefix] = float(obj)
    return out


def _run(tree: Path, bench: str, extra: list[str]) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    r = subprocess.run([sys.executable, str(tree / bench), *extra], cwd=tree, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{bench} in {tree} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--bench", default="benchmarks/akf.py", help="the benchmark, relative to the repository")
    ap.add_argument("--rounds", type=int, default=2, help="runs of each commit, interleaved")
    ap.add_argument("--args", default="--quick", help="the benchmark's arguments")
    args = ap.parse_args(argv)
    extra = shlex.split(args.args)
    with tempfile.TemporaryDirectory(prefix="bench_commits_") as td:
        trees = {tag: Path(td) / tag for tag in ("a", "b")}
        _export(args.a, trees["a"])
        _export(args.b, trees["b"])
        runs = {"a": [], "b": []}
        for i in range(args.rounds):
            for tag in ("a", "b") if i % 2 == 0 else ("b", "a"):
                print(f"round {i + 1}: {getattr(args, tag)} ...", file=sys.stderr)
                runs[tag].append(_figures(_run(trees[tag], args.bench, extra)))
    figs = {}
    for name in sorted(set(runs["a"][0]) & set(runs["b"][0])):
        a = max(r[name] for r in runs["a"] if name in r)
        b = max(r[name] for r in runs["b"] if name in r)
        figs[name] = {"a": a, "b": b, "ratio": round(b / a, 3) if a > 0 else None}
    ratios = [f["ratio"] for f in figs.values() if f["ratio"] is not None]
    print(json.dumps({"a": args.a, "b": args.b, "bench": args.bench, "rounds": args.rounds, "figures": figs,
                      "worst_ratio": min(ratios) if ratios else None,
                      "median_ratio": sorted(ratios)[len(ratios) // 2] if ratios else None}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
