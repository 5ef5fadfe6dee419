"""Every command's ``--help`` ends with one runnable example (``hybridhdr/_util/examples.py``),
the README's line where the README shows that command, and every example runs.

The examples that are lines of the README's short tour run verbatim in
``tests/test_readme_tour.py`` (checked here: they are in the tour block); this file runs the
others the same way: from a folder ``repo`` whose ``../shared/data`` is the sample data (skipped
when it is absent), after the example's inputs are made by the examples or tour lines that make
them (``crf/`` by ``calibrate crf``, ``rec.h5`` by ``capture record``, ``memorial/`` by
``capture brackets``), or, for the two that a
Mitsuba render or a crash makes (``sim.h5``, an interrupted ``rec.h5``), by a small stand-in.
``demo``, ``evaluate bench`` and ``evaluate paper`` are marked slow.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex

import pytest

from hybridhdr._util.examples import EXAMPLES
from hybridhdr.cli import build_parser, main

from .conftest import REPO_ROOT, SHARED_DATA


def _leaves(p, path=()):
    subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, p
    for a in subs:
        for name, child in a.choices.items():
            yield from _leaves(child, path + (name,))


def _readme_blocks():
    text = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
    return re.findall(r"```sh\n(.*?)```", text[text.index("## A short tour"):], flags=re.S)


def _commands(block):
    for line in block.splitlines():
        for part in line.split("&&"):
            argv = shlex.split(part, comments=True)
            if argv and argv[0] == "hybridhdr":
                yield argv


def _command_of(argv):
    """The command path of an argv (``["calibrate", "crf"]``) as the parser resolves it."""
    names = {" ".join(path) for path, _ in _leaves(build_parser())}
    for n in (2, 1):
        if " ".join(argv[:n]) in names:
            return " ".join(argv[:n])
    raise AssertionError(f"no command in {argv}")


def test_every_help_ends_with_its_example():
    leaves = dict((" ".join(path), p) for path, p in _leaves(build_parser()))
    assert set(leaves) == set(EXAMPLES), set(leaves) ^ set(EXAMPLES)
    for name, p in leaves.items():
        last = p.format_help().rstrip().splitlines()[-1].strip()
        assert last == EXAMPLES[name], name
        argv = shlex.split(last)
        assert argv[0] == "hybridhdr" and _command_of(argv[1:]) == name, last
        args = build_parser().parse_args(argv[1:])  # it parses, and to that command
        assert args._prog == f"hybridhdr {name}"


def test_examples_are_the_readmes_where_it_shows_the_command():
    readme = {}
    for block in _readme_blocks():
        for argv in _commands(block):
            readme.setdefault(_command_of(argv[1:]), []).append(argv)
    for name, line in EXAMPLES.items():
        if name in readme:
            assert shlex.split(line) in readme[name], (name, line, readme[name])


_TOUR = [argv for argv in _commands(_readme_blocks()[0])]
_OWN = [name for name, line in EXAMPLES.items() if shlex.split(line) not in _TOUR]
_SLOW = {"demo", "evaluate bench", "evaluate paper"}


def test_tour_examples_run_in_the_tour_test():
    """The examples that are tour lines are run (verbatim, on the sample data) by the tour test."""
    in_tour = [name for name in EXAMPLES if name not in _OWN]
    assert len(in_tour) >= 10


def _run(line, capsys):
    rc = main(shlex.split(line)[1:])
    out = capsys.readouterr()
    assert rc == 0, f"{line}\n{out.err[-2000:]}"
    return out


def _interrupted_recording(path):
    """A recording whose recorder stopped after its last flush without finishing the file, as a
    ``kill -9`` leaves it (what ``capture recover`` is for)."""
    from hybridhdr.capture.recorder import Recorder
    from hybridhdr.capture.sources import SyntheticEventSource
    src = SyntheticEventSource(1e5, sensor_size=(8, 8), chunk_us=1_000, duration_s=0.005, pace="fast")
    r = Recorder(path, src)
    r.start()
    r.wait()
    r.stop()
    r._jw.close()  # as if killed after the last flush


def _sim_standin(path):
    """``sim.h5`` as ``simulate`` writes it (events, frames, HDR references, the simulated
    sensor's thresholds declared), from the analytic scene instead of a Mitsuba render (minutes)."""
    import dataclasses

    from hybridhdr.formats.container import write_recording
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording((36, 48), 300_000, contrast_threshold=0.2, seed=0)
    cam = dataclasses.replace(rec.metadata.event_camera, contrast_threshold_on=0.2, contrast_threshold_off=0.2)
    write_recording(dataclasses.replace(rec, metadata=dataclasses.replace(rec.metadata, event_camera=cam)), path)


#: what an example needs first: other examples (by command), or a function making a file
_NEEDS = {
    "capture recover": [lambda: _interrupted_recording("rec.h5")],
    "capture sync": ["hybridhdr convert ../shared/data/aedat4/davis346_street.aedat4 street.h5"],
    "capture session": [EXAMPLES["capture record"], EXAMPLES["calibrate crf"], EXAMPLES["capture brackets"]],
    "evaluate metrics": [lambda: _sim_standin("sim.h5"), "hybridhdr reconstruct sim.h5 --out sim_video/"],
}


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in _SLOW else n for n in _OWN])
def test_help_example_runs(name, tmp_path, capsys, monkeypatch, request):
    line = EXAMPLES[name]
    if name == "demo":  # run once for this test and tests/test_cli.py (minutes): tests/conftest.py
        rc, _, err, _ = request.getfixturevalue("demo_run")
        assert rc == 0, f"{line}\n{err[-2000:]}"
        return
    steps = _NEEDS.get(name, [])
    if "../shared/data" in line + " ".join(s for s in steps if isinstance(s, str)):
        if not SHARED_DATA.is_dir():
            pytest.skip(f"the sample data folder {SHARED_DATA} is absent")
        (tmp_path / "shared").mkdir()
        os.symlink(SHARED_DATA, tmp_path / "shared" / "data")
    repo = tmp_path / "repo"
    repo.mkdir()
    monkeypatch.chdir(repo)
    for step in steps:
        step() if callable(step) else _run(step, capsys)
    if name == "capture serve-dv":
        _run_server_example(line, repo, capsys)
        return
    _run(line, capsys)


