"""AEDAT 4.0 reader: the DVXplorer sample and small files written with dv-processing."""

from __future__ import annotations

import datetime

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.formats import aedat4 as A
from hybridhdr.errors import FormatError



def make_aedat4(path, events, size=(32, 24), frames=(), triggers=(), compression="LZ4"):
    """Write an AEDAT4 file with dv-processing.

    events: EVENT_DTYPE array; frames: (t_us, exposure_us, image) tuples; triggers: (t_us, type code).
    """
    dv = pytest.importorskip("dv_processing")
    cfg = dv.io.MonoCameraWriter.Config("TestCam_ABC123")
    cfg.addEventStream(size)
    if len(frames):
        cfg.addFrameStream(size)
    cfg.addTriggerStream()
    cfg.compression = getattr(dv.CompressionType, compression)
    w = dv.io.MonoCameraWriter(str(path), cfg)
    store = dv.EventStore()
    for t, x, y, p in events.tolist():
        store.push_back(int(t), int(x), int(y), bool(p > 0))
    if len(events):
        w.writeEvents(store)
    for t, exp, img in frames:
        f = dv.Frame(int(t), img)
        f.exposure = datetime.timedelta(microseconds=int(exp))
        w.writeFrame(f)
    for t, code in triggers:
        w.writeTrigger(dv.Trigger(int(t), dv.TriggerType(code)))
    del w
    return path


def test_sample(shared_data):
    p = shared_data("aedat4/sample.aedat4")
    assert hh.detect_format(p) == "aedat4"
    with hh.open_reader(p) as r:
        assert r.sensor_size == hh.SensorSize(240, 320)
        assert r.trigger_stream is not None  # the file declares a trigger stream ...
        rec = r.read()
        chunks = [c.events for c in r.iter_chunks(10_000)]
    ev = rec.events
    assert rec.n_events == 111_954
    span = (int(ev["t"][-1]) - int(ev["t"][0])) / 1e6
    assert span == pytest.approx(0.590, abs=0.001)
    hh.validate_events(ev, rec.sensor_size)
    assert set(np.unique(ev["p"]).tolist()) == {-1, 1}
    assert len(rec.triggers) == 0  # ... which holds no trigger packets (checked with dv-processing too)
    assert rec.frames is None
    assert rec.metadata.event_camera.model == "DVXplorer_DXB00010"
    assert rec.metadata.event_camera.serial == "DXB00010"
    # first events as decoded by dv-processing: (1605537493718345, 154, 204, OFF)
    assert ev[0].tolist() == (1605537493718345, 154, 204, -1)
    assert all(len(c) <= 10_000 for c in chunks)
    np.testing.assert_array_equal(np.concatenate(chunks), ev)


def test_sample_matches_dv_processing(shared_data):
    dv = pytest.importorskip("dv_processing")
    p = shared_data("aedat4/sample.aedat4")
    rec = dv.io.MonoCameraRecording(str(p))
    parts = []
    while True:
        b = rec.getNextEventBatch()
        if b is None:
            break
        parts.append(b.numpy())
    ref = np.concatenate(parts)
    ev = hh.read(p).events
    np.testing.assert_array_equal(ev["t"], ref["timestamp"])
    np.testing.assert_array_equal(ev["x"], ref["x"])
    np.testing.assert_array_equal(ev["p"], np.where(ref["polarity"] > 0, 1, -1))


