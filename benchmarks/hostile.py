"""Hostile-input suite and full-disk runs: clean failures within memory and time bounds.

Usage: ``python benchmarks/hostile.py [--quick]``. Progress and the tables go to stderr; the last
stdout line is ONE JSON object: ``table`` (per reader: tried / clean / ok / traceback / crash /
hang / silent), ``max_peak_rss_mb``, ``max_seconds``, ``full_disk`` (``convert`` to every writer
and ``capture record`` on a small tmpfs: exit code, error lines, files left) and
``two_events_1_16_days_file_bytes``.

The cases are generated semantic inputs (tests/hostile/cases.py), each read in a forked child under
RLIMIT_AS and a timeout. Full-disk runs need ``unshare -rm`` (user namespaces); without it they are
reported as skipped with the reason. ``--quick`` uses a 20 s timeout per case and a smaller input
for the full-disk runs; the default uses 120 s and a larger input.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _full_disk(quick: bool) -> dict:
    import numpy as np

    import hybridhdr as hh
    from hybridhdr.formats.container import write_recording
    from tests.capture.test_full_disk import _NO_NS, _WRITERS, _events, _recording, run_on_tmpfs
    if _NO_NS is not None:
        return {"skipped": _NO_NS}
    out = {}
    with tempfile.TemporaryDirectory(prefix="hybridhdr-fulldisk-") as d:
        d = Path(d)
        n = 200_000 if quick else 2_000_000
        src = write_recording(_recording(n), d / "in.h5", compression=None)
        for fmt, name in _WRITERS:
            mnt = d / f"mnt_{fmt}"
            rc, err, files = run_on_tmpfs(mnt, "256k", [sys.executable, "-m", "hybridhdr", "convert", str(src),
                                                        str(mnt / name), "--to", fmt, "--no-progress"])
            out[f"convert_{fmt}"] = {"rc": rc, "error_lines": [ln for ln in err.splitlines() if "error:" in ln],
                                     "traceback": "Traceback" in err, "files_left": files}
        ev_file = d / "ev.raw"
        hh.write(hh.Recording(_events(300_000, seed=3), (480, 640)), ev_file)
        for label, size in (("record_journal_full", "128k"), ("record_finish_full", "5m")):
            mnt = d / f"mnt_{label}"
            rc, err, files = run_on_tmpfs(mnt, size, [sys.executable, "-m", "hybridhdr", "capture", "record",
                                                      "--events", str(ev_file), "--out", str(mnt / "rec.h5"),
                                                      "--pace", "fast", "--compression", "none", "--no-progress"])
            out[f"capture_{label}"] = {"rc": rc, "error_lines": [ln for ln in err.splitlines() if "error:" in ln],
                                       "traceback": "Traceback" in err, "files_left": files}
        del np
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "tests.hostile.cases", "--json"] + (["--quick"] if a.quick else []),
                       cwd=REPO, capture_output=True, text=True)
    suite = json.loads(r.stdout.strip().splitlines()[-1])
    from tests.hostile.cases import format_table
    print(format_table(suite["table"]), file=sys.stderr)
    bad = [c for c in suite["cases"] if c["outcome"] not in ("clean", "ok")]
    for c in bad:
        print(f"NOT CLEAN: {c}", file=sys.stderr)
    fd = _full_disk(a.quick)
    for k, v in fd.items():
        print(f"full disk {k}: {v}", file=sys.stderr)
    import numpy as np

    import hybridhdr as hh
    from hybridhdr.formats.container import write_recording
    with tempfile.TemporaryDirectory() as d:
        ev = hh.make_events([0, int(1.16 * 86400e6)], [0, 1], [0, 1], [1, -1])
        size = write_recording(hh.Recording(ev, (480, 640)), Path(d) / "two.h5").stat().st_size
    del np
    res = {"benchmark": "hostile", "quick": a.quick, "table": suite["table"], "not_clean": len(bad),
           "max_peak_rss_mb": suite["max_peak_rss_mb"], "max_seconds": suite["max_seconds"],
           "full_disk": fd, "two_events_1_16_days_file_bytes": size,
           "wall_s": round(time.perf_counter() - t0, 1)}
    print(json.dumps(res))
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
