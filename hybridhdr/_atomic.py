"""Atomic file output shared by the parts: write to a temporary name, rename when complete.

A crash or an exception leaves the previous file (or nothing) in place, never a half-written one.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path, suffix: str = ""):
    """Yield a temporary path beside ``path``; rename it to ``path`` if the block succeeds.

    ``suffix`` is appended to the temporary name (e.g. ``".png"`` for writers that pick the
    format from the extension). The parent folder is created. The file gets the mode a plain
    ``open()`` would give it (``0o666 & ~umask``). On error the temporary file is
    removed and the exception propagates.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=".partial" + suffix, dir=path.parent)
    try:
        os.fchmod(fd, umask_file_mode())  # as open() would create it: mkstemp's 0600 ignores the umask
    finally:
        os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_json_atomic(path, obj, *, default=None, indent: int = 1) -> Path:
    """Write ``obj`` as UTF-8 JSON (newline-terminated) to ``path`` atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=indent, default=default)
        f.write("\n")
    return path


def current_umask() -> int:
    """The process umask, read without changing it (``/proc/self/status``; else a brief
    ``os.umask`` round trip, which another thread creating a file at that instant could see)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def umask_file_mode() -> int:
    """The mode ``open()`` gives a new file: ``0o666 & ~umask`` (``mkstemp`` gives 0o600)."""
    return 0o666 & ~current_umask()