@pytest.mark.parametrize("compression", ["LZ4", "NONE", "ZSTD"])
def test_synthetic_events_frames_triggers(tmp_path, compression):
    rng = np.random.default_rng(0)
    n = 500
    ev = hh.make_events(1000 + np.sort(rng.integers(0, 50_000, n)), rng.integers(0, 32, n),
                        rng.integers(0, 24, n), rng.integers(0, 2, n))
    ev["x"][:2], ev["y"][:2] = (0, 31), (23, 0)  # sensor edges
    img0 = rng.integers(0, 256, (24, 32), dtype=np.uint8)
    img1 = rng.integers(0, 256, (24, 32), dtype=np.uint8)
    frames = [(2000, 500, img0), (30_000, 0, img1)]
    trig = [(1500, 1), (1600, 2), (1700, 0), (1800, 8), (1900, 9), (2500, 4), (2600, 5), (2700, 3)]
    p = make_aedat4(tmp_path / "s.aedat4", ev, frames=frames, triggers=trig, compression=compression)
    rec = hh.read(p)
    np.testing.assert_array_equal(rec.events, ev)
    assert rec.sensor_size == hh.SensorSize(24, 32)
    assert rec.metadata.event_camera.model == "TestCam_ABC123"
    fr = rec.frames
    np.testing.assert_array_equal(fr.images, np.stack([img0, img1]))
    np.testing.assert_array_equal(fr.t_start_us, [2000, 30_000])
    np.testing.assert_array_equal(fr.t_end_us, [2500, 30_000])
    tr = rec.triggers
    assert tr["t"].tolist() == [1500, 1600, 1800, 1900, 2500, 2600, 2700]  # TIMESTAMP_RESET skipped
    assert tr["channel"].tolist() == [0, 0, 3, 3, 1, 1, 0]
    assert tr["edge"].tolist() == [1, -1, 1, -1, 1, -1, 1]


def test_colour_frames_are_rgb(tmp_path):
    img = np.zeros((24, 32, 3), np.uint8)
    img[..., 0], img[..., 1], img[..., 2] = 10, 20, 30  # BGR as dv-processing takes it
    p = make_aedat4(tmp_path / "c.aedat4", hh.make_events([5], [1], [1], [1]), frames=[(10, 0, img)])
    fr = hh.read(p).frames
    assert fr.images.shape == (1, 24, 32, 3)
    assert fr.images[0, 0, 0].tolist() == [30, 20, 10]


def test_mixed_frame_dtypes_rejected(tmp_path):
    p = make_aedat4(tmp_path / "m.aedat4", hh.make_events([5], [1], [1], [1]),
                    frames=[(10, 0, np.zeros((24, 32), np.uint8)), (20, 0, np.zeros((24, 32), np.uint16))])
    with pytest.raises(FormatError, match="unlike the first frame"):
        hh.read(p)


def test_sensor_size_option_and_stream_option(tmp_path):
    p = make_aedat4(tmp_path / "o.aedat4", hh.make_events([5, 6], [31, 0], [1, 23], [1, 0]))
    r = hh.open_reader(p, sensor_size=(100, 200))
    assert r.sensor_size == hh.SensorSize(100, 200)
    assert r.metadata.provenance["sensor_size_source"] == "option"
    with pytest.raises(FormatError, match="event_stream=7 is not an id of a event stream"):
        hh.open_reader(p, event_stream=7)
    with pytest.raises(FormatError, match="outside the sensor width 16"):
        hh.read(p, sensor_size=(24, 16))


def test_out_of_sensor(tmp_path):
    p = make_aedat4(tmp_path / "x.aedat4", hh.make_events([1000, 1010], [40, 1], [3, 3], [1, 1]))
    with pytest.raises(FormatError, match="x=40 outside the sensor width 32"):
        hh.read(p)


def test_unsorted_timestamps(tmp_path):
    # uncompressed file; patch the second event's timestamp (a distinctive int64) to go backwards
    ev = hh.make_events([1000, 0x0102030405], [1, 2], [3, 3], [1, 1])
    p = make_aedat4(tmp_path / "u.aedat4", ev, compression="NONE")
    data = bytearray(p.read_bytes())
    key = (0x0102030405).to_bytes(8, "little")
    i = data.index(key)  # first occurrence: in the event packet (the file's index table follows it)
    data[i:i + 8] = (999).to_bytes(8, "little")
    p.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="event 1 has 999 µs after 1000 µs"):
        hh.read(p)


