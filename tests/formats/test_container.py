"""The HDF5 recording container: round trips, lazy slicing, streaming, atomicity, bad input."""

import os

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridhdr as hh
from hybridhdr.formats.container import RecordingFile, RecordingWriter, read_recording, write_recording
from hybridhdr.errors import FormatError


def random_recording(seed=0, n=20000, ss=(260, 346), t0=10**12):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t0, t0 + 3_000_000, n))
    ev = hh.make_events(t, rng.integers(0, ss[1], n), rng.integers(0, ss[0], n), rng.choice([-1, 1], n))
    fr = hh.Frames(rng.integers(0, 255, (4, *ss), dtype=np.uint8), t0 + np.arange(4) * 700_000,
                   t0 + np.arange(4) * 700_000 + 5000, gain=[1.0, 2.0, 1.0, 4.0], encoding="gamma")
    tr = hh.make_triggers(t0 + np.array([0, 5000, 700_000, 705_000]), [0, 0, 1, 1], [1, -1, 1, -1])
    hdr = hh.HDRReferences(rng.random((2, *ss), dtype=np.float32) * 1e3, t0 + np.array([2500, 702_500]))
    md = hh.Metadata(hh.CameraInfo(hh.SensorSize(*ss), "DAVIS346", "00001"),
                     hh.CameraInfo(hh.SensorSize(*ss), "FLIR BFS", "x"), {"R": [[1, 0], [0, 1]]},
                     {"note": "unit test"})
    return hh.Recording(ev, ss, fr, tr, hdr, md)


def test_round_trip_everything(tmp_path):
    rec = random_recording()
    p = write_recording(rec, tmp_path / "r.h5", buffer_events=3000)
    assert not (tmp_path / "r.h5.partial").exists()
    back = read_recording(p)
    assert np.array_equal(back.events, rec.events)
    assert np.array_equal(back.triggers, rec.triggers)
    assert np.array_equal(back.frames.images, rec.frames.images)
    assert np.array_equal(back.frames.t_start_us, rec.frames.t_start_us)
    assert np.array_equal(back.frames.gain, rec.frames.gain) and back.frames.encoding == "gamma"
    assert np.array_equal(back.hdr.images, rec.hdr.images) and back.hdr.images.dtype == np.float32
    assert back.metadata == rec.metadata and back.sensor_size == hh.SensorSize(260, 346)
    assert hh.detect_format(p) == "hybridhdr"
    assert np.array_equal(hh.read(p).events, rec.events)


