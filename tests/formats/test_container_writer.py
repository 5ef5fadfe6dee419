"""The container writer's fast path: chunk images staged in HDF5's shuffle layout, deflated in
threads, stored with direct chunk writes; the index built as events are staged."""

import h5py
import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.formats import _write_kernels as WK
from hybridhdr.formats.container import _CHUNK_ELEMS, INDEX_STRIDE, RecordingFile, RecordingWriter


def _events(n, seed=0, t0=10**9, ss=(480, 640)):
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.poisson(0.4, n))  # many events per millisecond, repeated times
    return hh.make_events(t, rng.integers(0, ss[1], n), rng.integers(0, ss[0], n), rng.choice([-1, 1], n))


def _index_by_definition(t, stride):
    b = t // 1000
    starts = np.concatenate(([0], np.flatnonzero(b[1:] != b[:-1]) + 1))
    keep, last = [], None
    for s in starts:
        if last is None or s >= last + stride:
            keep.append(s)
            last = s
    keep = np.asarray(keep, np.int64)
    return b[keep], keep


@pytest.mark.parametrize("compression", ["gzip", "lzf", None])
@pytest.mark.parametrize("threads", [0, 2])
def test_round_trip_across_chunks_flushes_and_sizes(tmp_path, compression, threads):
    n = 2 * _CHUNK_ELEMS + 12345
    ev = _events(n)
    p = tmp_path / "r.h5"
    cuts = [0, 7, 8, 100, _CHUNK_ELEMS - 3, _CHUNK_ELEMS + 5, _CHUNK_ELEMS + 6, 2 * _CHUNK_ELEMS + 1, n]
    with RecordingWriter(p, (480, 640), compression=compression, threads=threads, buffer_events=1000) as w:
        for a, b in zip(cuts[:-1], cuts[1:]):
            w.write_events(ev[a:b])
            if b in (100, _CHUNK_ELEMS + 5):
                w.flush()  # a partial chunk stored, then rewritten when it fills
    with h5py.File(p) as f:
        g = f["events"]
        assert g["t"].shape == (n,) and f.attrs["n_events"] == n
        if compression == "gzip":
            assert g["t"].compression == "gzip" and g["t"].shuffle and g["x"].shuffle
        assert g["t"].chunks == (_CHUNK_ELEMS,)
        ms, first = g["index_ms"][:], g["index_first"][:]
    ems, efirst = _index_by_definition(ev["t"], INDEX_STRIDE)
    assert np.array_equal(ms, ems) and np.array_equal(first, efirst)
    with RecordingFile(p) as r:
        assert np.array_equal(r.events(), ev)
        assert np.array_equal(r.events(int(ev["t"][5000]), int(ev["t"][200_000])),
                              hh.slice_time(ev, int(ev["t"][5000]), int(ev["t"][200_000])))


def test_flushed_partial_file_is_readable(tmp_path):
    ev = _events(50_000, seed=3)
    p = tmp_path / "r.h5"
    w = RecordingWriter(p, (480, 640))
    w.write_events(ev[:30_000])
    w.flush()
    with h5py.File(w.tmp_path, "r") as f:
        assert np.array_equal(f["events/t"][:], ev["t"][:30_000])
        assert np.array_equal(f["events/p"][:], ev["p"][:30_000])
    w.write_events(ev[30_000:])
    w.close()
    assert np.array_equal(hh.read(p).events, ev)


def test_extreme_and_negative_times_index(tmp_path):
    t = np.array([-(2**62), -(2**62) + 1, -5001, -5000, -1, 0, 999, 1000, 2**62, 2**63 - 1], np.int64)
    t = np.repeat(t, 3)
    ev = hh.make_events(t, np.zeros(len(t)), np.zeros(len(t)), np.ones(len(t)))
    st = np.zeros(4, np.int64)
    ms = np.empty(len(t) + 2, np.int64)
    first = np.empty_like(ms)
    bufs = [np.zeros(_CHUNK_ELEMS * s, np.uint8) for s in (8, 2, 2, 1)]
    rec = ev.view(np.uint8).reshape(len(ev), 16)
    m = WK.stage_events(rec, ev["t"], 0, len(ev), *bufs, 0, _CHUNK_ELEMS, True, 0, st, 1, ms, first, 0)
    ems, efirst = _index_by_definition(t, 1)
    assert np.array_equal(ms[:m], ems) and np.array_equal(first[:m], efirst)


