"""Full disks: every writer gives one clean error line, removes its partial output, exits 1, never crashes.

The end-to-end cases run ``hybridhdr convert`` / ``capture record`` / ``capture recover`` in a child
process whose output folder is a small tmpfs, mounted in a user + mount namespace
(``unshare -rm``); they skip with the reason where namespaces are not available. The unit cases
simulate ENOSPC by making ``os.pwrite`` fail and run everywhere.
"""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.model import Frames, Recording

REPO = Path(__file__).resolve().parents[2]


def _unshare_works() -> str | None:
    if shutil.which("unshare") is None:
        return "unshare(1) is not installed"
    try:
        r = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /tmp && echo ok"],
                           capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"unshare failed to run ({e})"
    if r.returncode != 0 or "ok" not in r.stdout:
        return f"cannot mount a tmpfs in a user namespace here ({r.stderr.strip()[:200]})"
    return None


_NO_NS = _unshare_works()
needs_tmpfs = pytest.mark.skipif(_NO_NS is not None, reason=f"full-disk runs need a tmpfs: {_NO_NS}")


def _events(n, seed=0, width=640, height=480, span_us=2_000_000):
    rng = np.random.default_rng(seed)
    return hh.make_events(np.sort(rng.integers(0, span_us, n)), rng.integers(0, width, n),
                          rng.integers(0, height, n), rng.choice([-1, 1], n))


def _recording(n=200_000, frames=True):
    fr = None
    if frames:
        rng = np.random.default_rng(1)
        k = 4
        ts = np.arange(k, dtype=np.int64) * 400_000
        fr = Frames(rng.integers(0, 255, (k, 480, 640), dtype=np.uint8), ts, ts + 10_000)
    return Recording(_events(n), (480, 640), fr)


def run_on_tmpfs(mount: Path, size: str, argv: list[str], timeout=120):
    """Run ``argv`` with a ``size`` tmpfs mounted on ``mount``; returns CompletedProcess and the listing."""
    mount.mkdir(parents=True, exist_ok=True)
    script = (f'mount -t tmpfs -o size={size} tmpfs "{mount}" || exit 99; '
              f'"$@"; rc=$?; echo "@@rc=$rc"; ls -A "{mount}" | sed "s/^/@@file=/"; exit 0')
    r = subprocess.run(["unshare", "-rm", "sh", "-c", script, "sh", *argv], capture_output=True, text=True,
                       timeout=timeout, cwd=REPO)
    assert "@@rc=" in r.stdout, r.stdout + r.stderr
    rc = int(r.stdout.split("@@rc=")[1].split()[0])
    files = [ln[len("@@file="):] for ln in r.stdout.splitlines() if ln.startswith("@@file=")]
    return rc, r.stderr, files


def _assert_clean(rc, err, files, what):
    assert rc == 1, f"{what}: exit {rc} (SIGSEGV is -11/139)\n{err[-2000:]}"
    lines = [ln for ln in err.splitlines() if ln.strip()]
    errs = [ln for ln in lines if "error:" in ln]
    assert len(errs) == 1, f"{what}: expected one error line, got:\n{err[-3000:]}"
    assert "Traceback" not in err and "Segmentation" not in err, err[-3000:]
    assert "No space left on device" in errs[0], errs[0]
    assert not [f for f in files if not f.endswith(".journal")], f"{what}: left {files}"


@pytest.fixture(scope="module")
def big_input(tmp_path_factory):
    d = tmp_path_factory.mktemp("fulldisk")
    p = d / "in.h5"
    from hybridhdr.formats.container import write_recording
    write_recording(_recording(), p, compression=None)
    return p


_WRITERS = [("hybridhdr", "out.h5"), ("akf_mat", "out.mat"), ("evt2", "out.raw"), ("evt3", "out3.raw"),
            ("dat", "out.dat"), ("ecd", "out_ecd"), ("aedat4", "out.aedat4")]


@needs_tmpfs
@pytest.mark.parametrize("fmt,name", _WRITERS, ids=[w[0] for w in _WRITERS])
def test_convert_to_full_disk(tmp_path, big_input, fmt, name):
    mnt = tmp_path / "mnt"
    rc, err, files = run_on_tmpfs(mnt, "256k", [sys.executable, "-m", "hybridhdr", "convert", str(big_input),
                                                 str(mnt / name), "--to", fmt, "--no-progress"])
    _assert_clean(rc, err, files, f"convert to {fmt}")


