"""The DAT writer's packing kernel (checks and packs in one pass): byte-identical files, the same
errors as the base class's checks, and ``convert`` EVT 2.0 -> DAT against a plain numpy packing."""

from __future__ import annotations

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr import EVENT_DTYPE, make_events
from hybridhdr.errors import EventValidationError
from hybridhdr.formats import _kernels as K
from hybridhdr.formats import prophesee as P

DATE = "2026-01-02 03:04:05"


def _dat_by_definition(events, height, width) -> bytes:
    """A DAT file written the plain way (docs/formats.md, 'Prophesee DAT'): the writer's header,
    the type byte 12 and size byte 8, then per event ``u32 t mod 2^32`` and
    ``u32 x | y << 14 | (p > 0) << 28``, little-endian."""
    head = (f"% Data file containing CD events.\n% Version 2\n% Date {DATE}\n% Height {height}\n"
            f"% Width {width}\n").encode("ascii") + bytes([12, 8])
    t = events["t"].astype(np.int64)
    x = events["x"].astype(np.int64)
    y = events["y"].astype(np.int64)
    p = (events["p"] > 0).astype(np.int64)
    words = np.empty((len(events), 2), "<u4")
    words[:, 0] = t % (1 << 32)
    words[:, 1] = x | (y << 14) | (p << 28)
    return head + words.tobytes()


@pytest.fixture(autouse=True)
def _fixed_date(monkeypatch):
    monkeypatch.setattr(P, "_now", lambda: DATE)


def _events(n, seed=0, height=480, width=640, t0=0, step=3):
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.integers(0, step, n))
    x = rng.integers(0, width, n)
    y = rng.integers(0, height, n)
    x[::97] = width - 1  # sensor edges
    y[::89] = height - 1
    return make_events(t, x, y, rng.choice([-1, 1], n))


def _write(path, parts, ss):
    with P.DatWriter(path, sensor_size=ss) as w:
        for part in parts:
            w.write_events(part)
    return path.read_bytes()


@pytest.mark.parametrize("cuts", [[], [1], [511, 512, 513], [1000, 1001, 4000], [5999]])
def test_bytes_match_plain_packing(tmp_path, cuts):
    # times cross 2^32 µs (the 32-bit field wraps) with steps just under 2^31 µs
    ev = _events(6000, seed=1, t0=(1 << 32) - 5000)
    ev["t"][3000:] += (1 << 31) - 3  # steps are 0-2 µs: the largest is 2^31 - 1
    ev["t"] -= (1 << 32) - 5000 - 7  # the first time must be < 2^32
    parts = np.split(ev, cuts)
    got = _write(tmp_path / "a.dat", parts, (480, 640))
    assert got == _dat_by_definition(ev, 480, 640)
    assert np.array_equal(P.DatReader(tmp_path / "a.dat").read_all().events[["t", "x", "y", "p"]],
                          ev[["t", "x", "y", "p"]])


def test_non_contiguous_and_big_sensor(tmp_path):
    # a strided view takes the base class's path; the bytes are the same
    ev = _events(3001, seed=2, height=16384, width=16384, step=2)
    strided = np.empty(2 * len(ev), EVENT_DTYPE)[::2]
    strided[:] = ev
    assert not strided.flags.c_contiguous
    a = _write(tmp_path / "a.dat", [strided], (16384, 16384))
    b = _write(tmp_path / "b.dat", [ev[:1234], ev[1234:]], (16384, 16384))
    assert a == b == _dat_by_definition(ev, 16384, 16384)


def test_convert_evt2_to_dat_matches_plain_packing(tmp_path):
    from hybridhdr._cli_tools import convert
    ev = _events(50_000, seed=3, t0=10**6)
    src = tmp_path / "in.raw"
    with P.Evt2Writer(src, sensor_size=(480, 640)) as w:
        w.write_events(ev)
    for chunk_events in (1 << 20, 4096, 1):
        out = tmp_path / f"out{chunk_events}.dat"
        res = convert(src, out, to_format="dat", chunk_events=chunk_events)
        assert res["events"] == len(ev)
        assert out.read_bytes() == _dat_by_definition(ev, 480, 640)


