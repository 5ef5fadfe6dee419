"""Process hygiene: termination signals end a command like Ctrl-C does, and helper processes end
with the process that started them (``docs/security.md``).

* :func:`signals_exit`: SIGTERM and SIGHUP raise ``SystemExit(128 + signal)`` in the main thread,
  so every ``finally``/``except BaseException`` clean-up (partial files, temp MP4s, writer
  pools) runs, exactly as for SIGINT.
* :func:`die_with_parent`: called first in a worker process; on Linux the kernel sends it SIGKILL
  when its parent dies (``prctl(PR_SET_PDEATHSIG)``), so a ``kill -9`` of the command leaves no
  writer or bench worker behind. Elsewhere a watchdog thread polls the parent's pid.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

__all__ = ["signals_exit", "die_with_parent", "die_with_process"]


@contextlib.contextmanager
def signals_exit():
    """SIGTERM/SIGHUP raise ``SystemExit(128 + signum)`` while the block runs (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _exit(signum, frame):
        raise SystemExit(128 + signum)

    old = {}
    for name in ("SIGTERM", "SIGHUP"):
        sg = getattr(signal, name, None)
        if sg is not None and signal.getsignal(sg) in (signal.SIG_DFL, None):
            old[sg] = signal.signal(sg, _exit)
    try:
        yield
    finally:
        for sg, h in old.items():
            signal.signal(sg, h)


def die_with_process(pid: int, period_s: float = 0.5) -> None:
    """End this (worker) process when process ``pid`` ends: for a worker whose parent is not the
    command (a multiprocessing forkserver's child), a daemon thread polls the command's pid."""
    pid = int(pid)

    def _gone() -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:
            return False
        try:  # killed but not yet reaped by its parent (a zombie) is gone too
            with open(f"/proc/{pid}/stat", "rb") as f:
                return f.read().rsplit(b")", 1)[1].split()[0] == b"Z"
        except (OSError, IndexError):
            return False

    def _watch():
        import time
        while True:
            if _gone():
                os._exit(1)
            time.sleep(period_s)
    threading.Thread(target=_watch, name="hybridhdr-command-watch", daemon=True).start()


def die_with_parent(parent_pid: int | None = None) -> None:
    """Make this (worker) process end when its parent ends; never raises."""
    expected = os.getppid() if parent_pid is None else int(parent_pid)
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            PR_SET_PDEATHSIG = 1
            if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0:
                if os.getppid() != expected:  # the parent died before prctl took effect
                    os._exit(1)
                return
        except (OSError, AttributeError):
            pass

    def _watch():  # pragma: no cover - non-Linux fallback
        import time
        while True:
            if os.getppid() != expected:
                os._exit(1)
            time.sleep(1.0)
    threading.Thread(target=_watch, name="hybridhdr-parent-watch", daemon=True).start()
