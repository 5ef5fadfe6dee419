"""ECD folder and E2VID txt/zip readers, ECD writer."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridhdr as hh
from hybridhdr.formats import text as T
from hybridhdr.errors import FormatError

SS = hh.SensorSize(180, 240)


def _events(n, ss=SS, seed=0, t0=0):
    rng = np.random.default_rng(seed)
    t = t0 + np.sort(rng.integers(0, 10_000_000, n))
    return hh.make_events(t, rng.integers(0, ss.width, n), rng.integers(0, ss.height, n), rng.integers(0, 2, n))


def _ecd_lines(ev):
    return "".join(f"{t / 1e6:.9f} {x} {y} {int(p > 0)}\n" for t, x, y, p in ev.tolist())


# ------------------------------------------------------------------------------------------------
# real sample
# ------------------------------------------------------------------------------------------------

def test_ecd_sample(shared_data):
    folder = shared_data("ecd_slider_depth")
    assert hh.detect_format(folder) == "ecd"
    assert hh.detect_format(folder / "events.txt") == "ecd"
    rec = hh.read(folder)
    ev = rec.events
    assert rec.n_events == 50_000
    assert int(ev["t"][0]) == 3811 and int(ev["t"][-1]) == 174156
    assert rec.sensor_size == SS
    assert abs((ev["p"] > 0).mean() - 0.42) < 0.005
    hh.validate_events(ev, SS)
    # first line of the file: 0.003811000 96 133 0
    assert ev[0].tolist() == (3811, 96, 133, -1)
    fr = rec.frames
    assert len(fr) == 87 and fr.images.dtype == np.uint8 and fr.shape == (180, 240)
    np.testing.assert_array_equal(fr.t_start_us[:3], [0, 38766, 77531])
    np.testing.assert_array_equal(fr.t_start_us, fr.t_end_us)
    cal = rec.metadata.calibration["event_camera"]
    assert cal["camera_matrix"][0][0] == pytest.approx(335.419462958)
    assert cal["dist_coeffs"][0] == pytest.approx(-0.138592767408)
    prov = rec.metadata.provenance
    assert prov["format"] == "ecd" and prov["sensor_size_source"] == "first frame"


def test_ecd_sample_chunks_match_read(shared_data):
    folder = shared_data("ecd_slider_depth")
    with hh.open_reader(folder) as r:
        chunks = [c.events for c in r.iter_chunks(7000)]
        whole = r.read().events
    assert all(len(c) <= 7000 for c in chunks)
    np.testing.assert_array_equal(np.concatenate(chunks), whole)


def test_ecd_small_blocks(tmp_path, monkeypatch):
    ev = _events(500, seed=3)
    p = tmp_path / "events.txt"
    p.write_text(_ecd_lines(ev))
    monkeypatch.setattr(T, "_BLOCK_BYTES", 97)  # block boundaries inside lines
    got = hh.read(p, sensor_size=SS).events
    np.testing.assert_array_equal(got, ev)


# ------------------------------------------------------------------------------------------------
# ECD writer round trips
# ------------------------------------------------------------------------------------------------

@st.composite
def event_streams(draw, ss=SS, max_n=40):
    n = draw(st.integers(0, max_n))
    base = draw(st.sampled_from([0, 3_811, 1 << 31, 1_700_000_000_123_456, (1 << 52) + 7]))
    dts = draw(st.lists(st.integers(0, 3), min_size=n, max_size=n))  # many equal timestamps
    xs = draw(st.lists(st.sampled_from([0, 1, ss.width - 1]) | st.integers(0, ss.width - 1), min_size=n, max_size=n))
    ys = draw(st.lists(st.sampled_from([0, ss.height - 1]) | st.integers(0, ss.height - 1), min_size=n, max_size=n))
    ps = draw(st.lists(st.sampled_from([-1, 1]), min_size=n, max_size=n))
    return hh.make_events(base + np.cumsum(np.asarray(dts, np.int64)), xs, ys, ps)


@settings(max_examples=30, deadline=None)
@given(ev=event_streams(), split=st.integers(0, 40))
def test_ecd_writer_roundtrip(tmp_path_factory, ev, split):
    out = tmp_path_factory.mktemp("ecd") / "rec"
    with hh.open_writer(out, "ecd", sensor_size=SS) as w:
        w.write_events(ev[:split])  # appending chunk by chunk
        w.write_events(ev[split:])
    assert not out.with_name("rec.partial").exists()
    with hh.open_reader(out, sensor_size=SS) as r:
        got = r.read().events
    np.testing.assert_array_equal(got, ev)


def test_ecd_writer_frames_roundtrip(tmp_path):
    rng = np.random.default_rng(5)
    ev = _events(300, seed=1)
    out = tmp_path / "seq"
    cases = {
        "grey8": hh.Frames(rng.integers(0, 256, (3, 180, 240), dtype=np.uint8), [0, 100, 200], [0, 100, 200]),
        "grey16": hh.Frames(rng.integers(0, 65536, (2, 180, 240), dtype=np.uint16), [10, 20], [15, 29]),
        "rgb": hh.Frames(rng.integers(0, 256, (2, 180, 240, 3), dtype=np.uint8), [10, 20], [10, 20]),
    }
    for name, fr in cases.items():
        p = out.with_name(name)
        rec = hh.Recording(ev, SS, fr)
        hh.write(rec, p, "ecd")
        back = hh.read(p)
        assert back.sensor_size == SS
        np.testing.assert_array_equal(back.events, ev)
        assert back.frames.images.dtype == fr.images.dtype
        np.testing.assert_array_equal(back.frames.images, fr.images)
        np.testing.assert_array_equal(back.frames.t_start_us, fr.t_start_us)
        np.testing.assert_array_equal(back.frames.t_end_us, fr.t_end_us)
        assert (p / "frame_exposures.txt").exists() == (name == "grey16")
        lines = (p / "images.txt").read_text().splitlines()
        assert lines[0].split()[1] == "images/frame_00000000.png"


def test_ecd_writer_line_format(tmp_path):
    ev = hh.make_events([3811, 1_000_000_000_123], [96, 0], [133, 179], [-1, 1])
    p = tmp_path / "o"
    hh.write(hh.Recording(ev, SS), p, "ecd")
    assert (p / "events.txt").read_text() == "0.003811000 96 133 0\n1000000.000123000 0 179 1\n"


def test_ecd_writer_refuses_nonempty_target(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("data")
    with pytest.raises(FileExistsError):
        hh.open_writer(tmp_path / "x", "ecd", sensor_size=SS)


def test_ecd_writer_abort_leaves_nothing(tmp_path):
    p = tmp_path / "rec"
    with pytest.raises(RuntimeError):
        with hh.open_writer(p, "ecd", sensor_size=SS) as w:
            w.write_events(_events(10))
            raise RuntimeError("boom")
    assert not p.exists() and not p.with_name("rec.partial").exists()


def test_ecd_writer_rejects_float_frames(tmp_path):
    fr = hh.Frames(np.zeros((1, 180, 240), np.float32), [0], [0])
    with pytest.raises(ValueError, match="uint8"):
        hh.write(hh.Recording(_events(3), SS, fr), tmp_path / "f", "ecd")


def test_ecd_events_only_infers_size(tmp_path):
    ev = hh.make_events([1, 2], [9, 3], [4, 7], [1, 0])
    d = tmp_path / "d"
    d.mkdir()
    (d / "events.txt").write_text(_ecd_lines(ev))
    r = hh.open_reader(d)
    assert r.sensor_size == hh.SensorSize(8, 10)
    assert r.metadata.provenance["sensor_size_source"] == "inferred"
    assert "max coordinate" in r.metadata.provenance["sensor_size_note"]
    assert r.read_frames() is None


def test_parse_seconds_exact():
    got = T.parse_seconds_exact([b"1700000000.123456", b"0.0000005", b"0.0000004999", b"-1.5", b"12", b"1e-3"])
    assert got.tolist() == [1_700_000_000_123_456, 1, 0, -1_500_000, 12_000_000, 1000]


# ------------------------------------------------------------------------------------------------
# E2VID
# ------------------------------------------------------------------------------------------------

def _e2vid_text(ev, w=240, h=180):
    return f"{w} {h}\n" + _ecd_lines(ev)


def test_e2vid_txt_and_zip(tmp_path):
    ev = _events(2000, seed=7)
    txt = tmp_path / "ev.txt"
    txt.write_text(_e2vid_text(ev))
    zp = tmp_path / "ev.zip"
    with zipfile.ZipFile(zp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.write(txt, "inner/ev.txt")
    for p in (txt, zp):
        assert hh.detect_format(p) == "e2vid"
        with hh.open_reader(p) as r:
            assert r.sensor_size == SS
            chunks = [c.events for c in r.iter_chunks(300)]
        np.testing.assert_array_equal(np.concatenate(chunks), ev)
    assert hh.read(zp).metadata.provenance["zip_member"] == "inner/ev.txt"


def test_e2vid_sensor_option_overrides(tmp_path):
    p = tmp_path / "a.txt"
    p.write_text(_e2vid_text(hh.make_events([1, 2], [300, 1], [1, 1], [1, 1]), 240, 180))
    with pytest.raises(FormatError, match="line 2: x = 300 is outside the sensor width 240"):
        hh.read(p)
    assert hh.read(p, sensor_size=(200, 400)).n_events == 2


def test_sniff_cases(tmp_path):
    assert T.sniff(tmp_path, b"") is None  # folder without events.txt
    assert T.sniff(tmp_path / "x", b"1 2\n0.1 1 2 1\n") == "e2vid"
    assert T.sniff(tmp_path / "x", b"0.1 1 2 1\n0.2 1 2 0\n") == "ecd"
    assert T.sniff(tmp_path / "x", b"\x00\x01binary\n\n") is None
    assert T.sniff(tmp_path / "x", b"hello world\nfoo\n") is None
    bad_zip = tmp_path / "b.zip"
    bad_zip.write_bytes(b"PK\x03\x04garbage")
    assert T.sniff(bad_zip, bad_zip.read_bytes()) is None
    two = tmp_path / "two.zip"
    with zipfile.ZipFile(two, "w") as zf:
        zf.writestr("a.txt", "1 2\n0.1 0 0 1\n")
        zf.writestr("b.txt", "1 2\n0.1 0 0 1\n")
    assert T.sniff(two, two.read_bytes()[:4096]) is None


# ------------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("body, match", [
    ("0.1 1 2 1\n0.2 1 2\n", "line 3: expected 4 columns"),
    ("0.1 1 2 1\n0.2 1 2 1 5\n", "line 3: expected 4 columns"),
    ("0.1 1 2 1\n0.2 a 2 1\n", "line 3: column 2 is not a number"),
    ("0.2 1 2 1\n0.1 1 2 1\n", "line 3: timestamps must be non-decreasing"),
    ("0.1 1 2 1\n0.2 1 2 2\n", "line 3: polarity 2.0 is not 0, 1 or -1"),
    ("0.1 1.5 2 1\n", "line 2: x = 1.5 is not a pixel index"),
    ("0.1 -1 2 1\n", "line 2: x = -1.0 is not a pixel index"),
    ("nan 1 2 1\n", "line 2: non-finite"),
    ("0.1 1 200 1\n", "line 2: y = 200 is outside the sensor height 180"),
    ("\n# comment\n0.1 1 2 1\n\n0.05 1 2 1\n", "line 6: timestamps must be non-decreasing"),
    ("1e20 1 2 1\n", "overflows int64"),
])
def test_bad_lines(tmp_path, body, match):
    p = tmp_path / "e.txt"
    p.write_text("240 180\n" + body)
    with pytest.raises(FormatError, match=match) as ei:
        hh.read(p, "e2vid")
    assert str(p) in str(ei.value)


def test_unsorted_across_blocks(tmp_path, monkeypatch):
    ev = _events(200, seed=2)
    lines = _ecd_lines(ev).splitlines(keepends=True)
    lines.insert(150, "0.000000 1 1 1\n")
    p = tmp_path / "events.txt"
    p.write_text("".join(lines))
    monkeypatch.setattr(T, "_BLOCK_BYTES", 512)
    with pytest.raises(FormatError, match="line 151: timestamps must be non-decreasing"):
        hh.read(p, sensor_size=SS)


def test_bad_e2vid_header(tmp_path):
    p = tmp_path / "h.txt"
    p.write_text("240 x\n0.1 1 2 1\n")
    with pytest.raises(FormatError, match="line 1: expected 'width height'"):
        hh.read(p, "e2vid")
    p.write_text("0 180\n0.1 1 2 1\n")
    with pytest.raises(FormatError, match="invalid sensor size"):
        hh.read(p, "e2vid")


def test_corrupt_zip(tmp_path):
    ev = _events(3000, seed=4)
    txt = tmp_path / "ev.txt"
    txt.write_text(_e2vid_text(ev))
    zp = tmp_path / "ev.zip"
    with zipfile.ZipFile(zp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.write(txt, "ev.txt")
    data = bytearray(zp.read_bytes())
    data[200:260] = b"\xff" * 60  # damage the deflate stream (the central directory survives)
    zp.write_bytes(bytes(data))
    with pytest.raises(FormatError):
        hh.read(zp, "e2vid")
    (tmp_path / "z2.zip").write_bytes(bytes(data[:100]))
    with pytest.raises(FormatError, match="exactly one .txt"):
        hh.read(tmp_path / "z2.zip", "e2vid")


def test_binary_garbage_as_text(tmp_path):
    p = tmp_path / "g.txt"
    p.write_bytes(b"240 180\n" + bytes(range(256)) * 8)
    with pytest.raises(FormatError):
        hh.read(p, "e2vid")
    p.write_bytes(b"240 180\n" + b"1" * (T._MAX_LINE_BYTES + 10))
    with pytest.raises(FormatError, match="longer than"):
        hh.read(p, "e2vid")


def test_ecd_bad_images_txt(tmp_path):
    d = tmp_path / "d"
    (d / "images").mkdir(parents=True)
    (d / "events.txt").write_text("0.1 1 2 1\n")
    (d / "images.txt").write_text("0.0 images/missing.png\n")
    with pytest.raises(FormatError, match="images.txt at record 1: cannot read the first frame"):
        hh.read(d, "ecd")
    (d / "images.txt").write_text("0.2 images/a.png\n0.1 images/b.png\n")
    with pytest.raises(FormatError, match="line 2: frame timestamps must be non-decreasing"):
        hh.read(d, "ecd", sensor_size=SS)
    (d / "images.txt").write_text("0.2\n")
    with pytest.raises(FormatError, match="line 1: expected 't images/frame_XXXXXXXX.png'"):
        hh.read(d, "ecd", sensor_size=SS)
    (d / "images.txt").write_text("0.2 images/a.png\n")
    (d / "images" / "a.png").write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    with pytest.raises(FormatError, match="line 1: cannot read frame"):
        hh.read(d, "ecd", sensor_size=SS)


def test_ecd_missing_events_txt(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(FormatError, match="no events.txt"):
        hh.open_reader(tmp_path / "d", "ecd")
