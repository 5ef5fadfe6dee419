"""Exact blurred hybrid recordings: a quantised log image shifted by whole pixels (known answers).

The sharp log image is ``L0 = log(I0 + I) = base + c·n(y, x)`` with integer levels ``n``; it moves
right by one pixel (periodic) every ``shift_us``. Events are then exact: at each shift a pixel
whose level changes by Δn emits |Δn| events of sign(Δn) at the shift time, and a frame exposed
over ``[s, e)`` is the exact time average of the linear intensity, so EDI with the true c
recovers the sharp image to rounding.
"""

from __future__ import annotations

import numpy as np

from hybridhdr import Frames, Recording, SensorSize, make_events


def levels(height, width, seed=0):
    """Bars 5 px wide every 12 px, of random level 2..5 (halved in the top half), on level 0."""
    rng = np.random.default_rng(seed)
    n = np.zeros((height, width), np.int64)
    for x0 in range(2, width - 6, 12):
        n[:, x0:x0 + 5] = rng.integers(2, 6)
    n[: height // 2] //= 2
    return n


def shifted_sequence(height=16, width=48, c=0.2, shift_us=1_000, duration_us=40_000, base=np.log(1.1),
                     seed=0, frame_starts=(0, 20_000), exposure_us=8_000, I0=1.0):
    """Return (events arrays t, x, y, p), frames as float linear intensity, and ``truth(t)``."""
    n0 = levels(height, width, seed)

    def level_at(t_us):
        return np.roll(n0, int(t_us // shift_us), axis=1)

    def truth(t_us):  # linear intensity I
        return np.exp(base + c * level_at(t_us)) - I0

    ts, xs, ys, ps = [], [], [], []
    prev = level_at(0)
    for j in range(1, duration_us // shift_us + 1):
        t = j * shift_us
        cur = level_at(t)
        d = cur - prev
        for k in range(1, int(np.abs(d).max(initial=0)) + 1):
            yy, xx = np.nonzero(np.abs(d) >= k)
            ts.append(np.full(yy.size, t, np.int64)); xs.append(xx); ys.append(yy)
            ps.append(np.sign(d[yy, xx]))
        prev = cur
    t = np.concatenate(ts); x = np.concatenate(xs); y = np.concatenate(ys); p = np.concatenate(ps)
    o = np.argsort(t, kind="stable")
    ev = make_events(t[o], x[o], y[o], p[o])
    imgs, s_list, e_list = [], [], []
    for s in frame_starts:
        e = s + exposure_us
        acc = np.zeros((height, width))
        cuts = sorted({s, e} | set(range((s // shift_us + 1) * shift_us, e, shift_us)))
        for a, b in zip(cuts[:-1], cuts[1:]):
            acc += (np.exp(base + c * level_at(a))) * (b - a)
        imgs.append(acc / (e - s) - I0)
        s_list.append(s); e_list.append(e)
    fr = Frames(np.stack(imgs), np.array(s_list, np.int64), np.array(e_list, np.int64), encoding="linear")
    return Recording(ev, SensorSize(height, width), fr), truth
