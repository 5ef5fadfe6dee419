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
import logging
import os
import shutil
import socket
import tempfile
import time
from pathlib import Path

from ..errors import UsageError

__all__ = ["atomic_path", "write_text_atomic", "write_json_atomic", "atomic_folder", "AtomicFolder",
           "current_umask", "umask_file_mode", "claim_partial", "release_partial", "PartialInUse",
           "atomic_outputs", "remap_paths", "refuse_overwriting_inputs", "refuse_existing_output",
           "unmark_partial", "signals_deferred", "check_outputs"]

_log = logging.getLogger(__name__)


class PartialInUse(FileExistsError):
    """``NAME.partial`` is held by another running writer, or is not ours (a symlink, a user's file)."""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def try_lock(fd: int) -> bool:
    """An exclusive lock on the open file (non-blocking): an open-file-description lock where Linux
    has one (independent of the ``flock`` HDF5 takes on the same file, and not dropped when another
    descriptor of the file is closed), else ``flock``."""
    import fcntl
    import struct
    try:
        if hasattr(fcntl, "F_OFD_SETLK"):
            fcntl.fcntl(fd, fcntl.F_OFD_SETLK, struct.pack("hhqqi4x", fcntl.F_WRLCK, 0, 0, 0, 0))
        else:  # pragma: no cover - not Linux
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except (BlockingIOError, PermissionError):
        return False
    except OSError as e:
        if e.errno in (errno.EAGAIN, errno.EACCES):
            return False
        return True  # no locking on this filesystem: the exclusive creation still holds


#: The file inside a partial output folder that says hybridhdr made it (and who holds it).
PARTIAL_MARK = ".hybridhdr-partial"
_MARK = PARTIAL_MARK
#: extended attribute that marks a partial *file* as ours (a folder holds the ``_MARK`` file instead):
#: a file named ``NAME.partial`` without it is a user's file, refused and never deleted
_XATTR = "user.hybridhdr.partial"


def _mark_file(fd: int) -> None:
    """Mark an open partial file as made by hybridhdr (where the filesystem keeps extended
    attributes; elsewhere a stale partial is refused instead of removed, never lost)."""
    with contextlib.suppress(OSError, AttributeError):
        os.setxattr(fd, _XATTR, _marker_text().encode())


def _file_is_ours(path) -> bool:
    try:
        os.getxattr(path, _XATTR, follow_symlinks=False)
        return True
    except (OSError, AttributeError):
        return False


def unmark_partial(path) -> None:
    """Drop the partial-file mark from a finished file (before or after its rename); never raises."""
    with contextlib.suppress(OSError, AttributeError):
        os.removexattr(path, _XATTR, follow_symlinks=False)


def _marker_text() -> str:
    return (f"pid {os.getpid()} host {socket.gethostname()} "
            f"started {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")


def _marker_owner_dead(marker: Path) -> bool:
    """True when the marker names a process of this host that no longer exists."""
    try:
        words = marker.read_text(encoding="utf-8", errors="replace").split()
        pid, host = int(words[1]), words[3]
    except (OSError, ValueError, IndexError):
        return False
    return host == socket.gethostname() and not _pid_alive(pid)


def _marker_in_use(marker: Path) -> bool:
    """True when a folder's marker is not written yet (a run creating it now) or names a live
    process of this host."""
    try:
        words = marker.read_text(encoding="utf-8", errors="replace").split()
        pid, host = int(words[1]), words[3]
    except (OSError, ValueError, IndexError):
        return True
    return host == socket.gethostname() and _pid_alive(pid) and pid != os.getpid()


