"""Formats: every file format hybridhdr reads or writes, each a module that registers itself here.

Event files (the hybridhdr container, Prophesee, AEDAT 4, text, HDF5 layouts, AKF .mat, rosbag) go
through :func:`read`, :func:`write`, :func:`open_reader` and :func:`open_writer`
(:mod:`.registry`); exposure-bracket folders are :mod:`.brackets`. See ``docs/formats.md``.
"""

from .base import (DEFAULT_CHUNK_EVENTS, DataDropWarning, EventChunk, EventFileReader, EventFileWriter,
                   FormatSpec, unsupported_parts)
from .registry import detect_format, format_for_output, formats, open_reader, open_writer, read, write

__all__ = [
    "read", "write", "open_reader", "open_writer", "detect_format", "format_for_output", "formats",
    "EventChunk", "EventFileReader", "EventFileWriter", "FormatSpec", "DataDropWarning", "unsupported_parts",
    "DEFAULT_CHUNK_EVENTS",
]
