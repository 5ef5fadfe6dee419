"""Previews users can watch: the robust preview tone map and ``hybridhdr view``."""

import numpy as np

from hybridhdr.reconstruct.output import LogPercentiles, tone_map


def test_tone_map_ignores_bad_pixels():
    rng = np.random.default_rng(0)
    img = np.exp(rng.normal(0, 1, (4, 60, 80))).astype(np.float32)
    ref, lim = tone_map(img)
    bad = img.copy()
    idx = rng.random(bad.shape) < 0.05  # 5 % clamped / broken pixels: more than the 1 % percentile tail
    bad[idx] = rng.choice(np.array([np.nan, np.inf, -np.inf, 0.0, 1e-6, -3.0], np.float32), int(idx.sum()))
    out, lim2 = tone_map(bad)
    assert abs(lim2[0] - lim[0]) < 0.1 and abs(lim2[1] - lim[1]) < 0.1  # the old map pinned lo at log 1e-6
    good = ~idx
    assert np.abs(out[good].astype(int) - ref[good].astype(int)).max() <= 8
    assert np.all(out[np.isnan(bad) | (bad <= 1e-6) | np.isneginf(bad)] == 0) and np.all(out[np.isposinf(bad)] == 255)
    # the streaming writer's exact percentiles agree bit for bit
    lp = LogPercentiles()
    for fr in bad:
        lp.add(fr)
    assert lp.limits(lambda: iter(bad)) == lim2
    # nothing valid at all: black, no error
    u8, _ = tone_map(np.full((2, 3), np.nan))
    assert not u8.any()
