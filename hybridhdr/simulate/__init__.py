"""Simulate: Mitsuba 3 scenes to events, LDR frames and HDR ground truth (see issue 5)."""

__all__: list[str] = []
