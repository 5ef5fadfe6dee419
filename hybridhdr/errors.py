"""Exception types shared by every part of hybridhdr.

All validation errors derive from :class:`ValueError` (or :class:`TypeError`) so that
callers can catch them with the standard types; the subclasses add structured context
(file, byte offset, record index) for tools that want it.
"""

from __future__ import annotations

import os

__all__ = ["FormatError", "UnknownFormatError", "EventValidationError", "UsageError", "InputMismatchError"]


class UsageError(ValueError):
    """What was asked cannot be done as asked: bad arguments found after parsing (``--end`` before
    ``--start``), an unknown method. The command line exits 2 for it, as argparse does for the
    arguments it refuses itself; errors of the data (an unreadable file, a failed fit) exit 1."""


class InputMismatchError(UsageError):
    """The input lacks what the method or command asked for needs: a method or verb that needs
    frames given a recording without them, a method that takes no frames asked to complete
    frames. A usage error (exit 2): another method or input is the fix, not another file."""


class EventValidationError(ValueError):
    """Events violate an invariant (unsorted time, coordinates outside the sensor, bad polarity)."""


class WindowOutsideDataError(ValueError):
    """A time window given to the API (``Recording.slice_time``, ``hybridhdr.read``,
    ``RecordingFile.events`` ...) lies wholly outside the recording's data; the message names the
    recording's span, as the command line's empty-window error does."""


class FormatError(ValueError):
    """A file does not match the format it claims (or was asked) to be.

    Parameters
    ----------
    path : str or os.PathLike or None
        The file being read.
    message : str
        What was expected and what was found.
    offset : int, optional
        Byte offset in the file where the problem was found.
    record : int, optional
        Index of the offending record (event, line, packet) where a byte offset is not meaningful.
    """

    def __init__(self, path, message: str, *, offset: int | None = None, record: int | None = None):
        self.path = None if path is None else os.fspath(path)
        self.offset = offset
        self.record = record
        where = []
        if offset is not None:
            where.append(f"byte offset {offset}")
        if record is not None:
            where.append(f"record {record}")
        loc = f" at {', '.join(where)}" if where else ""
        prefix = f"{self.path}{loc}: " if self.path is not None else (f"{loc.strip()}: " if loc else "")
        super().__init__(prefix + message)
        self.message = message


class UnknownFormatError(FormatError):
    """The format of a file could not be detected, or an unknown format name was given."""
