"""Frames from sensor_msgs/Image topics of ROS bags, and the colour filter they declare."""

from __future__ import annotations

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.errors import FormatError

pytest.importorskip("rosbags")

from hybridhdr.formats import rosbag as R  # noqa: E402
from hybridhdr.formats._ros_image import ENCODINGS, decode_image  # noqa: E402

from .test_rosbag import SS, _event_array_msgs, _events, _header, write_bag  # noqa: E402

T0 = 1_600_000_000_000_000


def _pixels(k, shape, dtype=np.uint8, seed=0):
    rng = np.random.default_rng(seed)
    hi = 256 if dtype == np.uint8 else 65536
    return rng.integers(0, hi, (k,) + shape).astype(dtype)


def _serialize(px: np.ndarray, encoding: str, bigendian=False, pad=0):
    """(data bytes, step) of one image as a camera driver would store it."""
    ch, nb, kind, _ = ENCODINGS[encoding]
    a = px if px.ndim == 3 else px[..., None]
    if kind == "bgr":
        a = a[..., ::-1]
    if ch == 4:
        a = np.concatenate([a, np.full(a.shape[:2] + (1,), 7, a.dtype)], axis=2)
    a = a.astype((">" if bigendian else "<") + ("u1" if nb == 1 else "u2"))
    rows = a.reshape(a.shape[0], -1).view(np.uint8)
    if pad:
        rows = np.concatenate([rows, np.full((rows.shape[0], pad), 0xEE, np.uint8)], axis=1)
    return rows.tobytes(), rows.shape[1]


def _image_msgs(ts, ros2, frames, stamps_us, encoding, bigendian=False, pad=0, data_fn=None):
    Image = ts.types["sensor_msgs/msg/Image"]
    out = []
    for i, (px, t) in enumerate(zip(frames, stamps_us)):
        data, step = _serialize(px, encoding, bigendian, pad)
        if data_fn is not None:
            data = data_fn(i, data)
        out.append((1_000_000 + i, Image(header=_header(ts, ros2, int(t)), height=px.shape[0], width=px.shape[1],
                                          encoding=encoding, is_bigendian=int(bigendian), step=step,
                                          data=np.frombuffer(data, np.uint8))))
    return out


def _int32_msgs(ts, values):
    Int32 = ts.types["std_msgs/msg/Int32"]
    return [(2_000_000 + i, Int32(data=int(v))) for i, v in enumerate(values)]


def _bag(tmp_path, ros2, images: dict, extra=None, name="b", events=True):
    """images: {topic: (frames, stamps_us, encoding[, kwargs])}."""
    ts = R.make_typestore(ros2=ros2)
    topics = {}
    if events:
        topics["/dvs/events"] = (R.EVENT_ARRAY, _event_array_msgs(ts, ros2, _events(300, t0=T0), 100))
    for topic, spec in images.items():
        frames, stamps, enc = spec[:3]
        kw = spec[3] if len(spec) > 3 else {}
        topics[topic] = ("sensor_msgs/msg/Image", _image_msgs(ts, ros2, frames, stamps, enc, **kw))
    for topic, values in (extra or {}).items():
        topics[topic] = ("std_msgs/msg/Int32", _int32_msgs(ts, values))
    path = tmp_path / (name if ros2 else name + ".bag")
    return write_bag(path, ros2, topics)


STAMPS = T0 + np.array([1_000, 34_000, 67_000])


@pytest.mark.parametrize("ros2", [False, True])
@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_topic_declares_both_cameras(tmp_path, ros2, pattern):
    px = _pixels(3, SS.shape)
    path = _bag(tmp_path, ros2, {"/dvs/image_raw": (px, STAMPS, f"bayer_{pattern}8")})
    with hh.open_reader(path) as r:
        md = r.metadata
        fr = r.read_frames()
    assert md.frame_camera.cfa == pattern.upper()
    assert md.event_camera.cfa == pattern.upper()  # same size as the events: one DAVIS pixel array
    assert md.frame_camera.sensor_size == SS
    assert md.provenance["image_topic"] == "/dvs/image_raw"
    assert "one pixel array" in md.provenance["event_cfa_source"]
    assert "zero-length" in md.provenance["frame_exposure"]
    np.testing.assert_array_equal(fr.images, px)
    assert fr.images.dtype == np.uint8 and fr.images.shape == (3,) + SS.shape
    np.testing.assert_array_equal(fr.t_start_us, STAMPS)
    np.testing.assert_array_equal(fr.t_end_us, STAMPS)
    assert fr.encoding == "unknown"


