"""Blinking-board event images: kernels, blink period, rejection, pose segmentation."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.calibrate import _kernels as K
from hybridhdr.calibrate.event_images import (BlinkParams, blink_image, blink_period_from_events,
                                              blink_period_from_triggers, event_images, window_statistics,
                                              windows_from_period, windows_from_triggers)
from hybridhdr.events import EVENT_DTYPE, SensorSize, make_events, make_triggers

from . import _sim as S

SIZE = SensorSize(96, 128)
PERIOD_US = 80_000


def _checker(shift=0, sq=12):
    """White-coverage image of a plain checkerboard region (no rendering needed)."""
    yy, xx = np.mgrid[0:SIZE.height, 0:SIZE.width]
    inside = (xx >= 16 + shift) & (xx < 112 + shift) & (yy >= 12) & (yy < 84)
    return (inside & ((((xx - shift) // sq) + (yy // sq)) % 2 == 0)).astype(np.float64)


@pytest.fixture(scope="module")
def three_poses():
    covs = [_checker(0), _checker(5), _checker(-4)]
    ev, tr, spans = S.blink_events(covs, period_us=PERIOD_US, periods=4, seed=3, motion_us=150_000,
                                   triggers=True, n_hot=20)
    return covs, ev, tr, spans


# ---------------------------------------------------------------------------------------------- kernels


def test_kernel_matches_py_func():
    rng = np.random.default_rng(0)
    n, w, h = 400, 7, 5
    x = rng.integers(0, w, n).astype(np.uint16)
    y = rng.integers(0, h, n).astype(np.uint16)
    p = rng.choice(np.array([-1, 1], np.int8), n)
    i0 = np.array([0, 100, 250, 250], np.int64)
    i1 = np.array([100, 250, 250, 400], np.int64)
    use = np.array([True, False, True, True])
    outs = []
    for f in (K.blink_window_stats, K.blink_window_stats.py_func):
        img = np.zeros(w * h)
        st = np.zeros((4, K.N_STATS), np.int64)
        f(x, y, p, i0, i1, w, w * h, use, 2, False, img, st)
        outs.append((img, st))
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_array_equal(outs[0][1], outs[1][1])
    # check window 0 by hand: pixels with >= 2 ON and >= 2 OFF
    idx = y[:100].astype(int) * w + x[:100]
    on = np.bincount(idx[p[:100] > 0], minlength=w * h)
    off = np.bincount(idx[p[:100] < 0], minlength=w * h)
    assert outs[0][1][0, K.S_BOTH] == np.sum((on >= 2) & (off >= 2))
    assert outs[0][1][0, K.S_ON_ONLY] == np.sum((on > 0) & (off == 0))
    assert outs[0][1][0, K.S_OFF_ONLY] == np.sum((off > 0) & (on == 0))
    assert outs[0][1][2, K.S_EVENTS] == 0
    t = np.sort(rng.integers(0, 10_000, n)).astype(np.int64)
    a = [np.zeros(10), np.zeros(10)]
    b = [np.zeros(10), np.zeros(10)]
    K.binned_signed_rate(t, p, 0, 1000, 10, a[0], a[1])
    K.binned_signed_rate.py_func(t, p, 0, 1000, 10, b[0], b[1])
    np.testing.assert_array_equal(a, b)
    assert a[1].sum() == n and a[0].sum() == p.sum()


# ---------------------------------------------------------------------------------------------- period


def test_period_from_triggers(three_poses):
    _, ev, tr, spans = three_poses
    per = blink_period_from_triggers(tr)
    assert per.period_us == PERIOD_US and per.source == "triggers"
    w0, w1, _ = windows_from_triggers(tr)
    assert np.all(w1 - w0 == PERIOD_US)
    assert len(w0) == 12  # 4 rising edges per pose, gaps between poses have none


def test_period_from_event_rate(three_poses):
    _, ev, _, spans = three_poses
    per = blink_period_from_events(ev)
    print(f"blink period from the event rate: {per.period_us:.2f} µs (true {PERIOD_US}), "
          f"periodicity {per.periodicity:.2f}")
    # 500 µs bins refined over ~10 multiples by parabolic interpolation: well under 0.1 %
    assert abs(per.period_us - PERIOD_US) < 0.001 * PERIOD_US
    assert per.source == "event_rate" and per.periodicity > 0.5
    # the window cuts fall in the quiet half-way gaps, so every window of the first pose holds one
    # ON and one OFF burst (the bursts are at span start + k*T and + k*T + T/2, +50..~500 µs)
    w0, w1 = windows_from_period(per, int(ev["t"][0]), int(ev["t"][-1]))
    t_on = spans[0][0] + PERIOD_US * np.arange(4)
    for t in t_on:
        k = np.searchsorted(w0, t, side="right") - 1
        assert w0[k] < t - 5_000 and t + PERIOD_US // 2 + 5_000 < w1[k]


def test_period_beyond_2_31_us(three_poses):
    _, ev, tr, _ = three_poses
    ev2 = ev.copy()
    ev2["t"] += 2**32
    a, b = blink_period_from_events(ev), blink_period_from_events(ev2)
    assert abs(a.period_us - b.period_us) < 1e-3 and b.phase_us - a.phase_us == 2**32


def test_no_blinking_is_an_error():
    rng = np.random.default_rng(1)
    n = 20_000
    ev = make_events(np.sort(rng.integers(0, 2_000_000, n)), rng.integers(0, 128, n), rng.integers(0, 96, n),
                     rng.choice([-1, 1], n))
    with pytest.raises(ValueError, match="no periodic blinking"):
        blink_period_from_events(ev)
    with pytest.raises(ValueError, match="two periods"):
        blink_period_from_events(ev[:10][ev[:10]["t"] < 15_000])
    with pytest.raises(ValueError, match="rising"):
        windows_from_triggers(make_triggers([5], [0], [1]))


def test_params_validation():
    with pytest.raises(ValueError, match="max_single_ratio"):
        BlinkParams(max_single_ratio=-1)
    with pytest.raises(ValueError, match="image_mode"):
        BlinkParams(image_mode="sum")
    with pytest.raises(ValueError, match="min_period_us"):
        BlinkParams(min_period_us=100_000, max_period_us=50_000)


# ---------------------------------------------------------------------------------------------- rejection


def test_single_polarity_rejection_and_hot_pixels():
    cov = _checker(0)
    ev, tr, spans = S.blink_events([cov], period_us=PERIOD_US, periods=3, seed=5, n_hot=0, triggers=True)
    w0, w1, _ = windows_from_triggers(tr)
    base = window_statistics(ev, SIZE, w0, w1)
    assert base.accepted.all()
    n_both = int(base.n_both[0])
    assert n_both > 0.9 * cov.sum()  # every white pixel fires both polarities each period
    rng = np.random.default_rng(2)
    black = np.argwhere(cov == 0)

    def add_on_only(n_pix, window):
        pix = black[rng.choice(len(black), n_pix, replace=False)]
        t = rng.integers(w0[window], w1[window], n_pix)
        extra = make_events(t, pix[:, 1], pix[:, 0], np.ones(n_pix))
        allev = np.concatenate([ev, extra])
        return allev[np.argsort(allev["t"], kind="stable")], pix

    # 10 % ON-only pixels in window 1: under the 15 % criterion -> accepted, and they stay dark
    ev10, pix = add_on_only(int(0.10 * n_both), 1)
    st = window_statistics(ev10, SIZE, w0, w1)
    assert st.accepted.all() and st.n_on_only[1] >= int(0.10 * n_both)
    img = blink_image(ev10, SIZE, tr)
    assert img[pix[:, 0], pix[:, 1]].max() == 0
    # 20 % ON-only pixels in window 1 (motion-like) -> only that window is rejected
    ev20, _ = add_on_only(int(0.20 * n_both), 1)
    st = window_statistics(ev20, SIZE, w0, w1)
    assert st.accepted.tolist() == [True, False, True]
    assert st.single_ratio[1] > 0.15 >= st.single_ratio[0]
    # everything rejected -> a clear error
    with pytest.raises(ValueError, match="all 3 blink windows were rejected"):
        blink_image(ev20, SIZE, tr, BlinkParams(min_both_pixels=10 * n_both))


def test_binary_and_count_images_show_the_board():
    cov = _checker(0)
    ev, tr, _ = S.blink_events([cov], period_us=PERIOD_US, periods=3, seed=6, triggers=True)
    for mode in ("count", "binary"):
        img = blink_image(ev, SIZE, tr, BlinkParams(image_mode=mode))
        assert img.dtype == np.uint8 and img.shape == SIZE.shape
        white, black = img[cov == 1], img[cov == 0]
        # 3x3 median removes isolated noise pixels; squares are solid
        assert np.median(white) >= 200 and np.percentile(black, 99) == 0, mode


# ---------------------------------------------------------------------------------------------- poses


@pytest.mark.parametrize("use_triggers", [True, False])
def test_pose_segmentation(three_poses, use_triggers):
    covs, ev, tr, spans = three_poses
    res = event_images(ev, SIZE, tr if use_triggers else None)
    print(res.summary())
    assert len(res.poses) == 3
    for k, (pose, (a, b)) in enumerate(zip(res.poses, spans)):
        # each pose lies within its true static span, give or take half a period (the event-rate
        # windows are cut half-way through the quiet gap before each ON burst)
        assert a - PERIOD_US // 2 <= pose.t0_us and pose.t1_us <= b + PERIOD_US // 2
        assert pose.n_windows >= 3
        # and its image is that pose's board
        im = pose.image.astype(float)
        corr = [np.corrcoef(im.ravel(), c.ravel())[0, 1] for c in covs]
        assert int(np.argmax(corr)) == k
        assert max(corr) > 0.9
    assert (~res.stats.accepted).sum() >= (0 if use_triggers else 4)  # motion windows rejected


def test_event_images_validation():
    with pytest.raises(ValueError, match="no events"):
        event_images(np.zeros(0, EVENT_DTYPE), SIZE)
    with pytest.raises(TypeError, match="BlinkParams"):
        event_images(make_events([0], [0], [0], [1]), SIZE, params={"median_radius": 1})
    with pytest.raises(ValueError, match="sensor"):
        event_images(make_events([0, 1], [500, 1], [0, 0], [1, 1]), SIZE)
