"""``convert`` EVT 2.0 -> container and -> DAT beside the EVT 2.0 reader alone, before and after.

Usage: ``python benchmarks/convert.py [--quick] [--old-commit REV] [--repeats N] [--tiles K]``.
Prints progress, then ONE JSON object on the last line.

Input: the real Prophesee recording ``shared/data/prophesee/sparklers_gen3_evt2.raw`` (640x480,
521,252 events over 96 ms) laid end to end ``K`` times (70 by default: 36.5 M events, 146 MB,
a large recording; 10 with ``--quick``), written once with our EVT 2.0 writer under
``benchmarks/_data/``. Timed, each in a long-lived child process per version (imports and JIT
warmed up on the original file first), interleaved round by round, best of ``--repeats``:

* ``reader``: ``Evt2Reader(path).iter_chunks(2**20)`` to the end (what ``convert`` streams);
* ``container``: ``convert(input, out.h5)`` (default gzip);
* ``dat``: ``convert(input, out.dat)``.

Outputs are deleted before each run (not timed): replacing an existing file costs its unlink.
``before`` is the parent of the commit that added the staged container writer
(``hybridhdr/_write_kernels.py``), checked out with ``git worktree add --detach`` under /tmp;
``after`` is this working tree. Both containers are decoded and compared (events and index).

The compression table is measured in this process on the first chunks of the input: one thread's
deflate speed of the staged (byte-shuffled) chunks and bytes per event, for zlib (HDF5's own
deflate, what the writer used before) and ISA-L (``isal``) at several levels, and the file size of
a container written with each ``compression=`` choice.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED_DATA, git, loadavg, worktree  # noqa: E402,F401

REPO = Path(__file__).resolve().parents[1]
SRC = SHARED_DATA / "prophesee" / "sparklers_gen3_evt2.raw"
DATA = Path(__file__).resolve().parent / "_data"
sys.path.insert(0, str(REPO))

_CHILD = r"""
import os, sys, time
sys.path.insert(0, os.environ["WT"])
from hybridhdr._cli_tools import convert
from hybridhdr.formats import prophesee as P
src, small, out = sys.argv[1], sys.argv[2], sys.argv[3]
for ext in (".h5", ".dat"):  # warm up: imports, JIT caches, thread pools
    convert(small, out + ext)
    os.unlink(out + ext)
for c in P.Evt2Reader(small).iter_chunks(1 << 20):
    pass
print("ready", flush=True)
for line in sys.stdin:
    task = line.strip()
    if task == "quit":
        break
    target = out + (".h5" if task == "container" else ".dat")
    if task != "reader" and os.path.exists(target):
        os.unlink(target)
    t0 = time.perf_counter()
    if task == "reader":
        n = 0
        for c in P.Evt2Reader(src).iter_chunks(1 << 20):
            n += len(c.events)
    else:
        n = convert(src, out + (".h5" if task == "container" else ".dat"))["events"]
    dt = time.perf_counter() - t0
    print(f"{dt} {n} {os.path.getsize(out + ('.h5' if task == 'container' else '.dat')) if task != 'reader' else 0}",
          flush=True)