def claim_partial(tmp, *, directory: bool = False) -> int:
    """Create ``tmp`` (a file, or a folder with a marker file) exclusively and lock it; returns the
    locked descriptor (keep it open while writing; :func:`release_partial` closes it).

    * Never through a symbolic link (``O_EXCL | O_NOFOLLOW``): a link at ``tmp`` is refused.
    * A ``tmp`` of the other kind (a user's folder where a file goes, or a file where a folder
      goes), or a folder without our marker, is refused and never deleted.
    * A ``tmp`` whose lock another live writer holds is refused (:class:`PartialInUse`): two runs
      writing the same output never share a partial file.
    * A file ``tmp`` carries a mark (an extended attribute) saying hybridhdr made it; a file
      without it is a user's file, refused and never deleted.
    * A ``tmp`` left by an interrupted run (ours, lock free) is removed with a warning, then claimed.
    """
    tmp = Path(tmp)
    mode = umask_file_mode()
    for attempt in (0, 1):
        try:
            if directory:
                os.mkdir(tmp)
                fd = os.open(tmp / PARTIAL_MARK, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
                os.write(fd, _marker_text().encode())
                try_lock(fd)
            else:
                # created and locked under a name of our own, then linked to ``tmp`` (atomic, and it
                # fails if ``tmp`` exists): no other run ever sees ``tmp`` unlocked while we live
                # (between a plain exclusive create and the lock, a concurrent run took the fresh
                # file for an interrupted run's, removed it and the first writer lost its output)
                own = tmp.with_name(f"{tmp.name}.{os.getpid()}.{os.urandom(4).hex()}")
                fd = os.open(own, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
                try:
                    try_lock(fd)
                    _mark_file(fd)
                    os.link(own, tmp, follow_symlinks=False)
                except FileExistsError:
                    os.close(fd)
                    raise
                except OSError as e:  # a filesystem without hard links: exclusive create, then lock
                    os.close(fd)
                    if e.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EXDEV):
                        raise
                    fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
                    try_lock(fd)
                    _mark_file(fd)
                except BaseException:
                    os.close(fd)
                    raise
                finally:
                    os.unlink(own)
            return fd
        except FileExistsError:
            if attempt:
                raise PartialInUse(errno.EEXIST, f"{tmp} was created by another run at the same moment; "
                                                 f"not writing the same output twice") from None
        if tmp.is_symlink():
            raise PartialInUse(errno.EEXIST, f"{tmp} exists and is a symbolic link; refusing to write through it "
                                             f"(remove it if it is yours)")
        if directory != tmp.is_dir() or (directory and not (tmp / PARTIAL_MARK).is_file()) \
                or (not directory and not _file_is_ours(tmp)):
            raise PartialInUse(errno.EEXIST, f"{tmp} exists and was not made by hybridhdr (a "
                                             f"{'folder' if tmp.is_dir() else 'file'}); it is never deleted: "
                                             f"move it away or choose another output name")
        lock_path = tmp / PARTIAL_MARK if directory else tmp
        try:
            fd = os.open(lock_path, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC)
        except OSError as e:
            raise PartialInUse(errno.EEXIST, f"{tmp} exists and cannot be checked ({e.strerror}); remove it "
                                             f"first") from None
        try:
            # a folder's marker is created, then locked: a marker not yet written, or naming a live
            # process, is a run starting now, never an interrupted one
            if not try_lock(fd) or (directory and _marker_in_use(lock_path)):
                raise PartialInUse(errno.EEXIST, f"{tmp} is being written by another running hybridhdr command; "
                                                 f"wait for it or choose another output name")
            if directory:
                shutil.rmtree(tmp)
            else:
                os.unlink(tmp)
        finally:
            os.close(fd)
        _log.warning("removed %s, left by an interrupted run", tmp)
    raise AssertionError("unreachable")


def release_partial(fd) -> None:
    """Close the descriptor :func:`claim_partial` returned (drops the lock); never raises."""
    if fd is not None:
        with contextlib.suppress(OSError):
            os.close(fd)


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
    tmp.parent.mkdir(parents=True, exist_ok=True)
    fd = claim_partial(tmp, directory=True)  # exclusive; a stale one of ours is removed, anything else refused
    try:
        yield tmp
        os.unlink(tmp / PARTIAL_MARK)
        os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        release_partial(fd)


_MARKER = PARTIAL_MARK  # the folder writer's name for it


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
                raise UsageError(f"--out {out} exists and is not a folder")
            refuse_existing_output(out, overwrite=self.overwrite, flag="--out", command=command)
        self.path = self.target.with_name(self.target.name + ".partial")
        self.target.parent.mkdir(parents=True, exist_ok=True)
        self._created = False
        self._lock = None
        if (self.path.exists() and not self.path.is_symlink() and self.path.is_dir()
                and (self.path / _MARKER).is_file() and _marker_owner_dead(self.path / _MARKER)):
            # left by a run that was killed (kill -9, power loss): its process is gone; clean and proceed
            shutil.rmtree(self.path, ignore_errors=True)
            _log.warning("removed %s, left by an interrupted %s run (its process is gone)", self.path, command)
        try:
            # exclusive and locked: a symlink, a user's folder or a live run's folder is refused, never deleted
            self._lock = claim_partial(self.path, directory=True)
        except PartialInUse as e:
            raise ValueError(f"{e.strerror if e.strerror else e}; remove it first if it is not in use") from None
        self._created = True

    def _ours(self, rel: str) -> bool:
        """Names the command writes (the only files ``overwrite`` replaces or removes)."""
        return any(fnmatch.fnmatchcase(rel, p) for p in self.outputs)

    def commit(self) -> Path:
        """Move the finished output to OUT (see the class docstring); returns OUT.

        All or nothing for SIGTERM, SIGINT and SIGHUP: they are held back while the entries move
        and act right after (the complete new output is then in OUT), so an interrupt never leaves
        an old output half replaced under its final name."""
        with signals_deferred():
            return self._commit()

    def _commit(self) -> Path:
        os.unlink(self.path / _MARKER)
        release_partial(self._lock)
        self._lock = None
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
        release_partial(self._lock)
        self._lock = None


_DEFERRED = ("SIGTERM", "SIGINT", "SIGHUP")


@contextlib.contextmanager
def signals_deferred():
    """Hold SIGTERM, SIGINT and SIGHUP back while the block runs (a few renames that must happen
    together); one that arrives meanwhile is raised again, with the handler it would have met,
    when the block ends. Python runs signal handlers in the main thread only, so the block is
    protected whichever thread the kernel delivers the signal to; outside the main thread the
    block runs as is."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []

    def _hold(signum, frame):
        pending.append(signum)

    old = {}
    for name in _DEFERRED:
        sg = getattr(signal, name, None)
        if sg is not None:
            with contextlib.suppress(OSError, ValueError):
                old[sg] = signal.signal(sg, _hold)
    try:
        yield
    finally:
        for sg, h in old.items():
            signal.signal(sg, h if h is not None else signal.SIG_DFL)
        for sg in dict.fromkeys(pending):
            signal.raise_signal(sg)


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


@contextlib.contextmanager
def atomic_outputs(out_dir, last: tuple[str, ...] = ()):
    """Several files of one command, all or none: yield a hidden staging folder inside ``out_dir``
    (created exclusively); when the block succeeds its entries are renamed into ``out_dir``
    (folders merged, the names in ``last`` moved last, so a report appears only with what it
    describes); when it fails (a full disk, an interrupt) the staging folder is removed and
    ``out_dir`` holds none of the new files. Renames within one folder need no space."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".hybridhdr-staging.", dir=out))
    try:
        yield stage

        def move(src: Path, dst: Path):
            entries = sorted(src.iterdir(), key=lambda p: (p.name in last, last.index(p.name) if p.name in last else 0))
            for p in entries:
                q = dst / p.name
                if p.is_dir() and not p.is_symlink() and q.is_dir() and not q.is_symlink():
                    move(p, q)
                else:
                    if q.is_dir() and not q.is_symlink():
                        raise IsADirectoryError(errno.EISDIR, f"{q} is a folder; not replacing it with a file")
                    os.replace(p, q)
        move(stage, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def remap_paths(obj, stage, out):
    """``obj`` (a dict/list of paths, as writers return them) with paths under ``stage`` moved to ``out``."""
    stage, out = Path(stage), Path(out)
    if isinstance(obj, dict):
        return {k: remap_paths(v, stage, out) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(remap_paths(v, stage, out) for v in obj)
    if isinstance(obj, Path):
        try:
            return out / obj.relative_to(stage)
        except ValueError:
            return obj
    return obj


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def refuse_overwriting_inputs(outputs, inputs) -> None:
    """Refuse (``ValueError``, before any work) an output that is one of the inputs, or an input
    inside an output folder that the command replaces: ``view rec.h5 --still rec.h5`` or
    ``simulate s.toml --out s.toml`` used to replace the input silently.

    ``outputs``: ``{"--out": path, ...}`` (None values skipped) or a list of paths;
    ``inputs``: paths (None skipped). Compared after following links (hard links too)."""
    items = outputs.items() if isinstance(outputs, dict) else [("output", o) for o in outputs]
    ins = [Path(os.fspath(i)) for i in inputs if i is not None]
    for flag, out in items:
        if out is None:
            continue
        out = Path(os.fspath(out))
        for i in ins:
            if not (i.exists() or i.is_symlink()):
                continue
            if (out.exists() or out.is_symlink()) and _same_file(out, i):
                raise ValueError(f"{flag} {out} is the input {i}; refusing to overwrite an input "
                                 f"(choose another output name)")
            if not out.exists() and os.path.realpath(out) == os.path.realpath(i):
                raise ValueError(f"{flag} {out} is the input {i}; refusing to overwrite an input")


def refuse_existing_output(out, *, overwrite: bool, flag: str = "--out", command: str = "this command") -> None:
    """The one rule for an output file or folder that already exists, in every verb that writes.

    An existing non-empty output is refused (``errors.UsageError``, a ``ValueError``: exit 2, before
    any work) unless ``overwrite``; an empty folder is accepted. ``flag`` names the option in the message, ``command`` the verb.
    The check is the same for files and folders, so ``simulate``, ``convert`` and ``calibrate sensor``
    refuse exactly as ``reconstruct`` does for its folder."""
    out = Path(os.fspath(out))
    if overwrite or not (out.exists() or out.is_symlink()):
        return
    if out.is_dir() and not out.is_symlink():
        if not any(out.iterdir()):
            return
        what = "exists and is not empty"
    else:
        what = "exists"
    raise UsageError(f"{flag} {out} {what}; choose another name or pass --overwrite "
                     f"(replaces what a {command} run writes)")


def check_outputs(outputs, inputs=(), *, overwrite: bool = False, command: str = "this command") -> None:
    """The one check every verb that writes makes before any work: no output is an input (nor
    holds one), no two outputs are the same file, and an existing output is refused unless
    ``overwrite`` (:func:`refuse_existing_output`). ``outputs``: ``{"--out": path, ...}``
    (None values skipped)."""
    outs = {flag: Path(os.fspath(o)) for flag, o in outputs.items() if o is not None}
    refuse_overwriting_inputs(outs, inputs)
    seen: dict[str, str] = {}
    for flag, o in outs.items():
        key = os.path.realpath(o)
        if key in seen:
            raise ValueError(f"{flag} {o} is also {seen[key]}; two outputs cannot be one file")
        seen[key] = f"{flag} {o}"
    for flag, o in outs.items():
        refuse_existing_output(o, overwrite=overwrite, flag=flag, command=command)
