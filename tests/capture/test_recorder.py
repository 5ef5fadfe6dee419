"""Recorder: bounded queue, drop counting, frames, journal integrity, SIGKILL + recover."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from hybridhdr import make_triggers
from hybridhdr.capture import recorder as R
from hybridhdr.capture.recorder import Recorder, journal_path, read_journal, recover
from hybridhdr.capture.sources import ReplayEventSource, ReplayFrameSource, SyntheticEventSource
from hybridhdr.formats.container import RecordingFile, read_recording, write_recording
from hybridhdr.errors import FormatError
from hybridhdr.model import Recording
from hybridhdr.simulate.procedural import procedural_recording

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _read_all(path):
    with RecordingFile(path) as f:
        return f.events(), f.metadata


def test_synthetic_fast_roundtrip_exact(tmp_path):
    src = SyntheticEventSource(2e6, sensor_size=(30, 40), chunk_us=1_000, duration_s=0.2, pace="fast", seed=1)
    out = tmp_path / "r.h5"
    stats = Recorder(out, src, queue_chunks=4, flush_interval_s=0.05, compression=None).record()
    ev, md = _read_all(out)
    assert stats.events_received == stats.events_written == src.events_emitted == len(ev) == 400_000
    assert src.check_events(ev) == len(ev)  # every event, in order, bit-exact
    assert stats.events_dropped == 0 and stats.policy == "block"
    assert md.provenance["recorder"]["events_written"] == 400_000
    assert not journal_path(out).exists() and not out.with_name("r.h5.partial").exists()


@pytest.mark.parametrize("journal_compression", ["lz4", None])
def test_replay_events_triggers_frames(tmp_path, journal_compression):
    rec, _ = procedural_recording(duration_us=150_000, seed=2)
    trig = make_triggers(np.arange(500, 150_000, 10_000), 1, np.tile([1, -1], 8)[:15])
    rec = Recording(rec.events, rec.sensor_size, rec.frames, trig, None, rec.metadata)
    src_path = tmp_path / "src.h5"
    write_recording(rec, src_path)
    out = tmp_path / "out.h5"
    stats = Recorder(out, ReplayEventSource(src_path, pace="fast", chunk_us=5_000),
                     ReplayFrameSource(src_path, pace="fast"), journal_compression=journal_compression,
                     flush_interval_s=0.05).record()
    back = read_recording(out)
    np.testing.assert_array_equal(back.events, rec.events)
    np.testing.assert_array_equal(back.triggers, rec.triggers)
    np.testing.assert_array_equal(back.frames.images, rec.frames.images)
    np.testing.assert_array_equal(back.frames.t_end_us, rec.frames.t_end_us)
    assert back.frames.encoding == rec.frames.encoding
    assert stats.frames_written == len(rec.frames) and stats.triggers_written == len(trig)
    assert back.metadata.provenance["sources"]["events"]["kind"] == "replay"


class _LiveSource(SyntheticEventSource):
    """A generator that claims to be a live device (cannot be back-pressured)."""

    can_backpressure = False


def test_drops_are_counted_logged_and_stored(tmp_path, monkeypatch, caplog):
    orig = R.JournalWriter.write_events

    def slow(self, ev):  # a writer slower than the source
        time.sleep(0.01)
        orig(self, ev)

    monkeypatch.setattr(R.JournalWriter, "write_events", slow)
    src = _LiveSource(1e6, sensor_size=(8, 8), chunk_us=1_000, duration_s=0.1, pace="fast")
    out = tmp_path / "d.h5"
    with caplog.at_level(logging.WARNING, logger="hybridhdr.capture.recorder"):
        stats = Recorder(out, src, queue_chunks=2, flush_interval_s=0.05, compression=None).record()
    assert stats.policy == "drop"
    assert stats.events_dropped > 0 and stats.event_chunks_dropped > 0
    assert stats.events_written + stats.events_dropped == stats.events_received == src.events_emitted
    ev, md = _read_all(out)
    assert len(ev) == stats.events_written
    assert md.provenance["recorder"]["events_dropped"] == stats.events_dropped
    # every chunk in the file is complete and exact; the missing ones are exactly the counted drops
    res = src.check_stream([ev])
    assert src.chunks_emitted - res["chunks_present"] == stats.event_chunks_dropped
    assert any("dropped" in r.getMessage() for r in caplog.records)


def test_block_policy_refused_for_live_source(tmp_path):
    with pytest.raises(ValueError, match="back-pressured"):
        Recorder(tmp_path / "x.h5", _LiveSource(1e3), on_full="block").start()


def test_refuses_existing_output_and_bad_args(tmp_path):
    (tmp_path / "x.h5").write_bytes(b"")
    with pytest.raises(FileExistsError):
        Recorder(tmp_path / "x.h5", SyntheticEventSource(1e3)).start()
    with pytest.raises(ValueError, match="on_full"):
        Recorder(tmp_path / "y.h5", SyntheticEventSource(1e3), on_full="maybe")
    with pytest.raises(ValueError, match="flush_interval_s"):
        Recorder(tmp_path / "y.h5", SyntheticEventSource(1e3), flush_interval_s=0)


def _journal_of(tmp_path, n_chunks=6):
    src = SyntheticEventSource(1e5, sensor_size=(8, 8), chunk_us=1_000, duration_s=n_chunks / 1000, pace="fast")
    r = Recorder(tmp_path / "j.h5", src, flush_interval_s=10.0)
    r.start()
    r.wait()
    r.stop()
    r._jw.close()  # leave the journal as a crash would (no END record, no container)
    return journal_path(tmp_path / "j.h5"), src


def test_recover_stops_at_torn_or_corrupt_record(tmp_path):
    jp, src = _journal_of(tmp_path)
    data = jp.read_bytes()
    full = read_journal(jp)
    assert full.stop_reason == "end of file" and full.flushes == 1
    offsets = []
    pos = 8
    while pos < len(data):
        _, rtype, _, _, stored, _, _, _ = R._HDR.unpack_from(data, pos)
        offsets.append((rtype, pos))
        pos += 32 + stored
    ev_recs = [p for t, p in offsets if t == R.T_EVENTS]
    assert len(ev_recs) == 6
    # tear the file in the middle of the last EVENTS record: the recovered prefix is still exact
    jp.write_bytes(data[: ev_recs[-1] + 40])
    res = recover(tmp_path / "j.h5")
    ev, md = _read_all(tmp_path / "j.h5")
    assert res["events"] == len(ev) == 500  # 6 chunks of 100, the last one (and the flush) torn off
    assert src.check_events(ev) == 500
    assert "truncated" in res["stop_reason"] and md.provenance["recorder"]["recovered"] is True
    # flip a payload byte of the 3rd EVENTS record: recovery stops before it (CRC)
    (tmp_path / "j.h5").unlink()
    bad = bytearray(data)
    bad[ev_recs[2] + 40] ^= 0xFF
    jp.write_bytes(bytes(bad))
    res = recover(tmp_path / "j.h5")
    assert res["events"] == 200 and "checksum" in res["stop_reason"]


def test_recover_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no journal"):
        recover(tmp_path / "none.h5")
    (tmp_path / "z.h5.journal").write_bytes(b"garbage!" * 4)
    with pytest.raises(FormatError, match="not a hybridhdr journal"):
        recover(tmp_path / "z.h5")


CHILD = textwrap.dedent("""
    import json, sys
    sys.path.insert(0, {repo!r})
    from hybridhdr.capture.sources import SyntheticEventSource
    from hybridhdr.capture.recorder import Recorder
    src = SyntheticEventSource(200_000, sensor_size=(64, 64), chunk_us=5_000, pace="realtime", seed=7)
    def on_flush(s):
        print(json.dumps({{"flushes": s["flushes"], "events_written": s["events_written"]}}), flush=True)
    Recorder({out!r}, src, flush_interval_s=0.15, on_flush=on_flush).record(60.0)
