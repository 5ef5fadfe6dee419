"""Event/frame self-calibration (hybridhdr.calibrate.selfcal): planted values recovered, leave-one-out."""

import warnings

import numpy as np
import pytest

from hybridhdr.calibrate.camera_model import GridEdgeWarning
from hybridhdr.calibrate.selfcal import (
    apply_time_offset,
    estimate_event_frame_calibration,
    self_calibration,
)
from hybridhdr.events import EVENT_DTYPE
from hybridhdr.model import Frames, Recording, SensorSize

H, W = 20, 28
PERIOD_US = 30_000
STEP_US = 100
SPEED = 300.0  # px/s: a pixel's log changes by several thresholds per frame period, as at real edges


def _scene(t_us):
    """Frame-linear radiance (H, W) at time t: a drifting two-frequency texture, 0.03 .. 0.93."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    s = t_us * 1e-6
    a = 0.5 + 0.5 * np.sin(2 * np.pi * (x - SPEED * s) / 17.0 + 0.7 * y)
    b = 0.5 + 0.5 * np.cos(2 * np.pi * (y + 0.6 * SPEED * s) / 13.0 + 0.3 * x)
    return 0.03 + 0.9 * a * b


def planted_recording(*, dark=0.04, c_on=0.2, c_off=0.3, offset_us=6_000, duration_us=400_000):
    """Ideal DVS events of ln(radiance + dark) (level crossings every 100 µs), 8-bit linear frames of
    the radiance at ``k·period + offset`` stamped at ``k·period`` (zero exposure): the frames stand
    for their stamp + ``offset_us``."""
    ref = np.log(_scene(0) + dark)
    rows = []
    for t in range(STEP_US, duration_us + 1, STEP_US):
        lv = np.log(_scene(t) + dark)
        while True:
            up = lv - ref >= c_on
            dn = ref - lv >= c_off
            if not (up.any() or dn.any()):
                break
            for m, pol, c in ((up, 1, c_on), (dn, -1, -c_off)):
                yy, xx = np.nonzero(m)
                rows.extend((t, x_, y_, pol) for y_, x_ in zip(yy, xx))
                ref[m] += c
    ev = np.array(rows, dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    ev = ev[np.argsort(ev["t"], kind="stable")].astype(EVENT_DTYPE)
    stamps = np.arange(0, duration_us + 1, PERIOD_US, dtype=np.int64)
    imgs = np.stack([np.clip(np.rint(255 * _scene(t + offset_us)), 0, 255).astype(np.uint8) for t in stamps])
    fr = Frames(images=imgs, t_start_us=stamps, t_end_us=stamps.copy(), encoding="linear")
    return Recording(events=ev, sensor_size=SensorSize(H, W), frames=fr)


@pytest.fixture(scope="module")
def planted():
    return planted_recording()


def test_recovers_planted_offset_log_model_and_thresholds(planted):
    cal = estimate_event_frame_calibration(planted)
    # the grid's step is period/40 = 750 µs: the offset within two steps. The estimate is the
    # offset at which the counts best explain the frames, which trails the planted one by the DVS
    # hysteresis lag (a change of about c/2 must accrue before the count follows a reversal: at
    # 150 px/s here it was 2.25 ms, at 300 px/s 0.75 ms)
    assert abs(cal.time_offset_us - 6_000) <= 1_500, cal.time_offset_us
    # I0 grid points are a factor 2 apart: the planted dark level 0.04 is a grid point; accept its neighbours
    assert 0.02 <= cal.intensity_offset <= 0.08, cal.intensity_offset
    # thresholds: the counts are quantised (a residual of up to one threshold at each end of an
    # interval), which attenuates least squares by a few per cent here; 15 % bounds it
    assert cal.c_on == pytest.approx(0.2, rel=0.15)
    assert cal.c_off == pytest.approx(0.3, rel=0.15)
    assert cal.c_off > cal.c_on  # the asymmetry is found, not averaged away
    assert cal.r2 > cal.r2_nominal + 0.1  # calibrating explains clearly more than the stamps as given


def test_zero_offset_planted_is_found(planted):
    rec = planted_recording(offset_us=0)
    cal = estimate_event_frame_calibration(rec)
    assert abs(cal.time_offset_us) <= 1_500


def test_leave_one_out_never_uses_the_excluded_frame(planted):
    """A frame replaced by garbage changes nothing when it is the excluded one."""
    base = estimate_event_frame_calibration(planted, exclude_frames=(5,))
    imgs = planted.frames.images.copy()
    imgs[5] = np.random.default_rng(0).integers(0, 256, imgs[5].shape, dtype=np.uint8)
    bad = Recording(events=planted.events, sensor_size=planted.sensor_size,
                    frames=Frames(images=imgs, t_start_us=planted.frames.t_start_us,
                                  t_end_us=planted.frames.t_end_us, encoding="linear"))
    same = estimate_event_frame_calibration(bad, exclude_frames=(5,))
    assert same.to_dict() == base.to_dict()
    with warnings.catch_warnings():  # the garbage frame may leave I0 unbounded (warned; not the point here)
        warnings.simplefilter("ignore", GridEdgeWarning)
        changed = estimate_event_frame_calibration(bad)  # the garbage frame used: the estimate moves
    assert changed.r2 < base.r2 - 0.01


def test_method_with_fixed_log_model_keeps_the_recordings_offset(planted):
    got = self_calibration(planted, intensity_offset=1.0)  # CF's published ln(I + 1)
    assert got["intensity_offset"] == 1.0
    assert abs(got["time_offset_us"] - 6_000) <= 1_500
    # in ln(I + 1) a frame change is smaller: its thresholds are too
    assert got["c_on"] < 0.2


def test_apply_time_offset_shifts_frames_only(planted):
    r = apply_time_offset(planted, 6_000)
    assert np.array_equal(r.frames.t_start_us, planted.frames.t_start_us + 6_000)
    assert r.events is planted.events


def test_clear_errors():
    rec = planted_recording(duration_us=40_000)  # two frames
    with pytest.raises(ValueError, match="at least three frames"):
        estimate_event_frame_calibration(rec)
    rec = planted_recording(duration_us=200_000)
    with pytest.raises(ValueError, match="not among"):
        estimate_event_frame_calibration(rec, exclude_frames=(99,))
    with pytest.raises(ValueError, match="intensity_offsets"):
        estimate_event_frame_calibration(rec, intensity_offsets=(0.0,))
