"""The one atomic writer: files and folders go to a temporary name beside the target and are
renamed into place when complete.

A crash or an exception leaves the previous file (or nothing) in place, never a half-written one.
New files get the mode ``open()`` would give them (``0o666 & ~umask``) and new folders the mode
``mkdir`` gives (``0o777 & ~umask``).

* :func:`atomic_path`: a file (any writer that takes a path: NumPy, OpenEXR, Matplotlib, ffmpeg);
  :func:`write_text_atomic` and :func:`write_json_atomic` for text and JSON.
* :func:`atomic_folder`: a folder written whole, as ``NAME.partial/`` renamed to ``NAME``.
* :class:`AtomicFolder`: a command's output folder, ``OUT.partial/`` moved into ``OUT`` on
  :meth:`~AtomicFolder.commit`, with the rules for an existing ``OUT`` spelled out in the class.
"""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import json
import os
import shutil
import socket
import tempfile
import time
from pathlib import Path

__all__ = ["atomic_path", "write_text_atomic", "write_json_atomic", "atomic_folder", "AtomicFolder",
           "current_umask", "umask_file_mode"]


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


def write_text_atomic(path, text: str, *, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding=encoding)
    return path


def write_json_atomic(path, obj, *, default=None, indent: int = 1) -> Path:
    """Write ``obj`` as UTF-8 JSON (newline-terminated) to ``path`` atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=indent, default=default)
        f.write("\n")
    return path


@contextlib.contextmanager
def atomic_folder(folder):
    """Yield ``FOLDER.partial/`` (created; a stale one from an interrupted run is removed first);
    rename it to ``folder`` if the block succeeds, remove it if the block fails.

    An existing empty ``folder`` is replaced; a non-empty one makes the rename fail (OSError).
    """
    folder = Path(folder)
    tmp = folder.with_name(folder.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        yield tmp
        os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


_MARKER = ".hybridhdr-partial"


class AtomicFolder:
    """``OUT.partial/`` while running, ``OUT`` when complete.

    * OUT absent: ``OUT.partial`` (beside OUT, created here, mode from the umask) is renamed to
      OUT by :meth:`commit`.
    * OUT an empty folder: its entries are moved in (``run.json`` last); the folder itself (its
      owner and mode) is kept.
    * OUT non-empty: refused (ValueError) unless ``overwrite``; then on commit, ``run.json`` is
      removed first, then the files the command writes (``outputs``: glob patterns relative to
      OUT, such as ``"frame_*.exr"`` or ``"previews/preview_*.png"``), then the new files are
      moved in, ``run.json`` last. Other files and every folder are left alone.
    * ``OUT.partial`` already there (an interrupted run, or not ours): refused; nothing is deleted.
    * :meth:`abort` removes ``OUT.partial``, which this object created; never anything else.
    """

    def __init__(self, out, *, outputs: tuple[str, ...], command: str, overwrite: bool = False):
        out = Path(out)
        self.requested = out
        self.target = Path(os.path.realpath(out)) if out.exists() else Path(os.path.abspath(out))
        self.overwrite = bool(overwrite)
        self.outputs = tuple(outputs)
        self.command = command
        if self.target.exists():
            if not self.target.is_dir():
                raise ValueError(f"--out {out} exists and is not a folder")
            if any(self.target.iterdir()) and not self.overwrite:
                raise ValueError(f"--out {out} exists and is not empty; choose another folder or pass --overwrite "
                                 f"(replaces the files a {command} run writes, keeps everything else)")
        self.path = self.target.with_name(self.target.name + ".partial")
        if self.path.exists() or self.path.is_symlink():
            raise ValueError(f"{self.path} exists (left by an interrupted run?); remove it first")
        self.target.parent.mkdir(parents=True, exist_ok=True)
        os.mkdir(self.path)  # exclusive: fails if another run took the name meanwhile
        self._created = True
        try:
            (self.path / _MARKER).write_text(f"pid {os.getpid()} host {socket.gethostname()} "
                                              f"started {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")
        except BaseException:
            self.abort()
            raise

    def _ours(self, rel: str) -> bool:
        """Names the command writes (the only files ``overwrite`` replaces or removes)."""
        return any(fnmatch.fnmatchcase(rel, p) for p in self.outputs)

    def commit(self) -> Path:
        """Move the finished output to OUT (see the class docstring); returns OUT."""
        os.unlink(self.path / _MARKER)
        if not self.target.exists():
            try:
                os.rename(self.path, self.target)
                self._created = False
                return self.target
            except OSError:
                if not self.target.exists():
                    raise
        if not self.target.is_dir() or (any(self.target.iterdir()) and not self.overwrite):
            raise OSError(errno.EEXIST, f"{self.target} appeared during the {self.command} run; the complete "
                                        f"output is left in {self.path}")
        if self.overwrite:
            old_run = self.target / "run.json"
            if old_run.is_file() or old_run.is_symlink():
                os.unlink(old_run)
            for p in list(self.target.iterdir()) + (list((self.target / "previews").iterdir())
                                                    if (self.target / "previews").is_dir() else []):
                rel = p.relative_to(self.target).as_posix()
                if self._ours(rel) and (p.is_file() or p.is_symlink()) and not p.is_dir():
                    os.unlink(p)
        entries = sorted(self.path.iterdir(), key=lambda p: p.name == "run.json")  # run.json last
        for p in entries:
            dst = self.target / p.name
            if p.is_dir() and dst.is_dir():
                for q in sorted(p.iterdir()):
                    os.replace(q, dst / q.name)
                os.rmdir(p)
            else:
                os.replace(p, dst)
        os.rmdir(self.path)
        self._created = False
        return self.target

    def abort(self) -> None:
        """Remove ``OUT.partial`` (created by this object) and its contents."""
        if self._created and self.path.is_dir() and not self.path.is_symlink():
            shutil.rmtree(self.path, ignore_errors=True)
        self._created = False


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
