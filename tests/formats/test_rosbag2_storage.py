"""ROS 2 bags by magic: SQLite (.db3) and MCAP storage files, alone or in a folder, an empty
storage id, files under other names; the size limits of ROS 1 apply to them too."""

from __future__ import annotations

import shutil
import sqlite3

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr._util.limits import LIMITS, LimitExceeded, allow_huge
from hybridhdr.errors import FormatError, UnknownFormatError

pytest.importorskip("rosbags")
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402

from hybridhdr.formats import rosbag as R  # noqa: E402

from .test_rosbag import SS, _build, _event_array_msgs, _events  # noqa: E402

PLUGINS = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}


def write_ros2(folder, storage, topics):
    """A ROS 2 bag folder written by rosbags (metadata.yaml + one .db3 or .mcap file)."""
    ts = R.make_typestore(ros2=True)
    with Writer2(folder, version=9, storage_plugin=PLUGINS[storage]) as w:
        conns = {t: w.add_connection(t, mt, typestore=ts) for t, (mt, _) in topics.items()}
        for stamp, t, m in sorted((st, t, m) for t, (mt, ms) in topics.items() for st, m in ms):
            w.write(conns[t], stamp, ts.serialize_cdr(m, topics[t][0]))
    return folder


def _bag(tmp_path, storage, ev, per_msg=64, size=SS, name="bag"):
    ts = R.make_typestore(ros2=True)
    return write_ros2(tmp_path / name, storage,
                      {"/dvs/events": (R.EVENT_ARRAY, _event_array_msgs(ts, True, ev, per_msg, size=size))})


def _storage_file(folder, storage):
    (f,) = folder.glob("*" + R.STORAGE_SUFFIX[storage])
    return f


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_ros2_storage_folder_file_and_renamed(tmp_path, storage):
    ev = _events(500)
    folder = _bag(tmp_path, storage, ev)
    data = _storage_file(folder, storage)
    head = data.read_bytes()[:16]
    assert head.startswith(R.MCAP_MAGIC if storage == "mcap" else R.SQLITE_MAGIC)
    assert R.storage_kind(data) == storage
    # the folder, the storage file alone, the file under another name, a folder without metadata.yaml
    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy(data, lone / "only_file.bin")
    renamed = tmp_path / ("renamed" + (".db" if storage == "sqlite3" else ".dat"))
    shutil.copy(data, renamed)
    for p in (folder, data, renamed, lone):
        assert hh.detect_format(p) == "rosbag", p
        with hh.open_reader(p) as r:
            assert r.sensor_size == SS and r.topic == "/dvs/events"
            assert r.metadata.provenance["ros_version"] == 2
            np.testing.assert_array_equal(r.read().events, ev)
    assert not list(tmp_path.glob("hybridhdr-bag-*"))


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_empty_storage_identifier(tmp_path, storage):
    ev = _events(200)
    folder = _bag(tmp_path, storage, ev)
    meta = folder / "metadata.yaml"
    text = meta.read_text()
    assert f"storage_identifier: {storage}" in text
    for empty in ("''", '""', ""):
        meta.write_text(text.replace(f"storage_identifier: {storage}", f"storage_identifier: {empty}"))
        np.testing.assert_array_equal(hh.read(folder).events, ev)
    assert meta.read_text() != text  # the folder itself is never rewritten (symlinks in a temp folder)


def test_other_sqlite_and_mcap_like_files(tmp_path):
    db = tmp_path / "notes.db3"
    con = sqlite3.connect(db)
    con.execute("CREATE TABLE notes (x TEXT)")
    con.commit()
    con.close()
    assert R.storage_kind(db) is None
    with pytest.raises(UnknownFormatError):
        hh.detect_format(db)
    # MCAP magic and nothing else: detected, then a clear error (not a crash in rosbags)
    bad = tmp_path / "x.mcap"
    bad.write_bytes(R.MCAP_MAGIC + b"\x01" + (10 ** 6).to_bytes(8, "little"))
    assert hh.detect_format(bad) == "rosbag"
    with pytest.raises(FormatError, match="past the end"):
        hh.read(bad)


def test_mcap_chunk_bomb_is_refused(tmp_path):
    folder = _bag(tmp_path, "mcap", _events(300))
    data = bytearray(_storage_file(folder, "mcap").read_bytes())
    # find the first Chunk record (opcode 0x06) by walking the records, declare 1 TiB uncompressed
    pos = 8
    while data[pos] != 0x06:
        pos += 9 + int.from_bytes(data[pos + 1:pos + 9], "little")
    data[pos + 9 + 16:pos + 9 + 24] = (1 << 40).to_bytes(8, "little")
    bomb = tmp_path / "bomb.mcap"
    bomb.write_bytes(bytes(data))
    with pytest.raises(LimitExceeded, match="MCAP chunk at byte .* declares 1,099,511,627,776 bytes.*--allow-huge"):
        hh.read(bomb)
    # truncated: a record past the end of the file
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(bytes(data[:pos + 40]))
    with pytest.raises(FormatError, match="past the end"):
        hh.read(cut)


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_message_and_sensor_limits_alike_for_ros1_and_ros2(tmp_path, kind, monkeypatch):
    ev = _events(300)
    if kind == "ros1":
        path = _build(tmp_path, False, lambda ts, r2: {"/e": (R.EVENT_ARRAY, _event_array_msgs(ts, r2, ev, 100))})
    else:
        path = _bag(tmp_path, kind, ev, per_msg=100)
    # each message holds 100 events (13 bytes each in ROS 1, more in CDR): above a 1000-byte limit
    monkeypatch.setitem(LIMITS, "max_packet_bytes", 1000)
    with pytest.raises(LimitExceeded, match="above the limit of 1,000"):
        hh.read(path)
    with allow_huge():
        np.testing.assert_array_equal(hh.read(path).events, ev)
    monkeypatch.undo()
    # a sensor side above max_side (8192) in the messages' height/width
    big = hh.SensorSize(9000, 346)
    if kind == "ros1":
        p2 = _build(tmp_path, False, lambda ts, r2: {"/e": (R.EVENT_ARRAY, _event_array_msgs(ts, r2, ev, 100, big))},
                    name="big")
    else:
        p2 = _bag(tmp_path, kind, ev, per_msg=100, size=big, name="big")
    with pytest.raises(LimitExceeded, match="larger than the limit of 8192"):
        hh.read(p2)