@pytest.mark.parametrize("pos", [0, 1, 7, 8, 13])
@pytest.mark.parametrize("shuffle", [True, False])
def test_stage_layout_is_hdf5_shuffle_or_plain(pos, shuffle):
    ev = _events(1003, seed=5)
    C = 2048
    bufs = [np.zeros(C * s, np.uint8) for s in (8, 2, 2, 1)]
    st = np.zeros(4, np.int64)
    idx = np.empty(1100, np.int64)
    WK.stage_events(ev.view(np.uint8).reshape(-1, 16), ev["t"], 2, 1000, *bufs, pos, C, shuffle, 0, st,
                    4096, idx, idx.copy(), 0)
    for b, f in zip(bufs, "txyp"):
        col = np.ascontiguousarray(ev[f][2:1002])
        s = col.itemsize
        if shuffle:
            got = b.reshape(s, C)[:, pos:pos + 1000]
            assert np.array_equal(got, col.view(np.uint8).reshape(1000, s).T), f
        else:
            assert np.array_equal(b[pos * s:(pos + 1000) * s], col.view(np.uint8)), f


@pytest.mark.parametrize("a,b", [(0, 2048), (3, 1000), (8, 16), (5, 7), (1990, 2048)])
@pytest.mark.parametrize("s", [8, 2, 1])
def test_unshuffle_inverts_the_shuffle(s, a, b):
    # unshuffle (8-byte elements: the same 8x8 transpose as stage_events) against numpy's
    # transpose of the shuffled image, compiled and as Python
    C = 2048
    rng = np.random.default_rng(s)
    col = rng.integers(0, 256, C * s, dtype=np.uint8)
    img = np.ascontiguousarray(col.reshape(C, s).T).reshape(-1)  # byte j of element k at j * C + k
    for fn in (WK.unshuffle, WK.unshuffle.py_func):
        out = np.zeros((b - a + 3) * s, np.uint8)
        assert fn(img, s, C, a, b, out, 3) == b - a
        assert np.array_equal(out[3 * s:], col[a * s:b * s]) and not out[:3 * s].any()


def test_invalid_events_still_name_the_record(tmp_path):
    ev = _events(100)
    bad = ev.copy()
    bad["x"][42] = 640
    with pytest.raises(ValueError, match="index 42"):
        with RecordingWriter(tmp_path / "a.h5", (480, 640)) as w:
            w.write_events(bad)
    bad = ev.copy()
    bad["t"][10] = bad["t"][9] - 1
    with pytest.raises(ValueError, match="index 10"):
        with RecordingWriter(tmp_path / "b.h5", (480, 640)) as w:
            w.write_events(bad)
    bad = ev.copy()
    bad["p"][3] = 0
    with pytest.raises(ValueError, match="index 3"):
        with RecordingWriter(tmp_path / "c.h5", (480, 640)) as w:
            w.write_events(bad)


def test_dat_writer_packs_as_before(tmp_path):
    from hybridhdr.formats import prophesee as P
    ev = _events(3000, seed=7, t0=2**32 - 500)  # crosses the 32-bit wrap
    with P.DatWriter(tmp_path / "a.dat", sensor_size=(480, 640)) as w:
        w.write_events(ev[:1000])
        w.write_events(ev[1000:][::1].copy())
    data = (tmp_path / "a.dat").read_bytes()
    body = np.frombuffer(data[data.index(bytes([12, 8])) + 2:], np.uint32).reshape(-1, 2)
    assert np.array_equal(body[:, 0], (ev["t"] & 0xFFFFFFFF).astype(np.uint32))
    assert np.array_equal(body[:, 1], ev["x"].astype(np.uint32) | (ev["y"].astype(np.uint32) << 14)
                          | ((ev["p"] > 0).astype(np.uint32) << 28))
    assert np.array_equal(P.DatReader(tmp_path / "a.dat").read_all().events, ev)
    gap = ev[:2].copy()
    gap["t"][1] = gap["t"][0] + 2**31
    with pytest.raises(ValueError, match="gap"):
        with P.DatWriter(tmp_path / "b.dat", sensor_size=(480, 640)) as w:
            w.write_events(gap)


