"""The one TOML reader: ``tomllib`` (Python >= 3.11) or its backport ``tomli``."""

from __future__ import annotations

from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

__all__ = ["load_toml", "loads_toml", "TOMLDecodeError"]

TOMLDecodeError = tomllib.TOMLDecodeError


def load_toml(path) -> dict:
    """The TOML file at ``path`` as a dict (raises :class:`TOMLDecodeError` if it is not TOML)."""
    with open(Path(path), "rb") as f:
        return tomllib.load(f)


def loads_toml(text: str) -> dict:
    """A TOML document given as text, as a dict."""
    return tomllib.loads(text)
