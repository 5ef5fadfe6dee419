"""Shared pieces of the ``hybridhdr`` command line: one help style, one set of common options,
argument types that validate numbers before any work starts, and CLI wording of errors.

Conventions (docs in README.md, "Command-line conventions"):

* every command (leaf of the command tree) takes the common options of :data:`COMMON`:
  ``--debug``, ``--no-progress``, ``-q/--quiet``, ``-v/--verbose``, and ``--json`` where the
  command has a machine-readable result (its function is marked with :func:`json_output`);
* option names are never abbreviated (``allow_abbrev=False``: ``--fp 300`` is an error, not ``--fps``);
* help prints a default once, and never for required options, flags or ``None`` defaults;
* errors start with the full command (``hybridhdr calibrate crf: error: ...``);
* rates of image streams are ``--fps`` (outputs, frames, previews); physical and sampling rates
  end in ``-hz`` (``--cutoff-hz``, ``--leak-rate-hz``); times are ``--start``/``--end`` with a
  unit (:mod:`hybridhdr._util.timearg`); durations and periods carry their unit in the name
  (``--duration-s``, ``--exposure-us``).
"""

from __future__ import annotations

import argparse
import math
import re


class UsageError(ValueError):
    """Bad arguments found after parsing (e.g. --end before --start): exit status 2, like argparse's."""


class HelpFormatter(argparse.HelpFormatter):
    """Shows ``(default: X)`` once: not when the help already states a default, not for required
    options, positionals, flags, ``None`` or empty defaults."""

    def _get_help_string(self, action):
        h = action.help or ""
        if h is argparse.SUPPRESS or "%(default)" in h or "default" in h.lower():
            return h
        if action.required or not action.option_strings or action.nargs == 0:
            return h
        d = action.default
        if d is None or d is argparse.SUPPRESS or d is False or (isinstance(d, (list, tuple)) and not d):
            return h
        return h + " (default: %(default)s)"


def json_output(func):
    """Mark a command function as printing a JSON result when ``args.json`` is set."""
    func.json_output = True
    return func


def _common_parent(with_json: bool) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    g = p.add_argument_group("common options")
    if with_json:
        g.add_argument("--json", action="store_true", help="print the result as one JSON object on stdout")
    g.add_argument("--no-progress", action="store_true", help="hide progress bars")
    g.add_argument("-q", "--quiet", action="store_true",
                   help="nothing on stderr but the error, if any (implies --no-progress)")
    g.add_argument("-v", "--verbose", action="count", default=0, help="log more (-v: info, -vv: debug)")
    g.add_argument("--debug", action="store_true", help="show tracebacks instead of one-line errors")
    return p


COMMON = _common_parent(with_json=True)
COMMON_NO_JSON = _common_parent(with_json=False)


def finalise(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Apply the conventions to a whole parser tree: one formatter, no abbreviations, the common
    options on every command (leaf), and each command's full name for error messages."""
    def walk(p):
        p.formatter_class = HelpFormatter
        p.allow_abbrev = False
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        for a in subs:
            for child in dict.fromkeys(a.choices.values()):
                walk(child)
        if subs:
            return
        func = p.get_default("func")
        parent = COMMON if getattr(func, "json_output", False) else COMMON_NO_JSON
        have = set(p._option_string_actions)
        for act in parent._actions:
            if any(s in have for s in act.option_strings):
                continue
            grp = next(g for g in parent._action_groups if act in g._group_actions)
            mine = next((g for g in p._action_groups if g.title == grp.title), None)
            if mine is None:
                mine = p.add_argument_group(grp.title)
            mine._add_action(act)
        p.set_defaults(_prog=p.prog, _parser=p)
    walk(parser)
    return parser


# -- argument types: validated by argparse, before any work --------------------------------------

def _number(kind, text, cond, what):
    try:
        v = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if isinstance(v, float) and not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    if not cond(v):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text}")
    return v


def positive_float(text):
    return _number(float, text, lambda v: v > 0, "a number > 0")


def nonneg_float(text):
    return _number(float, text, lambda v: v >= 0, "a number >= 0")


def positive_int(text):
    return _number(int, text, lambda v: v >= 1, "an integer >= 1")


def nonneg_int(text):
    return _number(int, text, lambda v: v >= 0, "an integer >= 0")


def max_workers() -> int:
    """The most worker processes a command may start: 4 per CPU (at least 16); more only thrashes."""
    import os
    return max(16, 4 * (os.cpu_count() or 1))


def worker_count(text):
    """``--workers``/``--writers``: an integer from 0 to :func:`max_workers` (``docs/security.md``)."""
    return _number(int, text, lambda v: 0 <= v <= max_workers(), f"an integer from 0 to {max_workers()} "
                                                                   f"(4 per CPU)")


def positive_worker_count(text):
    return _number(int, text, lambda v: 1 <= v <= max_workers(), f"an integer from 1 to {max_workers()} "
                                                                   f"(4 per CPU)")


#: ``--chunk-events`` at least this: tiny chunks cost a fixed overhead each and keep buffers alive
MIN_CHUNK_EVENTS = 1024


def chunk_events_count(text):
    return _number(int, text, lambda v: MIN_CHUNK_EVENTS <= v <= 1 << 30,
                   f"an integer from {MIN_CHUNK_EVENTS} to {1 << 30} (events per chunk)")