@needs_tmpfs
def test_capture_record_finish_on_full_disk(tmp_path, big_input):
    # the journal fits, the container written by the finish step does not
    mnt = tmp_path / "mnt"
    ev_file = tmp_path / "ev.raw"
    hh.write(Recording(_events(300_000, seed=3), (480, 640)), ev_file)
    rc, err, files = run_on_tmpfs(mnt, "5m", [sys.executable, "-m", "hybridhdr", "capture", "record",
                                              "--events", str(ev_file), "--out", str(mnt / "rec.h5"),
                                              "--pace", "fast", "--compression", "none", "--no-progress"])
    if rc == 0:
        pytest.skip("the container fitted on the 5 MB tmpfs (journal compression differs here)")
    _assert_clean(rc, err, [f for f in files if not f.endswith(".journal")], "capture record")
    assert "rec.h5.journal" in files and "capture recover" in err


@needs_tmpfs
def test_capture_record_journal_on_full_disk(tmp_path):
    mnt = tmp_path / "mnt"
    ev_file = tmp_path / "ev.raw"
    hh.write(Recording(_events(300_000, seed=4), (480, 640)), ev_file)
    rc, err, files = run_on_tmpfs(mnt, "128k", [sys.executable, "-m", "hybridhdr", "capture", "record",
                                                "--events", str(ev_file), "--out", str(mnt / "rec.h5"),
                                                "--pace", "fast", "--no-progress"])
    _assert_clean(rc, err, files, "capture record (journal)")
    assert files == ["rec.h5.journal"], files  # kept for recover; nothing under the final name


@needs_tmpfs
def test_capture_recover_to_full_disk(tmp_path):
    from hybridhdr.capture.recorder import Recorder
    from hybridhdr.capture.sources import ReplayEventSource
    ev_file = tmp_path / "ev.raw"
    hh.write(Recording(_events(300_000, seed=5), (480, 640)), ev_file)
    rec = Recorder(tmp_path / "rec.h5", ReplayEventSource(ev_file, pace="fast"), compression=None)
    rec.start()
    rec.wait()
    rec.stop()
    rec._jw.close()  # as after kill -9: the journal stays, no container
    assert (tmp_path / "rec.h5.journal").exists()
    mnt = tmp_path / "mnt"
    rc, err, files = run_on_tmpfs(mnt, "256k", [sys.executable, "-m", "hybridhdr", "capture", "recover",
                                                str(tmp_path / "rec.h5"), "--out", str(mnt / "rec.h5"),
                                                "--compression", "none"])
    _assert_clean(rc, err, files, "capture recover")
    assert (tmp_path / "rec.h5.journal").exists()


# -- simulated ENOSPC (runs everywhere) -------------------------------------------------------------
@pytest.fixture
def enospc_after(monkeypatch):
    """Make the guarded HDF5 file fail with ENOSPC once ``limit`` bytes have been written."""
    import hybridhdr.formats._safe_h5 as safe

    def arm(limit):
        state = {"n": 0}
        real = os.pwrite

        def pwrite(fd, data, offset):
            if state["n"] + len(data) > limit:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            state["n"] += len(data)
            return real(fd, data, offset)
        monkeypatch.setattr(safe.os, "pwrite", pwrite)
    return arm


@pytest.mark.parametrize("limit", [0, 3000, 200_000])
@pytest.mark.parametrize("fmt,name", [("hybridhdr", "o.h5"), ("akf_mat", "o.mat")])
def test_hdf5_writers_enospc_clean(tmp_path, enospc_after, limit, fmt, name):
    from hybridhdr.formats._safe_h5 import DiskWriteError
    rec = _recording(50_000)
    enospc_after(limit)
    with pytest.raises(DiskWriteError, match="No space left on device") as ei:
        hh.write(rec, tmp_path / name, fmt)
    assert ei.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []


def test_convert_cli_enospc_one_line(tmp_path, enospc_after, capsys):
    from hybridhdr.cli import main
    from hybridhdr.formats.container import write_recording
    src = tmp_path / "in.h5"
    write_recording(_recording(20_000), src)
    enospc_after(5000)
    rc = main(["convert", str(src), str(tmp_path / "out.h5"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1
    assert err.count("error:") == 1 and "No space left on device" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.h5"]


@needs_tmpfs
def test_aedat4_output_too_big_for_the_disk(tmp_path, big_input):
    # the event spool fits on the 5 MB tmpfs, the AEDAT4 file would not: dv-processing would stop
    # the process on a full disk, so the writer refuses before it starts
    pytest.importorskip("dv_processing")
    mnt = tmp_path / "mnt"
    rc, err, files = run_on_tmpfs(mnt, "5m", [sys.executable, "-m", "hybridhdr", "convert", str(big_input),
                                              str(mnt / "out.aedat4"), "--no-progress"])
    _assert_clean(rc, err, files, "convert to aedat4 (output too big)")
