"""Progress bars on stderr that other lines never cut through.

:func:`progress_bars` yields a factory of tqdm bars on the real stderr. While it is open, what
the command writes to ``sys.stderr`` (``print(..., file=sys.stderr)``, warnings) and what logging
prints goes through ``tqdm.write``: the bars are cleared, the line printed, the bars drawn again
below it, instead of a line glued to a half-drawn bar. On exit every bar is closed (its last
state left on screen once) before the caller prints its final line, so nothing of a bar comes
after it.
"""

from __future__ import annotations

import contextlib
import sys

__all__ = ["progress_bars", "LinesAboveBars"]


class LinesAboveBars:
    """A text stream that prints each complete line with ``tqdm.write`` on ``stream``."""

    def __init__(self, stream):
        self.stream = stream
        self._buf = ""

    def write(self, s: str) -> int:
        from tqdm import tqdm
        self._buf += s
        while "\n" in self._buf:
            line, self._buf = self._buf.split("\n", 1)
            tqdm.write(line, file=self.stream)
        return len(s)

    def flush(self) -> None:
        if self._buf:
            from tqdm import tqdm
            line, self._buf = self._buf, ""
            tqdm.write(line, file=self.stream)
        self.stream.flush()

    def isatty(self) -> bool:
        return bool(getattr(self.stream, "isatty", lambda: False)())

    @property
    def encoding(self):
        return getattr(self.stream, "encoding", "utf-8")


@contextlib.contextmanager
def progress_bars(enabled: bool = True):
    """``with progress_bars(not args.no_progress) as bar: b = bar(total=N, unit="ev", desc=...)``.

    ``bar(...)`` takes tqdm's arguments and returns a bar on stderr (None when ``enabled`` is
    false: the caller checks). A total gives the bar its percentage and ETA. Lines written to
    stderr or logged inside the block are printed above the bars; the bars are closed on exit.
    """
    if not enabled:
        yield lambda **kw: None
        return
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm
    real = sys.stderr
    bars: list = []

    def bar(**kw):
        kw.setdefault("file", real)
        kw.setdefault("dynamic_ncols", True)
        b = tqdm(**kw)
        bars.append(b)
        return b

    try:
        with logging_redirect_tqdm(), contextlib.redirect_stderr(LinesAboveBars(real)):
            yield bar
    finally:
        for b in bars:
            b.close()
        real.flush()