def test_zlib_fallback_and_strided_input(tmp_path, monkeypatch):
    import zlib

    import hybridhdr.formats.container as container
    monkeypatch.setattr(container, "_DEFLATE", zlib.compress)  # what runs without isal
    ev = _events(_CHUNK_ELEMS + 999, seed=11)
    p = tmp_path / "z.h5"
    with RecordingWriter(p, (480, 640)) as w:
        w.write_events(ev[:-10:2])  # a strided view
        w.write_events(ev[-5:])
    assert np.array_equal(hh.read(p).events, np.concatenate([ev[:-10:2], ev[-5:]]))


def test_parallel_chunk_read_equals_h5py(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    from hybridhdr.formats._chunk_read import read_columns
    ev = _events(3 * _CHUNK_ELEMS + 777, seed=13)
    p = tmp_path / "r.h5"
    with RecordingWriter(p, (480, 640)) as w:
        w.write_events(ev)
    n = len(ev)
    with h5py.File(p) as f, ThreadPoolExecutor(2) as pool:
        ds = {k: f["events/" + k] for k in "txyp"}
        for i0, i1 in ((0, n), (5, n - 3), (_CHUNK_ELEMS - 1, _CHUNK_ELEMS + 1), (1000, 1009), (n - 1, n), (7, 7)):
            for pl in (None, pool):
                got = read_columns(ds, i0, i1, pl)
                for k in "txyp":
                    assert np.array_equal(got[k], ds[k][i0:i1]), (k, i0, i1)
    p2 = tmp_path / "lzf.h5"
    with RecordingWriter(p2, (480, 640), compression="lzf") as w:
        w.write_events(ev[:100])
    with h5py.File(p2) as f:
        assert read_columns({"t": f["events/t"]}, 0, 100) is None  # another filter: h5py reads it


def test_events_ok_fused_check_names_the_first_bad_record():
    """The one-pass check (``_write_kernels.events_ok``) against numpy's per-record flags: every
    kind of fault (time order, polarity, x, y), alone and with a second fault after it, at
    random places including the first and last record, with and without a sensor size."""
    rng = np.random.default_rng(7)
    n = 20_000
    ev = hh.make_events(np.sort(rng.integers(0, 10**6, n)), rng.integers(0, 64, n), rng.integers(0, 48, n),
                               rng.choice([-1, 1], n))

    def first_bad(e, w, h):
        bad = np.zeros(len(e), bool)
        bad[1:] = e["t"][1:] < e["t"][:-1]
        bad |= (e["p"] != 1) & (e["p"] != -1)
        if w > 0:
            bad |= (e["x"] >= w) | (e["y"] >= h)
        return int(np.argmax(bad)) if bad.any() else -1

    assert WK.events_ok(ev.view(np.int64), 64, 48) == -1
    assert WK.events_ok(ev[:0].view(np.int64), 64, 48) == -1
    for k in range(60):
        e = ev.copy()
        i = (0, n - 1)[k % 2] if k < 10 else int(rng.integers(0, n))
        kind = k % 5
        if kind == 0:
            e["t"][i] = -1 if i else e["t"][1] + 1  # record 0 fails through record 1's order
        elif kind == 1:
            e["x"][i] = 64
        elif kind == 2:
            e["y"][i] = 48
        else:
            e["p"][i] = (0, 2)[kind - 3]
        if k % 3 == 0:
            e["y"][min(n - 1, i + 5)] = 60
        for w, h in ((64, 48), (0, 0), (70, 61)):
            assert WK.events_ok(e.view(np.int64), w, h) == first_bad(e, w, h), (k, i, w, h)
