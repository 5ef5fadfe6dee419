"""ColorVideoVDP's per-frame log lines are dropped without turning the process's logging off: a
bench scoring in threads used ``logging.disable`` save/restore pairs that crossed, and left every
WARNING of the process off for the rest of the run (a later test's log line vanished)."""

import logging
import os
import threading

from hybridhdr.evaluate import cvvdp_metric as C


def _record(path, level=logging.WARNING):
    return logging.LogRecord("root", level, path, 1, "msg", None, None)


def test_only_pycvvdp_records_are_dropped():
    pyc = os.path.join(os.sep, "x", "site-packages", "pycvvdp", "display_model.py")
    assert not C._DROP.filter(_record(pyc))
    assert not C._DROP.filter(_record(pyc, logging.INFO))
    assert C._DROP.filter(_record(pyc, logging.ERROR))  # its errors still show
    assert C._DROP.filter(_record(os.path.join(os.sep, "x", "hybridhdr", "cli.py")))


def test_overlapping_threads_leave_logging_as_it_was():
    root = logging.getLogger()
    before = (list(root.filters), logging.root.manager.disable)
    inside, release = threading.Barrier(3), threading.Event()

    def hold():
        with C._quiet_cvvdp():
            inside.wait()
            release.wait(10)

    ts = [threading.Thread(target=hold) for _ in range(2)]
    for t in ts:
        t.start()
    inside.wait()
    assert root.filters.count(C._DROP) == 1  # installed once, while either thread is inside
    assert logging.root.manager.disable == before[1]  # never the process-wide switch
    release.set()
    for t in ts:
        t.join(10)
    assert (list(root.filters), logging.root.manager.disable) == before
