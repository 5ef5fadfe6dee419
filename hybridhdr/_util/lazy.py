"""Lazy package exports (PEP 562): a part's top-level names that load their module on first use,
so that building the command line's parser (``hybridhdr --help``) imports no numba, kernels, cv2,
h5py or matplotlib, which would slow every command's start (``benchmarks/cli_start.py``)."""

from __future__ import annotations

import importlib
import sys

__all__ = ["lazy_exports"]


def lazy_exports(package: str, table: dict):
    """``(__getattr__, __dir__)`` for ``package`` (its ``__name__``): each name of ``table``
    (``{name: ".module"}``, relative to the package) is imported from its module on first access
    and then kept in the package's namespace; any other name is an AttributeError."""

    def __getattr__(name):
        mod = table.get(name)
        if mod is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(mod, package), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__():
        return sorted(set(vars(sys.modules[package])) | set(table))

    return __getattr__, __dir__