def _run_server_example(line, repo, capsys):
    """``capture serve-dv`` serves until its clients have everything, then ends its process: it
    runs as its own process, and ``capture record`` on the URLs it prints (port 0: free ports it
    chose) is the client."""
    import selectors
    import subprocess
    import sys
    import time

    pytest.importorskip("dv_processing", reason="dv-processing (the [dv] extra) is not installed")
    import re
    argv = shlex.split(line)
    asked = [argv[i + 1] for i, a in enumerate(argv) if a in ("--events", "--frames", "--triggers", "--imu")]
    urls = None
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen([sys.executable, "-m", "hybridhdr", *argv[1:]], cwd=repo, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        sel = selectors.DefaultSelector()
        sel.register(proc.stderr, selectors.EVENT_READ)
        t_end = time.monotonic() + 120
        while time.monotonic() < t_end:  # its line saying the sockets listen (a probe would count as a client)
            if sel.select(timeout=0.5):
                got = proc.stderr.readline()
                if "waiting for clients" in got:
                    urls = re.findall(r" on (dv-\S+?)[,;]", got)
                    break
                assert got or proc.poll() is None, f"{line}: the server ended (exit {proc.poll()})"
        else:
            raise AssertionError(f"{line}: the server did not open its sockets")
        assert len(urls) == len(asked), got
        for a, u in zip(asked, urls):  # port 0 became a free port, anything else is served as given
            assert u == a if not a.endswith(":0") else re.fullmatch(r"dv-tcp://127\.0\.0\.1:[1-9]\d*", u), (a, u)
        rec = ["capture", "record", "--out", "served.h5", "--reconnect-s", "1", "--no-progress"]
        for u in urls:
            rec += ["--source", u]
        assert main(rec) == 0, capsys.readouterr().err[-2000:]
        served = proc.communicate(timeout=60)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=30)
    assert proc.returncode == 0 and "served 78,830 events, 59 frames, 236 triggers, 2,363 imu" in served, served
