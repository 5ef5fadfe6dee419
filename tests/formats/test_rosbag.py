"""ROS1/ROS2 bag reader on small bags written with rosbags' writers."""

from __future__ import annotations

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.errors import FormatError

pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402

from hybridhdr.formats import rosbag as R  # noqa: E402

SS = hh.SensorSize(260, 346)


def _events(n, seed=0, t0=1_600_000_000_000_000):
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.integers(0, 3, n))  # equal timestamps included
    ev = hh.make_events(t, rng.integers(0, SS.width, n), rng.integers(0, SS.height, n), rng.integers(0, 2, n))
    ev["x"][:2], ev["y"][:2] = (0, SS.width - 1), (SS.height - 1, 0)
    return ev


def _header(ts, ros2, t_us):
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    stamp = Time(sec=int(t_us // 1_000_000), nanosec=int(t_us % 1_000_000) * 1000)
    return Header(stamp=stamp, frame_id="cam") if ros2 else Header(seq=0, stamp=stamp, frame_id="cam")


def _event_array_msgs(ts, ros2, ev, per_msg, size=SS):
    Event = ts.types["dvs_msgs/msg/Event"]
    EA = ts.types[R.EVENT_ARRAY]
    Time = ts.types["builtin_interfaces/msg/Time"]
    out = []
    for i in range(0, len(ev), per_msg):
        part = ev[i:i + per_msg]
        evs = [Event(x=int(x), y=int(y), ts=Time(sec=int(t // 1_000_000), nanosec=int(t % 1_000_000) * 1000),
                     polarity=bool(p > 0)) for t, x, y, p in part.tolist()]
        out.append((1_000_000 + i, EA(header=_header(ts, ros2, part["t"][0]), height=size.height,
                                                  width=size.width, events=evs)))
    return out


def _packet_msgs(ts, ros2, payloads, encoding="evt3", size=SS):
    EP = ts.types[R.EVENT_PACKET]
    return [(1000 + i, EP(header=_header(ts, ros2, i), height=size.height, width=size.width, seq=i, time_base=0,
                          encoding=encoding, is_bigendian=False, events=np.frombuffer(pl, np.uint8)))
            for i, pl in enumerate(payloads)]


def write_bag(path, ros2, topics):
    """topics: {topic: (msgtype, [(timestamp_ns, msg), ...])}."""
    ts = R.make_typestore(ros2=ros2)
    if ros2:
        w = Writer2(path, version=9)
    else:
        w = Writer1(path)
    with w:
        conns = {t: w.add_connection(t, mt, typestore=ts) for t, (mt, _) in topics.items()}
        allm = sorted((stamp, t, m) for t, (mt, ms) in topics.items() for stamp, m in ms)
        for stamp, t, m in allm:
            mt = topics[t][0]
            data = ts.serialize_cdr(m, mt) if ros2 else ts.serialize_ros1(m, mt)
            w.write(conns[t], stamp, data)
    return path


def _build(tmp_path, ros2, topics_fn, name="b"):
    ts = R.make_typestore(ros2=ros2)
    path = tmp_path / (name if ros2 else name + ".bag")
    return write_bag(path, ros2, topics_fn(ts, ros2))


@pytest.mark.parametrize("ros2", [False, True])
def test_event_array(tmp_path, ros2):
    ev = _events(700)
    path = _build(tmp_path, ros2, lambda ts, r2: {"/dvs/events": (R.EVENT_ARRAY, _event_array_msgs(ts, r2, ev, 128))})
    assert hh.detect_format(path) == "rosbag"
    with hh.open_reader(path) as r:
        assert r.sensor_size == SS
        assert r.topic == "/dvs/events"
        assert r.metadata.provenance["ros_version"] == (2 if ros2 else 1)
        chunks = [c.events for c in r.iter_chunks(300)]
    assert max(map(len, chunks)) == 300
    np.testing.assert_array_equal(np.concatenate(chunks), ev)


def test_ns_rounding(tmp_path):
    ts = R.make_typestore(ros2=False)
    Event, EA, Time = ts.types["dvs_msgs/msg/Event"], ts.types[R.EVENT_ARRAY], ts.types["builtin_interfaces/msg/Time"]
    evs = [Event(x=1, y=1, ts=Time(sec=5, nanosec=ns), polarity=True) for ns in (499, 500, 1499, 999_999_999)]
    msg = EA(header=_header(ts, False, 0), height=10, width=10, events=evs)
    path = write_bag(tmp_path / "r.bag", False, {"/e": (R.EVENT_ARRAY, [(1, msg)])})
    assert hh.read(path).events["t"].tolist() == [5_000_000, 5_000_001, 5_000_001, 6_000_000]


@pytest.mark.parametrize("ros2", [False, True])
def test_event_packet_evt3(tmp_path, ros2):
    pytest.importorskip("hybridhdr.formats.prophesee")
    from hybridhdr.formats.prophesee import Evt3Decoder  # noqa: F401  (must exist)
    rng = np.random.default_rng(3)
    n = 3000
    ev = hh.make_events(10_000 + np.sort(rng.integers(0, 200_000, n)), rng.integers(0, SS.width, n),
                        rng.integers(0, SS.height, n), rng.integers(0, 2, n))
    tr = hh.make_triggers([20_000, 90_000], [0, 0], [1, -1])
    raw = tmp_path / "s.raw"
    hh.write(hh.Recording(ev, SS, triggers=tr), raw, "evt3")
    data = raw.read_bytes()
    body = data[data.index(b"% end\n") + 6:]
    cuts = [0, 1000, 1001, 4000, len(body) // 2, len(body)]  # one cut splits a 16-bit word
    payloads = [body[a:b] for a, b in zip(cuts[:-1], cuts[1:])]
    path = _build(tmp_path, ros2, lambda ts, r2: {
        "/a_images": (R.EVENT_ARRAY, []),
        "/evk/events": (R.EVENT_PACKET, _packet_msgs(ts, r2, payloads))})
    with hh.open_reader(path, topic="/evk/events") as r:
        assert r.metadata.provenance["encoding"] == "evt3"
        rec = r.read()
        chunks = list(r.iter_chunks(700))
    np.testing.assert_array_equal(rec.events, ev)
    np.testing.assert_array_equal(rec.triggers, tr)
    np.testing.assert_array_equal(np.concatenate([c.events for c in chunks]), ev)


def test_unsupported_encoding_and_topics(tmp_path):
    path = _build(tmp_path, False, lambda ts, r2: {
        "/evk/events": (R.EVENT_PACKET, _packet_msgs(ts, r2, [b"\x00" * 8], encoding="mono"))})
    with pytest.raises(FormatError, match="encoding 'mono' is not supported"):
        hh.read(path)
    with pytest.raises(FormatError, match="topic '/nope' is not in the bag"):
        hh.open_reader(path, topic="/nope")

    def only_header(ts, r2):
        return {"/h": ("std_msgs/msg/Header", [(1, _header(ts, r2, 0))])}
    path2 = _build(tmp_path, False, only_header, name="h")
    with pytest.raises(FormatError, match="no event topic of a supported type"):
        hh.open_reader(path2)
    with pytest.raises(FormatError, match="has type std_msgs/msg/Header"):
        hh.open_reader(path2, topic="/h")


def test_default_topic_is_first_by_name(tmp_path):
    ev1, ev2 = _events(50, seed=1), _events(60, seed=2)
    path = _build(tmp_path, False, lambda ts, r2: {
        "/cam_b/events": (R.EVENT_ARRAY, _event_array_msgs(ts, r2, ev2, 20)),
        "/cam_a/events": (R.EVENT_ARRAY, _event_array_msgs(ts, r2, ev1, 20))})
    np.testing.assert_array_equal(hh.read(path).events, ev1)
    np.testing.assert_array_equal(hh.read(path, topic="/cam_b/events").events, ev2)


def test_zero_size_inferred(tmp_path):
    ev = _events(40)
    path = _build(tmp_path, False, lambda ts, r2: {
        "/e": (R.EVENT_ARRAY, _event_array_msgs(ts, r2, ev, 10, size=hh.SensorSize(1, 1)))})
    # height = width = 1 stored -> events outside the sensor are an error
    with pytest.raises(FormatError, match="outside the sensor"):
        hh.read(path)
    assert hh.read(path, sensor_size=SS).n_events == 40


def test_unsorted_events(tmp_path):
    ev = _events(40)
    ev2 = ev.copy()
    ev2["t"][20:] -= 1_000  # second message goes back in time
    path = _build(tmp_path, False, lambda ts, r2: {"/e": (R.EVENT_ARRAY, _event_array_msgs(ts, r2, ev2, 20))})
    with pytest.raises(FormatError, match="message 1: event 20 has .* µs after .* non-decreasing"):
        hh.read(path)


def test_corrupt_bags(tmp_path):
    ev = _events(300)
    path = _build(tmp_path, False, lambda ts, r2: {"/e": (R.EVENT_ARRAY, _event_array_msgs(ts, r2, ev, 100))})
    data = path.read_bytes()
    bad = tmp_path / "t.bag"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError):
        hh.read(bad, "rosbag")
    bad.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 50)
    with pytest.raises(FormatError, match="cannot open the bag"):
        hh.read(bad, "rosbag")


def test_sniff(tmp_path):
    assert R.sniff(tmp_path / "x.bag", b"#ROSBAG V2.0\n....") == "rosbag"
    assert R.sniff(tmp_path, b"") is None
    (tmp_path / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: 9\n")
    assert R.sniff(tmp_path, b"") == "rosbag"


@pytest.mark.parametrize("ext", [".txt", ".h5", ".zip", ".bin", ""])
def test_ros1_bag_under_another_name_is_read(tmp_path, ext):
    # detection is by the '#ROSBAG V2.0' magic, never by the extension
    ev = _events(300)
    path = _build(tmp_path, False, lambda ts, r2: {"/dvs/events": (R.EVENT_ARRAY, _event_array_msgs(ts, r2, ev, 128))})
    renamed = path.rename(tmp_path / ("renamed" + ext))
    assert hh.detect_format(renamed) == "rosbag"
    np.testing.assert_array_equal(hh.read(renamed).events, ev)
    assert not list(tmp_path.glob("*.bag"))
