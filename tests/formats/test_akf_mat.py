"""AKF .mat reader (v7.3 and v5) and v7.3 writer."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridhdr as hh
from hybridhdr.formats import akf_mat as M
from hybridhdr.errors import FormatError

h5py = pytest.importorskip("h5py")
scipy_io = pytest.importorskip("scipy.io")

SS = hh.SensorSize(18, 24)


def _events(n, seed=0):
    rng = np.random.default_rng(seed)
    return hh.make_events(np.sort(rng.integers(0, 1_000_000, n)), rng.integers(0, SS.width, n),
                          rng.integers(0, SS.height, n), rng.integers(0, 2, n))


def _frames(k=3, seed=1):
    rng = np.random.default_rng(seed)
    ts = np.sort(rng.integers(0, 900_000, k))
    return hh.Frames(rng.integers(0, 256, (k, SS.height, SS.width), dtype=np.uint8), ts,
                     ts + rng.integers(0, 20_001, k))


def write_v5(path, ev, frames=None, extra=None, one_based=True):
    d = {"events": np.c_[ev["t"], ev["x"] + one_based, ev["y"] + one_based, ev["p"] > 0].astype(np.float64),
         "im_height": float(SS.height), "im_width": float(SS.width)}
    if frames is not None:
        d["image"] = np.transpose(frames.images, (1, 2, 0))
        ex = (frames.t_end_us - frames.t_start_us).astype(float)
        d["time_image"] = (frames.t_start_us + ex / 2).reshape(-1, 1)
        d["exposure"] = ex.reshape(-1, 1)
    d.update(extra or {})
    scipy_io.savemat(path, d)
    return path


# ------------------------------------------------------------------------------------------------
# round trips
# ------------------------------------------------------------------------------------------------

@st.composite
def streams(draw, max_n=40):
    n = draw(st.integers(0, max_n))
    base = draw(st.sampled_from([0, 1, 1 << 31, (1 << 52) - 100]))
    dts = draw(st.lists(st.integers(0, 2), min_size=n, max_size=n))
    xs = draw(st.lists(st.sampled_from([0, SS.width - 1]) | st.integers(0, SS.width - 1), min_size=n, max_size=n))
    ys = draw(st.lists(st.sampled_from([0, SS.height - 1]) | st.integers(0, SS.height - 1), min_size=n, max_size=n))
    ps = draw(st.lists(st.sampled_from([-1, 1]), min_size=n, max_size=n))
    return hh.make_events(base + np.cumsum(np.asarray(dts, np.int64)), xs, ys, ps)


@settings(max_examples=30, deadline=None)
@given(ev=streams(), split=st.integers(0, 40), with_frames=st.booleans())
def test_v73_roundtrip(tmp_path_factory, ev, split, with_frames):
    path = tmp_path_factory.mktemp("akf") / "r.mat"
    fr = _frames(4) if with_frames else None
    with hh.open_writer(path, sensor_size=SS) as w:
        assert w.format_name == "akf_mat"
        w.write_events(ev[:split])
        w.write_events(ev[split:])
        if fr is not None:
            w.write_frames(fr.select(slice(0, 2)))
            w.write_frames(fr.select(slice(2, 4)))
    assert hh.detect_format(path) == "akf_mat"
    rec = hh.read(path)
    assert rec.sensor_size == SS
    np.testing.assert_array_equal(rec.events, ev)
    if fr is None:
        assert rec.frames is None
    else:
        np.testing.assert_array_equal(rec.frames.images, fr.images)
        np.testing.assert_array_equal(rec.frames.t_start_us, fr.t_start_us)
        np.testing.assert_array_equal(rec.frames.t_end_us, fr.t_end_us)


def test_v73_file_layout(tmp_path):
    ev = _events(50)
    fr = _frames(2)
    md = hh.Metadata(provenance={"akf_mat": {"ct": 0.12, "f_Q": list(np.linspace(0, 1, 256))}})
    path = tmp_path / "a.mat"
    hh.write(hh.Recording(ev, SS, fr, metadata=md), path)
    head = path.read_bytes()[:512]
    assert head.startswith(b"MATLAB 7.3 MAT-file")
    assert head[124:126] == b"\x00\x02" and head[126:128] == b"IM"
    with h5py.File(path, "r") as f:
        assert f.userblock_size == 512
        assert f["events"].shape == (4, 50)  # MATLAB N x 4, reversed by HDF5
        assert f["image"].shape == (2, SS.width, SS.height)
        for k in f:
            assert f[k].attrs["MATLAB_class"] in (b"double", b"uint8")
        np.testing.assert_array_equal(f["events"][1], ev["x"] + 1.0)  # 1-based
        np.testing.assert_array_equal(f["events"][3], (ev["p"] > 0).astype(float))
    rec = hh.read(path)
    akf = rec.metadata.provenance["akf_mat"]
    assert akf["ct"] == pytest.approx(0.12) and len(akf["f_Q"]) == 256
    # options override provenance
    path2 = tmp_path / "b.mat"
    hh.write(hh.Recording(ev, SS, metadata=md), path2, ct=0.3)
    assert hh.read(path2).metadata.provenance["akf_mat"]["ct"] == pytest.approx(0.3)


def test_v73_empty(tmp_path):
    path = tmp_path / "e.mat"
    hh.write(hh.Recording(hh.empty_events(), SS), path)
    with h5py.File(path, "r") as f:
        assert f["events"].attrs["MATLAB_empty"] == 1
    rec = hh.read(path)
    assert rec.n_events == 0 and rec.sensor_size == SS


def test_writer_rejects_colour_frames(tmp_path):
    fr = hh.Frames(np.zeros((1, SS.height, SS.width, 3), np.uint8), [0], [0])
    with pytest.raises(ValueError, match="grey"):
        hh.write(hh.Recording(_events(3), SS, fr), tmp_path / "c.mat")
    assert not (tmp_path / "c.mat").exists() and not (tmp_path / "c.mat.partial").exists()


def test_v5(tmp_path):
    ev = _events(300)
    fr = _frames(3)
    hdr = np.random.default_rng(2).random((SS.height, SS.width, 3, 3))
    path = write_v5(tmp_path / "v5.mat", ev, fr, extra={"ct": 0.2, "f_Q": np.arange(256.0), "HDR_mat": hdr})
    assert hh.detect_format(path) == "akf_mat"
    with hh.open_reader(path) as r:
        assert r.version == "5" and r.sensor_size == SS
        rec = r.read()
        h = r.read_hdr()
    np.testing.assert_array_equal(rec.events, ev)
    np.testing.assert_array_equal(rec.frames.images, fr.images)
    np.testing.assert_array_equal(rec.frames.t_start_us, fr.t_start_us)
    np.testing.assert_array_equal(rec.frames.t_end_us, fr.t_end_us)
    assert rec.metadata.provenance["akf_mat"]["f_Q"][255] == 255.0
    assert h.images.shape == (3, SS.height, SS.width, 3) and h.images.dtype == np.float32
    np.testing.assert_allclose(h.images[1], hdr[..., 1].astype(np.float32))
    np.testing.assert_array_equal(h.t_us, np.rint((fr.t_start_us + fr.t_end_us) / 2))


def test_exposure_rounding_and_missing(tmp_path):
    # time_image 1000 (mid), exposure 5: start = rint(997.5) = 998 (half to even), end = 1003
    ev = _events(5)
    extra = {"image": np.zeros((SS.height, SS.width, 1), np.uint8), "time_image": 1000.0, "exposure": 5.0}
    path = write_v5(tmp_path / "r.mat", ev, extra=extra)
    fr = hh.read(path).frames
    assert fr.t_start_us.tolist() == [998] and fr.t_end_us.tolist() == [1003]
    extra.pop("exposure")
    path = write_v5(tmp_path / "n.mat", ev, extra=extra)
    fr = hh.read(path).frames
    assert fr.t_start_us.tolist() == [1000] and fr.t_end_us.tolist() == [1000]


def test_size_from_image_or_inferred(tmp_path):
    ev = _events(40)
    path = tmp_path / "s.mat"
    scipy_io.savemat(path, {"events": np.c_[ev["t"], ev["x"] + 1, ev["y"] + 1, ev["p"]].astype(float)})
    r = hh.open_reader(path)
    assert r.sensor_size == hh.SensorSize(int(ev["y"].max()) + 1, int(ev["x"].max()) + 1)
    assert r.metadata.provenance["sensor_size_source"] == "inferred"
    np.testing.assert_array_equal(r.read().events, ev)  # p = -1 in the file is OFF


# ------------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------------

def test_v5_bad(tmp_path):
    ev = _events(20)
    p = tmp_path / "b.mat"
    scipy_io.savemat(p, {"foo": 1.0})
    with pytest.raises(FormatError, match="no 'events' variable"):
        hh.read(p)
    scipy_io.savemat(p, {"events": np.zeros((5, 3))})
    with pytest.raises(FormatError, match="N x 4"):
        hh.read(p)
    write_v5(p, ev, one_based=False)  # 0-based coordinates: x = 0 is invalid
    with pytest.raises(FormatError, match="1-based [xy] = 0.0 is not in"):
        hh.read(p)
    bad = ev.copy()
    bad["t"][10] = 0
    bad["t"][:10] = 5
    write_v5(p, bad)
    with pytest.raises(FormatError, match="event 10: timestamps must be non-decreasing"):
        hh.read(p)
    write_v5(p, ev, extra={"im_width": 3.0})
    with pytest.raises(FormatError, match="not in 1..3"):
        hh.read(p)
    write_v5(p, ev, extra={"im_width": 2.5})
    with pytest.raises(FormatError, match="im_width must be one whole number"):
        hh.read(p)
    write_v5(p, ev, extra={"image": np.zeros((SS.height, SS.width, 2), np.uint8)})
    with pytest.raises(FormatError, match="no time_image"):
        hh.read(p)
    write_v5(p, ev, extra={"image": np.zeros((SS.height, SS.width, 2), np.uint8), "time_image": [1.0, 2.0, 3.0]})
    with pytest.raises(FormatError, match="time_image must hold 2"):
        hh.read(p)
    arr = np.c_[ev["t"], ev["x"] + 1, ev["y"] + 1, ev["p"]].astype(float)
    arr[3, 0] = np.inf
    scipy_io.savemat(p, {"events": arr, "im_height": 18.0, "im_width": 24.0})
    with pytest.raises(FormatError, match="event 3: non-finite"):
        hh.read(p)


def test_v73_bad(tmp_path):
    ev = _events(30)
    p = tmp_path / "b.mat"
    hh.write(hh.Recording(ev, SS), p)
    with h5py.File(p, "a") as f:
        del f["events"]
        f["events"] = np.zeros((3, 30))
    with pytest.raises(FormatError, match="N x 4"):
        hh.read(p)
    with h5py.File(p, "a") as f:
        del f["events"]
        f.create_group("events")
    with pytest.raises(FormatError, match="must be a numeric array"):
        hh.read(p)
    data = p.read_bytes()
    p.write_bytes(data[:700])
    with pytest.raises(FormatError, match="corrupt or truncated"):
        hh.read(p)
    p.write_bytes(b"MATLAB 5.0 MAT-file" + b"\x00" * 20)
    with pytest.raises(FormatError, match="truncated MAT-file header"):
        hh.read(p)
    p.write_bytes(b"something else")
    with pytest.raises(FormatError, match="not a MATLAB"):
        hh.read(p, "akf_mat")


def test_sniff():
    assert M.sniff(None, b"MATLAB 7.3 MAT-file, Platform") == "akf_mat"
    assert M.sniff(None, b"MATLAB 5.0 MAT-file, Platform") == "akf_mat"
    assert M.sniff(None, b"\x89HDF\r\n\x1a\n") is None
    assert M.sniff(None, b"") is None
    assert M.matlab_v73_header("x")[:19] == b"MATLAB 7.3 MAT-file" and len(M.matlab_v73_header()) == 128


@pytest.mark.parametrize("compressed", [False, True])
def test_read_mat5_matches_scipy(tmp_path, compressed):
    rng = np.random.default_rng(9)
    d = {"a": rng.random((3, 5)), "b": rng.integers(0, 255, (4, 2, 3), dtype=np.uint8),
         "c": rng.integers(-5, 5, (2, 7)).astype(np.int16), "s": 2.5, "e": np.zeros((0, 4)),
         "f": rng.random(6).astype(np.float32), "txt": "hello", "cell": np.array([1, "x"], dtype=object)}
    p = tmp_path / "m.mat"
    scipy_io.savemat(p, d, do_compression=compressed)
    ref = scipy_io.loadmat(p)
    got = M.read_mat5(p)
    for k in ("a", "b", "c", "s", "e", "f"):
        assert got[k].dtype == ref[k].dtype and got[k].shape == ref[k].shape, k
        np.testing.assert_array_equal(got[k], ref[k])
    assert got["txt"].dtype == object and got["cell"].dtype == object
    assert set(M.read_mat5(p, ["a", "zz"])) == {"a"}


def write_authors_hdr_mat(path, ev, frames, hdr_rgb, *, matlab_header=True):
    """A file with the layout of the authors' HDR/AHDR sequences (MATLAB v7.3: axes reversed in
    HDF5): events N x 4 (1-based x, y), image H x W x K uint8, time_image, exposure, f_Q and
    HDR_mat H x W x 3 x K (double, 0 = unregistered)."""
    kw = {"userblock_size": 512} if matlab_header else {}
    with h5py.File(path, "w", **kw) as f:
        f["events"] = np.stack([ev["t"].astype(float), ev["x"] + 1.0, ev["y"] + 1.0, (ev["p"] > 0) * 1.0])
        f["image"] = np.transpose(frames.images, (0, 2, 1))                   # MATLAB H x W x K
        f["time_image"] = ((frames.t_start_us + frames.t_end_us) / 2.0)[:, None]
        f["exposure"] = (frames.t_end_us - frames.t_start_us).astype(float)[:, None]
        f["f_Q"] = np.full((1, 256), 7e5)
        f["HDR_mat"] = np.transpose(hdr_rgb, (0, 3, 2, 1))                  # MATLAB H x W x 3 x K
        for k in f:
            f[k].attrs["MATLAB_class"] = np.bytes_(b"uint8" if k == "image" else b"double")
    if matlab_header:
        with open(path, "r+b") as fh:
            fh.write(M.matlab_v73_header())
    return path


@pytest.mark.parametrize("matlab_header", [True, False])
def test_authors_hdr_layout_reads_as_recording_with_references(tmp_path, matlab_header):
    ev = _events(50)
    fr = _frames(3)
    hdr = np.random.default_rng(3).random((3, SS.height, SS.width, 3)) * 400.0
    hdr[:, :2] = 0.0                                            # unregistered rows
    p = write_authors_hdr_mat(tmp_path / "seq.mat", ev, fr, hdr, matlab_header=matlab_header)
    from hybridhdr.formats import detect_format
    assert detect_format(p) == "akf_mat"
    rec = hh.read(p)
    assert rec.hdr is not None and rec.hdr.images.shape == (3, SS.height, SS.width, 3)
    np.testing.assert_allclose(rec.hdr.images, hdr.astype(np.float32))
    assert (rec.hdr.images[:, :2] == 0).all()                   # kept as stored: 0 = unregistered
    np.testing.assert_array_equal(rec.hdr.t_us, np.rint((fr.t_start_us + fr.t_end_us) / 2).astype(np.int64))
    np.testing.assert_array_equal(rec.frames.images, fr.images)
    assert len(rec.events) == 50
    part = hh.read(p, t_start_us=int(rec.hdr.t_us[1]))
    assert len(part.hdr) == 2 and part.hdr.t_us[0] == rec.hdr.t_us[1]
