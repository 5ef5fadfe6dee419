"""Start-up of the ``hybridhdr`` command: ``hybridhdr --help`` against importing the heavy parts.

Usage: ``python benchmarks/cli_start.py [--quick] [--repeats N]``. Prints ONE JSON object on the
last line.

Every command pays the parser's start-up before it does anything. The five parts'
packages load their modules lazily (PEP 562), so building the parser imports no numba, kernels,
cv2, h5py or matplotlib; a verb's heavy modules load when that verb runs. Timed, each in a fresh
child process (best and median of ``--repeats``, interleaved):

* ``help``: ``python -m hybridhdr --help``;
* ``python_numpy``: ``python -c "import numpy"`` (the floor every command pays);
* ``heavy_imports``: ``python -c "import hybridhdr.cli, hybridhdr.reconstruct.api,
  hybridhdr.calibrate.thresholds, hybridhdr.evaluate.bench"`` — what ``--help`` imported before
  (the eager package ``__init__``\\ s pulled these in); ``ratio`` = heavy / help.

Also reports whether building the parser left numba in ``sys.modules``. The machine is shared:
the load average is printed beside the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _time(cmd, env):
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    return time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 repeats (default 5)")
    ap.add_argument("--repeats", type=int, default=None)
    a = ap.parse_args(argv)
    n = a.repeats or (3 if a.quick else 5)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    py = sys.executable
    cmds = {"help": [py, "-m", "hybridhdr", "--help"],
            "python_numpy": [py, "-c", "import numpy"],
            "heavy_imports": [py, "-c", "import hybridhdr.cli, hybridhdr.reconstruct.api, "
                                        "hybridhdr.calibrate.thresholds, hybridhdr.evaluate.bench"]}
    times = {k: [] for k in cmds}
    for _ in range(n):
        for k, c in cmds.items():
            times[k].append(_time(c, env))
    probe = subprocess.run([py, "-c", "import sys, hybridhdr.cli as c; c.build_parser(); "
                                      "print(sorted(m for m in ('numba', 'cv2', 'h5py', 'matplotlib', 'scipy') "
                                      "if m in sys.modules))"], env=env, capture_output=True, text=True, check=True)
    res = {k: {"best_s": round(min(v), 3), "median_s": round(statistics.median(v), 3)} for k, v in times.items()}
    res["ratio_heavy_over_help"] = round(min(times["heavy_imports"]) / min(times["help"]), 2)
    res["heavy_modules_after_build_parser"] = json.loads(probe.stdout.strip().replace("'", '"'))
    res["repeats"] = n
    res["loadavg_1min"] = round(os.getloadavg()[0], 2)
    for k in cmds:
        print(f"{k}: best {res[k]['best_s']} s, median {res[k]['median_s']} s", file=sys.stderr)
    print(json.dumps(res))


if __name__ == "__main__":
    main()
