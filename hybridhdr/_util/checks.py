"""Input checks with one wording for every part: shapes, dtypes and ranges (after kornia's
``KORNIA_CHECK_SHAPE``).

A shape spec names each dimension: a number is a fixed size, a name (``H``, ``W``, ``K``, ``N``
...) any size, bound to the same value wherever it appears in one alternative and to ``sizes``
when given there; ``|`` separates alternatives.

>>> import numpy as np
>>> check_shape(np.zeros((4, 5, 3)), "H W | H W 3", "image")
{'H': 4, 'W': 5}
>>> check_shape(np.zeros(3), "K", "t_us", sizes={"K": 2})
Traceback (most recent call last):
...
ValueError: t_us must have shape (2,), got (3,)
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

__all__ = ["check_shape", "describe_shape", "check_dtype", "check_range"]


def _alternatives(spec: str) -> list[list[str]]:
    return [alt.split() for alt in spec.split("|")]


def describe_shape(spec: str, sizes: dict | None = None) -> str:
    """``"K H W | K H W 3"`` -> ``"(K, H, W) or (K, H, W, 3)"``, known sizes filled in."""
    sizes = sizes or {}
    out = []
    for dims in _alternatives(spec):
        names = [str(sizes.get(d, d)) for d in dims]
        out.append(f"({names[0]},)" if len(names) == 1 else f"({', '.join(names)})")
    return " or ".join(out)


def check_shape(a, spec: str, name: str, *, sizes: dict | None = None,
                error: Callable[[str], Exception] = ValueError) -> dict[str, int]:
    """Check that ``a`` (an array or a shape tuple) matches ``spec``; returns the named sizes.

    Raises ``error(message)`` (ValueError by default; pass e.g. ``lambda m: FormatError(path, m)``)
    with the message "``name`` must have shape (H, W) or (H, W, 3), got (…)".
    """
    shape = tuple(int(n) for n in (a if isinstance(a, tuple) else np.shape(a)))
    for dims in _alternatives(spec):
        if len(dims) != len(shape):
            continue
        bound = dict(sizes or {})
        for d, n in zip(dims, shape):
            if d.isdigit():
                if int(d) != n:
                    break
            elif bound.setdefault(d, n) != n:
                break
        else:
            return {d: bound[d] for d in dims if not d.isdigit()}
    raise error(f"{name} must have shape {describe_shape(spec, sizes)}, got {shape}")


_KIND_WORDS = {"u": "unsigned integer", "i": "signed integer", "f": "floating-point", "b": "boolean",
               "c": "complex"}


def check_dtype(a, kinds: str, name: str, *, error: Callable[[str], Exception] = TypeError) -> np.dtype:
    """Check that the dtype kind of ``a`` is one of ``kinds`` (NumPy kind letters, e.g. ``"ui"``)."""
    dt = np.asarray(a).dtype if not isinstance(a, np.dtype) else a
    if dt.kind not in kinds:
        want = " or ".join(_KIND_WORDS.get(k, k) for k in kinds)
        raise error(f"{name} must have a {want} dtype, got {dt}")
    return dt


def check_range(value, name: str, *, lo=None, hi=None, lo_open: bool = False, hi_open: bool = False,
                error: Callable[[str], Exception] = ValueError, unit: str = "") -> float:
    """Check that the number ``value`` is finite and inside the given bounds; returns it as float.

    Anything but a real number (a bool, a string, None) raises TypeError; a number out of range,
    NaN or infinite raises ``error`` (ValueError). ``unit`` is named in the message.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number, got {type(value).__name__} {value!r}")
    v = float(value)
    ok = math.isfinite(v)
    if ok and lo is not None:
        ok = v > lo if lo_open else v >= lo
    if ok and hi is not None:
        ok = v < hi if hi_open else v <= hi
    if not ok:
        bounds = []
        if lo is not None:
            bounds.append(f"{'>' if lo_open else '>='} {lo:g}")
        if hi is not None:
            bounds.append(f"{'<' if hi_open else '<='} {hi:g}")
        want = "finite" + "".join(f" and {b}" for b in bounds) + (f" ({unit})" if unit else "")
        raise error(f"{name} must be {want}, got {value}")
    return v