def test_truncated_and_garbage(tmp_path, shared_data):
    src = shared_data("aedat4/sample.aedat4").read_bytes()
    p = tmp_path / "t.aedat4"
    p.write_bytes(src[:200_000])
    with pytest.raises(FormatError, match="truncated file"):
        hh.read(p)
    bad = bytearray(src)
    start = 14 + 4 + int.from_bytes(src[14:18], "little")  # first packet header
    bad[start + 4:start + 8] = (10 ** 9).to_bytes(4, "little")
    p.write_bytes(bytes(bad))
    with pytest.raises(FormatError, match=f"byte offset {start}, record 0: packet 0 .* has size 1000000000"):
        hh.read(p)
    bad = bytearray(src)
    bad[start + 20:start + 40] = b"\x00" * 20  # inside the LZ4 frame
    p.write_bytes(bytes(bad))
    with pytest.raises(FormatError, match="record 0: corrupt packet 0"):
        hh.read(p)
    p.write_bytes(src[:300])  # inside the XML header
    with pytest.raises(FormatError):
        hh.read(p, "aedat4")
    p.write_bytes(b"not an aedat file at all")
    with pytest.raises(FormatError, match="expected magic"):
        hh.read(p, "aedat4")


def test_sniff():
    assert A.sniff(None, b"#!AER-DAT4.0\r\n....") == "aedat4"
    assert A.sniff(None, b"#!AER-DAT3.1\r\n") is None
    assert A.sniff(None, b"") is None


def _dv_imu_samples(dv, path):
    rec = dv.io.MonoCameraRecording(str(path))
    out = []
    while True:
        b = rec.getNextImuBatch()
        if b is None:
            return out
        out += [b[k] for k in range(len(b))]


def _assert_imu_equals_dv(imu, ref):
    """Every sample and every field of ``imu`` (IMU_DTYPE) equals dv-processing's ``dv.IMU`` objects
    exactly (dv hands float32 values over as Python floats: converting back is exact)."""
    assert len(imu) == len(ref)
    np.testing.assert_array_equal(imu["t"], [int(s.timestamp) for s in ref])
    for name, _, dv_name in hh.events.IMU_FIELDS:
        np.testing.assert_array_equal(imu[name], np.array([getattr(s, dv_name) for s in ref], np.float32),
                                      err_msg=name)


def test_davis346_imu_matches_dv_processing(shared_data):
    dv = pytest.importorskip("dv_processing")
    p = shared_data("aedat4/davis346_street.aedat4")
    ref = _dv_imu_samples(dv, p)
    imu = hh.read(p).imu
    assert len(imu) == 2363  # counted with dv-processing
    # the first sample as dv-processing decodes it: lying flat, y axis along gravity, 28.5 °C
    assert int(imu["t"][0]) == 1589163147369190
    assert imu["accel_y_g"][0] == np.float32(-0.9951171875) and imu["temperature_c"][0] == np.float32(28.51789665222168)
    _assert_imu_equals_dv(imu, ref)
    p2 = shared_data("aedat4/sample.aedat4")  # a DVXplorer's IMU, too
    _assert_imu_equals_dv(hh.read(p2).imu, _dv_imu_samples(dv, p2))


def test_synthetic_imu_with_magnetometer(tmp_path):
    dv = pytest.importorskip("dv_processing")
    cfg = dv.io.MonoCameraWriter.Config("TestCam_ABC123")
    cfg.addEventStream((32, 24))
    cfg.addImuStream()
    w = dv.io.MonoCameraWriter(str(tmp_path / "i.aedat4"), cfg)
    store = dv.EventStore()
    store.push_back(1000, 1, 2, True)
    w.writeEvents(store)
    rng = np.random.default_rng(3)
    vals = rng.normal(0, 30, (40, 10)).astype(np.float32)
    for k in range(40):
        w.writeImu(dv.IMU(1000 + 250 * k, *[float(v) for v in vals[k]]))
    del w
    ref = _dv_imu_samples(dv, tmp_path / "i.aedat4")
    imu = hh.read(tmp_path / "i.aedat4").imu
    _assert_imu_equals_dv(imu, ref)
    assert len(imu) == 40 and np.all(imu["mag_z_ut"] != 0)
    # dv.IMU's argument order: timestamp, temperature, accelerometer, gyroscope, magnetometer
    np.testing.assert_array_equal(imu["temperature_c"], vals[:, 0])
    np.testing.assert_array_equal(imu["gyro_x_deg_s"], vals[:, 4])
    np.testing.assert_array_equal(imu["mag_z_ut"], vals[:, 9])
