"""DSEC and Monash HDF5 readers on small synthetic files written in the documented layouts."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.formats import hdf5_layouts as L
from hybridhdr.errors import FormatError

h5py = pytest.importorskip("h5py")

T_OFFSET = 1_600_000_000_000


def _cols(n=3000, w=640, h=480, seed=0):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 2_000_000, n)).astype(np.uint32)
    t[5:9] = t[5]  # equal timestamps
    x = rng.integers(0, w, n).astype(np.uint16)
    y = rng.integers(0, h, n).astype(np.uint16)
    x[:2], y[:2] = (0, w - 1), (h - 1, 0)
    p = rng.integers(0, 2, n).astype(np.uint8)
    return t, x, y, p


def write_dsec(path, t, x, y, p, t_offset=T_OFFSET, compress=False, ms=True):
    kw = {}
    if compress:
        hdf5plugin = pytest.importorskip("hdf5plugin")
        kw = dict(hdf5plugin.Blosc(cname="zstd", clevel=5))
    with h5py.File(path, "w") as f:
        for k, v in dict(x=x, y=y, t=t, p=p).items():
            f.create_dataset(f"events/{k}", data=v, chunks=True if len(v) else None, **kw)
        if ms:
            # t[ms_to_idx[m]] >= 1000 m > t[ms_to_idx[m] - 1]
            f["ms_to_idx"] = np.searchsorted(t, np.arange(int(t[-1]) // 1000 + 2) * 1000).astype(np.uint64) \
                if len(t) else np.zeros(1, np.uint64)
        if t_offset is not None:
            f["t_offset"] = np.int64(t_offset)
    return path


def write_monash(path, t, x, y, p, res=(480, 640), images=True, num_events=None):
    with h5py.File(path, "w") as f:
        f["events/xs"] = x.astype(np.int16)
        f["events/ys"] = y.astype(np.int16)
        f["events/ts"] = t.astype(np.float64) / 1e6
        f["events/ps"] = p.astype(bool)
        if res is not None:
            f.attrs["sensor_resolution"] = np.asarray(res)
        f.attrs["num_events"] = len(t) if num_events is None else num_events
        if images:
            h, w = (480, 640) if res is None else res
            for k in range(3):
                d = f.create_dataset(f"images/image{k:09d}", data=np.full((h, w), 10 * k, np.uint8))
                d.attrs["timestamp"] = 0.25 * k
                d.attrs["event_idx"] = int(np.searchsorted(t, 250_000 * k))
    return path


def _expected(t, x, y, p, off=0):
    return hh.make_events(t.astype(np.int64) + off, x, y, p)


# ------------------------------------------------------------------------------------------------
# DSEC
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("compress", [False, True])
def test_dsec_roundtrip(tmp_path, compress):
    t, x, y, p = _cols()
    path = write_dsec(tmp_path / "events.h5", t, x, y, p, compress=compress)
    assert hh.detect_format(path) == "dsec"
    with hh.open_reader(path) as r:
        assert r.sensor_size == hh.SensorSize(480, 640)
        assert r.metadata.provenance["t_offset_us"] == T_OFFSET
        assert r.metadata.provenance["t_offset_added"] is True
        chunks = [c.events for c in r.iter_chunks(700)]
    assert max(len(c) for c in chunks) == 700
    np.testing.assert_array_equal(np.concatenate(chunks), _expected(t, x, y, p, T_OFFSET))
    raw = hh.read(path, add_t_offset=False).events
    np.testing.assert_array_equal(raw, _expected(t, x, y, p))


def test_dsec_without_t_offset_and_window(tmp_path):
    t, x, y, p = _cols(500)
    path = write_dsec(tmp_path / "e.h5", t, x, y, p, t_offset=None)
    assert hh.detect_format(path) == "dsec"
    rec = hh.read(path, t_start_us=500_000, t_end_us=1_000_000)
    exp = hh.slice_time(_expected(t, x, y, p), 500_000, 1_000_000)
    np.testing.assert_array_equal(rec.events, exp)


def test_dsec_empty(tmp_path):
    z = np.zeros(0, np.uint32)
    path = write_dsec(tmp_path / "e.h5", z, z.astype(np.uint16), z.astype(np.uint16), z.astype(np.uint8))
    assert hh.read(path).n_events == 0


def test_container_like_file_not_sniffed_as_dsec(tmp_path):
    path = tmp_path / "c.h5"
    with h5py.File(path, "w") as f:
        f.attrs["hybridhdr_format_version"] = "1.0"
        for k in "xytp":
            f[f"events/{k}"] = np.zeros(1, np.int64)
        f["ms_to_idx"] = np.zeros(1, np.int64)
    assert L.sniff(path, path.read_bytes()[:4096]) is None
    plain = tmp_path / "plain.h5"
    with h5py.File(plain, "w") as f:
        f["data"] = np.zeros(3)
    assert L.sniff(plain, plain.read_bytes()[:4096]) is None
    assert L.sniff(plain, b"not hdf5") is None
    trunc = tmp_path / "trunc.h5"
    trunc.write_bytes(plain.read_bytes()[:600])
    assert L.sniff(trunc, trunc.read_bytes()) is None


def _mutate(path, fn):
    with h5py.File(path, "a") as f:
        fn(f)
    return path


@pytest.mark.parametrize("mutation, match", [
    (lambda f: f.__delitem__("events/p"), "missing dataset events/p"),
    (lambda f: (f.__delitem__("events/y"), f.create_dataset("events/y", data=np.zeros(5, np.uint16))),
     "has 5 entries but the event count is 400"),
    (lambda f: (f.__delitem__("events/x"), f.create_dataset("events/x", data=np.zeros((400, 2), np.uint16))),
     "must be 1-D"),
    (lambda f: f["events/t"].__setitem__(300, 0), "event 300: timestamps must be non-decreasing"),
    (lambda f: f["events/x"].__setitem__(123, 640), "event 123: x = 640 is outside the sensor width 640"),
    (lambda f: f["events/p"].__setitem__(7, 3), "event 7: polarity 3 is not 0/1"),
    (lambda f: (f.__delitem__("t_offset"), f.create_dataset("t_offset", data=np.array([1.0, 2.0]))),
     "/t_offset must be one number"),
    (lambda f: (f.__delitem__("events/t"), f.create_dataset("events/t", data=np.array(["a"] * 400, "S1"))),
     "must be numeric"),
])
def test_dsec_bad(tmp_path, mutation, match):
    t, x, y, p = _cols(400)
    path = _mutate(write_dsec(tmp_path / "b.h5", t, x, y, p), mutation)
    with pytest.raises(FormatError, match=match) as ei:
        hh.read(path, "dsec")
    assert str(path) in str(ei.value)


def test_dsec_unsorted_across_chunks(tmp_path):
    t, x, y, p = _cols(400)
    t[200] = t[199] - 1  # a decrease exactly at the chunk boundary
    path = write_dsec(tmp_path / "u.h5", t, x, y, p)
    with pytest.raises(FormatError, match="event 200: timestamps must be non-decreasing"):
        list(hh.open_reader(path).iter_chunks(200))


def test_truncated_hdf5(tmp_path):
    t, x, y, p = _cols(2000)
    path = write_dsec(tmp_path / "t.h5", t, x, y, p)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="cannot open as HDF5"):
        hh.read(path, "dsec")


def test_missing_hdf5plugin_message(tmp_path):
    pytest.importorskip("hdf5plugin")
    t, x, y, p = _cols(200)
    path = write_dsec(tmp_path / "z.h5", t, x, y, p, compress=True)
    code = ("import sys; sys.modules['hdf5plugin'] = None\n"
            "import hybridhdr as hh\n"
            "try:\n    hh.read(sys.argv[1], 'dsec')\n"
            "except hh.FormatError as e:\n    print('FormatError:', e)\n")
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=60)
    assert "FormatError:" in out.stdout, out.stderr
    assert "pip install hdf5plugin" in out.stdout and "Blosc" in out.stdout


# ------------------------------------------------------------------------------------------------
# Monash
# ------------------------------------------------------------------------------------------------

def test_monash_roundtrip(tmp_path):
    t, x, y, p = _cols(2500, seed=3)
    path = write_monash(tmp_path / "m.h5", t, x, y, p)
    assert hh.detect_format(path) == "monash"
    with hh.open_reader(path) as r:
        assert r.sensor_size == hh.SensorSize(480, 640)
        chunks = [c.events for c in r.iter_chunks(1000)]
        fr = r.read_frames()
    np.testing.assert_array_equal(np.concatenate(chunks), _expected(t, x, y, p))
    assert fr.images.shape == (3, 480, 640) and fr.images.dtype == np.uint8
    np.testing.assert_array_equal(fr.t_start_us, [0, 250_000, 500_000])
    np.testing.assert_array_equal(fr.t_end_us, fr.t_start_us)
    np.testing.assert_array_equal(fr.images[:, 0, 0], [0, 10, 20])


def test_monash_resolution_order(tmp_path):
    t, x, y, p = _cols(100, w=64, h=32)
    # (height, width) as event_utils writes it
    path = write_monash(tmp_path / "a.h5", t, x, y, p, res=(32, 64))
    assert hh.open_reader(path).sensor_size == hh.SensorSize(32, 64)
    # a file with (width, height) is recognised from the frame shape
    path2 = tmp_path / "b.h5"
    write_monash(path2, t, x, y, p, res=(32, 64))
    with h5py.File(path2, "a") as f:
        f.attrs["sensor_resolution"] = np.array([64, 32])
    r = hh.open_reader(path2)
    assert r.sensor_size == hh.SensorSize(32, 64)
    assert "transposed" in r.metadata.provenance["sensor_size_note"]
    # no attribute, no images: inferred
    path3 = write_monash(tmp_path / "c.h5", t, x, y, p, res=None, images=False)
    r = hh.open_reader(path3)
    assert r.sensor_size == hh.SensorSize(int(y.max()) + 1, int(x.max()) + 1)
    assert r.metadata.provenance["sensor_size_source"] == "inferred"
    assert r.read_frames() is None


@pytest.mark.parametrize("mutation, match", [
    (lambda f: f["events/xs"].__setitem__(10, -3), "event 10: negative x = -3"),
    (lambda f: f["events/ts"].__setitem__(50, np.nan), "event 50: timestamp nan s is not finite"),
    (lambda f: f["events/ts"].__setitem__(50, 0.0), "event 50: timestamps must be non-decreasing"),
    (lambda f: f["events/ys"].__setitem__(0, 480), "event 0: y = 480 is outside the sensor height 480"),
    (lambda f: f["images/image000000001"].attrs.__delitem__("timestamp"), "has no 'timestamp' attribute"),
    (lambda f: f.attrs.__setitem__("num_events", 5), "num_events = 5"),
    (lambda f: f.attrs.__setitem__("sensor_resolution", np.array([0, 5])), "sensor_resolution must be"),
])
def test_monash_bad(tmp_path, mutation, match):
    t, x, y, p = _cols(100, seed=4)
    t = t + 1  # t[50] = 0 is then a decrease
    path = _mutate(write_monash(tmp_path / "m.h5", t, x, y, p), mutation)
    with pytest.raises(FormatError, match=match):
        hh.read(path, "monash")


def test_monash_image_shape_mismatch(tmp_path):
    t, x, y, p = _cols(50)
    path = write_monash(tmp_path / "m.h5", t, x, y, p)
    with h5py.File(path, "a") as f:
        del f["images/image000000002"]
        d = f.create_dataset("images/image000000002", data=np.zeros((10, 10), np.uint8))
        d.attrs["timestamp"] = 1.0
    with pytest.raises(FormatError, match="unlike the first image"):
        hh.read(path, "monash")
