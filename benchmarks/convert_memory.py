"""Peak memory and speed of `hybridhdr convert` on a large file (goal: < 1 GB for a 1 GB file).

Synthesises a Prophesee EVT 2.0 file of the target size with our streaming writer (cached under
benchmarks/_data/), then converts it to the hybridhdr container and to DAT in a child process and
reports the child's peak resident memory (ru_maxrss) and throughput.

    python benchmarks/convert_memory.py           # 1 GB input
    python benchmarks/convert_memory.py --quick   # 120 MB input, < 60 s
    python benchmarks/convert_memory.py --quick --repeats 3   # best of 3 per target

``to_<target>_mev_per_s`` divides the events by the child's whole wall time, which includes
starting Python and the imports (0.6-1 s on a 2-core VM, more than converting the 120 MB input
takes). ``to_<target>_convert_mev_per_s`` divides them by the wall time of the ``convert`` call
alone, timed inside the child (it still includes loading the Numba kernels from their cache,
about 0.5 s). ``to_<target>_cpu_s`` is the child's CPU time (user + system, all threads): on a
shared machine it varies less than the wall time. Times are the least of the repeats.

The last line printed is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DATA = HERE / "_data"


def make_evt2(path: Path, target_bytes: int, seed: int = 0) -> int:
    """Write an EVT 2.0 file of about ``target_bytes`` in 4 M-event chunks; returns the event count."""
    import hybridhdr as hh
    rng = np.random.default_rng(seed)
    ss = hh.SensorSize(480, 640)
    n_total = 0
    t0 = 0
    with hh.open_writer(path, "evt2", sensor_size=ss) as w:
        while path.with_name(path.name + ".partial").stat().st_size < target_bytes:
            n = 4_000_000
            dt = rng.exponential(0.05, n)  # ~20 Mev/s
            t = t0 + np.floor(np.cumsum(dt)).astype(np.int64)
            w.write_events(hh.make_events(t, rng.integers(0, ss.width, n), rng.integers(0, ss.height, n),
                                          rng.choice([-1, 1], n)))
            t0 = int(t[-1])
            n_total += n
    return n_total


_CHILD = ("import atexit, sys\n"
          "def _hwm():\n"
          "    for line in open('/proc/self/status'):\n"
          "        if line.startswith('VmHWM:'):\n"
          "            sys.stderr.write('HWM_KB ' + line.split()[1] + '\\n')\n"
          "atexit.register(_hwm)\n"
          "import time\n"
          "import hybridhdr._cli_tools as T\n"
          "_convert = T.convert\n"
          "def _timed(*a, **k):\n"
          "    t = time.perf_counter()\n"
          "    r = _convert(*a, **k)\n"
          "    sys.stderr.write('CONVERT_S %r\\n' % (time.perf_counter() - t))\n"
          "    return r\n"
          "T.convert = _timed\n"
          "from hybridhdr.cli import main\n"
          "sys.exit(main(sys.argv[1:]))\n")


def run_child(args: list[str]) -> tuple[float, float, float, float | None]:
    """Run ``hybridhdr ARGS`` in a child process; return (seconds, the child's own peak RSS in MB,
    its CPU seconds (user + system, all threads), the seconds of its ``convert`` call or None).

    The peak is the child's ``VmHWM`` read from /proc at exit (``ru_maxrss`` of children would
    report the largest of all children so far); the CPU time is the growth of this process's
    ``RUSAGE_CHILDREN`` over the run (the children run one at a time).
    """
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _CHILD, *args], check=True, stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True)
    dt = time.perf_counter() - t
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    hwm = [int(line.split()[1]) for line in proc.stderr.splitlines() if line.startswith("HWM_KB ")]
    if not hwm:
        raise RuntimeError(f"child did not report its peak memory: {proc.stderr[-2000:]}")
    conv = [float(line.split()[1]) for line in proc.stderr.splitlines() if line.startswith("CONVERT_S ")]
    return (dt, hwm[-1] / 1024.0, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime),
            conv[-1] if conv else None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="120 MB input instead of 1 GB")
    ap.add_argument("--repeats", type=int, default=1, help="runs per target: the fastest is reported "
                                                           "(the peak RSS is the largest)")
    args = ap.parse_args()
    target = 120 * 2**20 if args.quick else 2**30
    DATA.mkdir(parents=True, exist_ok=True)
    src = DATA / f"convert_src_{target >> 20}MB.raw"
    if not src.exists():
        print(f"synthesising {src.name} ...", flush=True)
        make_evt2(src, target)
    size_mb = src.stat().st_size / 2**20
    import hybridhdr as hh
    info = json.loads(subprocess.run([sys.executable, "-m", "hybridhdr", "info", str(src), "--json"],
                                     check=True, capture_output=True, text=True).stdout)
    n = info["events"]
    results = {"input_format": "evt2", "input_mb": round(size_mb, 1), "events": n}
    # baseline: interpreter + imports only
    _, base_rss, _, _ = run_child(["--version"])
    results["baseline_rss_mb"] = round(base_rss, 1)
    for to, ext in (("dat", ".dat"), ("hybridhdr", ".h5")):
        out = DATA / f"convert_out{ext}"
        dts, rsss, cpus, convs = [], [], [], []
        for _ in range(max(1, args.repeats)):
            dt, rss, cpu, conv = run_child(["convert", str(src), str(out), "--to", to, "--no-progress"])
            os.unlink(out)
            dts.append(dt)
            rsss.append(rss)
            cpus.append(cpu)
            convs.append(conv)
        dt, conv = min(dts), min(convs)
        results[f"to_{to}_s"] = round(dt, 2)
        results[f"to_{to}_mev_per_s"] = round(n / dt / 1e6, 1)
        results[f"to_{to}_peak_rss_mb"] = round(max(rsss), 1)
        results[f"to_{to}_cpu_s"] = round(min(cpus), 2)
        results[f"to_{to}_convert_s"] = round(conv, 2)
        results[f"to_{to}_convert_mev_per_s"] = round(n / conv / 1e6, 1)
    results["peak_rss_mb"] = max(results["to_dat_peak_rss_mb"], results["to_hybridhdr_peak_rss_mb"])
    results["goal_peak_rss_mb"] = 1024
    results["meets_goal"] = results["peak_rss_mb"] < 1024
    results["repeats"] = max(1, args.repeats)
    print(f"{size_mb:.0f} MB EVT2 ({n:,} events): peak RSS {results['peak_rss_mb']} MB "
          f"(goal < 1024 MB)")
    for to in ("dat", "hybridhdr"):
        print(f"  to {to}: {results[f'to_{to}_s']} s, {results[f'to_{to}_mev_per_s']} Mev/s "
              f"(the convert call {results[f'to_{to}_convert_s']} s, {results[f'to_{to}_convert_mev_per_s']} "
              f"Mev/s; {results[f'to_{to}_cpu_s']} CPU s)")
    print(json.dumps(results))


if __name__ == "__main__":
    main()
