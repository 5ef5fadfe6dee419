"""The one TOML reader: ``tomllib`` (Python >= 3.11) or its backport ``tomli``.

Files are read with a size bound and only when they are regular files (a FIFO or ``/dev/zero``
given as a config is one error line); a document nested too deeply for the parser
(``RecursionError``) is a :class:`TOMLDecodeError` like any other malformed TOML.
"""

from __future__ import annotations

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

__all__ = ["load_toml", "loads_toml", "TOMLDecodeError"]

TOMLDecodeError = tomllib.TOMLDecodeError

#: nesting deeper than this ("[[[[...", "a = [[[[...", "{a={a=...") is refused before parsing
MAX_DEPTH = 64


def _check_depth(text: str) -> None:
    depth = deepest = 0
    in_str = None
    escaped = False
    for ch in text:  # a cheap over-estimate: brackets and braces outside quoted strings
        if in_str:
            if escaped:
                escaped = False
            elif ch == "\\" and in_str == '"':
                escaped = True
            elif ch == in_str:
                in_str = None
            continue
        if ch in "\"'":
            in_str = ch
        elif ch in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > MAX_DEPTH:
                    raise TOMLDecodeError(f"nested more than {MAX_DEPTH} levels deep (arrays or inline tables)")
        elif ch in "]}":
            depth = max(0, depth - 1)


def load_toml(path) -> dict:
    """The TOML file at ``path`` as a dict (raises :class:`TOMLDecodeError` if it is not TOML)."""
    from .limits import read_text_bounded
    return loads_toml(read_text_bounded(path, "TOML file"))


def loads_toml(text: str) -> dict:
    """A TOML document given as text, as a dict."""
    _check_depth(text)
    try:
        return tomllib.loads(text)
    except RecursionError:
        raise TOMLDecodeError(f"nested too deeply to parse (over {MAX_DEPTH} levels)") from None
