"""Capture: read and write hybrid recordings in every supported event format.

Readers and writers are reached through :func:`hybridhdr.read`, :func:`hybridhdr.open_reader`
and :func:`hybridhdr.open_writer`; the formats live in :mod:`hybridhdr.capture.formats`.
"""

from ..io import FORMAT_DESCRIPTIONS, detect_format, open_reader, open_writer, read, write

__all__ = ["FORMAT_DESCRIPTIONS", "detect_format", "open_reader", "open_writer", "read", "write"]
