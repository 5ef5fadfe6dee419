"""The container's sparse time index (format 2.0) and reading format 1.0 files (dense index)."""

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridhdr as hh
import hybridhdr.formats.container as container
from hybridhdr._util.limits import LimitExceeded, allow_huge
from hybridhdr.formats.container import RecordingFile, read_recording, write_recording
from hybridhdr.errors import FormatError


def _events(t, ss=(4, 5)):
    t = np.asarray(t, dtype=np.int64)
    n = len(t)
    return hh.make_events(t, np.arange(n) % ss[1], np.arange(n) % ss[0], np.where(np.arange(n) % 2, 1, -1))


def write_v10(path, events, ss=(4, 5)):
    """A format 1.0 file exactly as hybridhdr 1.0 wrote it (dense millisecond index)."""
    t = events["t"]
    with h5py.File(path, "w") as f:
        f.attrs["hybridhdr_format_version"] = "1.0"
        f.attrs["sensor_height"], f.attrs["sensor_width"] = ss
        f.attrs["metadata_json"] = "{}"
        f.attrs["n_events"] = len(t)
        g = f.create_group("events")
        for name in ("t", "x", "y", "p"):
            g[name] = events[name]
        origin = (int(t[0]) // 1000) * 1000 if len(t) else 0
        if len(t):
            m = (int(t[-1]) - origin) // 1000
            idx = np.searchsorted(t, origin + 1000 * np.arange(m + 1), side="left")
            idx = np.concatenate([idx, [len(t)]])
        else:
            idx = np.zeros(0, np.int64)
        g["ms_to_idx"] = idx.astype(np.int64)
        g["ms_to_idx"].attrs["origin_us"] = origin


_T = np.sort(np.concatenate([np.random.default_rng(0).integers(-3_000_000, 3_000_000, 3000),
                             np.full(500, 1234_567), np.arange(0, 40_000, 7)]))


@pytest.mark.parametrize("version", ["1.0", "2.0"])
@settings(max_examples=60, deadline=None)
@given(a=st.integers(-3_500_000, 3_500_000), b=st.integers(-3_500_000, 3_500_000))
def test_windows_equal_slices(tmp_path_factory, version, a, b):
    p = tmp_path_factory.getbasetemp() / f"idx_{version}.h5"
    ev = _events(_T)
    if not p.exists():
        if version == "1.0":
            write_v10(p, ev)
        else:
            old = container.INDEX_STRIDE
            container.INDEX_STRIDE = 3
            try:
                write_recording(hh.Recording(ev, (4, 5)), p, buffer_events=333)
            finally:
                container.INDEX_STRIDE = old
    t0, t1 = sorted((a, b))
    with RecordingFile(p) as r:
        assert r.format_version == (version if version == "1.0" else container.FORMAT_VERSION)
        i0, i1 = r.index_range(t0, t1)  # the index itself, whatever the window
        assert np.array_equal(ev[i0:i1], hh.slice_time(ev, t0, t1))
        if t1 <= _T[0] or t0 > _T[-1]:  # wholly outside the data: an error naming the span, not empty
            from hybridhdr.errors import WindowOutsideDataError
            with pytest.raises(WindowOutsideDataError, match="spans"):
                r.events(t0, t1)
        else:
            assert np.array_equal(r.events(t0, t1), hh.slice_time(ev, t0, t1))
        assert r.index_range(None, t0)[1] == np.searchsorted(_T, t0)


def test_two_events_a_day_apart_make_a_small_file(tmp_path):
    ev = _events([0, int(1.16 * 86400e6)])
    p = write_recording(hh.Recording(ev, (4, 5)), tmp_path / "r.h5")
    assert p.stat().st_size < 1 << 20, p.stat().st_size
    with h5py.File(p) as f:
        assert f["events/index_ms"].shape == (1,)
    assert np.array_equal(read_recording(p).events, ev)


def test_int64_extreme_timestamps(tmp_path):
    big = np.iinfo(np.int64).max
    ev = _events([-big - 1, -big, -5, 0, big - 1, big])
    p = write_recording(hh.Recording(ev, (4, 5)), tmp_path / "r.h5")
    assert p.stat().st_size < 1 << 20
    with RecordingFile(p) as r:
        assert np.array_equal(r.events(), ev)
        assert np.array_equal(r.events(-5, big), ev[2:5])
        assert np.array_equal(r.events(big, None), ev[5:])


def test_v10_index_is_read_lazily(tmp_path):
    # a 1.0 file whose dense index declares 10^10 entries but stores none: refused at once
    p = tmp_path / "forged.h5"
    ev = _events([0, 5])
    write_v10(p, ev)
    with h5py.File(p, "a") as f:
        del f["events/ms_to_idx"]
        f["events"].create_dataset("ms_to_idx", shape=(10**10,), dtype="<i8", chunks=(1 << 16,))
    with pytest.raises(FormatError, match="chunks"):
        RecordingFile(p)


def test_v10_old_files_still_read(tmp_path):
    ev = _events(_T)
    write_v10(tmp_path / "old.h5", ev)
    rec = hh.read(tmp_path / "old.h5")
    assert np.array_equal(rec.events, ev)
    assert hh.detect_format(tmp_path / "old.h5") == "hybridhdr"


def test_newer_major_refused_naming_versions(tmp_path):
    p = write_recording(hh.Recording(_events([1, 2]), (4, 5)), tmp_path / "r.h5")
    with h5py.File(p, "a") as f:
        f.attrs["hybridhdr_format_version"] = "3.0"
    with pytest.raises(FormatError, match=r"3\.0 is not supported.*reads 1\.x and 2\.x"):
        RecordingFile(p)


def test_sparse_index_inconsistent_is_format_error(tmp_path):
    p = write_recording(hh.Recording(_events(np.arange(10_000)), (4, 5)), tmp_path / "r.h5")
    with h5py.File(p, "a") as f:
        f["events/index_first"][0] = 7
    with pytest.raises(FormatError, match="time index"):
        RecordingFile(p)


def test_huge_sensor_is_refused_unless_allowed(tmp_path):
    p = write_recording(hh.Recording(_events([1, 2]), (4, 5)), tmp_path / "r.h5")
    with h5py.File(p, "a") as f:
        f.attrs["sensor_height"] = 65536
        f.attrs["sensor_width"] = 65536
    with pytest.raises(LimitExceeded, match="8192"):
        RecordingFile(p)
    with allow_huge():
        with RecordingFile(p) as r:
            assert r.sensor_size == hh.SensorSize(65536, 65536)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_frames_are_errors(tmp_path, bad):
    ims = np.ones((2, 4, 5), np.float32)
    fr = hh.Frames(ims, np.array([0, 10]), np.array([5, 15]))
    p = write_recording(hh.Recording(_events([1, 2]), (4, 5), fr), tmp_path / "r.h5")
    with h5py.File(p, "a") as f:
        f["frames/images"][1, 2, 3] = bad
    with pytest.raises(FormatError, match="non-finite"):
        read_recording(p)
    ims[0, 0, 0] = bad
    with pytest.raises(FormatError, match="non-finite"):
        write_recording(hh.Recording(_events([1, 2]), (4, 5), hh.Frames(ims, [0, 10], [5, 15])), tmp_path / "w.h5")
    assert not (tmp_path / "w.h5").exists() and not (tmp_path / "w.h5.partial").exists()
