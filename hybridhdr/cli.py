"""The ``hybridhdr`` command line: one entry point, the five parts as subcommands.

Each part's ``hybridhdr/<part>/cli.py`` has ``add_parser(subparsers)``; the command functions
import their heavy dependencies only when they run.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys

from . import _cli_tools, view
from ._util.procs import signals_exit
from ._util.cliargs import HelpFormatter, UsageError, cli_wording, finalise
from ._version import __version__
from .calibrate import cli as calibrate_cli
from .capture import cli as capture_cli
from .evaluate import cli as evaluate_cli
from .reconstruct import cli as reconstruct_cli
from .simulate import cli as simulate_cli


#: The five parts' subcommands, in the order ``--help`` lists them.
PART_CLIS = (capture_cli, calibrate_cli, simulate_cli, reconstruct_cli, evaluate_cli)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hybridhdr", formatter_class=HelpFormatter, allow_abbrev=False,
                                description="HDR video from hybrid event/frame cameras "
                                            "(Wang et al., ICCV 2021, Asynchronous Kalman Filter).")
    p.add_argument("--version", action="version", version=f"hybridhdr {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for part_cli in PART_CLIS:
        part_cli.add_parser(sub)
    _cli_tools.add_parsers(sub)
    view.add_parser(sub)
    return finalise(p)


class _NullWriter:
    """stderr under --quiet: everything is dropped but error lines (``...: error: ...``, whoever
    prints them: main, or a command that reports a usage error itself and exits 2), which go to
    the real stderr: ``-q`` hides progress and notes, never why a command failed."""

    def __init__(self, real=None):
        self._real = real if real is not None else sys.stderr
        self._buf = ""

    def write(self, s):
        self._buf += s
        *lines, self._buf = self._buf.split("\n")
        for ln in lines:
            if "error:" in ln:
                self._real.write(ln + "\n")
        if len(self._buf) > 65536:  # a progress bar's carriage returns, never a line end
            self._buf = self._buf[-4096:]
        return len(s)

    def flush(self):
        if "error:" in self._buf:
            self._real.write(self._buf + "\n")
        self._buf = ""
        self._real.flush()

    def isatty(self):
        return False


def main(argv=None) -> int:
    parser = build_parser()
    try:  # usage errors return 2 (argparse prints them); --help and --version still exit 0
        args, extra = parser.parse_known_args(argv)
        if extra:
            getattr(args, "_parser", parser).error(f"unrecognized arguments: {' '.join(extra)}")
    except SystemExit as e:
        if e.code in (0, None):
            raise
        return int(e.code) if isinstance(e.code, int) else 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    prog = getattr(args, "_prog", f"hybridhdr {args.command}")
    quiet = getattr(args, "quiet", False)
    if quiet:
        args.no_progress = True
    verbose = getattr(args, "verbose", 0)
    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    try:
        # SIGTERM/SIGHUP end a command as Ctrl-C does: partial outputs and temp files are removed
        from ._util.limits import allow_huge
        with _command_logging(level), signals_exit(), allow_huge(bool(getattr(args, "allow_huge", False))), contextlib.redirect_stderr(_NullWriter(sys.stderr)) if quiet else contextlib.nullcontext():
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (ValueError, TypeError, FileNotFoundError, OSError, ImportError) as e:
        if getattr(args, "debug", False):
            raise
        print(f"{prog}: error: {cli_wording(str(e))}", file=sys.stderr)
        return 2 if isinstance(e, UsageError) else 1



class _CurrentStderr(logging.StreamHandler):
    """A handler on whatever ``sys.stderr`` is when a record is emitted (a redirected or captured
    stderr included), not the stream of the moment it was made."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):
        pass


@contextlib.contextmanager
def _command_logging(level: int):
    """The command's logging for the duration of one ``main`` call: a ``name: message`` handler on
    the root logger at ``level``, removed afterwards with the root's level restored, so a second
    ``main`` call in the same process (a test, a notebook) gets its own ``-q``/``-v`` and not the
    first call's. A program that configured logging itself (the root has handlers) is left alone."""
    root = logging.getLogger()
    if root.handlers:
        yield
        return
    h = _CurrentStderr()
    h.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    old = root.level
    root.addHandler(h)
    root.setLevel(level)
    try:
        yield
    finally:
        root.removeHandler(h)
        root.setLevel(old)

if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
