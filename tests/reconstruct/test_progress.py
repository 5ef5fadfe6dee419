"""Progress of ``reconstruct``: each event counted once (also by the two-sided pass, whose two
passes both go through the events), output frames counted once whatever files each makes
(EXR, PNG, MP4), a total (so a percentage and an ETA), and no other line cut through a bar."""

from __future__ import annotations

import re
import sys

import pytest

from hybridhdr.cli import main


@pytest.fixture(scope="module")
def rec_file(tmp_path_factory):
    import dataclasses

    from hybridhdr.formats.container import write_recording
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording((20, 30), 300_000, seed=0)
    cam = dataclasses.replace(rec.metadata.event_camera, contrast_threshold_on=0.2, contrast_threshold_off=0.2)
    rec = dataclasses.replace(rec, metadata=dataclasses.replace(rec.metadata, event_camera=cam))
    return write_recording(rec, tmp_path_factory.mktemp("p") / "rec.h5"), rec


@pytest.mark.parametrize("workers", [1, 2])
def test_two_sided_pass_counts_each_event_once(rec_file, workers):
    from hybridhdr.reconstruct.api import reconstruct_iter
    path, rec = rec_file
    counted = []
    outs = list(reconstruct_iter(str(path), "akf", mode="offline", fps=50, n_workers=workers,
                                 progress=counted.append))
    assert outs
    n = len(rec.events)
    # both passes together went through the events up to the last output: between half and all of
    # them, never more (the forward pass alone would be at most n; both counted in full: up to 2n)
    assert 0.5 * n <= sum(counted) <= n, (sum(counted), n)


def test_causal_pass_still_counts_events(rec_file):
    from hybridhdr.reconstruct.api import reconstruct_iter
    path, rec = rec_file
    counted = []
    list(reconstruct_iter(str(path), "akf", mode="causal", fps=50, progress=counted.append))
    assert 0.5 * len(rec.events) <= sum(counted) <= len(rec.events)


def test_cli_bar_has_a_total_counts_frames_and_ends_before_the_final_line(rec_file, tmp_path, capsys):
    path, rec = rec_file
    rc = main(["reconstruct", str(path), "--out", str(tmp_path / "o"), "--fps", "100", "--png", "--mp4"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    n_frames = int(re.search(r"akf: (\d+) frames", cap.out).group(1))
    last_state = cap.err.replace("\r", "\n").strip().splitlines()[-1]
    n = len(rec.events)
    assert f"{n / 1000:.1f}k/{n / 1000:.1f}k" in last_state and "100%" in last_state, last_state  # a total
    assert f"{n_frames} frames written" in last_state, last_state  # frames, not EXR + PNG + MP4 files
    assert "img" not in cap.err
    # the lines printed before the run come before the bar, each on its own line
    head = cap.err.split("\r", 1)[0]
    assert head.endswith("\n") and "device:" in head


def _write_beside_a_bar(progress_bars, logging):
    with progress_bars(True) as new_bar:
        b = new_bar(total=10, desc="work")
        b.update(3)
        print("a line in the middle", file=sys.stderr)
        # a handler and a level of its own, on stderr as it is now: other tests' commands configure
        # the root logger once per process (``-q`` leaves it at ERROR, its handler on a stream pytest
        # has closed since), and the result must not depend on the test order
        # (and ``logging.disable``/a ``disabled`` flag left by a library's logging set-up are undone)
        log = logging.getLogger("hybridhdr.test")
        h = logging.StreamHandler()
        old = log.level, log.propagate, log.disabled, logging.root.manager.disable
        log.addHandler(h)
        log.setLevel(logging.WARNING)
        log.propagate = False
        log.disabled = False
        logging.disable(logging.NOTSET)
        try:
            log.warning("a logged line")
        finally:
            log.removeHandler(h)
            log.setLevel(old[0])
            log.propagate, log.disabled = old[1], old[2]
            logging.disable(old[3])
        b.update(7)
    print("final line", file=sys.stderr)


def test_lines_written_while_a_bar_runs_do_not_cut_through_it():
    import contextlib
    import io
    import logging

    from hybridhdr._util.progress import progress_bars
    # stderr is a buffer of this test's own (not pytest's capture, which other tests' bars and
    # handlers may still hold), so the test sees exactly what the block wrote
    buf = io.StringIO()
    with contextlib.redirect_stderr(buf):
        _write_beside_a_bar(progress_bars, logging)
    err = buf.getvalue()
    for text in ("a line in the middle", "a logged line"):
        lines = [ln for ln in err.split("\n") if text in ln]
        assert lines, f"{text!r} is missing from stderr: {err!r}"
        line = lines[0]
        assert line.split("\r")[-1].strip().endswith(text) and "work" not in line.split("\r")[-1], repr(line)
    assert err.rstrip().endswith("final line") and "work" not in err.rstrip().rsplit("\n", 1)[-1]
    with progress_bars(False) as new_bar:
        assert new_bar(total=3) is None