"""



def _default_old() -> str:
    added = git("log", "--diff-filter=A", "--format=%H", "--", "hybridhdr/_write_kernels.py").split()
    return f"{added[-1]}^" if added else "HEAD"




def make_input(tiles: int) -> tuple[Path, int]:
    """The sparklers recording laid end to end ``tiles`` times (cached)."""
    from hybridhdr.formats import prophesee as P
    DATA.mkdir(parents=True, exist_ok=True)
    path = DATA / f"sparklers_x{tiles}_evt2.raw"
    r = P.Evt2Reader(SRC)
    ev = r.read_all().events
    if not path.exists():
        span = int(ev["t"][-1] - ev["t"][0]) + 1
        with P.Evt2Writer(path, sensor_size=r.sensor_size, metadata=r.metadata) as w:
            for k in range(tiles):
                e = ev.copy()
                e["t"] += k * span
                w.write_events(e)
    return path, len(ev) * tiles


class Child:
    def __init__(self, wt: Path, src: Path, out: Path):
        env = dict(os.environ, WT=str(wt), PYTHONPATH=str(wt), NUMBA_CACHE_DIR=str(wt / ".numba-cache"))
        self.p = subprocess.Popen([sys.executable, "-c", _CHILD, str(src), str(SRC), str(out)], env=env,
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=str(wt))
        line = self.p.stdout.readline()
        if line.strip() != "ready":
            raise RuntimeError(f"child in {wt} failed to start: {line!r}")

    def run(self, task: str) -> tuple[float, int, int]:
        self.p.stdin.write(task + "\n")
        self.p.stdin.flush()
        line = self.p.stdout.readline()
        if not line:
            raise RuntimeError(f"child died during {task}")
        dt, n, size = line.split()
        return float(dt), int(n), int(size)

    def close(self):
        try:
            self.p.stdin.write("quit\n")
            self.p.stdin.flush()
        except OSError:
            pass
        self.p.wait(timeout=60)


def compression_table(src: Path, n_events: int) -> list[dict]:
    """One thread's deflate speed and size per event of staged chunks, per codec and level."""
    import zlib

    from hybridhdr.formats import _write_kernels as WK
    from hybridhdr.formats import prophesee as P
    from hybridhdr.formats.container import _CHUNK_ELEMS as C
    ev = None
    for c in P.Evt2Reader(src).iter_chunks(n_events):
        ev = c.events
        break
    n = len(ev) - len(ev) % C
    ev = ev[:n]
    rec = ev.view(np.uint8).reshape(n, 16)
    st = np.zeros(4, np.int64)
    idx = np.empty(C, np.int64)
    chunks = []
    t0 = time.perf_counter()
    for a in range(0, n, C):
        bufs = [np.empty(C * s, np.uint8) for s in (8, 2, 2, 1)]
        WK.stage_events(rec, ev["t"], a, C, *bufs, 0, C, True, a, st, 4096, idx, idx.copy(), 0)
        chunks.append(bufs)
    stage_s = time.perf_counter() - t0
    codecs = [("zlib", zlib.compress, lvl) for lvl in (1, 2, 3, 6)]
    try:
        from isal import isal_zlib
        codecs[1:1] = [("isal", isal_zlib.compress, lvl) for lvl in (0, 1, 2)]
    except ImportError:
        pass
    rows = [{"codec": "none", "level": None, "deflate_mev_s": None, "bytes_per_event": 13.0}]
    for name, fn, lvl in codecs:
        best, size = float("inf"), 0
        for _ in range(2):
            t0 = time.perf_counter()
            size = sum(len(fn(b, lvl)) for bufs in chunks for b in bufs)
            best = min(best, time.perf_counter() - t0)
        rows.append({"codec": name, "level": lvl, "deflate_mev_s": round(n / best / 1e6, 1),
                     "bytes_per_event": round(size / n, 3)})
    rows.append({"codec": "stage (copy into shuffled chunk images + index)", "level": None,
                 "deflate_mev_s": round(n / stage_s / 1e6, 1), "bytes_per_event": None})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 tiles (5.2 M events), 2 repeats: < 60 s")
    ap.add_argument("--tiles", type=int, default=None, help="copies of the sparklers recording (default 70)")
    ap.add_argument("--repeats", type=int, default=None, help="best of this many interleaved runs")
    ap.add_argument("--old-commit", default=None, help="the 'before' version (default: parent of the commit "
                                                       "adding hybridhdr/_write_kernels.py)")
    args = ap.parse_args(argv)
    if not SRC.exists():
        print(json.dumps({"skipped": f"{SRC} is absent"}))
        return 0
    tiles = args.tiles or (10 if args.quick else 70)
    repeats = args.repeats or (2 if args.quick else 4)
    src, n = make_input(tiles)
    old_rev = args.old_commit or _default_old()
    res: dict = {"input": f"sparklers_gen3_evt2.raw x{tiles}", "events": n, "input_mb": round(src.stat().st_size / 1e6, 1),
                 "old_commit": git("rev-parse", "--short", old_rev), "new": "working tree",
                 "cpu_count": os.cpu_count(), "loadavg_start": loadavg(), "repeats": repeats}
    print(f"input {src.name}: {n:,} events, {res['input_mb']} MB; before = {res['old_commit']}", file=sys.stderr)
    tmp = Path(tempfile.mkdtemp(prefix="hh-convert-"))
    children = {}
    try:
        children["before"] = Child(worktree(old_rev), src, tmp / "before")
        children["after"] = Child(REPO, src, tmp / "after")
        times = {(v, task): [] for v in children for task in ("reader", "container", "dat")}
        sizes = {}
        for _ in range(repeats):
            for task in ("reader", "container", "dat"):
                for v, ch in children.items():
                    dt, m, size = ch.run(task)
                    if m != n:
                        raise RuntimeError(f"{v} {task}: {m} events, expected {n}")
                    times[v, task].append(dt)
                    sizes[v, task] = size
        import hybridhdr as hh
        from hybridhdr.formats.container import RecordingFile
        with RecordingFile(tmp / "before.h5") as a, RecordingFile(tmp / "after.h5") as b:
            res["containers_equal"] = bool(np.array_equal(a.events(), b.events())
                                           and np.array_equal(a._idx_ms, b._idx_ms)
                                           and np.array_equal(a._idx_first, b._idx_first))
        import re
        res["dat_files_equal_but_date"] = (re.sub(rb"% Date [^\n]*\n", b"", (tmp / "before.dat").read_bytes())
                                           == re.sub(rb"% Date [^\n]*\n", b"", (tmp / "after.dat").read_bytes()))
        del hh
    finally:
        for ch in children.values():
            ch.close()
    for (v, task), ts in times.items():
        res[f"{v}_{task}_mev_s"] = round(n / min(ts) / 1e6, 1)
        res[f"{v}_{task}_median_mev_s"] = round(n / statistics.median(ts) / 1e6, 1)
    for v in children:
        for task in ("container", "dat"):
            res[f"{v}_{task}_of_reader"] = round(res[f"{v}_{task}_mev_s"] / res[f"{v}_reader_mev_s"], 2)
        res[f"{v}_container_mb"] = round(sizes[v, "container"] / 1e6, 1)
        res[f"{v}_container_bytes_per_event"] = round(sizes[v, "container"] / n, 3)
    print(f"{'':10} {'reader':>8} {'container':>10} {'DAT':>8}  (Mev/s, best of {repeats}; load "
          f"{res['loadavg_start']})", file=sys.stderr)
    for v in children:
        print(f"{v:10} {res[f'{v}_reader_mev_s']:8.1f} {res[f'{v}_container_mev_s']:10.1f} "
              f"{res[f'{v}_dat_mev_s']:8.1f}   container {res[f'{v}_container_of_reader']:.2f}x, DAT "
              f"{res[f'{v}_dat_of_reader']:.2f}x the reader; {res[f'{v}_container_mb']} MB", file=sys.stderr)
    res["compression"] = compression_table(src, 4_000_000 if args.quick else 8_000_000)
    for row in res["compression"]:
        print(f"  {row['codec']:<10} level {row['level']}: {row['deflate_mev_s']} Mev/s (1 thread), "
              f"{row['bytes_per_event']} B/event", file=sys.stderr)
    from hybridhdr.formats.container import DEFLATE_IMPL
    res["deflate_impl"] = DEFLATE_IMPL
    shutil.rmtree(tmp, ignore_errors=True)
    res["loadavg_end"] = loadavg()
    res["goal_of_reader"] = 0.5
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
