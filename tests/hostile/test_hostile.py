"""The hostile-input suite (tests/hostile/cases.py) as a test: 0 tracebacks, crashes, hangs, silent results.

Every case runs in a forked child under RLIMIT_AS (address space at fork + 1.5 GiB) with a 20 s
timeout; the whole suite takes about 15 s. ``benchmarks/hostile.py`` prints the same table.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hybridhdr._util.limits import LimitExceeded, allow_huge, check_fps_outputs, check_output_count

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def suite():
    pytest.importorskip("dv_processing")
    pytest.importorskip("rosbags")
    r = subprocess.run([sys.executable, "-m", "tests.hostile.cases", "--quick", "--json"], cwd=REPO,
                       capture_output=True, text=True, timeout=600)
    assert r.stdout.strip(), r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_no_traceback_crash_hang_or_silent_result(suite):
    bad = [c for c in suite["cases"] if c["outcome"] not in ("clean", "ok")]
    assert not bad, json.dumps(bad, indent=1)
    readers = set(suite["table"])
    assert {"hybridhdr", "evt2", "evt3", "dat", "aedat4", "ecd", "e2vid", "dsec", "monash", "akf_mat", "rosbag",
            "journal"} <= readers


def test_every_case_within_time_and_memory(suite):
    for c in suite["cases"]:
        assert c["peak_rss_mb"] < 1024, c
        assert c["seconds"] < 20, c


def test_output_count_checked_before_work():
    assert check_output_count(300) == 300
    assert check_fps_outputs(0, 1_000_000, 300) == 301
    with pytest.raises(LimitExceeded, match="--allow-huge"):
        check_fps_outputs(0, 1_000_000, 1e12)
    with pytest.raises(LimitExceeded):
        check_output_count(10**7)
    with pytest.raises(ValueError):
        check_fps_outputs(0, 1_000_000, float("nan"))
    with pytest.raises(ValueError):
        check_fps_outputs(0, 1_000_000, -5)
    with allow_huge():
        assert check_output_count(10**7) == 10**7
