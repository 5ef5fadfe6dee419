"""The ``hybridhdr`` command line: one entry point, the five parts as subcommands.

Each part may provide ``hybridhdr/<part>/cli.py`` with ``add_parser(subparsers)``; the command
functions import their heavy dependencies only when they run.
"""

from __future__ import annotations

import argparse
import importlib
import sys

PARTS = {
    "capture": "record and read hybrid data (devices, brackets, sync, recorder)",
    "calibrate": "stereo rig, camera response and noise profile, HDR references",
    "simulate": "render scenes to events, LDR frames and HDR ground truth",
    "reconstruct": "HDR video from events and frames (AKF and baselines)",
    "evaluate": "metrics and benchmarks",
}

_PLANNED = {"capture": 8, "calibrate": 6, "simulate": 5, "reconstruct": 3, "evaluate": 7}


def _fmt():
    from ._cliargs import HelpFormatter
    return HelpFormatter


def _unavailable(part):
    def run(args) -> int:
        print(f"hybridhdr {part}: not available in this version yet (planned in issue #{_PLANNED[part]}); "
              f"'hybridhdr info', 'convert' and 'demo' work now", file=sys.stderr)
        return 2
    return run


def build_parser() -> argparse.ArgumentParser:
    from . import __version__
    p = argparse.ArgumentParser(prog="hybridhdr", formatter_class=_fmt(), allow_abbrev=False,
                                description="HDR video from hybrid event/frame cameras "
                                            "(Wang et al., ICCV 2021, Asynchronous Kalman Filter).")
    p.add_argument("--version", action="version", version=f"hybridhdr {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for part, helptext in PARTS.items():
        try:
            mod = importlib.import_module(f"hybridhdr.{part}.cli")
        except ModuleNotFoundError as e:
            if e.name != f"hybridhdr.{part}.cli":
                raise
            sp = sub.add_parser(part, help=helptext, formatter_class=_fmt(), description=helptext)
            sp.set_defaults(func=_unavailable(part))
            continue
        mod.add_parser(sub)
    from . import _cli_tools
    _cli_tools.add_parsers(sub)
    from . import view
    view.add_parser(sub)
    from ._cliargs import finalise
    return finalise(p)


class _NullWriter:
    """stderr under --quiet: everything but main's own error line is dropped."""

    def write(self, s):
        return len(s)

    def flush(self):
        pass

    def isatty(self):
        return False


def main(argv=None) -> int:
    import contextlib
    import logging

    from ._cliargs import UsageError, cli_wording
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
    logging.basicConfig(level=logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)],
                        format="%(name)s: %(message)s")
    try:
        with contextlib.redirect_stderr(_NullWriter()) if quiet else contextlib.nullcontext():
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (ValueError, TypeError, FileNotFoundError, OSError, ImportError) as e:
        if getattr(args, "debug", False):
            raise
        print(f"{prog}: error: {cli_wording(str(e))}", file=sys.stderr)
        return 2 if isinstance(e, UsageError) else 1


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