@pytest.mark.parametrize("case,match", [
    ("order", r"\['t'\] must be non-decreasing; index 700 has"),
    ("p", r"\['p'\] must be \+1 or -1; index 513 has 0"),
    ("x", r"\['x'\] must be < sensor width 640; index 511 has 640"),
    ("y", r"\['y'\] must be < sensor height 480; index 1023 has 480"),
    ("chunk", "must be appended in time order"),
    ("negative", "timestamps must be >= 0"),
    ("first", r"first DAT timestamp must be < 2\^32"),
    ("gap", r"gap of 2\^31"),
])
def test_bad_input_errors_and_leaves_nothing(tmp_path, case, match):
    # written as ev[:10], then ev[10:] (the indices in the messages count from ev[10])
    ev = _events(2000, seed=4, t0=100)
    first = ev[:10].copy()
    if case == "order":
        ev["t"][710] = ev["t"][709] - 1
    elif case == "p":
        ev["p"][523] = 0
    elif case == "x":
        ev["x"][521] = 640
    elif case == "y":
        ev["y"][1033] = 480
    elif case == "chunk":
        ev["t"] -= 50
    elif case == "negative":
        ev["t"] -= 1000
        first = ev[:0]
    elif case == "first":
        ev["t"] += 1 << 32
        first = ev[:0]
    elif case == "gap":
        ev["t"][1500:] += 1 << 31
    path = tmp_path / "bad.dat"
    with pytest.raises(ValueError, match=match):
        with P.DatWriter(path, sensor_size=(480, 640)) as w:
            w.write_events(first)
            w.write_events(ev[10:])
    assert list(tmp_path.iterdir()) == []


def test_bad_type_and_closed_writer(tmp_path):
    w = P.DatWriter(tmp_path / "a.dat", sensor_size=(4, 4))
    with pytest.raises(TypeError, match="EVENT_DTYPE"):
        w.write_events(np.zeros(3, np.int64))
    w.write_events(make_events([1, 2], [0, 3], [3, 0], [1, -1]))
    w.close()
    with pytest.raises(ValueError, match="closed"):
        w.write_events(make_events([3], [0], [0], [1]))
    assert (tmp_path / "a.dat").read_bytes() == _dat_by_definition(make_events([1, 2], [0, 3], [3, 0], [1, -1]), 4, 4)


def _first_bad(ev, prev, width, height):
    t = ev["t"].astype(np.int64)
    bad = (np.diff(np.concatenate(([prev], t))) < 0) | (ev["x"] >= width) | (ev["y"] >= height) \
        | ((ev["p"] != 1) & (ev["p"] != -1))
    return int(np.flatnonzero(bad)[0]) if bad.any() else -1


@pytest.mark.parametrize("where", [None, 0, 1, 511, 512, 1023, 1024, 2499])
@pytest.mark.parametrize("what", ["t", "x", "y", "p"])
def test_kernel_matches_py_func_and_definition(what, where):
    ev = _events(2500, seed=5, height=20, width=30, t0=(1 << 32) - 100)
    ev.view(np.uint8).reshape(-1, 16)[:, 13:] = 0xAB  # padding bytes are ignored
    if where is not None:
        if what == "t":
            ev["t"][where] = ev["t"][where - 1] - 1 if where else 5
        elif what == "x":
            ev["x"][where] = 30
        elif what == "y":
            ev["y"][where] = 21
        else:
            ev["p"][where] = 2
    prev = int(ev["t"][0]) if what != "t" or where != 0 else 6
    res = []
    for fn in (K.dat_encode, getattr(K.dat_encode, "py_func", K.dat_encode)):
        out = np.zeros(2 * len(ev), np.uint32)
        bad, gap = fn(ev.view(np.int64), prev, 30, 20, out)
        res.append((int(bad), int(gap), out))
    assert res[0][:2] == res[1][:2]
    bad = res[0][0]
    assert bad == _first_bad(ev, prev, 30, 20)
    if bad < 0:
        assert np.array_equal(res[0][2], res[1][2])
        want = np.frombuffer(_dat_by_definition(ev, 20, 30)[-8 * len(ev):], "<u4")
        assert np.array_equal(res[0][2], want)
        assert res[0][1] == int(np.diff(np.concatenate(([prev], ev["t"]))).max())


def test_empty_and_one_event(tmp_path):
    a = _write(tmp_path / "a.dat", [hh.empty_events(), make_events([5], [1], [2], [-1]), hh.empty_events()], (4, 4))
    assert a == _dat_by_definition(make_events([5], [1], [2], [-1]), 4, 4)
    assert _write(tmp_path / "b.dat", [], (4, 4)) == _dat_by_definition(hh.empty_events(), 4, 4)
