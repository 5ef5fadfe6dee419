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

__all__ = ["signals_exit", "raise_if_signalled", "die_with_parent", "die_with_process"]


# signals received inside an active :func:`signals_exit` block, in order; emptied when the outermost
# block ends. Python prints and drops an exception raised by a signal handler while a weakref
# callback or a ``__del__`` runs, so a received signal is also kept here and acted on again at the
# next :func:`raise_if_signalled` check (a render loop's) or at the end of the block.
_received: list[int] = []
_depth = 0


def _exception_for(signum: int) -> BaseException:
    if signum == getattr(signal, "SIGINT", None):
        return KeyboardInterrupt()
    return SystemExit(128 + signum)


def raise_if_signalled() -> None:
    """Raise the exception of a signal received in the current :func:`signals_exit` block (a no-op
    when none was): long loops call it once per step, so a signal whose exception Python dropped
    still ends the command at the next step."""
    if _received:
        raise _exception_for(_received[0])


@contextlib.contextmanager
def signals_exit(*, sigint: bool = False):
    """SIGTERM/SIGHUP raise ``SystemExit(128 + signum)`` while the block runs (main thread only);
    with ``sigint``, SIGINT raises KeyboardInterrupt through the same path. A handler is installed
    only over the default one (a caller's own handler is left alone; an enclosing block's is
    kept). Whatever leaves the block after a signal was received, it leaves as that signal's
    exception (a renderer that wraps an exception raised inside it in its own error, or a dropped
    handler exception, still ends the command with 128 + signal)."""
    global _depth
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _exit(signum, frame):
        _received.append(signum)
        raise _exception_for(signum)

    names = ("SIGTERM", "SIGHUP") + (("SIGINT",) if sigint else ())
    old = {}
    for name in names:
        sg = getattr(signal, name, None)
        if sg is None:
            continue
        cur = signal.getsignal(sg)
        if cur in (signal.SIG_DFL, None, signal.default_int_handler) or getattr(cur, "_hybridhdr_signals_exit", False):
            old[sg] = signal.signal(sg, _exit)
    _exit._hybridhdr_signals_exit = True
    _depth += 1
    try:
        yield
        raise_if_signalled()
    except BaseException:
        if _received:
            raise _exception_for(_received[0]) from None
        raise
    finally:
        for sg, h in old.items():
            signal.signal(sg, h)
        _depth -= 1
        if _depth == 0:
            _received.clear()


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