""")


def test_sigkill_then_recover_keeps_everything_up_to_last_flush(tmp_path):
    out = tmp_path / "killed.h5"
    script = tmp_path / "child.py"
    script.write_text(CHILD.format(repo=REPO, out=str(out)))
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    last = None
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            last = json.loads(line)
            if last["flushes"] >= 3:
                break
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(10)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    assert last is not None and last["flushes"] >= 3 and last["events_written"] > 0
    assert journal_path(out).exists() and not out.exists()
    res = recover(out)
    ev, md = _read_all(out)
    # everything up to the last flush the child reported is there (and possibly later intact records)
    assert res["events"] == len(ev) >= last["events_written"]
    assert res["flushes"] >= last["flushes"]
    gen = SyntheticEventSource(200_000, sensor_size=(64, 64), chunk_us=5_000, seed=7)
    assert gen.check_events(ev) == len(ev)  # exact, in order: event i is what the child generated
    assert md.provenance["recorder"]["recovered"] is True


def test_pack_columns_kernel_matches_py_func():
    from hybridhdr.capture._kernels import pack_columns
    ev = SyntheticEventSource(1e6, sensor_size=(5, 7), chunk_us=20, seed=3).base
    outs = []
    for f in (pack_columns, pack_columns.py_func):
        cols = [np.empty(len(ev), ev.dtype[k]) for k in ("t", "x", "y", "p")]
        assert f(ev["t"], ev["x"], ev["y"], ev["p"], *cols) == len(ev)
        outs.append(cols)
    for a, b, k in zip(outs[0], outs[1], ("t", "x", "y", "p")):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, ev[k])
    empty = ev[:0]
    assert pack_columns(empty["t"], empty["x"], empty["y"], empty["p"],
                        *[np.empty(0, ev.dtype[k]) for k in ("t", "x", "y", "p")]) == 0


def imu_sample(k):
    """IMU sample number ``k`` (array of ``k``) of the deterministic IMU stream the tests below record:
    every field a distinct float32 function of ``k``, NaN magnetometer x on every 5th (not measured)."""
    from hybridhdr.events import IMU_FIELDS, empty_imu
    k = np.asarray(k, np.int64)
    out = empty_imu(len(k))
    out["t"] = 1_000 * k
    for j, (name, _, _) in enumerate(IMU_FIELDS):
        out[name] = ((k % 997) * 0.125 + j * 1.5 - 40.0).astype(np.float32)
    out["mag_x_ut"][k % 5 == 0] = np.nan
    return out


class ImuSyntheticSource(SyntheticEventSource):
    """Synthetic events with ``imu_per_chunk`` IMU samples handed over with every chunk, as a live
    DAVIS's event source does."""

    imu_per_chunk = 7

    def _iter(self):
        from hybridhdr.formats import EventChunk
        k = 0
        for c in super()._iter():
            yield EventChunk(c.events, c.triggers, imu_sample(np.arange(k, k + self.imu_per_chunk)))
            k += self.imu_per_chunk


