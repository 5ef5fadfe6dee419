"""ROS 1 chunks: decompressed sizes bounded before rosbags inflates them (hybridhdr/formats/_ros1_chunks.py)."""

from __future__ import annotations

import struct

import pytest

pytest.importorskip("rosbags")

import hybridhdr  # noqa: E402
from hybridhdr._util.limits import LimitExceeded, allow_huge  # noqa: E402
from hybridhdr.formats import rosbag as R  # noqa: E402
from hybridhdr.formats._ros1_chunks import check_ros1_chunks  # noqa: E402
from hybridhdr.errors import FormatError  # noqa: E402


def _bag(path, compression, n=6000, messages=3):
    from rosbags.rosbag1 import Writer
    ts = R.make_typestore(ros2=False)
    Event, EA = ts.types["dvs_msgs/msg/Event"], ts.types[R.EVENT_ARRAY]
    Time, Header = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
    w = Writer(path)
    if compression != "none":
        w.set_compression(getattr(Writer.CompressionFormat, compression.upper()))
    w.chunk_threshold = 64 << 10  # several chunks (rosbags closes a chunk past this size)
    with w:
        c = w.add_connection("/dvs/events", R.EVENT_ARRAY, typestore=ts)
        for k in range(messages):
            evs = [Event(x=i % 64, y=i % 48, ts=Time(sec=1 + k, nanosec=i * 100), polarity=bool(i % 2))
                   for i in range(n)]
            msg = EA(header=Header(seq=k, stamp=Time(sec=1 + k, nanosec=0), frame_id="c"), height=48, width=64,
                     events=evs)
            w.write(c, (1 + k) * 1_000_000_000, ts.serialize_ros1(msg, R.EVENT_ARRAY))
    return path


@pytest.mark.parametrize("compression", ["none", "bz2", "lz4"])
def test_valid_bags_pass_and_read(tmp_path, compression):
    p = _bag(tmp_path / "a.bag", compression)
    assert check_ros1_chunks(p) == 3  # a chunk per message (64 KiB chunks, 78 KB messages)
    assert len(hybridhdr.read(p).events) == 3 * 6000


def _patch_size(p, value):
    b = bytearray(p.read_bytes())
    i = b.index(b"size=", b.index(b"op=\x05") - 64)
    struct.pack_into("<I", b, i + 5, value)
    p.write_bytes(bytes(b))


def test_declared_size_above_the_limit_and_lying_headers(tmp_path):
    p = _bag(tmp_path / "a.bag", "bz2", messages=1)
    _patch_size(p, 0xFFFFFFF0)
    with pytest.raises(LimitExceeded, match=r"chunk 0 \(decompressed\) declares 4,294,967,280 bytes.*--allow-huge"):
        check_ros1_chunks(p)
    with allow_huge():  # lifted: the data itself is honest (shorter than declared), so the bag reads
        assert len(hybridhdr.read(p).events) == 6000
    q = _bag(tmp_path / "b.bag", "lz4", messages=1)
    _patch_size(q, 100)
    with pytest.raises(FormatError, match="lz4 data expands beyond the 100 bytes its header declares"):
        hybridhdr.read(q)
    (tmp_path / "c.bag").write_bytes(b"#ROSBAG V2.0\n" + struct.pack("<I", 1 << 30))
    with pytest.raises(FormatError, match="record header of 1,073,741,824 bytes"):
        check_ros1_chunks(tmp_path / "c.bag")