def test_time_index_matches_definition(tmp_path, monkeypatch):
    import hybridhdr.formats.container as container
    monkeypatch.setattr(container, "INDEX_STRIDE", 50)
    rec = random_recording(1, n=5000)
    p = write_recording(rec, tmp_path / "r.h5", buffer_events=777)
    with h5py.File(p) as f:
        ms, first = f["events/index_ms"][:], f["events/index_first"][:]
        assert f.attrs["hybridhdr_format_version"] == "2.1" and "ms_to_idx" not in f["events"]
    t = rec.events["t"]
    assert first[0] == 0 and np.all(np.diff(ms) > 0) and np.all(np.diff(first) >= 50)
    # each entry is the first event of its millisecond
    assert np.array_equal(first, np.searchsorted(t, 1000 * ms, side="left"))
    assert np.all(t[first[1:] - 1] // 1000 < ms[1:])
    # greedy: no millisecond start that is >= 50 events after an entry is skipped before the next entry
    starts = np.flatnonzero(np.diff(t // 1000)) + 1
    for a, b in zip(first[:-1], first[1:]):
        assert not np.any((starts >= a + 50) & (starts < b))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10**6), st.integers(0, 10**6), st.integers(1, 5000))
def test_lazy_window_equals_slice(tmp_path_factory, a, b, chunk):
    p = tmp_path_factory.getbasetemp() / "lazy.h5"
    rec = random_recording(2, n=3000, t0=-500_000)  # negative times too
    if not p.exists():
        write_recording(rec, p, buffer_events=1000)
    t0, t1 = sorted([a - 500_000, b - 500_000])
    with RecordingFile(p) as r:
        first, last = r.data_span_us()
        if t1 <= first or t0 > last:  # wholly outside the data: an error naming the span, not empty
            from hybridhdr.errors import WindowOutsideDataError
            with pytest.raises(WindowOutsideDataError, match="spans"):
                r.events(t0, t1)
            with pytest.raises(WindowOutsideDataError, match="spans"):
                r.event_columns(t0, t1)
        else:
            assert np.array_equal(r.events(t0, t1), hh.slice_time(rec.events, t0, t1))
            cols = r.event_columns(t0, t1)
            assert np.array_equal(cols["t"], hh.slice_time(rec.events, t0, t1)["t"])
        chunks = list(r.iter_chunks(chunk))
        assert np.array_equal(np.concatenate([c.events for c in chunks]), rec.events)
        assert np.array_equal(np.concatenate([c.triggers for c in chunks]), rec.triggers)


def test_time_windows(tmp_path):
    rec = random_recording(3, n=4000)
    p = write_recording(rec, tmp_path / "r.h5")
    with RecordingFile(p) as r:
        wins = list(r.iter_time_windows(250_000, chunk_events=333))
    t_first = int(rec.events["t"][0])
    assert [w[0] for w in wins] == [t_first + 250_000 * i for i in range(len(wins))]
    for t0, ev in wins:
        assert np.array_equal(ev, hh.slice_time(rec.events, t0, t0 + 250_000))
    assert sum(len(w[1]) for w in wins) == len(rec.events)


def test_streaming_writer_flush_and_abort(tmp_path):
    p = tmp_path / "s.h5"
    w = RecordingWriter(p, (10, 10), buffer_events=10)
    w.write_events(hh.make_events(np.arange(25), np.arange(25) % 10, 0, 1))
    w.flush()
    assert (tmp_path / "s.h5.partial").exists() and not p.exists()
    with pytest.raises(ValueError, match="time order"):
        w.write_events(hh.make_events([3], [0], [0], [1]))
    w.abort()
    assert not (tmp_path / "s.h5.partial").exists() and not p.exists()
    # exception inside the context manager leaves nothing behind
    with pytest.raises(RuntimeError):
        with RecordingWriter(p, (10, 10)) as w2:
            w2.write_events(hh.make_events([1], [1], [1], [1]))
            raise RuntimeError("boom")
    assert os.listdir(tmp_path) == []


def test_writer_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="sensor_size"):
        RecordingWriter(tmp_path / "a.h5")
    with RecordingWriter(tmp_path / "a.h5", (4, 4)) as w:
        with pytest.raises(ValueError, match="width 4"):
            w.write_events(hh.make_events([0], [4], [0], [1]))
        with pytest.raises(TypeError, match="EVENT_DTYPE"):
            w.write_events(np.zeros(3))
        w.write_frames(hh.Frames(np.zeros((1, 4, 4), np.uint8), [0], [1]))
        with pytest.raises(ValueError, match="shape"):
            w.write_frames(hh.Frames(np.zeros((1, 5, 4), np.uint8), [2], [3]))
    with pytest.raises(ValueError, match="compression"):
        RecordingWriter(tmp_path / "b.h5", (4, 4), compression="zip")


def test_empty_recording(tmp_path):
    p = write_recording(hh.Recording(sensor_size=(3, 3)), tmp_path / "e.h5")
    with RecordingFile(p) as r:
        assert r.n_events == 0 and r.time_range_us is None and len(r.events(0, 10)) == 0
        assert r.read().n_events == 0


