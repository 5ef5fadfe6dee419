"""HDF5 output that survives a full disk: the first I/O error is recorded, never shown to HDF5.

HDF5 writes lazily (chunk and metadata caches), so a full disk surfaces as errors while datasets
are deallocated or the file is closed, after which the library is in a state where closing the
remaining handles can crash the process (SIGSEGV, hundreds of lines of h5py tracebacks). Here
the file is opened through h5py's ``fileobj`` driver on a :class:`GuardedFile`: a write that
fails (``ENOSPC``, ``EIO``, ``EDQUOT``, ...) is recorded and its bytes are kept in a small memory
overlay instead, so HDF5 always sees success and can close cleanly. The writer checks
:meth:`GuardedFile.check` after each operation and raises the recorded error as one plain
:class:`OSError` naming the file; the caller then closes the HDF5 file and removes the partial
output (:func:`close_and_remove`).
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

__all__ = ["GuardedFile", "open_h5_for_writing", "close_and_remove", "DiskWriteError"]

#: after a failure, bytes HDF5 still writes (cache flushes while closing) are kept in memory up to this
_OVERLAY_LIMIT = 256 << 20


class DiskWriteError(OSError):
    """A write to an output file failed (full disk, quota, I/O error); the partial output is removed."""


class GuardedFile:
    """A binary file object for h5py's ``fileobj`` driver that never raises on write.

    Positional reads and writes go straight to the file descriptor (``os.pread``/``os.pwrite``,
    no Python buffering, so an error is seen at the write that caused it). After the first failed
    write, later writes go to an in-memory overlay that reads consult, so HDF5 stays consistent
    while it closes; nothing more reaches the disk.
    """

    def __init__(self, path):
        self.path = Path(path)
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666)
        self._pos = 0
        self._eof = 0
        self.error: OSError | None = None
        self._overlay: dict[int, bytes] = {}
        self._overlay_bytes = 0

    # -- the file-object protocol h5py uses --------------------------------------------------
    def seek(self, offset, whence=os.SEEK_SET):
        if whence == os.SEEK_SET:
            self._pos = int(offset)
        elif whence == os.SEEK_CUR:
            self._pos += int(offset)
        else:
            self._pos = self._eof + int(offset)
        return self._pos

    def tell(self):
        return self._pos

    def seekable(self):
        return True

    def readable(self):
        return True

    def writable(self):
        return True

    def readinto(self, buf):
        mv = memoryview(buf).cast("B")
        n = len(mv)
        got = 0
        if self._fd is not None:
            while got < n:
                try:
                    k = os.preadv(self._fd, [mv[got:]], self._pos + got)
                except OSError as e:
                    self._record(e)
                    break
                if k == 0:
                    break
                got += k
        if got < n:
            mv[got:] = bytes(n - got)
        if self._overlay:
            a, b = self._pos, self._pos + n
            for off, data in self._overlay.items():
                e = off + len(data)
                if e <= a or off >= b:
                    continue
                s0, s1 = max(a, off), min(b, e)
                mv[s0 - a:s1 - a] = data[s0 - off:s1 - off]
        self._pos += n
        return n

    def read(self, size=-1):
        if size is None or size < 0:
            size = max(0, self._eof - self._pos)
        buf = bytearray(size)
        k = self.readinto(buf)
        return bytes(buf[:k])

    def write(self, data):
        mv = memoryview(data).cast("B")
        n = len(mv)
        if self.error is None:
            done = 0
            try:
                while done < n:
                    k = os.pwrite(self._fd, mv[done:], self._pos + done)
                    if k <= 0:
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                    done += k
            except OSError as e:
                self._record(e)
                self._keep(self._pos + done, bytes(mv[done:]))
        else:
            self._keep(self._pos, bytes(mv))
        self._pos += n
        self._eof = max(self._eof, self._pos)
        return n

    def truncate(self, size=None):
        size = self._pos if size is None else int(size)
        if self.error is None:
            try:
                os.ftruncate(self._fd, size)
            except OSError as e:
                self._record(e)
        self._eof = size
        return size

    def flush(self):
        pass

    def fileno(self):
        return self._fd

    # -- ours ----------------------------------------------------------------------------------
    def _record(self, e: OSError) -> None:
        if self.error is None:
            self.error = e

    def _keep(self, offset: int, data: bytes) -> None:
        if self._overlay_bytes + len(data) > _OVERLAY_LIMIT:
            return  # the file is being thrown away; HDF5 only needs to be able to finish closing
        old = self._overlay.pop(offset, None)
        if old is not None:
            self._overlay_bytes -= len(old)
        self._overlay[offset] = data
        self._overlay_bytes += len(data)

    def check(self) -> None:
        """Raise the recorded write error (once there is one) as a :class:`DiskWriteError`."""
        if self.error is not None:
            raise _as_disk_error(self.error, self.path)

    def sync(self) -> None:
        """``fsync`` the descriptor (errors are recorded and raised by :meth:`check`)."""
        if self.error is None and self._fd is not None:
            try:
                os.fsync(self._fd)
            except OSError as e:
                self._record(e)
        self.check()

    def close(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            try:
                os.close(fd)
            except OSError as e:
                self._record(e)
        self._overlay.clear()
        self._overlay_bytes = 0

    @property
    def closed(self) -> bool:
        return self._fd is None


def _as_disk_error(e: OSError, path) -> DiskWriteError:
    code = e.errno if e.errno is not None else errno.EIO
    what = os.strerror(code)
    return DiskWriteError(code, f"cannot write {path}: {what}; the partial output was removed")


def open_h5_for_writing(path, **kwargs):
    """Create an HDF5 file at ``path`` on a :class:`GuardedFile`; returns ``(h5py.File, guard)``."""
    import h5py
    guard = GuardedFile(path)
    try:
        f = h5py.File(guard, "w", **kwargs)
    except BaseException:
        guard.close()
        raise
    guard.check()
    return f, guard


def close_and_remove(f, guard: GuardedFile | None, path) -> None:
    """Close the HDF5 file (every handle it owns, then the file), the descriptor, and unlink ``path``.

    Never raises: this is the clean-up path after an error.
    """
    if f is not None:
        try:
            f.close()
        except Exception:
            pass
    if guard is not None:
        guard.close()
    try:
        Path(path).unlink()
    except (FileNotFoundError, IsADirectoryError, PermissionError, OSError):
        pass
