"""Time windows on the command line: ``--start``/``--end`` with a unit, relative to the recording.

``--start 2.5s``, ``--end 1500ms``, ``--start 913716224us`` (also ``µs``, ``min``); a bare
number is seconds. Times count from the recording's first timestamp (the earliest event or
frame exposure start, as ``hybridhdr info`` prints it) unless ``--absolute`` is given, in which
case they are sensor time. ``--start-us``/``--end-us`` are kept as deprecated aliases meaning
absolute microseconds. The window is half-open, ``[start, end)``.
"""

from __future__ import annotations

import argparse
import math
import re
import sys

from .cliargs import UsageError

_UNITS = {"s": 1_000_000, "ms": 1_000, "us": 1, "µs": 1, "μs": 1, "min": 60_000_000}
_TIME = re.compile(r"^\s*([+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?)\s*([a-zµμ]*)\s*$")


def parse_time_us(text: str) -> int:
    """``'2.5s'`` -> 2_500_000; ``'1500ms'``, ``'913716224us'``, ``'0'`` (seconds); rounds to µs."""
    m = _TIME.match(str(text))
    if not m or m.group(2) not in ("",) + tuple(_UNITS):
        raise ValueError(f"expected a time such as 2.5s, 1500ms or 913716224us, got {text!r}")
    v = float(m.group(1)) * _UNITS[m.group(2) or "s"]
    if not math.isfinite(v):
        raise ValueError(f"expected a finite time, got {text!r}")
    return int(round(v))


def time_arg(text: str) -> int:
    """argparse type of ``--start``/``--end`` (µs)."""
    try:
        return parse_time_us(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_time_window(parser, what: str = "events") -> None:
    """``--start``, ``--end``, ``--absolute`` and the deprecated ``--start-us``/``--end-us``."""
    g = parser.add_argument_group("time window ([start, end); a bare number is seconds)")
    g.add_argument("--start", type=time_arg, default=None, metavar="TIME",
                   help=f"keep {what} from this time on: 2.5s, 1500ms, 913716224us; counted from the recording's "
                        f"first timestamp unless --absolute")
    g.add_argument("--end", type=time_arg, default=None, metavar="TIME", help=f"keep {what} before this time")
    g.add_argument("--absolute", action="store_true",
                   help="--start/--end are sensor time (the timestamps in the file), not relative to its start")
    g.add_argument("--start-us", type=int, default=None, help="deprecated: --start TIMEus --absolute")
    g.add_argument("--end-us", type=int, default=None, help="deprecated: --end TIMEus --absolute")


def window_given(args) -> bool:
    return any(getattr(args, k, None) is not None for k in ("start", "end", "start_us", "end_us"))


def check_window(args) -> None:
    """Errors that need no data: mixed spellings, negative relative times, end <= start."""
    if (args.start is not None or args.end is not None) and (args.start_us is not None or args.end_us is not None):
        raise UsageError("give --start/--end or the deprecated --start-us/--end-us, not both")
    if args.start_us is not None or args.end_us is not None:
        print("note: --start-us/--end-us are deprecated; use --start/--end with a unit (relative to the recording's "
              "first timestamp, or sensor time with --absolute)", file=sys.stderr)
        lo, hi, rel = args.start_us, args.end_us, False
    else:
        lo, hi, rel = args.start, args.end, not args.absolute
    if rel:
        for name, v in (("--start", lo), ("--end", hi)):
            if v is not None and v < 0:
                raise UsageError(f"{name} {fmt_us(v)} is before the recording's first timestamp (times are relative "
                                 f"to it; --absolute for sensor time)")
    if lo is not None and hi is not None and hi <= lo:
        names = ("--start-us", "--end-us") if args.start_us is not None or args.end_us is not None else ("--start",
                                                                                                         "--end")
        raise UsageError(f"{names[1]} ({fmt_us(hi)}) must be after {names[0]} ({fmt_us(lo)})")


def resolve_window(args, origin_us: int | None) -> tuple[int | None, int | None]:
    """The absolute [start, end) in µs (None: open); relative times are added to ``origin_us``
    (call :func:`check_window` first)."""
    if args.start_us is not None or args.end_us is not None:
        return args.start_us, args.end_us
    if args.absolute or origin_us is None:
        return args.start, args.end
    return (None if args.start is None else origin_us + args.start,
            None if args.end is None else origin_us + args.end)


def fmt_us(v: int) -> str:
    return f"{v / 1e6:.6g} s" if abs(v) >= 1000 else f"{v} µs"


class EmptyWindowError(ValueError):
    """The time window holds no data (exit status 1: the arguments were well formed)."""


def empty_window_error(args, t0, t1, span) -> ValueError:
    """``span``: the recording's :class:`hybridhdr.formats.span.Span`."""
    rel = "" if t0 is None and t1 is None else f" [{'-' if t0 is None else f'{t0:,}'}, " \
                                               f"{'-' if t1 is None else f'{t1:,}'}) µs sensor time"
    hint = "" if args.absolute or args.start_us is not None or args.end_us is not None else \
        " (--start/--end count from the recording's first timestamp)"
    return EmptyWindowError(f"nothing in the time window{rel}{hint}; the recording has {span.describe()}")