def test_bad_files(tmp_path):
    p = write_recording(random_recording(4, n=2000), tmp_path / "r.h5")
    with pytest.raises(FormatError, match="no 'hybridhdr_format_version'"):
        with h5py.File(tmp_path / "other.h5", "w") as f:
            f["x"] = 1
        RecordingFile(tmp_path / "other.h5")
    data = p.read_bytes()
    (tmp_path / "trunc.h5").write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="trunc.h5"):
        r = RecordingFile(tmp_path / "trunc.h5")
        r.events()
    (tmp_path / "rand.h5").write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(FormatError, match="rand.h5"):
        RecordingFile(tmp_path / "rand.h5")
    with pytest.raises(hh.UnknownFormatError, match="could not detect"):
        hh.read(tmp_path / "rand.h5")
    # unsorted timestamps and out-of-sensor coordinates written behind our back
    for field, value, msg in (("t", 0, "non-decreasing|decreases"), ("x", 999, "width")):
        q = tmp_path / f"bad_{field}.h5"
        q.write_bytes(data)
        with h5py.File(q, "r+") as f:
            f["events"][field][100] = value
        with pytest.raises(FormatError, match=msg):
            with RecordingFile(q) as r:
                r.events()
        with pytest.raises(FormatError, match=msg):
            with RecordingFile(q) as r:
                r.event_columns()
    q = tmp_path / "bad_len.h5"
    q.write_bytes(data)
    with h5py.File(q, "r+") as f:
        f["events/x"].resize((10,))
    with pytest.raises(FormatError, match=r"events/x has shape \(10,\)"):
        RecordingFile(q)
    q = tmp_path / "bad_ver.h5"
    q.write_bytes(data)
    with h5py.File(q, "r+") as f:
        f.attrs["hybridhdr_format_version"] = "9.0"
    with pytest.raises(FormatError, match="version 9.0 is not supported"):
        RecordingFile(q)


def test_iter_event_columns_matches_events_and_checks_order(tmp_path):
    """Column chunks concatenate to the stored events; a decrease across a chunk boundary is caught."""
    from hybridhdr import Recording, SensorSize, make_events
    from hybridhdr.formats.container import RecordingFile, write_recording
    from hybridhdr.errors import FormatError
    rng = np.random.default_rng(3)
    n = 10_007
    t = np.sort(rng.integers(0, 50_000, n))
    ev = make_events(t, rng.integers(0, 20, n), rng.integers(0, 10, n), rng.choice([-1, 1], n))
    path = write_recording(Recording(ev, SensorSize(10, 20)), tmp_path / "r.h5")
    with RecordingFile(path) as f:
        chunks = list(f.iter_event_columns(1_000, t_start_us=5_000, t_end_us=45_000))
        ref = f.events(5_000, 45_000)
    assert all(len(c[0]) <= 1_000 for c in chunks)
    for k, name in enumerate(("t", "x", "y", "p")):
        got = np.concatenate([c[k] for c in chunks])
        np.testing.assert_array_equal(got, ref[name])
        assert all(c[k].flags.c_contiguous for c in chunks)
    import h5py
    with h5py.File(path, "r+") as h:  # break time order exactly at a chunk boundary
        h["events/t"][1_000] = h["events/t"][999] - 1
    with RecordingFile(path) as f, pytest.raises(FormatError, match="decreases at index 1000"):
        list(f.iter_event_columns(1_000))


def test_large_reads_through_the_parallel_inflater_equal_the_events(tmp_path):
    """Reads of >= 65536 records go through hybridhdr.formats._chunk_read (raw chunks inflated in two
    threads): the same records as written, also across chunk boundaries and windows."""
    from hybridhdr import Recording, SensorSize, make_events
    from hybridhdr.formats.container import RecordingFile, write_recording
    rng = np.random.default_rng(7)
    n = 300_001
    t = np.sort(rng.integers(0, 2_000_000, n)).astype(np.int64)
    x = rng.integers(0, 40, n).astype(np.uint16)
    y = rng.integers(0, 30, n).astype(np.uint16)
    p = np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8)
    path = write_recording(Recording(make_events(t, x, y, p), SensorSize(30, 40)), tmp_path / "r.h5")
    with RecordingFile(path) as f:
        c = f.event_columns()
        for k, a in (("t", t), ("x", x), ("y", y), ("p", p)):
            np.testing.assert_array_equal(c[k], a)
        w = f.event_columns(t_start_us=123_457, t_end_us=1_777_777)
        m = (t >= 123_457) & (t < 1_777_777)
        np.testing.assert_array_equal(w["t"], t[m])
        np.testing.assert_array_equal(w["x"], x[m])


