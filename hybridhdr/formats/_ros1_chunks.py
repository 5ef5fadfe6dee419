"""Bound the decompressed size of a ROS 1 bag's chunks before ``rosbags`` decompresses them.

A ROS 1 bag (format 2.0, http://wiki.ros.org/Bags/Format/2.0) is ``#ROSBAG V2.0\\n`` followed by
records ``<u32 header_len><header><u32 data_len><data>``; a header is a sequence of
``<u32 field_len>name=value`` fields, ``op`` naming the record type. Chunk records (``op`` = 0x05)
hold the messages, compressed as a whole (``compression`` = ``none``, ``bz2`` or ``lz4``) with the
decompressed length in ``size`` (u32). ``rosbags`` decompresses a chunk in one call, so a chunk
that declares or expands to gigabytes would be allocated whole.

:func:`check_ros1_chunks` walks the top-level records (seeking over their data), refuses a chunk
whose declared ``size`` is above the packet limit (:func:`hybridhdr._util.limits.check_packet_size`,
``--allow-huge`` lifts it) and verifies each compressed chunk's true decompressed length with
the standard library's incremental decompressors (``bz2.BZ2Decompressor`` and
``lz4.frame.LZ4FrameDecompressor`` take ``max_length``), in pieces of 4 MiB that are discarded:
memory stays bounded, and a chunk that expands beyond its declared size is an error. The cost is
one extra decompression of the bag (LZ4: a few GB/s; bz2: tens of MB/s).
"""

from __future__ import annotations

import bz2
import struct
from pathlib import Path

from ..errors import FormatError
from .._util.limits import check_packet_size

__all__ = ["check_ros1_chunks"]

_MAGIC = b"#ROSBAG V2.0\n"
_OP_CHUNK = 0x05
_PIECE = 4 << 20
#: Record headers are a handful of short fields; anything larger is not a bag.
_MAX_HEADER = 1 << 20


def _fields(path, header: bytes, offset: int) -> dict:
    out, pos = {}, 0
    while pos < len(header):
        if pos + 4 > len(header):
            raise FormatError(path, "truncated record header field", offset=offset)
        (n,) = struct.unpack_from("<I", header, pos)
        pos += 4
        if n > len(header) - pos:
            raise FormatError(path, f"record header field of {n} bytes overruns its header", offset=offset)
        name, sep, value = header[pos:pos + n].partition(b"=")
        if not sep:
            raise FormatError(path, "record header field without '='", offset=offset)
        out[name] = value
        pos += n
    return out


def _expanded_size(path, comp: str, f, n: int, limit: int, offset: int) -> int:
    """Decompress ``n`` bytes from ``f`` piecewise; the output length, stopping above ``limit``."""
    if comp == "bz2":
        d = bz2.BZ2Decompressor()
    elif comp == "lz4":
        try:
            import lz4.frame
        except ImportError:  # rosbags could not read it either; let it say so
            return 0
        d = lz4.frame.LZ4FrameDecompressor()
    else:
        raise FormatError(path, f"chunk compression {comp!r} is not none, bz2 or lz4", offset=offset)
    total, left = 0, n
    try:
        while left > 0:
            data = f.read(min(left, _PIECE))
            if not data:
                break
            left -= len(data)
            out = d.decompress(data, max_length=_PIECE)
            total += len(out)
            while total <= limit and not d.needs_input and not d.eof:
                out = d.decompress(b"", max_length=_PIECE)
                if not out:
                    break
                total += len(out)
            if total > limit or d.eof:
                break
    except (OSError, EOFError, RuntimeError, ValueError) as e:  # corrupt stream: rosbags would fail too
        raise FormatError(path, f"chunk: corrupt {comp} data ({type(e).__name__}: {e})", offset=offset) from None
    return total


def check_ros1_chunks(path) -> int:
    """Check every chunk of the ROS 1 bag at ``path``; returns the number of chunks seen.

    Raises :class:`hybridhdr._util.limits.LimitExceeded` for a chunk declaring more than the packet
    limit, :class:`FormatError` for one that expands beyond its declared size or is malformed.
    A truncated bag stops the walk quietly (``rosbags`` reports it when it reads).
    """
    path = Path(path)
    n_chunks = 0
    with open(path, "rb") as f:
        if f.read(len(_MAGIC)) != _MAGIC:
            raise FormatError(path, "not a ROS 1 bag (no '#ROSBAG V2.0' line)", offset=0)
        size = path.stat().st_size
        pos = len(_MAGIC)
        while pos + 4 <= size:
            f.seek(pos)
            (hlen,) = struct.unpack("<I", f.read(4))
            if hlen > _MAX_HEADER:
                raise FormatError(path, f"record header of {hlen:,} bytes (a bag's are a few hundred)", offset=pos)
            header = f.read(hlen)
            raw = f.read(4)
            if len(header) < hlen or len(raw) < 4:
                return n_chunks  # truncated
            (dlen,) = struct.unpack("<I", raw)
            fields = _fields(path, header, pos)
            data_at = pos + 8 + hlen
            if fields.get(b"op") == bytes([_OP_CHUNK]):
                n_chunks += 1
                comp = fields.get(b"compression", b"none").decode("ascii", "replace")
                declared = fields.get(b"size")
                if declared is None or len(declared) != 4:
                    raise FormatError(path, "chunk record without a 4-byte 'size' field", offset=pos)
                (declared,) = struct.unpack("<I", declared)
                check_packet_size(declared, path, what=f"chunk {n_chunks - 1} (decompressed)", offset=pos)
                if comp != "none":
                    got = _expanded_size(path, comp, f, min(dlen, max(0, size - data_at)), declared, pos)
                    if got > declared:
                        raise FormatError(path, f"chunk {n_chunks - 1}: {comp} data expands beyond the {declared:,} "
                                                f"bytes its header declares", offset=pos)
            pos = data_at + dlen
    return n_chunks
