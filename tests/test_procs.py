"""``hybridhdr._util.procs.signals_exit``: a termination signal ends the block with 128 + signal,
even when Python drops the exception the handler raised (a handler that runs while a ``__del__``
or a weakref callback runs has its exception printed and ignored: CI saw a SIGTERM'd simulation
finish and exit 0 that way)."""

import os
import signal
import subprocess
import sys
import textwrap

import pytest

from hybridhdr._util import procs

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGTERM") or os.name != "posix", reason="POSIX signals")

_CHILD = textwrap.dedent("""
    import os, signal, sys, time
    from hybridhdr._util.procs import signals_exit, raise_if_signalled

    class Dropper:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)
            t = time.time()
            while time.time() - t < 2:   # the handler runs here, inside __del__: its SystemExit is dropped
                pass

    steps = 0
    with signals_exit():
        d = Dropper()
        del d
        print("survived the dropped exception", flush=True)
        for steps in range(1000):
            raise_if_signalled()        # a loop's per-step check ends it here
        print("loop finished", flush=True)
""")


def test_dropped_handler_exception_still_ends_the_block_with_the_signal():
    p = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "PYTHONPATH": os.getcwd()})
    assert "Exception ignored" in p.stderr, p.stderr  # the situation under test really happened
    assert "survived the dropped exception" in p.stdout
    assert "loop finished" not in p.stdout
    assert p.returncode == 128 + signal.SIGTERM, (p.returncode, p.stderr)


def test_signal_leaves_the_block_as_its_own_exception_and_state_is_cleared():
    # an error that wraps the handler's exception (Mitsuba's) still leaves as SystemExit(143)
    with pytest.raises(SystemExit) as e:
        with procs.signals_exit():
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                for _ in range(10**7):  # the handler runs between bytecodes
                    pass
            except SystemExit:
                raise RuntimeError("a renderer's own error") from None
    assert e.value.code == 128 + signal.SIGTERM
    procs.raise_if_signalled()  # nothing pending once the block has ended
    assert signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None)


def test_sigint_is_a_keyboard_interrupt_only_when_asked():
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("SIGINT is not Python's default handler in this process")
    with pytest.raises(KeyboardInterrupt):
        with procs.signals_exit(sigint=True):
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(10**7):
                pass
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