def random_imu(seed=0, n=500, t0=10**12):
    rng = np.random.default_rng(seed)
    imu = hh.empty_imu(n)
    imu["t"] = np.sort(rng.integers(t0, t0 + 3_000_000, n))
    for name, _, _ in hh.events.IMU_FIELDS:
        imu[name] = rng.normal(0, 50, n).astype(np.float32)
    imu["mag_x_ut"][::7] = np.nan  # NaN: a quantity not measured, kept as it is
    return imu


def test_imu_round_trip_exact_and_windowed(tmp_path):
    import dataclasses
    rec = random_recording(5, n=3000)
    imu = random_imu(5)
    rec = dataclasses.replace(rec, imu=imu)
    p = tmp_path / "imu.h5"
    with RecordingWriter(p, rec.sensor_size, rec.metadata) as w:  # streamed in three batches
        w.write_events(rec.events)
        for part in np.array_split(imu, 3):
            w.write_imu(part)
    back = read_recording(p)
    assert back.imu.dtype == hh.IMU_DTYPE and len(back.imu) == len(imu)
    assert back.imu.tobytes() == imu.tobytes()  # every field bit for bit, NaN included
    with h5py.File(p) as f:
        assert f["imu/gyro_x_deg_s"].attrs["unit"] == "deg/s" and f["imu/accel_z_g"].dtype == np.float32
    t0, t1 = int(imu["t"][100]), int(imu["t"][400])
    win = read_recording(p, t0, t1)
    assert win.imu.tobytes() == imu[100:400].tobytes()
    assert rec.slice_time(t0, t1).imu.tobytes() == imu[100:400].tobytes()
    p2 = write_recording(rec, tmp_path / "whole.h5")
    assert read_recording(p2).imu.tobytes() == imu.tobytes()
    with RecordingWriter(tmp_path / "order.h5", rec.sensor_size) as w:
        w.write_imu(imu[200:])
        with pytest.raises(ValueError, match="IMU samples must be appended in time order"):
            w.write_imu(imu[:10])


def test_file_without_imu_group_reads_with_no_imu(tmp_path):
    """Containers written before the /imu group existed (format 2.0) still read, with no IMU samples."""
    rec = random_recording(6, n=1000)
    p = write_recording(rec, tmp_path / "old.h5")
    with h5py.File(p, "r+") as f:
        del f["imu"]
        f.attrs["hybridhdr_format_version"] = "2.0"
    back = read_recording(p)
    assert back.imu.dtype == hh.IMU_DTYPE and len(back.imu) == 0
    assert np.array_equal(back.events, rec.events) and np.array_equal(back.triggers, rec.triggers)
    assert len(hh.Recording().imu) == 0  # the model's default


def test_corrupt_imu_tables_are_format_errors(tmp_path):
    import dataclasses
    rec = dataclasses.replace(random_recording(7, n=1000), imu=random_imu(7, n=50))
    data = write_recording(rec, tmp_path / "r.h5").read_bytes()

    def variant(name, edit):
        q = tmp_path / f"{name}.h5"
        q.write_bytes(data)
        with h5py.File(q, "r+") as f:
            edit(f)
        return q

    def declared_huge(f):  # a header declaring 10^12 samples with (almost) nothing stored
        del f["imu"]
        g = f.create_group("imu")
        for name, dt, _ in (("t", "<i8", 0),) + tuple((n, "<f4", 0) for n, _, _ in hh.events.IMU_FIELDS):
            g.create_dataset(name, shape=(10**12,), dtype=dt, chunks=(1 << 16,))

    cases = [
        ("short", lambda f: f["imu/gyro_y_deg_s"].resize((10,)), r"imu/gyro_y_deg_s.*\(50,\)|shape"),
        ("missing", lambda f: f["imu"].__delitem__("temperature_c"), "missing dataset 'temperature_c'"),
        ("unsorted", lambda f: f["imu/t"].__setitem__(20, 0), "non-decreasing"),
        ("inf", lambda f: f["imu/accel_x_g"].__setitem__(3, np.inf), "must be finite"),
        ("huge", declared_huge, "chunks|limit|declares"),
    ]
    for name, edit, msg in cases:
        q = variant(name, edit)
        with RecordingFile(q) as r:
            with pytest.raises(FormatError, match=msg):
                r.read_imu()