def image_side(text):
    """An image width or height in pixels: 1 to the side limit (8192; ``--allow-huge`` is not read
    here, so larger sizes need the Python API with ``allow_huge``)."""
    from .limits import LIMITS, huge_allowed
    lim = LIMITS["max_side"]
    return _number(int, text, lambda v: v >= 1 and (v <= lim or huge_allowed()),
                   f"an integer from 1 to {lim} pixels (set HYBRIDHDR_ALLOW_HUGE=1 for more)")


def fraction(text):
    return _number(float, text, lambda v: 0 < v < 1, "a number between 0 and 1 (exclusive)")


# -- flags shared by several verbs (one vocabulary: tests/test_cli_flags.py) ----------------------

class _DeprecatedAlias(argparse.Action):
    """Stores like ``store``; when given under a deprecated spelling, says which to use instead."""

    def __init__(self, option_strings, dest, *, deprecated=(), **kw):
        self.deprecated = tuple(deprecated)
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        if option_string in self.deprecated:
            import sys
            print(f"note: {option_string} is deprecated; use {self.option_strings[0]}", file=sys.stderr)
        setattr(namespace, self.dest, values)


def add_format_arg(parser, *, dest: str = "format", what: str = "input format") -> None:
    """``--format NAME`` (the input file's format; default: detected from its header, as the
    Python API's ``format=``), with ``--from`` kept as a deprecated alias."""
    parser.add_argument("--format", "--from", dest=dest, default=None, metavar="NAME", action=_DeprecatedAlias,
                        deprecated=("--from",),
                        help=f"{what} (default: detected from the file; --from is a deprecated alias)")


# -- CLI wording of library messages -------------------------------------------------------------

_PY_TO_CLI = {"method": "--method", "mode": "--mode", "fps": "--fps", "times_us": "--times-us",
              "t_start_us": "--start", "t_end_us": "--end", "thresholds": "--thresholds", "cfa": "--cfa",
              "weights": "--weights", "profile": "--profile", "n_workers": "--workers",
              "chunk_events": "--chunk-events", "augment": "--augmentation", "demosaic": "--demosaic",
              "format": "--from", "frame_encoding": "--frame-encoding"}
_KW = re.compile(r"\b(" + "|".join(_PY_TO_CLI) + r")=(?:'([^']*)'|\"([^\"]*)\"|([\w.+-]+))")


def cli_wording(msg: str) -> str:
    """``method='highpass'`` -> ``--method highpass`` (and the other keyword arguments the CLI names)."""
    def rep(m):
        val = next(g for g in m.groups()[1:] if g is not None)
        return f"{_PY_TO_CLI[m.group(1)]} {val}"
    return _KW.sub(rep, msg)


# -- one JSON object on stdout -------------------------------------------------------------------

def to_json(obj) -> str:
    """``obj`` as strict JSON: NaN/±inf become null; numpy scalars/arrays, paths and tuples are
    converted (``json.dumps(..., allow_nan=False)`` would fail on them otherwise)."""
    import json
    import math
    from pathlib import PurePath

    def conv(v):
        if isinstance(v, bool) or v is None or isinstance(v, str):
            return v
        if isinstance(v, int):
            return v
        if isinstance(v, float):
            return v if math.isfinite(v) else None
        if isinstance(v, PurePath):
            return str(v)
        if isinstance(v, dict):
            return {str(k): conv(x) for k, x in v.items()}
        if isinstance(v, (list, tuple, set, frozenset)):
            return [conv(x) for x in v]
        tolist = getattr(v, "tolist", None)  # numpy scalars and arrays
        if callable(tolist):
            return conv(tolist())
        if hasattr(v, "to_dict"):
            return conv(v.to_dict())
        return str(v)
    return json.dumps(conv(obj), allow_nan=False)


class json_stdout:
    """``with json_stdout(args.json) as emit: ...; emit(result)``.

    With ``enabled`` everything printed inside the block goes to stderr (progress notes, library
    messages), and ``emit(obj)`` writes the one JSON object (:func:`to_json`) to the real stdout;
    without it the block runs unchanged and ``emit`` does nothing."""

    def __init__(self, enabled: bool):
        self.enabled = bool(enabled)
        self._redirect = None

    def __enter__(self):
        import contextlib
        import sys
        self._stdout = sys.stdout
        if self.enabled:
            self._redirect = contextlib.redirect_stdout(sys.stderr)
            self._redirect.__enter__()
        return self.emit

    def emit(self, obj) -> None:
        if self.enabled:
            self._stdout.write(to_json(obj) + "\n")
            self._stdout.flush()

    def __exit__(self, *exc):
        if self._redirect is not None:
            return self._redirect.__exit__(*exc)
        return False


def json_command(func):
    """A command with a JSON result (:func:`json_output`) that reports it with ``args.emit_json(obj)``.

    While it runs with ``--json``, whatever it (or the library) prints goes to stderr, so stdout
    holds exactly the one JSON object; without ``--json`` it prints as usual and ``emit_json`` does
    nothing."""
    import functools

    @functools.wraps(func)
    def run(args):
        with json_stdout(getattr(args, "json", False)) as emit:
            args.emit_json = emit
            return func(args)
    return json_output(run)
