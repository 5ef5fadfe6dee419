"""Recordings the evaluation builds from a user's recording (over-exposed, held-out inputs) keep
every part they do not change: the IMU samples and triggers ride along (a rebuilt recording that is
written out must not lose them)."""

import numpy as np

from hybridhdr.events import EVENT_DTYPE, SensorSize, empty_imu, make_triggers
from hybridhdr.evaluate import overexpose as O
from hybridhdr.evaluate.realdata import holdout_input
from hybridhdr.model import Frames, Recording


def _rec():
    ss = SensorSize(4, 5)
    ev = np.zeros(40, dtype=EVENT_DTYPE)
    ev["t"] = np.arange(40) * 1000
    ev["x"], ev["y"], ev["p"] = np.arange(40) % 5, np.arange(40) % 4, 1
    t = np.array([0, 10_000, 20_000, 30_000], np.int64)
    codes = np.full((4, 4, 5), 60, np.uint8)
    imu = empty_imu(8)
    imu["t"] = np.arange(8) * 5000
    imu["accel_z_g"] = 1.0
    return Recording(ev, ss, Frames(codes, t, t, encoding="linear"), make_triggers([500, 25_500], 0, 1), imu=imu)


def test_overexposed_recording_keeps_imu_and_triggers():
    rec = _rec()
    over, _ = O.overexpose_recording(rec, 4)
    np.testing.assert_array_equal(over.imu, rec.imu)
    np.testing.assert_array_equal(over.triggers, rec.triggers)
    assert not np.array_equal(over.frames.images, rec.frames.images)  # what it changes, it changes


def test_held_out_inputs_keep_imu_up_to_their_cut():
    rec = _rec()
    loo, _ = holdout_input(rec, 1, "leave_one_out")
    np.testing.assert_array_equal(loo.imu, rec.imu)
    nxt, t = holdout_input(rec, 2, "next_frame")
    assert len(nxt.frames) == 2 and int(nxt.events["t"].max()) < t + 1
    np.testing.assert_array_equal(nxt.imu, rec.imu[rec.imu["t"] < t])
    assert 0 < len(nxt.imu) < len(rec.imu)