def test_imu_samples_are_journaled_and_stored_exactly(tmp_path):
    src = ImuSyntheticSource(1e6, sensor_size=(30, 40), chunk_us=2_000, duration_s=0.1, pace="fast", seed=2)
    out = tmp_path / "imu.h5"
    stats = Recorder(out, src, queue_chunks=4, flush_interval_s=0.02).record()
    back = read_recording(out)
    n = 50 * ImuSyntheticSource.imu_per_chunk  # 0.1 s in chunks of 2 ms
    assert stats.imu_written == len(back.imu) == n and stats.imu_dropped == 0
    assert back.imu.tobytes() == imu_sample(np.arange(n)).tobytes()  # every sample, every field, NaN too
    assert src.check_events(back.events) == len(back.events) == stats.events_written
    assert back.metadata.provenance["recorder"]["imu_written"] == n


def test_imu_recovered_from_a_torn_journal(tmp_path):
    src = ImuSyntheticSource(1e5, sensor_size=(8, 8), chunk_us=1_000, duration_s=0.006, pace="fast", seed=1)
    r = Recorder(tmp_path / "j.h5", src, flush_interval_s=3600)
    r.start()
    r.wait()
    r.stop()
    r._jw.close()  # the journal as a crash leaves it: no END record, no container
    jp = journal_path(tmp_path / "j.h5")
    data = jp.read_bytes()
    offsets, pos = [], 8
    while pos < len(data):
        _, rtype, _, _, stored, _, _, _ = R._HDR.unpack_from(data, pos)
        offsets.append((rtype, pos))
        pos += 32 + stored
    imu_recs = [p for t, p in offsets if t == R.T_IMU]
    assert len(imu_recs) == 6
    jp.write_bytes(data[: imu_recs[-1] + 40])  # tear the last IMU record
    res = recover(tmp_path / "j.h5")
    back = read_recording(tmp_path / "j.h5")
    assert res["imu"] == len(back.imu) == 5 * ImuSyntheticSource.imu_per_chunk
    assert back.imu.tobytes() == imu_sample(np.arange(len(back.imu))).tobytes()


CHILD_IMU = textwrap.dedent("""
    import json, sys
    sys.path.insert(0, {repo!r})
    from tests.capture.test_recorder import ImuSyntheticSource
    from hybridhdr.capture.recorder import Recorder
    src = ImuSyntheticSource(100_000, sensor_size=(32, 32), chunk_us=5_000, pace="realtime", seed=9)
    def on_flush(s):
        print(json.dumps({{"flushes": s["flushes"], "imu_written": s["imu_written"]}}), flush=True)
    Recorder({out!r}, src, flush_interval_s=0.15, on_flush=on_flush).record(60.0)
""")


def test_sigkill_then_recover_keeps_imu_up_to_last_flush(tmp_path):
    out = tmp_path / "killed_imu.h5"
    script = tmp_path / "child_imu.py"
    script.write_text(CHILD_IMU.format(repo=REPO, out=str(out)))
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    last = None
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            last = json.loads(line)
            if last["flushes"] >= 3 and last["imu_written"] > 0:
                break
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(10)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    assert last is not None and last["imu_written"] > 0
    res = recover(out)
    back = read_recording(out)
    # every IMU sample written before the last flush the child reported is there, exact and in order
    assert res["imu"] == len(back.imu) >= last["imu_written"]
    assert back.imu.tobytes() == imu_sample(np.arange(len(back.imu))).tobytes()
    assert back.metadata.provenance["recorder"]["recovered"] is True


def test_imu_out_of_order_across_chunks_stops_the_recording_with_a_clear_error(tmp_path):
    class Backwards(ImuSyntheticSource):
        def _iter(self):
            from hybridhdr.formats import EventChunk
            for i, c in enumerate(SyntheticEventSource._iter(self)):
                yield EventChunk(c.events, c.triggers, imu_sample(np.arange(7) + (100 if i == 0 else 0)))

    src = Backwards(1e5, sensor_size=(8, 8), chunk_us=1_000, duration_s=0.005, pace="fast", seed=1)
    with pytest.raises(RuntimeError, match="IMU samples out of time order") as e:
        Recorder(tmp_path / "b.h5", src).record()
    assert "capture recover" in str(e.value) and journal_path(tmp_path / "b.h5").exists()
