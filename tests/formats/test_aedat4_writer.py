"""AEDAT4 writer (through dv-processing): round trip through our reader and dv-processing's."""

from __future__ import annotations

import datetime

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.model import Frames

dv = pytest.importorskip("dv_processing")

SS = hh.SensorSize(24, 32)


def _recording(n=3000, colour=False, dtype=np.uint8, seed=0):
    rng = np.random.default_rng(seed)
    t = 1_000 + np.sort(rng.integers(0, 200_000, n))
    ev = hh.make_events(t, rng.integers(0, SS.width, n), rng.integers(0, SS.height, n), rng.integers(0, 2, n))
    ev["x"][:2], ev["y"][:2] = (0, SS.width - 1), (SS.height - 1, 0)
    k = 4
    shape = (k, SS.height, SS.width, 3) if colour else (k, SS.height, SS.width)
    hi = 256 if dtype == np.uint8 else 65536
    imgs = rng.integers(0, hi, shape).astype(dtype)
    ts = np.array([5_000, 60_000, 110_000, 160_000])
    te = ts + np.array([500, 0, 4_000, 10_000])
    frames = Frames(imgs, ts, te, encoding="raw")
    trig = hh.make_triggers([1_500, 1_600, 50_000, 50_100, 90_000, 90_500, 120_000, 120_001],
                            [0, 0, 1, 1, 2, 2, 3, 3], [1, -1, 1, -1, 1, -1, 1, -1])
    return hh.Recording(ev, SS, frames, trig)


def _dv_read(path):
    """Events, frames and triggers as dv-processing reads them."""
    r = dv.io.MonoCameraRecording(str(path))
    evs = []
    while True:
        b = r.getNextEventBatch()
        if b is None:
            break
        evs.append(b.numpy())
    frames = []
    if r.isFrameStreamAvailable():
        while True:
            f = r.getNextFrame()
            if f is None:
                break
            frames.append(f)
    trig = []
    if r.isTriggerStreamAvailable():
        while True:
            tp = r.getNextTriggerBatch()
            if tp is None:
                break
            trig += [(int(x.timestamp), int(x.type.value)) for x in tp]
    return np.concatenate(evs) if evs else None, frames, trig, r.getCameraName()


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_round_trip_ours_and_dv(tmp_path, compression):
    rec = _recording()
    p = hh.write(rec, tmp_path / "out.aedat4", compression=compression, packet_events=700)
    assert hh.detect_format(p) == "aedat4"
    assert sorted(q.name for q in tmp_path.iterdir()) == ["out.aedat4"]  # no spool or partial left
    back = hh.read(p)
    np.testing.assert_array_equal(back.events, rec.events)
    assert back.sensor_size == SS
    np.testing.assert_array_equal(back.frames.images, rec.frames.images)
    np.testing.assert_array_equal(back.frames.t_start_us, rec.frames.t_start_us)
    np.testing.assert_array_equal(back.frames.t_end_us, rec.frames.t_end_us)
    np.testing.assert_array_equal(back.triggers, rec.triggers)
    # dv-processing reads the same
    ev, frames, trig, name = _dv_read(p)
    np.testing.assert_array_equal(ev["timestamp"], rec.events["t"])
    np.testing.assert_array_equal(ev["x"], rec.events["x"])
    np.testing.assert_array_equal(ev["y"], rec.events["y"])
    np.testing.assert_array_equal(np.where(ev["polarity"] > 0, 1, -1), rec.events["p"])
    assert len(frames) == 4
    for f, img, t0, t1 in zip(frames, rec.frames.images, rec.frames.t_start_us, rec.frames.t_end_us):
        np.testing.assert_array_equal(f.image, img)
        assert f.timestamp == t0 and f.exposure == datetime.timedelta(microseconds=int(t1 - t0))
    assert trig == [(1_500, 1), (1_600, 2), (50_000, 4), (50_100, 5), (90_000, 6), (90_500, 7), (120_000, 8),
                    (120_001, 9)]
    assert name == "hybridhdr"


@pytest.mark.parametrize("colour,dtype", [(True, np.uint8), (False, np.uint16)])
def test_colour_and_16_bit_frames(tmp_path, colour, dtype):
    rec = _recording(300, colour=colour, dtype=dtype)
    p = hh.write(rec, tmp_path / "c.aedat4")
    back = hh.read(p)
    np.testing.assert_array_equal(back.frames.images, rec.frames.images)  # RGB in, RGB out (BGR in the file)
    _, frames, _, _ = _dv_read(p)
    want = rec.frames.images[0][..., ::-1] if colour else rec.frames.images[0]
    np.testing.assert_array_equal(np.squeeze(frames[0].image), want)


def test_events_only_sample_and_cli_convert(shared_data, tmp_path, capsys):
    from hybridhdr.cli import main
    src = shared_data("aedat4/sample.aedat4")
    out = tmp_path / "copy.aedat4"
    assert main(["convert", str(src), str(out), "--no-progress"]) == 0
    a, b = hh.read(src), hh.read(out)
    np.testing.assert_array_equal(a.events, b.events)
    assert b.metadata.event_camera.model == "DVXplorer_DXB00010"  # the camera name is kept
    r = dv.io.MonoCameraRecording(str(out))
    assert not r.isFrameStreamAvailable() and not r.isTriggerStreamAvailable()  # only what there is
    # from another format: an EVT 3.0 file to AEDAT4
    evt3 = shared_data("prophesee/evt3_sample.raw")
    out2 = tmp_path / "from_evt3.aedat4"
    assert main(["convert", str(evt3), str(out2), "--no-progress"]) == 0
    np.testing.assert_array_equal(hh.read(out2).events, hh.read(evt3).events)


