"""Evaluate: metrics, benchmark runner, speed-accuracy charts (see issue 7)."""

__all__: list[str] = []
