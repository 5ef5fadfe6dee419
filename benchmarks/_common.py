"""Helpers shared by the benchmarks: synthetic event streams and cached test files.

Generated files live in ``benchmarks/_data/`` (git-ignored) and are reused when their name
(format, event count, seed) matches.
"""

from __future__ import annotations

import os
import resource
import time
from pathlib import Path

import numpy as np

DATA_DIR = Path(__file__).resolve().parent / "_data"
REPO = Path(__file__).resolve().parents[1]
#: The sample data: ``$HYBRIDHDR_SHARED_DATA``, else ``../shared/data`` beside the repository.
SHARED_DATA = Path(os.environ.get("HYBRIDHDR_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def synth_events(n: int, width: int, height: int, seed: int = 0, rate_mev_s: float = 2.0,
                 t0_us: int = 0) -> np.ndarray:
    """A sorted synthetic event stream with clusters of same-time, same-row neighbours.

    Parameters
    ----------
    n : int
        Number of events.
    width, height : int
        Sensor size in pixels.
    seed : int
        Seed of the local generator.
    rate_mev_s : float
        Mean event rate in millions of events per second (sets the time span).
    t0_us : int
        First cluster time in µs.

    Returns
    -------
    ndarray of shape (n,), dtype EVENT_DTYPE
        About 60 % of the clusters are single events; the rest are runs of 2-12 events at
        neighbouring columns (1-2 px apart), as edges produce, so EVT 3.0 vectors are exercised.
    """
    from hybridhdr.events import EVENT_DTYPE

    rng = np.random.default_rng(seed)
    m = n  # upper bound on clusters
    lens = np.where(rng.random(m) < 0.6, 1, rng.integers(2, 13, m))
    cs = np.cumsum(lens)
    k = int(np.searchsorted(cs, n)) + 1
    lens = lens[:k].copy()
    lens[-1] -= int(cs[k - 1]) - n if int(cs[k - 1]) > n else 0
    lens = lens[lens > 0]
    k = len(lens)
    mean_dt = lens.mean() / rate_mev_s  # µs between clusters
    tk = t0_us + np.cumsum(rng.poisson(mean_dt, k)).astype(np.int64)
    yk = rng.integers(0, height, k).astype(np.uint16)
    pk = np.where(rng.random(k) < 0.5, 1, -1).astype(np.int8)
    xk = rng.integers(0, max(1, width - 24), k)
    rep = np.repeat(np.arange(k), lens)
    first = np.repeat(np.cumsum(lens) - lens, lens)
    step = 1 + (rng.random(n) < 0.3)
    cum = np.cumsum(step)
    off = cum - cum[first] if n else cum  # 0 for the first of each cluster
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"] = tk[rep]
    ev["x"] = np.minimum(xk[rep] + off, width - 1)
    ev["y"] = yk[rep]
    ev["p"] = pk[rep]
    # keep x strictly increasing inside clusters after clipping: drop nothing, clipping only
    # affects the last pixels of the row and equal x at the same t is legal
    return ev


def encode_evt21(events: np.ndarray, legacy: bool = False) -> bytes:
    """EVT 2.1 words for ``events`` (test/benchmark encoder, no 2^34 µs loop bridging)."""
    from hybridhdr.formats.prophesee import _encode_evt21
    return _encode_evt21(events, legacy=legacy)


def make_file(fmt: str, n: int, seed: int = 0, chunk: int = 5_000_000, log=print) -> Path:
    """Write (or reuse) a synthetic ``fmt`` file of ``n`` events under :data:`DATA_DIR`."""
    from hybridhdr.formats import prophesee as P
    from hybridhdr.events import SensorSize

    DATA_DIR.mkdir(parents=True, exist_ok=True)
    ext = "dat" if fmt == "dat" else "raw"
    path = DATA_DIR / f"synth_{fmt}_{n}_{seed}.{ext}"
    if path.exists():
        return path
    ss = SensorSize(720, 1280) if fmt in ("evt3", "evt21") else SensorSize(480, 640)
    t_start = time.perf_counter()
    if fmt == "evt21":
        header = (f"% evt 2.1\n% format EVT21;height={ss.height};width={ss.width}\n"
                  f"% geometry {ss.width}x{ss.height}\n% end\n").encode()
        tmp = path.with_name(path.name + ".partial")
        with open(tmp, "wb") as f:
            f.write(header)
            t_next = 0
            for i0 in range(0, n, chunk):
                ev = synth_events(min(chunk, n - i0), ss.width, ss.height, seed + i0, t0_us=t_next)
                t_next = int(ev["t"][-1]) + 1
                f.write(encode_evt21(ev))
        os.replace(tmp, path)
    else:
        with P.WRITERS[fmt](path, sensor_size=ss) as w:
            t_next = 0
            for i0 in range(0, n, chunk):
                ev = synth_events(min(chunk, n - i0), ss.width, ss.height, seed + i0, t0_us=t_next)
                t_next = int(ev["t"][-1]) + 1
                w.write_events(ev)
    log(f"  wrote {path.name}: {path.stat().st_size / 1e6:.1f} MB in {time.perf_counter() - t_start:.1f} s")
    return path


def best_of(fn, repeat: int = 3):
    """Run ``fn`` ``repeat`` times; return (best seconds, last result)."""
    best = float("inf")
    res = None
    for _ in range(repeat):
        res = None
        t0 = time.perf_counter()
        res = fn()
        best = min(best, time.perf_counter() - t0)
    return best, res


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MB (Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def loadavg() -> float | None:
    """1-minute load average (other processes share the cores: read speed-ups against it)."""
    try:
        return float(Path("/proc/loadavg").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def git(*args) -> str:
    """``git -C REPO ARGS`` (stdout, stripped)."""
    import subprocess
    return subprocess.run(["git", "-C", str(REPO), *args], check=True, capture_output=True, text=True).stdout.strip()


def worktree(rev: str) -> Path:
    """A detached git worktree of ``rev`` under the temporary folder (reused; the main tree is untouched)."""
    import shutil
    import tempfile
    sha = git("rev-parse", rev)
    wt = Path(tempfile.gettempdir()) / f"hybridhdr-wt-{sha[:12]}"
    if not (wt / "hybridhdr" / "cli.py").exists():
        if wt.exists():
            shutil.rmtree(wt)
        git("worktree", "add", "--detach", str(wt), sha)
    return wt
