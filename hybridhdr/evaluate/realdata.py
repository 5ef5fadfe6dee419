"""Real-data scoring without ground truth: the frames' well-exposed codes."""

from __future__ import annotations

import math

__all__ = ["WELL_EXPOSED_8BIT", "well_exposed_range"]

#: Well-exposed codes of an 8-bit frame (inclusive); scaled to other bit depths.
WELL_EXPOSED_8BIT = (20, 235)


def well_exposed_range(max_code: int, codes_8bit=WELL_EXPOSED_8BIT) -> tuple[int, int]:
    """Well-exposed codes ``(lo, hi)`` (inclusive) for frames with top code ``max_code``: the 8-bit
    range scaled by ``max_code / 255`` (lo rounded up, hi rounded down)."""
    s = int(max_code) / 255.0
    return int(math.ceil(codes_8bit[0] * s - 1e-9)), int(math.floor(codes_8bit[1] * s + 1e-9))