def test_bayer_frames_of_another_size_leave_the_events_undeclared(tmp_path):
    px = _pixels(2, (120, 160))
    path = _bag(tmp_path, False, {"/cam/image_raw": (px, STAMPS[:2], "bayer_grbg8")})
    with hh.open_reader(path) as r:
        assert r.metadata.frame_camera.cfa == "GRBG"
        assert r.metadata.event_camera.cfa is None
        assert "pass --cfa" in r.metadata.provenance["event_cfa_source"]
        np.testing.assert_array_equal(r.read_frames().images, px)


@pytest.mark.parametrize("ros2", [False, True])
def test_mono8_declares_nothing(tmp_path, ros2):
    px = _pixels(3, SS.shape, seed=1)
    path = _bag(tmp_path, ros2, {"/dvs/image_raw": (px, STAMPS, "mono8")})
    with hh.open_reader(path) as r:
        assert r.metadata.frame_camera.cfa is None and r.metadata.event_camera.cfa is None
        assert "needs --cfa" in r.metadata.provenance["frame_cfa_source"]
        rec = r.read()
    np.testing.assert_array_equal(rec.frames.images, px)
    assert rec.metadata.frame_camera.sensor_size == SS


@pytest.mark.parametrize("ros2", [False, True])
@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_colour_encodings_give_rgb_frames(tmp_path, ros2, encoding):
    px = _pixels(3, SS.shape + (3,), seed=2)
    path = _bag(tmp_path, ros2, {"/dvs/image_color": (px, STAMPS, encoding)})
    with hh.open_reader(path) as r:
        fr = r.read_frames()
        md = r.metadata
    assert fr.images.shape == (3,) + SS.shape + (3,)
    np.testing.assert_array_equal(fr.images, px)  # R, G, B order whatever the stored order
    assert md.frame_camera.cfa is None and md.event_camera.cfa is None
    assert "demosaicked RGB" in md.provenance["frame_cfa_source"]


@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("encoding", ["mono16", "bayer_bggr16", "rgb16", "bgra16"])
def test_16bit_and_byte_order(tmp_path, bigendian, encoding):
    ch = ENCODINGS[encoding][0]
    shape = SS.shape + ((3,) if ch > 1 else ())
    px = _pixels(2, shape, np.uint16, seed=3)
    path = _bag(tmp_path, False, {"/dvs/image_raw": (px, STAMPS[:2], encoding, {"bigendian": bigendian})})
    fr = hh.open_reader(path).read_frames()
    assert fr.images.dtype == np.uint16 and fr.images.dtype.isnative
    np.testing.assert_array_equal(fr.images, px)
    # a 16-bit sample whose bytes differ: the byte order matters
    assert np.any((px >> 8) != (px & 0xFF))


def test_row_padding_step(tmp_path):
    px = _pixels(2, SS.shape + (3,), seed=4)
    path = _bag(tmp_path, False, {"/dvs/image_raw": (px, STAMPS[:2], "bgr8", {"pad": 6})})
    np.testing.assert_array_equal(hh.open_reader(path).read_frames().images, px)


