"""Prophesee RAW (EVT 2.0 / 2.1 / 3.0) and DAT: sample files, round trips, streaming, bad input."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hybridhdr import EVENT_DTYPE, TRIGGER_DTYPE, FormatError, SensorSize, make_events, make_triggers
from hybridhdr.formats import _kernels as K
from hybridhdr.formats import prophesee as P
from hybridhdr.formats import detect_format

SAMPLES = {
    # file: (format, events, first t, last t, sensor)
    "prophesee/sparklers_gen3_evt2.raw": ("evt2", 521_252, 913_716_224, 913_812_095, SensorSize(480, 640)),
    "prophesee/evt2_sample.raw": ("evt2", 539_481, 1_317_888, 1_367_888, SensorSize(480, 640)),
    "prophesee/evt3_sample.raw": ("evt3", 219_596, 11_718_656, 11_727_457, SensorSize(720, 1280)),
}


# ------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------
def _write(fmt, path, events, triggers=None, sensor=(480, 640), batches=1, **opts):
    """Write in ``batches`` write_events calls; each batch's triggers (those before the next batch)
    are written right after it, as ``write_chunk`` does."""
    tr = triggers if triggers is not None else np.zeros(0, TRIGGER_DTYPE)
    with P.WRITERS[fmt](path, sensor_size=sensor, **opts) as w:
        parts = [q for q in np.array_split(events, batches) if len(q)] if len(events) else []
        for i, part in enumerate(parts):
            w.write_events(part)
            if "triggers" in w.supports:
                k = len(tr) if i == len(parts) - 1 else int(np.searchsorted(tr["t"], parts[i + 1]["t"][0], "right"))
                w.write_triggers(tr[:k])
                tr = tr[k:]
        if len(tr) and "triggers" in w.supports:
            w.write_triggers(tr)
    return Path(path)


def _read(fmt, path, **opts):
    c = P.READERS[fmt](path, **opts).read_all()
    return c.events, c.triggers


def _stream(fmt, path, chunk_events, **opts):
    evs, trs = [], []
    for c in P.READERS[fmt](path, **opts).iter_chunks(chunk_events):
        evs.append(c.events)
        trs.append(c.triggers)
    ev = np.concatenate(evs) if evs else np.zeros(0, EVENT_DTYPE)
    tr = np.concatenate(trs) if trs else np.zeros(0, TRIGGER_DTYPE)
    return ev, tr[np.argsort(tr["t"], kind="stable")]


def _raw_file(tmp, name, header: str, words: np.ndarray) -> Path:
    p = Path(tmp) / name
    p.write_bytes(header.encode() + np.ascontiguousarray(words).tobytes())
    return p


@st.composite
def event_streams(draw, sensor, max_dt, max_clusters=40, t_cap=None):
    """Sorted events: clusters (singles or same-t/y/p runs) with sensor-edge coordinates."""
    h, w = sensor
    n = draw(st.integers(0, max_clusters))
    t = draw(st.integers(0, min(max_dt, 1 << 20)))
    ts, xs, ys, ps = [], [], [], []
    for _ in range(n):
        t += draw(st.one_of(st.just(0), st.integers(0, 70), st.integers(0, max_dt)))
        if t_cap is not None and t >= t_cap:
            break
        y = draw(st.one_of(st.just(h - 1), st.just(0), st.integers(0, h - 1)))
        p = draw(st.sampled_from([-1, 1]))
        run = draw(st.integers(1, 14))
        x = draw(st.one_of(st.just(w - 1), st.just(0), st.integers(0, w - 1)))
        for _ in range(run):
            if x >= w:
                break
            ts.append(t); xs.append(x); ys.append(y); ps.append(p)
            x += draw(st.integers(0, 3))  # 0 gives equal x (a run break)
    return make_events(np.array(ts, np.int64), np.array(xs, np.int64), np.array(ys, np.int64),
                       np.array(ps, np.int64))


@st.composite
def trigger_streams(draw, t_max, max_channel):
    k = draw(st.integers(0, 6))
    t = np.sort(np.array([draw(st.integers(0, max(0, t_max))) for _ in range(k)], np.int64))
    ch = [draw(st.integers(0, max_channel - 1)) for _ in range(k)]
    e = [draw(st.sampled_from([-1, 1])) for _ in range(k)]
    return make_triggers(t, np.array(ch, np.int64), np.array(e, np.int64))


SENSORS = st.sampled_from([(480, 640), (720, 1280), (3, 13), (1, 1), (2048, 2048)])
HSET = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ------------------------------------------------------------------------------------------------
# sample files
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("rel", list(SAMPLES))
def test_sample_files(shared_data, rel):
    path = shared_data(rel)
    fmt, n, t0, t1, ss = SAMPLES[rel]
    assert P.sniff(path, path.read_bytes()[:4096]) == fmt
    assert detect_format(path) == fmt
    r = P.READERS[fmt](path)
    assert r.sensor_size == ss
    assert r.metadata.event_camera.sensor_size == ss
    assert r.metadata.event_camera.model.startswith("hal_plugin_gen")
    assert r.metadata.provenance["format"] == fmt
    rec = r.read()
    ev = rec.events
    assert len(ev) == n
    assert (int(ev["t"][0]), int(ev["t"][-1])) == (t0, t1)
    assert np.all(np.diff(ev["t"]) >= 0)
    assert r.stats["out_of_order_events"] == 0
    # streaming with tiny blocks and chunks gives the same events
    s_ev, _ = _stream(fmt, path, 777, block_bytes=4096 + 8)
    assert np.array_equal(s_ev, ev)


def test_evt3_sample_matches_evt3_package(shared_data):
    evt3 = pytest.importorskip("evt3")
    path = shared_data("prophesee/evt3_sample.raw")
    ev, _ = _read("evt3", path)
    ref = evt3.decode_file(str(path))
    assert np.array_equal(ev["t"], ref.timestamp.astype(np.int64))
    assert np.array_equal(ev["x"], ref.x)
    assert np.array_equal(ev["y"], ref.y)
    assert np.array_equal(ev["p"], np.where(ref.polarity > 0, 1, -1))
    # ≈ 8.8 ms span by the spec (expelliarmus reports ~54 ms, wrongly)
    assert 8_700 <= int(ev["t"][-1] - ev["t"][0]) <= 8_900


@pytest.mark.parametrize("rel", ["prophesee/sparklers_gen3_evt2.raw", "prophesee/evt2_sample.raw"])
def test_evt2_samples_match_expelliarmus(shared_data, rel):
    ex = pytest.importorskip("expelliarmus")
    path = shared_data(rel)
    ev, _ = _read("evt2", path)
    ref = ex.Wizard(encoding="evt2").read(path)
    for f in ("t", "x", "y"):
        assert np.array_equal(ev[f], ref[f].astype(ev[f].dtype))
    assert np.array_equal(ev["p"], np.where(ref["p"] > 0, 1, -1))


def test_sample_rewrite_round_trip(shared_data, tmp_path):
    path = shared_data("prophesee/evt3_sample.raw")
    rec = P.Evt3Reader(path).read()
    for fmt in ("evt3", "evt2", "dat"):
        out = _write(fmt, tmp_path / f"o.{fmt}", rec.events, sensor=rec.sensor_size)
        ev, _ = _read(fmt, out)
        assert np.array_equal(ev, rec.events), fmt
    # the EVT3 writer uses vectors: the file is far smaller than one ADDR_X per event
    assert (tmp_path / "o.evt3").stat().st_size < 2 * len(rec.events) * 1.6


# ------------------------------------------------------------------------------------------------
# round trips (hypothesis)
# ------------------------------------------------------------------------------------------------
@HSET
@given(data=st.data(), sensor=SENSORS, batches=st.integers(1, 3))
def test_round_trip_evt3(data, sensor, batches):
    ev = data.draw(event_streams(sensor, max_dt=(1 << 25) + 7))  # crosses 2^24 µs loops
    tmax = int(ev["t"][-1]) if len(ev) else 1000
    tr = data.draw(trigger_streams(tmax + 5, 16))
    with tempfile.TemporaryDirectory() as d:
        p = _write("evt3", Path(d) / "a.raw", ev, tr, sensor, batches)
        assert P.sniff(p, p.read_bytes()[:4096]) == "evt3"
        got, gtr = _read("evt3", p, reorder_window_us=0)
        assert np.array_equal(got, ev)
        assert np.array_equal(gtr, tr)
        s_ev, s_tr = _stream("evt3", p, 3, block_bytes=6)
        assert np.array_equal(s_ev, ev)
        assert np.array_equal(s_tr, tr)


@HSET
@given(data=st.data(), sensor=SENSORS, batches=st.integers(1, 3))
def test_round_trip_evt2(data, sensor, batches):
    ev = data.draw(event_streams(sensor, max_dt=(1 << 35) + 3, t_cap=1 << 44))  # crosses 2^34 µs
    tmax = int(ev["t"][-1]) if len(ev) else 1000
    tr = data.draw(trigger_streams(tmax + 5, 32))
    with tempfile.TemporaryDirectory() as d:
        p = _write("evt2", Path(d) / "a.raw", ev, tr, sensor, batches)
        assert P.sniff(p, p.read_bytes()[:4096]) == "evt2"
        got, gtr = _read("evt2", p, reorder_window_us=0)
        assert np.array_equal(got, ev)
        assert np.array_equal(gtr, tr)
        s_ev, s_tr = _stream("evt2", p, 2, block_bytes=12)
        assert np.array_equal(s_ev, ev)
        assert np.array_equal(s_tr, tr)


@HSET
@given(data=st.data(), sensor=SENSORS, batches=st.integers(1, 3))
def test_round_trip_dat(data, sensor, batches):
    ev = data.draw(event_streams(sensor, max_dt=(1 << 31) - 1))  # crosses 2^32 µs
    with tempfile.TemporaryDirectory() as d:
        p = _write("dat", Path(d) / "a.dat", ev, None, sensor, batches)
        assert P.sniff(p, p.read_bytes()[:4096]) == "dat"
        got, _ = _read("dat", p)
        assert np.array_equal(got, ev)
        s_ev, _ = _stream("dat", p, 3, block_bytes=16)
        assert np.array_equal(s_ev, ev)
        if len(ev):
            got_par, _ = _read("dat", p, parallel=True)
            assert np.array_equal(got_par, ev)


@HSET
@given(data=st.data(), sensor=st.sampled_from([(480, 640), (720, 1280), (320, 320), (3, 40)]),
       legacy=st.booleans())
def test_round_trip_evt21(data, sensor, legacy):
    ev = data.draw(event_streams(sensor, max_dt=5000))
    body = P._encode_evt21(ev, legacy=legacy)
    h, w = sensor
    end = ";endianness=legacy" if legacy else ""
    with tempfile.TemporaryDirectory() as d:
        p = _raw_file(d, "a.raw", f"% evt 2.1\n% format EVT21;height={h};width={w}{end}\n% end\n",
                      np.frombuffer(body, np.uint8))
        assert P.sniff(p, p.read_bytes()[:4096]) == "evt21"
        r = P.Evt21Reader(p)
        assert r.legacy == legacy
        got = r.read_all().events
        assert np.array_equal(got, ev)
        s_ev, _ = _stream("evt21", p, 5, block_bytes=24)
        assert np.array_equal(s_ev, ev)
        # the wrong byte order does not silently give the same events
        if len(ev):
            try:
                other = P.Evt21Reader(p, legacy=not legacy).read_all().events
            except FormatError:
                pass
            else:
                assert not np.array_equal(other, ev)


def test_evt21_byte_order_example(tmp_path):
    # Prophesee's example: the 64-bit word 0x0102030405060708 arrives as 04 03 02 01 08 07 06 05
    # in legacy order. A POS event word with mask 0b101 at x=32, y=7, t6=3 after TIME_HIGH 1:
    header = (1 << 28) | (3 << 22) | (32 << 11) | 7
    mask = 0b101
    th = 8 << 28 | 1
    std = np.array([0, th, mask, header], np.uint32)     # mask in bytes 0-3, header in 4-7
    leg = np.array([th, 0, header, mask], np.uint32)     # header in bytes 0-3, mask in 4-7
    word = 0x0102030405060708  # header = high 32 bits, mask = low 32 bits
    legacy_bytes = np.array([word >> 32, word & 0xFFFFFFFF], "<u4").view(np.uint8)
    assert legacy_bytes.tolist() == [4, 3, 2, 1, 8, 7, 6, 5]
    assert np.array([word], "<u8").view(np.uint8).tolist() == [8, 7, 6, 5, 4, 3, 2, 1]  # standard
    for words, endian in ((std, ""), (leg, ";endianness=legacy")):
        p = _raw_file(tmp_path, f"e{endian != ''}.raw", f"% format EVT21;height=100;width=100{endian}\n", words)
        ev = P.Evt21Reader(p).read_all().events
        assert ev[["t", "x", "y", "p"]].tolist() == [(67, 32, 7, 1), (67, 34, 7, 1)]


# ------------------------------------------------------------------------------------------------
# decoding rules (hand-made words)
# ------------------------------------------------------------------------------------------------
def evt3_words(*ws):
    return np.array(ws, np.uint16)


def test_evt3_rules(tmp_path):
    w = evt3_words(
        0x2005,                # ADDR_X before the first TIME_HIGH: skipped
        0x8FFE,                # TIME_HIGH 0xFFE
        0x0003,                # ADDR_Y 3
        0x6005,                # TIME_LOW 5
        0x2801,                # ADDR_X 1, ON
        0x3004,                # VECT_BASE_X 4, OFF
        0x4805,                # VECT_12 bits 0, 2, 11 -> x 4, 6, 15
        0x5003,                # VECT_8 bits 0, 1 -> x 16, 17
        0x7001, 0xF002, 0xE014, 0xD000,  # CONTINUED / OTHERS / IMU skipped
        0xA301,                # trigger channel 3 rising
        0x6003,                # TIME_LOW going back: no wrap inferred (within window)
        0x8002,                # TIME_HIGH drop 0xFFE -> 0x002: loop
        0x2002,                # ADDR_X 2 OFF at t = 2^24 + 0x002 << 12
    )
    p = _raw_file(tmp_path, "r.raw", "% evt 3.0\n% geometry 32x8\n", w)
    c = P.Evt3Reader(p).read_all()
    t0 = 0xFFE << 12
    assert c.events[["t", "x", "y", "p"]].tolist() == [
        (t0 + 5, 1, 3, 1), (t0 + 5, 4, 3, -1), (t0 + 5, 6, 3, -1), (t0 + 5, 15, 3, -1),
        (t0 + 5, 16, 3, -1), (t0 + 5, 17, 3, -1), ((1 << 24) + (2 << 12), 2, 3, -1)]
    assert c.triggers.tolist() == [(t0 + 5, 3, 1)]


def test_evt2_rules(tmp_path):
    w = np.array([
        (1 << 28) | (5 << 11) | 2,            # CD before first TIME_HIGH: skipped
        (8 << 28) | 0xFFFFFFF,                # TIME_HIGH max
        (1 << 28) | (63 << 22) | (7 << 11) | 3,
        (0xA << 28) | (2 << 22) | (4 << 8) | 0,   # trigger ch 4 falling
        (0xE << 28), (0xD << 28), (0xF << 28),
        (8 << 28) | 1,                        # wrap: 2^34 + 64
        (0 << 28) | (1 << 22) | (9 << 11) | 4,
    ], np.uint32)
    p = _raw_file(tmp_path, "r.raw", "% evt 2.0\n% format EVT2;height=8;width=16\n", w)
    c = P.Evt2Reader(p).read_all()
    tmax = (0xFFFFFFF << 6)
    assert c.events[["t", "x", "y", "p"]].tolist() == [(tmax + 63, 7, 3, 1), ((1 << 34) + 65, 9, 4, -1)]
    assert c.triggers.tolist() == [(tmax + 2, 4, -1)]


def test_reorder_window(tmp_path):
    # EVT 2.0: two events in one TIME_HIGH period out of order by 10 µs, then on
    th = (8 << 28) | 100
    w = np.array([th, (1 << 28) | (20 << 22) | (1 << 11) | 1, (1 << 28) | (10 << 22) | (2 << 11) | 1,
                  (1 << 28) | (30 << 22) | (3 << 11) | 1], np.uint32)
    p = _raw_file(tmp_path, "d.raw", "% evt 2.0\n% geometry 16x16\n", w)
    r = P.Evt2Reader(p)
    ev = r.read_all().events
    assert ev["t"].tolist() == [6410, 6420, 6430] and ev["x"].tolist() == [2, 1, 3]
    assert r.stats["out_of_order_events"] == 1
    s_ev, _ = _stream("evt2", p, 1, block_bytes=4)
    assert np.array_equal(s_ev, ev)
    with pytest.raises(FormatError, match="byte offset .*backwards"):
        P.Evt2Reader(p, reorder_window_us=5).read_all()
    # a big jump back that is no wrap is corrupt data
    w2 = np.array([(8 << 28) | 1000, (1 << 28) | (1 << 11), (8 << 28) | 10, (1 << 28) | (2 << 11)], np.uint32)
    p2 = _raw_file(tmp_path, "b.raw", "% evt 2.0\n% geometry 16x16\n", w2)
    with pytest.raises(FormatError) as ei:
        P.Evt2Reader(p2).read_all()
    assert "b.raw" in str(ei.value) and "byte offset" in str(ei.value) and ei.value.offset == p2.stat().st_size - 4


def test_streaming_reorder_across_chunks(tmp_path):
    # events encoded up to 40 µs out of order (within the 1000 µs window): whatever the chunk and
    # block sizes, the chunks are sorted, continue each other and add up to read_all's array (the
    # held-back events are decoded into the start of the next chunk's buffer)
    rng = np.random.default_rng(11)
    n = 3000
    t = np.cumsum(rng.integers(0, 3, n)).astype(np.int64) + 64 * 1000
    order = np.argsort(t + rng.integers(0, 40, n), kind="stable")
    ts, xs, ys = t[order], rng.integers(0, 16, n)[order], rng.integers(0, 16, n)[order]
    ps = rng.integers(0, 2, n)[order]
    words, th = [], -1
    for ti, xi, yi, pi in zip(ts.tolist(), xs.tolist(), ys.tolist(), ps.tolist()):
        if ti >> 6 != th:
            th = ti >> 6
            words.append((8 << 28) | th)
        words.append((pi << 28) | ((ti & 63) << 22) | (xi << 11) | yi)
    p = _raw_file(tmp_path, "d.raw", "% evt 2.0\n% geometry 16x16\n", np.array(words, np.uint32))
    r = P.Evt2Reader(p)
    ref = r.read_all().events
    assert r.stats["out_of_order_events"] > 0
    assert np.array_equal(ref["t"], np.sort(t))
    for chunk_events in (1, 7, 100, 2999, 5000):
        for opts in ({}, {"block_bytes": 12}, {"reorder_window_us": 100}):
            got = list(P.Evt2Reader(p, **opts).iter_chunks(chunk_events))
            ev = np.concatenate([c.events for c in got])
            for k in "txyp":
                assert np.array_equal(ev[k], ref[k]), (chunk_events, opts, k)
            assert all(len(c.events) <= chunk_events + 1000 for c in got)


# ------------------------------------------------------------------------------------------------
# stream decoders
# ------------------------------------------------------------------------------------------------
def test_evt3_decoder_odd_splits(shared_data):
    path = shared_data("prophesee/evt3_sample.raw")
    r = P.Evt3Reader(path)
    ref = r.read_all()
    body = path.read_bytes()[r._data_offset:]
    dec = P.Evt3Decoder(r.sensor_size)
    rng = np.random.default_rng(3)
    evs, trs, pos = [], [], 0
    while pos < len(body):
        k = int(rng.integers(1, 40001))
        e, t = dec.decode(body[pos:pos + k])
        evs.append(e)
        trs.append(t)
        pos += k
    evs.append(dec.flush()[0])
    assert np.array_equal(np.concatenate(evs), ref.events)
    one, _ = P.decode_evt3(np.frombuffer(body, np.uint8), r.sensor_size)
    assert np.array_equal(one, ref.events)
    dec2 = P.Evt3Decoder()
    dec2.decode(body[:3])
    with pytest.raises(FormatError, match="partial"):
        dec2.flush()


def test_evt2_decoder(shared_data):
    path = shared_data("prophesee/evt2_sample.raw")
    r = P.Evt2Reader(path)
    body = path.read_bytes()[r._data_offset:]
    ev, _ = P.decode_evt2(body, r.sensor_size)
    assert np.array_equal(ev, r.read_all().events)


# ------------------------------------------------------------------------------------------------
# writers
# ------------------------------------------------------------------------------------------------
def test_writer_header_and_metadata(tmp_path):
    from hybridhdr import CameraInfo, Metadata
    md = Metadata(event_camera=CameraInfo(SensorSize(720, 1280), "hal_plugin_imx636", "ABC 1"))
    ev = make_events([5, 6], [1, 1279], [719, 0], [1, -1])
    with P.Evt3Writer(tmp_path / "m.raw", sensor_size=(720, 1280), metadata=md) as w:
        w.write_events(ev)
    text = (tmp_path / "m.raw").read_bytes().split(b"% end\n")[0].decode()
    assert "% format EVT3;height=720;width=1280" in text and "% geometry 1280x720" in text
    r = P.Evt3Reader(tmp_path / "m.raw")
    assert r.metadata.event_camera == CameraInfo(SensorSize(720, 1280), "hal_plugin_imx636", "ABC 1")
    assert r.metadata.provenance["header"]["evt"] == "3.0"


@pytest.mark.parametrize("fmt", ["evt2", "evt3", "dat"])
def test_writer_rejects_negative_time(tmp_path, fmt):
    w = P.WRITERS[fmt](tmp_path / f"n.{fmt}", sensor_size=(10, 10))
    with pytest.raises(ValueError, match=">= 0"):
        w.write_events(make_events([-1, 3], [0, 1], [0, 0], [1, 1]))
    w.abort()
    assert not (tmp_path / f"n.{fmt}").exists() and not (tmp_path / f"n.{fmt}.partial").exists()


def test_writer_trigger_rules(tmp_path):
    ev = make_events([10, 20, 30], [0, 1, 2], [0, 0, 0], [1, 1, 1])
    with P.Evt3Writer(tmp_path / "t.raw", sensor_size=(4, 4)) as w:
        w.write_events(ev[:2])
        w.write_triggers(make_triggers([15], [1], [1]))   # inside the pending batch: fine
        w.write_events(ev[2:])
        with pytest.raises(ValueError, match="earlier than events already encoded"):
            w.write_triggers(make_triggers([5], [1], [1]))
        with pytest.raises(ValueError, match="channels must be < 16"):
            w.write_triggers(make_triggers([50], [16], [1]))
    ev2, tr2 = _read("evt3", tmp_path / "t.raw")
    assert np.array_equal(ev2, ev) and tr2.tolist() == [(15, 1, 1)]


def test_dat_writer_limits(tmp_path):
    with pytest.raises(ValueError, match="2\\^32"):
        with P.DatWriter(tmp_path / "a.dat", sensor_size=(4, 4)) as w:
            w.write_events(make_events([1 << 32], [0], [0], [1]))
    with pytest.raises(ValueError, match="2\\^31"):
        with P.DatWriter(tmp_path / "b.dat", sensor_size=(4, 4)) as w:
            w.write_events(make_events([0, 1 << 31], [0, 0], [0, 0], [1, 1]))
    assert not list(tmp_path.iterdir())


def test_empty_files_round_trip(tmp_path):
    for fmt in ("evt2", "evt3", "dat"):
        p = _write(fmt, tmp_path / f"e.{fmt}", np.zeros(0, EVENT_DTYPE))
        ev, tr = _read(fmt, p)
        assert len(ev) == 0 and len(tr) == 0
        assert P.sniff(p, p.read_bytes()[:4096]) == fmt


# ------------------------------------------------------------------------------------------------
# sniffing and headers
# ------------------------------------------------------------------------------------------------
def test_sniff_variants(tmp_path):
    cases = {
        b"% evt 3.0\n": ("x.bin", "evt3"), b"% format EVT3;height=1;width=1\n": ("x.bin", "evt3"),
        b"% evt 2.1\n": ("x.bin", "evt21"), b"% format EVT21;endianness=legacy\n": ("x", "evt21"),
        b"% format EVT2\n": ("x", "evt2"), b"% evt 2.0\n": ("x.dat", "evt2"),
        b"% Version 2\n% Width 3\n% Height 2\n\x0c\x08": ("x.bin", "dat"),
        b"% Date 2020\n% Height 2\n\x00\x08": ("x", "dat"),
        b"% plugin_name hal_plugin_gen3_fx3\n": ("x.raw", "evt2"),
        b"% plugin_name hal_plugin_gen3_fx3\n\x00": ("x.bin", None),
        b"% Date 2020\n": ("x.dat", "dat"),
        b"% just text\n": ("x.txt", None),
        b"t x y p\n": ("x.raw", None), b"\x89HDF\r\n": ("x.h5", None), b"": ("x.raw", None),
    }
    for head, (name, want) in cases.items():
        assert P.sniff(tmp_path / name, head) == want, head


def test_header_without_newline_does_not_hang(tmp_path):
    p = tmp_path / "big.raw"
    p.write_bytes(b"% evt 3.0 " + b"a" * (P.HEADER_MAX_BYTES + 10))
    with pytest.raises(FormatError, match="header"):
        P.Evt3Reader(p)
    assert P.sniff(p, p.read_bytes()[:4096]) is None


def test_geometry_inference():
    h = P.parse_header(b"% plugin_name hal_plugin_gen41_evk3\n")
    assert P._geometry(h) == SensorSize(720, 1280)
    assert P._geometry(P.parse_header(b"% plugin_name hal_plugin_genx320\n")) == SensorSize(320, 320)
    assert P._geometry(P.parse_header(b"% plugin_name hal_plugin_gen3_fx3\n")) == SensorSize(480, 640)
    assert P._geometry(P.parse_header(b"% geometry 346x260\n")) == SensorSize(260, 346)
    assert P._geometry(P.parse_header(b"% system_ID 21\n")) is None


def test_sensor_size_option_overrides(shared_data):
    r = P.Evt2Reader(shared_data("prophesee/evt2_sample.raw"), sensor_size=(1000, 1000))
    assert r.sensor_size == SensorSize(1000, 1000)


# ------------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------------
def _expect_format_error(path, fmt, match=None, **opts):
    with pytest.raises(FormatError) as ei:
        r = P.READERS[fmt](path, **opts)
        r.read_all()
    msg = str(ei.value)
    assert path.name in msg and "byte offset" in msg, msg
    if match:
        assert match in msg, msg
    return ei.value


def test_bad_inputs(tmp_path):
    ev = make_events([1, 2, 3, 70000], [1, 2, 3, 4], [1, 1, 1, 2], [1, -1, 1, 1])
    for fmt in ("evt2", "evt3", "dat"):
        good = _write(fmt, tmp_path / f"g.{fmt}", ev, sensor=(8, 8))
        data = good.read_bytes()
        # truncated: half a word / a partial record at the end
        p = tmp_path / f"trunc.{fmt}"
        p.write_bytes(data[:-1])
        e = _expect_format_error(p, fmt, "partial")
        assert e.offset == len(data) - {"evt3": 2, "evt2": 4, "dat": 8}[fmt]
        # the last word / record held the last event
        assert np.array_equal(P.READERS[fmt](p, allow_truncated=True).read_all().events, ev[:-1])
        # header only
        hdr_end = P.READERS[fmt](good)._data_offset - (2 if fmt == "dat" else 0)
        p = tmp_path / f"hdr.{fmt}"
        p.write_bytes(data[:hdr_end])
        _expect_format_error(p, fmt)
        # random bytes (no header)
        p = tmp_path / f"rand.{fmt}"
        p.write_bytes(np.random.default_rng(0).integers(0, 256, 1000, dtype=np.uint8).tobytes())
        _expect_format_error(p, fmt, "header")
    # wrong header: an EVT3 file read as EVT2, a RAW file read as DAT
    _expect_format_error(tmp_path / "g.evt3", "evt2", "declares")
    _expect_format_error(tmp_path / "g.evt2", "dat", "declares")
    # coordinates outside the declared sensor (written for 8x8, declared 4x4)
    for fmt in ("evt2", "evt3", "dat"):
        data = (tmp_path / f"g.{fmt}").read_bytes()
        if fmt == "dat":
            data = data.replace(b"Height 8", b"Height 2").replace(b"Width 8", b"Width 2")
        else:
            data = data.replace(b"height=8;width=8", b"height=2;width=2").replace(b"geometry 8x8", b"geometry 2x2")
        p = tmp_path / f"oob.{fmt}"
        p.write_bytes(data)
        _expect_format_error(p, fmt, "outside the sensor")


def test_dat_bad_type_and_size(tmp_path):
    good = _write("dat", tmp_path / "g.dat", make_events([1], [1], [1], [1]), sensor=(4, 4))
    data = good.read_bytes()
    off = P.DatReader(good)._data_offset - 2
    for b0, b1, msg in ((14, 8, "ExtTrigger"), (40, 8, "OpticalFlow"), (12, 16, "unknown DAT")):
        p = tmp_path / f"t{b0}_{b1}.dat"
        p.write_bytes(data[:off] + bytes([b0, b1]) + data[off + 2:])
        with pytest.raises(FormatError, match=msg) as ei:
            P.DatReader(p)
        assert ei.value.offset == off


def test_dat_backwards_time(tmp_path):
    rec = np.array([[100, 1], [50, 2]], np.uint32)
    p = tmp_path / "bw.dat"
    p.write_bytes(b"% Version 2\n% Height 4\n% Width 4\n\x0c\x08" + rec.tobytes())
    ev = P.DatReader(p).read_all().events  # 50 µs back: inside the default 1000 µs window
    assert ev["t"].tolist() == [50, 100]
    with pytest.raises(FormatError, match="backwards") as ei:
        P.DatReader(p, reorder_window_us=0).read_all()
    assert ei.value.offset == p.stat().st_size - 8


def test_unused_word_types(tmp_path):
    p = _raw_file(tmp_path, "u.raw", "% evt 3.0\n", evt3_words(0x8001, 0xB000, 0x2001))
    _expect_format_error(p, "evt3", "unused EVT 3.0 word type 0xB")
    ev = P.Evt3Reader(p, strict=False).read_all().events
    assert len(ev) == 0  # the ADDR_X has no row yet
    p = _raw_file(tmp_path, "u2.raw", "% evt 2.0\n", np.array([(8 << 28), (3 << 28)], np.uint32))
    _expect_format_error(p, "evt2", "unused EVT 2.0 word type 0x3")


def test_reader_options_validated(shared_data):
    path = shared_data("prophesee/evt2_sample.raw")
    with pytest.raises(TypeError, match="unknown option"):
        P.Evt2Reader(path, blocksize=3)
    with pytest.raises(ValueError):
        P.Evt2Reader(path, reorder_window_us=-1)


# ------------------------------------------------------------------------------------------------
# kernels against their pure-Python versions
# ------------------------------------------------------------------------------------------------
def _run_decoder(fn, words, extra=()):
    out = np.zeros(2 * 64, np.int64)
    tt, tc, te = np.zeros(8, np.int64), np.zeros(8, np.uint16), np.zeros(8, np.int8)
    stt = K.new_state()
    res = fn(words, 0, out, 0, 64, tt, tc, te, 0, 8, stt, 20, 20, 100, True, *extra)
    return tuple(int(v) for v in res), out, tt, tc, te, stt


@pytest.mark.parametrize("name, words, extra", [
    ("evt2_decode", np.array([0x80000001, 0x10400801, 0x00800802, 0xA0000101, 0x10001002], np.uint32), ()),
    ("evt3_decode", evt3_words(0x8001, 0x0002, 0x6003, 0x2801, 0x3002, 0x4805, 0x5003, 0xA101, 0x2013), ()),
    ("evt21_decode", np.array([0, 0x80000001, 0b1011, 0x10401002, 1, 0x00001003], np.uint32), (False,)),
    ("evt21_decode", np.array([0x80000001, 0, 0x10401002, 0b1011, 0x00001003, 1], np.uint32), (True,)),
])
def test_decode_kernels_match_py_func(name, words, extra):
    fn = getattr(K, name)
    a = _run_decoder(fn, words, extra)
    b = _run_decoder(getattr(fn, "py_func", fn), words, extra)
    assert a[0] == b[0]
    for u, v in zip(a[1:], b[1:]):
        assert np.array_equal(u, v)
    assert a[0][1] > 0


def test_dat_kernels_match_py_func():
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.integers(0, 1 << 29, 200)).astype(np.int64)  # wraps 2^32 several times
    words = np.empty(400, np.uint32)
    words[0::2] = t & 0xFFFFFFFF
    words[1::2] = rng.integers(0, 20, 200) | (rng.integers(0, 20, 200) << 14) | (rng.integers(0, 2, 200) << 28)
    outs = []
    for fn, extra in ((K.dat_decode, ()), (getattr(K.dat_decode, "py_func", K.dat_decode), ()), (K.dat_decode_parallel, (7,)),
                      (getattr(K.dat_decode_parallel, "py_func", K.dat_decode_parallel), (7,))):
        out = np.zeros(400, np.int64)
        s = K.new_state()
        res = fn(words, out, s, 20, 20, 0, *extra)
        assert tuple(int(v) for v in res) == (200, 0, 0)
        outs.append((out, s))
    for out, s in outs[1:]:
        assert np.array_equal(out, outs[0][0]) and np.array_equal(s, outs[0][1])
    assert np.array_equal(outs[0][0][0::2], t)


def test_encode_kernels_match_py_func():
    t = np.array([0, 0, 0, 0, 5000, (1 << 24) + 3, (1 << 35)], np.int64)
    x = np.array([1, 2, 4, 9, 3, 3, 3], np.uint16)
    y = np.array([2, 2, 2, 2, 5, 5, 1], np.uint16)
    p = np.array([1, 1, 1, 1, -1, 1, 1], np.int8)
    tt, tch, te = np.array([0, 6000], np.int64), np.array([1, 2], np.uint16), np.array([1, -1], np.int8)
    for fn, extra, dt in ((K.evt2_encode, (), np.uint32), (K.evt3_encode, (True,), np.uint16)):
        res = []
        for f in (fn, getattr(fn, "py_func", fn)):
            es = np.full(4, -1, np.int64)
            out = np.zeros(20000, dt)
            nw = f(t, x, y, p, tt, tch, te, es, out, *extra)
            res.append((nw, out[:nw].copy(), es))
        assert res[0][0] == res[1][0] and np.array_equal(res[0][1], res[1][1])
        assert np.array_equal(res[0][2], res[1][2])


def test_count_kernels():
    w3 = evt3_words(0x8001, 0x2001, 0x4FFF, 0x50F0, 0x2002)
    assert K.evt3_count(w3) == getattr(K.evt3_count, "py_func", K.evt3_count)(w3) == 1 + 12 + 4 + 1
    w21 = np.array([0xFF, 0x10000000, 0, 0x80000000], np.uint32)
    assert K.evt21_count(w21, False) == getattr(K.evt21_count, "py_func", K.evt21_count)(w21, False) == 8
