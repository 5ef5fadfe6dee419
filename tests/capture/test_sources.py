"""Sources: file replay (windows, triggers, pacing), frame replay, synthetic generator."""

from __future__ import annotations

import time

import numpy as np
import pytest

from hybridhdr import make_triggers
from hybridhdr.capture.sources import (FrameItem, ReplayEventSource, ReplayFrameSource, SyntheticEventSource,
                                       frames_from_items)
from hybridhdr.formats.container import write_recording
from hybridhdr.events import concatenate_events
from hybridhdr.model import Recording
from hybridhdr.simulate.procedural import procedural_recording


@pytest.fixture(scope="module")
def rec_file(tmp_path_factory):
    rec, _ = procedural_recording(duration_us=200_000, seed=3)
    trig = make_triggers(np.arange(1_000, 200_000, 25_000), 0, np.tile([1, -1], 4))
    rec = Recording(rec.events, rec.sensor_size, rec.frames, trig, None, rec.metadata)
    p = tmp_path_factory.mktemp("src") / "rec.h5"
    write_recording(rec, p)
    return p, rec


def test_replay_fast_windows_are_exact_and_half_open(rec_file):
    path, rec = rec_file
    with ReplayEventSource(path, pace="fast", chunk_us=7_000, read_chunk_events=5_000) as src:
        chunks = list(src)
        info = src.device_info()
    assert info["format"] == "hybridhdr" and src.sensor_size == rec.sensor_size
    ev = concatenate_events([c.events for c in chunks])
    np.testing.assert_array_equal(ev, rec.events)  # nothing lost, duplicated or reordered
    tr = np.concatenate([c.triggers for c in chunks])
    np.testing.assert_array_equal(tr, rec.triggers)
    t0 = int(rec.events["t"][0])
    for k, c in enumerate(chunks[:-1]):  # every full window is [t0 + 7000k, t0 + 7000(k+1))
        if len(c.events):
            assert c.events["t"].min() >= t0 + 7_000 * k and c.events["t"].max() < t0 + 7_000 * (k + 1)


def test_replay_realtime_paces_with_speed(rec_file):
    path, rec = rec_file
    span_s = (int(rec.events["t"][-1]) - int(rec.events["t"][0])) / 1e6
    t = time.perf_counter()
    with ReplayEventSource(path, pace="realtime", speed=4.0, chunk_us=10_000) as src:
        n = sum(len(c.events) for c in src)
    dt = time.perf_counter() - t
    assert n == len(rec.events)
    # 4x speed: about span/4 = 0.05 s; at least that (pacing), with generous slack for a loaded machine
    assert span_s / 4 * 0.9 <= dt < span_s / 4 + 2.0


def test_replay_stop_ends_iteration(rec_file):
    path, _ = rec_file
    src = ReplayEventSource(path, pace="fast", chunk_us=1_000).open()
    got = 0
    for _ in src:
        got += 1
        src.stop()
    src.close()
    assert got == 1


def test_replay_frames(rec_file):
    path, rec = rec_file
    with ReplayFrameSource(path, pace="fast") as fs:
        items = list(fs)
    assert [it.sequence for it in items] == list(range(len(rec.frames)))
    fr = frames_from_items(items, encoding=fs.encoding)
    np.testing.assert_array_equal(fr.images, rec.frames.images)
    np.testing.assert_array_equal(fr.t_start_us, rec.frames.t_start_us)
    assert items[0].exposure_us == int(rec.frames.exposure_us[0])


def test_replay_frames_refuses_file_without_frames(tmp_path):
    from hybridhdr import make_events
    p = tmp_path / "ev.h5"
    write_recording(Recording(make_events([0, 1], [0, 0], [0, 0], [1, 1]), (2, 2)), p)
    with pytest.raises(ValueError, match="holds no frames"):
        ReplayFrameSource(p).open()


def test_bad_arguments():
    with pytest.raises(ValueError, match="pace must be one of"):
        SyntheticEventSource(1e6, pace="slow")
    with pytest.raises(ValueError, match="rate_ev_per_s must be > 0"):
        SyntheticEventSource(0)
    with pytest.raises(ValueError, match="speed must be > 0"):
        ReplayEventSource("x.h5", speed=0)
    with pytest.raises(ValueError, match="exposure end"):
        FrameItem(np.zeros((2, 2)), 10, 5, 0)


def test_synthetic_stream_and_check():
    src = SyntheticEventSource(1e6, sensor_size=(10, 20), chunk_us=1_000, duration_s=0.01, pace="fast", seed=5)
    chunks = list(src)
    assert len(chunks) == 10 and src.events_emitted == 10 * 1_000
    ev = concatenate_events([c.events for c in chunks])
    assert np.all(np.diff(ev["t"]) >= 0) and ev["x"].max() < 20 and ev["y"].max() < 10
    assert src.check_events(ev) == len(ev)
    # same seed -> same bits
    again = SyntheticEventSource(1e6, sensor_size=(10, 20), chunk_us=1_000, duration_s=0.01, pace="fast", seed=5)
    np.testing.assert_array_equal(again.base, src.base)
    # a lost chunk is detected at the first event after the gap
    with pytest.raises(ValueError, match="event 3000 differs"):
        src.check_events(np.concatenate([ev[:3_000], ev[4_000:]]))


def test_synthetic_check_stream_counts_missing_chunks():
    src = SyntheticEventSource(1e6, sensor_size=(10, 20), chunk_us=1_000, duration_s=0.01, pace="fast", seed=5)
    chunks = [c.events for c in src]
    kept = [c for i, c in enumerate(chunks) if i not in (3, 4, 8)]
    ev = concatenate_events(kept)
    res = src.check_stream([ev[:1500], ev[1500:4200], ev[4200:]])  # blocks cut inside chunks
    assert res == {"events": 7_000, "chunks_present": 7, "chunks_missing": 3, "first_missing": [3, 4, 8]}
    res = src.check_stream([concatenate_events(kept[:-1])])  # a missing tail is not visible in the stream
    assert res["chunks_missing"] == 2 and res["chunks_present"] == 6
    with pytest.raises(ValueError, match="partially lost"):
        src.check_stream([ev[:-1]])
    with pytest.raises(ValueError, match="duplicated or reordered"):
        src.check_stream([concatenate_events([chunks[0], chunks[2], chunks[1]])])
