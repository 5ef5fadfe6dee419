"""Radiance RGBE (``.hdr``) images, read in pure Python, including files damaged by a text-mode copy.

The simulator's fast reader for intact files is :func:`hybridhdr.simulate.ahdr.read_rgbe` (a Numba
kernel); it falls back to this one for damaged files.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ..errors import FormatError

__all__ = ["read_rgbe"]


def read_rgbe(path, *, repair_newlines: bool = True) -> np.ndarray:
    """Read a Radiance RGBE ``.hdr`` file (flat or new-style run-length encoded) as float32 (H, W, 3).

    Format: Ward, "Real Pixels", Graphics Gems II (1991): a text header ended by a blank line, a
    resolution line (``-Y H +X W``: rows top to bottom), then per scanline either flat RGBE
    quadruples or, when it starts with bytes 2, 2, the four components run-length encoded
    separately. Value = mantissa * 2^(E - 136). (OpenCV rejects files whose first header
    line is not ``#?RADIANCE``, such as Debevec's ``memorial.hdr``.)

    ``repair_newlines``: a file that went through a text-mode copy (every CR and LF byte turned
    into CR LF, so no lone CR is left -- the state of ``shared/data/brackets/memorial/memorial.hdr``,
    which OpenCV refuses with "bad scanline data") is decoded by searching, scanline by scanline,
    for the reading of each CR LF as an original 10, 13 or 13 10 under which every run-length
    component sums to the width and the next scanline header is valid (a depth-first search with
    memoised dead ends). Bytes 10 and 13 inside literal runs cannot be told apart after the
    damage; such values take 10, a mantissa error of at most 3/256 on a few pixels.
    """
    data = Path(path).read_bytes()
    cands = [(i, len(sep)) for sep in (b"\n\n", b"\n\r\n") if (i := data.find(sep)) >= 0]
    if not cands:
        raise FormatError(path, "not a Radiance RGBE file (no blank line ending the header)")
    pos, seplen = min(cands)
    if b"FORMAT=32-bit_rle_rgbe" not in data[:pos]:
        raise FormatError(path, "not a Radiance RGBE file (no FORMAT=32-bit_rle_rgbe header)")
    end = data.find(b"\n", pos + seplen)
    res = data[pos + seplen:end].split()
    if len(res) != 4 or res[0] != b"-Y" or res[2] != b"+X":
        raise FormatError(path, f"only the standard '-Y H +X W' orientation is supported, got {res!r}")
    h, w = int(res[1]), int(res[3])
    p = end + 1
    try:
        out = _rgbe_strict(data, p, h, w)
    except ValueError as err:
        if not repair_newlines or data.count(b"\r") != data.count(b"\r\n") or not data.count(b"\r\n"):
            raise FormatError(path, f"{err}") from None
        out = _rgbe_repair(data, p, h, w)
        if out is None:
            raise FormatError(path, f"{err}; the newline repair found no consistent decoding either") from None
    e = out[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return (out[..., :3].astype(np.float64) * scale[..., None]).astype(np.float32)


def _rgbe_strict(data: bytes, p: int, h: int, w: int) -> np.ndarray:
    buf = np.frombuffer(data, np.uint8)
    out = np.empty((h, w, 4), np.uint8)
    for y in range(h):
        if p + 4 > buf.size:
            raise ValueError(f"file ends in scanline {y}")
        if 8 <= w < 32768 and buf[p] == 2 and buf[p + 1] == 2 and (int(buf[p + 2]) << 8 | int(buf[p + 3])) == w:
            p += 4
            for c in range(4):
                x = 0
                while x < w:
                    if p >= buf.size:
                        raise ValueError(f"file ends in scanline {y}")
                    n = int(buf[p])
                    if n > 128:
                        n -= 128
                        if x + n > w:
                            raise ValueError(f"bad scanline data: run of {n} overruns scanline {y} at byte {p}")
                        out[y, x:x + n, c] = buf[p + 1]
                        p += 2
                    else:
                        if n == 0 or x + n > w:
                            raise ValueError(f"bad scanline data: literal of {n} overruns scanline {y} at byte {p}")
                        out[y, x:x + n, c] = buf[p + 1:p + 1 + n]
                        p += 1 + n
                    x += n
        else:
            if p + 4 * w > buf.size:
                raise ValueError(f"file ends in scanline {y}")
            out[y] = buf[p:p + 4 * w].reshape(w, 4)
            p += 4 * w
    return out


def _rgbe_repair(d: bytes, p: int, h: int, w: int):
    """Decode run-length RGBE damaged by CR/LF -> CR LF conversion (see :func:`read_rgbe`)."""
    L = len(d)

    def opts1(q):
        # (end, value) readings of one clean byte at damaged offset q
        if q >= L:
            return ()
        c = d[q]
        if c == 13:
            return ((q + 2, 10), (q + 2, 13), (q + 1, 13))  # 10, 13, or the 13 of an original 13 10
        if c == 10:
            return ((q + 1, 10),) if q > 0 and d[q - 1] == 13 else ()
        return ((q + 1, c),)

    arr = np.frombuffer(d, np.uint8)
    ncr = np.concatenate([[0], np.cumsum(arr == 13)])  # ncr[i] = number of CR bytes in d[:i]

    def take(q, n):
        # {end: clean bytes} for reading n clean bytes from damaged offset q. A CR LF pair fully
        # inside [q, e) reads as 1 byte (10) or 2 (13 10); a CR just before e is a 13 whose LF
        # starts the next read. So e is reachable iff 0 <= (e - q - n) <= pairs inside.
        if q + n <= L and d.find(b"\r", q, q + n) < 0 and d.find(b"\n", q, q + n) < 0:
            return {q + n: d[q:q + n]}
        if q < L and d[q] == 10 and not (q > 0 and d[q - 1] == 13):
            return {}
        res = {}
        c0 = int(ncr[q])
        for e in range(min(q + 2 * n, L), q + n - 1, -1):
            singles = e - q - n
            if singles <= int(ncr[max(e - 1, q)]) - c0:
                res[e] = _Lazy(q, e, singles)
        return res

    class _Lazy:
        # the clean bytes of d[q:e] with the first `singles` CR LF pairs read as one byte
        __slots__ = ("q", "e", "singles")

        def __init__(self, q, e, singles):
            self.q, self.e, self.singles = q, e, singles

        def get(self):
            seg = arr[self.q:self.e]
            if self.singles:
                seg = np.delete(seg, np.flatnonzero(seg[:-1] == 13)[:self.singles])
            return seg

        def __getitem__(self, i):
            return int(self.get()[i])

    def headers(q):
        return [e for e, hb in take(q, 4).items() if hb[0] == 2 and hb[1] == 2 and (hb[2] << 8 | hb[3]) == w]

    out = np.zeros((h, w, 4), np.uint8)
    fail: set = set()

    def comp(q, y, c, x, last):
        key = (q, c, x)
        if key in fail:
            return None
        if x == w:
            if c == 3:
                r = (q if L - q < 8 else None) if last else (q if headers(q) else None)
            else:
                r = comp(q, y, c + 1, 0, last)
            if r is None:
                fail.add(key)
            return r
        for q1, n in opts1(q):
            if n > 128:
                n -= 128
                if x + n > w:
                    continue
                for q2, val in opts1(q1):
                    r = comp(q2, y, c, x + n, last)
                    if r is not None:
                        out[y, x:x + n, c] = val
                        return r
            else:
                if n == 0 or x + n > w:
                    continue
                for q2, vals in take(q1, n).items():
                    r = comp(q2, y, c, x + n, last)
                    if r is not None:
                        out[y, x:x + n, c] = np.frombuffer(vals, np.uint8) if isinstance(vals, bytes) else vals.get()
                        return r
        fail.add(key)
        return None

    old = sys.getrecursionlimit()
    sys.setrecursionlimit(max(old, 4 * w + 4 * 1024))
    try:
        for y in range(h):
            fail.clear()
            nxt = None
            for ph in headers(p):
                nxt = comp(ph, y, 0, 0, y == h - 1)
                if nxt is not None:
                    break
            if nxt is None:
                return None
            p = nxt
    finally:
        sys.setrecursionlimit(old)
    return out
