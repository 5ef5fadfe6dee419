"""Shared fixtures: the sample data in ../shared/data (skipped with a reason when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# One OpenMP thread per test process and per worker it starts (they inherit the environment):
# PyTorch's intra-op pool (ColorVideoVDP's JOD, the learned baselines) and OpenBLAS. The suite
# runs on 2 cores with bench worker processes beside the test process, and oversubscribed OpenMP
# threads spin-wait: a JOD took 10-20x longer with 2 threads than with 1 on a loaded 2-core
# machine, for the same bits (checked on 36x48 to 173x130 frames). A value set in the environment wins.
os.environ.setdefault("OMP_NUM_THREADS", "1")

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("HYBRIDHDR_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


def shared_file(rel: str) -> Path:
    """Path of a sample file under ../shared/data, or skip the test with the reason."""
    p = SHARED_DATA / rel
    if not p.exists():
        pytest.skip(f"sample data {rel!r} not found under {SHARED_DATA} (the ../shared folder is absent)")
    return p


@pytest.fixture
def shared_data():
    """Callable fixture: ``shared_data("prophesee/evt3_sample.raw")`` -> Path, or skip."""
    return shared_file


@pytest.fixture(scope="module")
def procedural_rec_file(tmp_path_factory):
    """``(path, recording)``: a 100 ms procedural recording (seed 4) written to a container, once
    per test module (the CLI tests read it as users' input)."""
    from hybridhdr.formats.container import write_recording
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording(duration_us=100_000, seed=4)
    p = tmp_path_factory.mktemp("rec") / "src.h5"
    write_recording(rec, p)
    return p, rec


def sigint_default() -> None:
    """``preexec_fn`` of a child a test interrupts with SIGINT: a child inherits an ignored SIGINT
    from a parent started in the background (``cmd &`` in a non-interactive shell), and Python then
    installs no KeyboardInterrupt handler; the test needs the default, as a terminal gives."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """``(rc, stdout, stderr, folder)`` of one ``hybridhdr demo`` (its ``--help`` example, verbatim)
    run from an empty folder through ``hybridhdr.cli.main``. The demo simulates, reconstructs and
    evaluates for minutes, so the tests about it (the example runs; what it prints and writes) read
    this one run instead of each running it."""
    import contextlib
    import io
    import shlex

    from hybridhdr._util.examples import EXAMPLES
    from hybridhdr.cli import main
    folder = tmp_path_factory.mktemp("demo")
    out, err = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(shlex.split(EXAMPLES["demo"])[1:])
    finally:
        os.chdir(cwd)
    return rc, out.getvalue(), err.getvalue(), folder
