"""What a recording covers in time (:class:`Span`), read from any supported file."""

from __future__ import annotations

from dataclasses import dataclass

from .registry import open_reader

__all__ = ["Span", "recording_span"]


@dataclass
class Span:
    """What a recording covers: events (first, last t) and frames (first exposure start, last
    exposure mid, last exposure end), µs sensor time; None for a part that is absent."""

    events: tuple[int, int] | None
    frames: tuple[int, int, int] | None
    n_events: int | None = None

    @property
    def origin_us(self) -> int | None:
        firsts = [p[0] for p in (self.events, self.frames) if p is not None]
        return min(firsts) if firsts else None

    def describe(self) -> str:
        o = self.origin_us
        parts = []
        if self.events is not None:
            a, b = self.events
            parts.append(f"events {a:,}..{b:,} µs ({(a - o) / 1e6:g}..{(b - o) / 1e6:g} s from the start)")
        if self.frames is not None:
            a, _, b = self.frames
            parts.append(f"frames {a:,}..{b:,} µs ({(a - o) / 1e6:g}..{(b - o) / 1e6:g} s)")
        return "; ".join(parts) if parts else "no events or frames"


def recording_span(path, format=None, *, full: bool = True, chunk_events: int = 1 << 20, **reader_opts) -> Span:
    """The :class:`Span` of a recording file. ``full=False`` reads only the first chunk of events
    (enough for the origin; the events' last time is then None)."""
    with open_reader(path, format, **reader_opts) as r:
        ev = None
        n = None
        tr = getattr(r, "time_range_us", None)
        try:
            tr = tr() if callable(tr) else tr
        except Exception:  # noqa: BLE001 - a reader that cannot say: stream
            tr = None
        if tr is not None:
            ev = (int(tr[0]), int(tr[1]))
        else:
            first = last = None
            n = 0
            for c in r.iter_chunks(chunk_events):
                if len(c.events):
                    if first is None:
                        first = int(c.events["t"][0])
                        if not full:
                            last = None
                            break
                    last = int(c.events["t"][-1])
                    n += len(c.events)
            if first is not None:
                ev = (first, last)
            if not full:
                n = None
        fr = r.read_frames()
        frames = None
        if fr is not None and len(fr):
            frames = (int(fr.t_start_us.min()), int(fr.t_mid_us.max()), int(fr.t_end_us.max()))
    return Span(ev, frames, n)
