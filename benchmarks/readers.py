"""Benchmark: Prophesee readers (file -> event array), ours against the fastest peers.

Usage::

    python benchmarks/readers.py            # 50 M events per format
    python benchmarks/readers.py --quick    # 5 M events per format, < 60 s on 2 cores

Synthesises one file per format with our writers (cached in ``benchmarks/_data/``), then times,
best of 3 in the same run (ours and the peer alternating, after touching enough memory once): our EVT 3.0 reader vs the ``evt3`` package, our EVT 2.0 vs
``expelliarmus``, our DAT vs ``expelliarmus``, and our EVT 2.1 alone (no peer reads it correctly).
Our readers are timed through ``Reader(path).read_all()`` (file -> one EVENT_DTYPE array) with a
warmed-up JIT. Finally a streaming pass (``iter_chunks``) over the largest file runs in a fresh
process to measure its peak RSS. The last line printed is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

from _common import make_file  # noqa: E402


def _alternate(fns, repeat):
    """Best time of each function, runs interleaved (a, b, a, b, ...) so that both see the same
    memory state; returns lists of (best seconds, result)."""
    best = [float("inf")] * len(fns)
    res = [None] * len(fns)
    errors = [None] * len(fns)
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            if fn is None or errors[i] is not None:
                continue
            try:
                t0 = time.perf_counter()
                r = fn()
                dt = time.perf_counter() - t0
            except Exception as e:  # noqa: BLE001 - a failing peer is reported, not fatal
                errors[i] = f"{type(e).__name__}: {e}"
                continue
            best[i] = min(best[i], dt)
            res[i] = r
    return best, res, errors


def _pretouch(n_bytes):
    """Touch ``n_bytes`` of fresh memory once: on a VM the first touch of guest memory is far
    slower than later ones, which would penalise whichever reader runs first."""
    import numpy as np
    a = np.empty(n_bytes // 8, np.int64)
    a[:] = 0
    del a


def _ours(fmt, path):
    from hybridhdr.formats import prophesee as P

    def run():
        return len(P.READERS[fmt](path).read_all().events)
    return run


def _peer(fmt, path):
    if fmt == "evt3":
        import evt3

        def run():
            return len(evt3.decode_file(str(path)).timestamp)
        return "evt3 " + _version("evt3"), run
    if fmt in ("evt2", "dat"):
        from expelliarmus import Wizard

        def run():
            return len(Wizard(encoding=fmt).read(path))
        return "expelliarmus " + _version("expelliarmus"), run
    return None, None


def _version(dist):
    try:
        from importlib.metadata import version
        return version(dist)
    except Exception:  # noqa: BLE001
        return "?"


def _stream_rss(fmt, path, warm_path, chunk_events=1 << 20):
    code = (
        "import resource, sys, time\n"
        "from hybridhdr.formats import prophesee as P\n"
        f"for c in P.READERS[{fmt!r}]({str(warm_path)!r}).iter_chunks(1000): pass\n"
        f"r = P.READERS[{fmt!r}]({str(path)!r})\n"
        "t0 = time.perf_counter(); n = 0\n"
        f"for c in r.iter_chunks({chunk_events}): n += len(c.events)\n"
        "dt = time.perf_counter() - t0\n"
        # VmHWM is this process's own peak (ru_maxrss would include the parent's, kept over exec)
        "hwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM')]\n"
        "print(n, dt, int(hwm[0].split()[1]) / 1024 if hwm else "
        "resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)\n")
    env = dict(os.environ, PYTHONPATH=str(HERE.parent))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    n, dt, rss = out.stdout.split()
    return int(n), float(dt), float(rss)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="5 M events per format instead of 50 M")
    ap.add_argument("--events", type=int, default=None, help="events per format (overrides --quick)")
    ap.add_argument("--repeat", type=int, default=3, help="best of this many runs")
    args = ap.parse_args(argv)
    n = args.events or (5_000_000 if args.quick else 50_000_000)
    import numba

    print(f"Prophesee readers, {n:,} events per format, best of {args.repeat}, "
          f"{os.cpu_count()} CPUs, numba threads {numba.get_num_threads()}")
    t_all = time.perf_counter()
    files = {fmt: make_file(fmt, n) for fmt in ("evt3", "evt2", "dat", "evt21")}
    # warm the JIT (compiles or loads the numba cache) on a small file of each format
    small = {fmt: make_file(fmt, 20_000, seed=1) for fmt in files}
    for fmt, p in small.items():
        _ours(fmt, p)()
    _pretouch(3 * 16 * n)
    result = {"events_per_file": n, "repeat": args.repeat, "cpus": os.cpu_count(), "formats": {}}
    for fmt, path in files.items():
        entry = {"file": path.name, "file_mb": round(path.stat().st_size / 1e6, 1)}
        name, run = _peer(fmt, path)
        (dt, pdt), (cnt, pcnt), (err, perr) = _alternate([_ours(fmt, path), run], args.repeat)
        if err or cnt != n:
            raise SystemExit(f"our {fmt} reader failed ({err}) or returned {cnt} events, expected {n}")
        entry["ours_mev_s"] = round(n / dt / 1e6, 1)
        entry["ours_s"] = round(dt, 4)
        if run is not None:
            entry["peer"] = name
            if perr is not None:
                entry["peer_error"] = perr
            else:
                entry["peer_mev_s"] = round(n / pdt / 1e6, 1)
                entry["peer_s"] = round(pdt, 4)
                entry["peer_events"] = int(pcnt)
                entry["ratio_ours_over_peer"] = round(pdt / dt, 2)
        else:
            entry["peer"] = None
            entry["note"] = "no peer decodes EVT 2.1 correctly (expelliarmus lacks it; see formats.md)"
        line = f"{fmt:6s} ours {entry['ours_mev_s']:7.1f} Mev/s"
        if "peer_mev_s" in entry:
            line += f"   {entry['peer']}: {entry['peer_mev_s']:7.1f} Mev/s   ratio {entry['ratio_ours_over_peer']:.2f}x"
        elif "peer_error" in entry:
            line += f"   {entry['peer']} failed: {entry['peer_error']}"
        print(line)
        result["formats"][fmt] = entry
    big = max(files, key=lambda f: files[f].stat().st_size)
    cnt, dt, rss = _stream_rss(big, files[big], small[big])
    result["streaming"] = {"format": big, "file_mb": round(files[big].stat().st_size / 1e6, 1),
                           "events": cnt, "seconds": round(dt, 3), "peak_rss_mb": round(rss, 1),
                           "chunk_events": 1 << 20}
    print(f"streaming {big} ({result['streaming']['file_mb']} MB): {cnt / dt / 1e6:.1f} Mev/s, "
          f"peak RSS {rss:.0f} MB")
    result["total_seconds"] = round(time.perf_counter() - t_all, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
