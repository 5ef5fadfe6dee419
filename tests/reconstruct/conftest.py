"""Synthetic hybrid recordings with ideal events from an analytic log-intensity signal."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr import Frames, Recording, SensorSize, make_events


def ideal_recording(height=12, width=16, duration_us=200_000, frame_period_us=40_000, c=0.1, seed=0,
                    t0_us=5_000, grid_us=50, noise_events=50):
    """A drifting grating: L(x, y, t) = log(0.35 + 0.25 sin(2π(x/7 + y/11 - t/0.1 s))).

    Events are level crossings of c (ideal, on a ``grid_us`` grid) plus a few seeded noise events;
    frames are 8-bit codes round(255 exp(L)) at ``t0_us + k frame_period_us`` (zero exposure).
    """
    rng = np.random.default_rng(seed)
    tg = np.arange(t0_us, t0_us + duration_us, grid_us, dtype=np.int64)
    yy, xx = np.mgrid[0:height, 0:width]

    def logi(t_us):
        ph = 2 * np.pi * (xx / 7.0 + yy / 11.0 - (np.asarray(t_us, float)[..., None, None] - t0_us) / 100_000.0)
        return np.log(0.35 + 0.25 * np.sin(ph))

    L = logi(tg)  # (T, H, W)
    lvl = np.floor((L - L[0]) / c).astype(np.int64)
    d = np.diff(lvl, axis=0)
    ts, xs, ys, ps = [], [], [], []
    for k in (1, 2, 3):
        for sgn in (1, -1):
            idx = np.nonzero(sgn * d >= k)
            ts.append(tg[idx[0] + 1]); ys.append(idx[1]); xs.append(idx[2]); ps.append(np.full(len(idx[0]), sgn))
    t = np.concatenate(ts); x = np.concatenate(xs); y = np.concatenate(ys); p = np.concatenate(ps)
    t = np.concatenate([t, rng.integers(t0_us, t0_us + duration_us, noise_events)])
    x = np.concatenate([x, rng.integers(0, width, noise_events)])
    y = np.concatenate([y, rng.integers(0, height, noise_events)])
    p = np.concatenate([p, rng.choice([-1, 1], noise_events)])
    o = np.argsort(t, kind="stable")
    ev = make_events(t[o], x[o], y[o], p[o])
    ft = np.arange(t0_us, t0_us + duration_us, frame_period_us, dtype=np.int64)
    codes = np.clip(np.round(255 * np.exp(logi(ft))), 0, 255).astype(np.uint8)
    fr = Frames(codes, ft, ft, encoding="raw")
    return Recording(ev, SensorSize(height, width), fr), logi


def shift_recording(rec: Recording, dt_us: int) -> Recording:
    ev = rec.events.copy()
    ev["t"] += dt_us
    fr = rec.frames
    fr = Frames(fr.images, fr.t_start_us + dt_us, fr.t_end_us + dt_us, encoding=fr.encoding)
    return Recording(ev, rec.sensor_size, fr)


def constant_frames_recording(codes, times_us, height=3, width=3, events=None):
    imgs = np.stack([np.full((height, width), c, np.uint8) for c in codes])
    t = np.asarray(times_us, np.int64)
    ev = events if events is not None else make_events(np.zeros(0, np.int64), [], [], [])
    return Recording(ev, SensorSize(height, width), Frames(imgs, t, t, encoding="raw"))


@pytest.fixture
def ideal():
    return ideal_recording()