def test_out_of_order_and_unstorable_input_are_clean_errors(tmp_path):
    rec = _recording(200)
    w = hh.open_writer(tmp_path / "o.aedat4", "aedat4", sensor_size=SS)
    w.write_events(rec.events[100:])
    with pytest.raises(ValueError, match="time order"):
        w.write_events(rec.events[:100])  # never reaches dv-processing (which would abort the process)
    w.abort()
    assert not list(tmp_path.iterdir())
    bad = hh.make_triggers([10], [7], [1])
    with pytest.raises(ValueError, match="channel 7"):
        hh.write(hh.Recording(rec.events, SS, triggers=bad), tmp_path / "t.aedat4")
    assert not list(tmp_path.iterdir())
    fl = Frames(np.zeros((1, SS.height, SS.width), np.float32), [0], [10])
    with pytest.raises(ValueError, match="8- or 16-bit"):
        hh.write(hh.Recording(rec.events, SS, frames=fl), tmp_path / "f.aedat4")
    assert not list(tmp_path.iterdir())
    with pytest.raises(ValueError, match="compression"):
        hh.write(rec, tmp_path / "x.aedat4", compression="gzip")
    assert not list(tmp_path.iterdir())
    # frames written later but earlier in time are sorted (each AEDAT4 stream must be in time order)
    fr = rec.frames

    def part(sl):
        return Frames(fr.images[sl], fr.t_start_us[sl], fr.t_end_us[sl], encoding="raw")
    w = hh.open_writer(tmp_path / "r.aedat4", "aedat4", sensor_size=SS)
    w.write_events(rec.events)
    w.write_frames(part(slice(2, None)))
    w.write_frames(part(slice(0, 2)))
    w.close()
    np.testing.assert_array_equal(hh.read(tmp_path / "r.aedat4").frames.t_start_us, fr.t_start_us)


def test_missing_dv_processing_is_a_clear_error(tmp_path, monkeypatch):
    import builtins
    real = builtins.__import__

    def no_dv(name, *a, **k):
        if name == "dv_processing":
            raise ImportError("No module named 'dv_processing'")
        return real(name, *a, **k)
    monkeypatch.setattr(builtins, "__import__", no_dv)
    with pytest.raises(ImportError, match=r"hybridhdr\[aedat4\]"):
        hh.write(_recording(10), tmp_path / "m.aedat4")
    assert not list(tmp_path.iterdir())


def test_too_little_free_space_refused_before_dv_processing(tmp_path, monkeypatch):
    import collections
    import errno
    import shutil
    rec = _recording(2000)
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10 ** 9, 10 ** 9 - 1000, 1000))
    with pytest.raises(OSError) as e:
        hh.write(rec, tmp_path / "full.aedat4")
    assert e.value.errno == errno.ENOSPC and "No space left on device" in str(e.value)
    assert not list(tmp_path.iterdir())


def test_imu_round_trip_through_dv_processing(tmp_path):
    """IMU samples written as AEDAT4 read back bit for bit, by hybridhdr's reader and by dv-processing."""
    rec = _recording(300)
    imu = hh.empty_imu(90)
    imu["t"] = np.sort(np.random.default_rng(1).integers(int(rec.events["t"][0]), int(rec.events["t"][-1]), 90))
    for j, (name, _, _) in enumerate(hh.events.IMU_FIELDS):
        imu[name] = (np.arange(90) * 0.37 + j).astype(np.float32)
    import dataclasses
    p = tmp_path / "imu.aedat4"
    hh.write(dataclasses.replace(rec, imu=imu), p)
    assert hh.read(p).imu.tobytes() == imu.tobytes()
    r = dv.io.MonoCameraRecording(str(p))
    got = []
    while (b := r.getNextImuBatch()) is not None:
        got += [b[k] for k in range(len(b))]
    assert [int(s.timestamp) for s in got] == imu["t"].tolist()
    np.testing.assert_array_equal(np.float32([s.magnetometerZ for s in got]), imu["mag_z_ut"])
    np.testing.assert_array_equal(np.float32([s.gyroscopeX for s in got]), imu["gyro_x_deg_s"])


def test_davis346_imu_survives_container_and_back(tmp_path, shared_data):
    """aedat4 -> container -> aedat4 keeps the DAVIS346 recording's 2,363 IMU samples bit for bit."""
    from hybridhdr.formats.container import read_recording, write_recording
    src = shared_data("aedat4/davis346_street.aedat4")
    h5 = write_recording(hh.read(src), tmp_path / "street.h5")
    back = tmp_path / "street.aedat4"
    hh.write(read_recording(h5), back)
    assert hh.read(back).imu.tobytes() == hh.read(src).imu.tobytes() and len(hh.read(back).imu) == 2363