@pytest.mark.parametrize("ros2", [False, True])
def test_davis_exposure_topic(tmp_path, ros2):
    px = _pixels(3, SS.shape)
    exposure = [5000, 2001, 0]
    path = _bag(tmp_path, ros2, {"/dvs/image_raw": (px, STAMPS, "mono8")}, extra={"/dvs/exposure": exposure})
    with hh.open_reader(path) as r:
        assert r.metadata.provenance["exposure_topic"] == "/dvs/exposure"
        fr = r.read_frames()
    e = np.array(exposure)
    np.testing.assert_array_equal(fr.t_start_us, STAMPS - e // 2)
    np.testing.assert_array_equal(fr.t_end_us, STAMPS - e // 2 + e)
    np.testing.assert_array_equal(fr.exposure_us, e)
    # ignored on request; a mismatch in counts falls back to zero-length exposures
    fr0 = hh.open_reader(path, exposure_topic="").read_frames()
    np.testing.assert_array_equal(fr0.exposure_us, [0, 0, 0])
    path2 = _bag(tmp_path, ros2, {"/dvs/image_raw": (px, STAMPS, "mono8")}, extra={"/dvs/exposure": [5000, 10]},
                 name="c")
    np.testing.assert_array_equal(hh.open_reader(path2).read_frames().t_start_us, STAMPS)


def test_image_topic_choice(tmp_path):
    a, b = _pixels(1, SS.shape, seed=5), _pixels(1, SS.shape, seed=6)
    path = _bag(tmp_path, False, {"/dvs/image_raw": (a, STAMPS[:1], "mono8"),
                                  "/dvs/image_color": (b[..., None].repeat(3, -1), STAMPS[:1], "rgb8"),
                                  "/other/image_raw": (b, STAMPS[:1], "bayer_rggb8")})
    with hh.open_reader(path) as r:  # the image_raw next to /dvs/events
        assert r.image_topic == "/dvs/image_raw"
        np.testing.assert_array_equal(r.read_frames().images, a)
    with hh.open_reader(path, image_topic="/other/image_raw") as r:
        assert r.metadata.frame_camera.cfa == "RGGB"
        np.testing.assert_array_equal(r.read_frames().images, b)
    with pytest.raises(FormatError, match="image topic '/nope' is not in the bag"):
        hh.open_reader(path, image_topic="/nope")
    with pytest.raises(FormatError, match="has type dvs_msgs/msg/EventArray"):
        hh.open_reader(path, image_topic="/dvs/events")
    # ambiguous: no frames, and the provenance says why
    p2 = _bag(tmp_path, False, {"/a/image_raw": (a, STAMPS[:1], "mono8"), "/b/image_raw": (b, STAMPS[:1], "mono8")},
              name="amb")
    with hh.open_reader(p2) as r:
        assert r.read_frames() is None
        assert "pass image_topic=" in r.metadata.provenance["image_topic_note"]


def test_unknown_encoding(tmp_path):
    px = _pixels(1, SS.shape)
    path = _bag(tmp_path, False, {"/dvs/image_raw": (px, STAMPS[:1], "mono8")})
    # rewrite the encoding of the stored message: same length, unknown name
    raw = path.read_bytes()
    path.write_bytes(raw.replace(b"mono8", b"yuv42", 1) if raw.count(b"mono8") == 1 else raw)
    assert b"yuv42" in path.read_bytes()
    with hh.open_reader(path) as r:  # chosen by default: skipped, events still read
        assert r.read_frames() is None
        assert "'yuv42'" in r.metadata.provenance["image_topic_note"]
        assert len(r.read().events) == 300
    with pytest.raises(FormatError, match=r"image encoding 'yuv42' is not supported; supported: mono8, rgb8, rgba8"):
        hh.open_reader(path, image_topic="/dvs/image_raw")
    with pytest.raises(FormatError, match="encoding 'yuv42' is not supported"):
        decode_image(2, 2, "yuv42", 0, 2, b"\0" * 4)


@pytest.mark.parametrize("ros2", [False, True])
def test_truncated_and_inconsistent_images(tmp_path, ros2):
    px = _pixels(3, SS.shape)
    short = _bag(tmp_path, ros2, {"/dvs/image_raw": (px, STAMPS, "mono8", {"data_fn": lambda i, d: d[:-1] if i == 1
                                                                             else d})}, name="short")
    with pytest.raises(FormatError, match=r"message 1 of /dvs/image_raw: 260 rows of step 346 need 89960 bytes of "
                                          r"data, the message has 89959"):
        hh.open_reader(short).read_frames()
    with pytest.raises(FormatError, match="shorter than one row"):
        decode_image(2, 4, "rgb8", 0, 11, b"\0" * 22)
    with pytest.raises(FormatError, match="must be positive"):
        decode_image(0, 4, "mono8", 0, 4, b"")
    # a later image of another size
    ts = R.make_typestore(ros2=ros2)
    msgs = (_image_msgs(ts, ros2, px[:1], STAMPS[:1], "mono8")
            + _image_msgs(ts, ros2, px[1:2, :10], STAMPS[1:2], "mono8"))
    msgs[1] = (msgs[1][0] + 1, msgs[1][1])
    p3 = write_bag(tmp_path / ("m2" if ros2 else "m2.bag"), ros2, {"/dvs/image_raw": ("sensor_msgs/msg/Image", msgs),
                                                                    "/dvs/events": (R.EVENT_ARRAY, _event_array_msgs(
                                                                        ts, ros2, _events(10, t0=T0), 10))})
    with pytest.raises(FormatError, match="mono8 10x346 image, unlike the first one's mono8 260x346"):
        hh.open_reader(p3).read_frames()


def test_truncated_ros1_message_fields(tmp_path):
    """A stored message cut inside its data field: the length prefix overruns the message."""
    px = _pixels(1, (4, 6))
    path = _bag(tmp_path, False, {"/dvs/image_raw": (px, STAMPS[:1], "mono8")})
    r = hh.open_reader(path)
    good = None
    with r._reader() as rr:
        for rec, (conn, ts, raw) in r._messages(rr, "/dvs/image_raw"):
            good = raw
    assert r._image_fields(None, good, 0, "/t")["data"].nbytes == 24
    with pytest.raises(FormatError, match="message 0 is truncated"):
        r._image_fields(None, good[:-5], 0, "/t")
    with pytest.raises(FormatError, match="bytes after the image data"):
        r._image_fields(None, good + b"\0", 0, "/t")


def test_frames_past_the_limit_are_refused_before_decoding(tmp_path):
    from hybridhdr._util.limits import LIMITS, LimitExceeded
    px = _pixels(3, SS.shape)
    path = _bag(tmp_path, False, {"/dvs/image_raw": (px, STAMPS, "mono8")})
    old = LIMITS["max_frame_bytes"]
    LIMITS["max_frame_bytes"] = 2 * SS.height * SS.width
    try:
        with pytest.raises(LimitExceeded):
            hh.open_reader(path).read_frames()
    finally:
        LIMITS["max_frame_bytes"] = old


@pytest.mark.parametrize("encoding,cfa", [("bayer_rggb8", "RGGB"), ("rgb8", None)])
def test_container_round_trip_keeps_cfa(tmp_path, encoding, cfa):
    from hybridhdr.formats.container import RecordingFile, write_recording
    shape = SS.shape + ((3,) if encoding == "rgb8" else ())
    px = _pixels(3, shape, seed=7)
    path = _bag(tmp_path, False, {"/dvs/image_raw": (px, STAMPS, encoding)}, extra={"/dvs/exposure": [100, 200, 300]})
    rec = hh.read(path)
    assert rec.metadata.frame_camera.cfa == cfa and rec.metadata.event_camera.cfa == cfa
    out = write_recording(rec, tmp_path / "r.h5")
    with RecordingFile(out) as f:
        md = f.metadata
        fr = f.read_frames()
    assert md.frame_camera.cfa == cfa and md.event_camera.cfa == cfa
    assert md.provenance["image_encoding"] == encoding
    np.testing.assert_array_equal(fr.images, px)
    np.testing.assert_array_equal(fr.t_start_us, rec.frames.t_start_us)
    np.testing.assert_array_equal(fr.t_end_us, rec.frames.t_end_us)


def test_same_input_same_bits(tmp_path):
    px = _pixels(3, SS.shape)
    path = _bag(tmp_path, False, {"/dvs/image_raw": (px, STAMPS, "bayer_gbrg8")})
    a, b = hh.read(path), hh.read(path)
    assert a.frames.images.tobytes() == b.frames.images.tobytes()
    assert a.metadata.to_dict() == b.metadata.to_dict()


def test_reconstruct_sees_the_declared_pattern(tmp_path):
    """What the colour reconstruction reads (source_cfa) is the reader's declaration; --cfa overrides."""
    from hybridhdr.reconstruct.colour import source_cfa
    px = _pixels(2, SS.shape)
    bayer = _bag(tmp_path, False, {"/dvs/image_raw": (px, STAMPS[:2], "bayer_bggr8")}, name="bayer")
    rgb = _bag(tmp_path, False, {"/dvs/image_raw": (px[..., None].repeat(3, -1), STAMPS[:2], "rgb8")}, name="rgb")
    with hh.open_reader(bayer) as r:
        assert source_cfa(r) == ("BGGR", "BGGR")
        assert source_cfa(r, "none") == (None, None)
    with hh.open_reader(rgb) as r:
        assert source_cfa(r) == (None, None)
        assert source_cfa(r, "gbrg") == ("GBRG", "GBRG")
