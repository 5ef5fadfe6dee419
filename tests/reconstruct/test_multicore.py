"""The parallel phases (column split, reversal, start, carried variance, fusion, band
clamps, output collection) give the serial path's bits, and the phase timer measures them."""

from __future__ import annotations

import math

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr import Frames, Recording, SensorSize
from hybridhdr._util import phases as PH
from hybridhdr.events import events_fields
from hybridhdr.reconstruct import AKFParams, FrameMeasurements, reconstruct
from hybridhdr.reconstruct import _kernels as K
from hybridhdr.reconstruct import event_arrays as EA
from hybridhdr.reconstruct._engine import AKFEngine
from hybridhdr.reconstruct.event_arrays import EventArrays
from hybridhdr.reconstruct.smoother import reverse_events


@pytest.fixture
def small_parts(monkeypatch):
    """Whole-array passes split into parts of 500 events (in threads) instead of 262,144."""
    monkeypatch.setattr(EA, "PARALLEL_MIN_EVENTS", 500)


def _rec(n=6000, h=24, w=30, seed=0, n_frames=7):
    rng = np.random.default_rng(seed)
    span = 240_000
    t = np.sort(rng.integers(0, span, n)).astype(np.int64)
    t[50:90] = t[50]  # equal timestamps
    ev = hh.make_events(t, rng.integers(0, w, n), rng.integers(0, h, n), rng.choice([-1, 1], n))
    ft = np.linspace(0, span, n_frames).astype(np.int64)
    codes = rng.integers(0, 256, (n_frames, h, w)).astype(np.uint8)
    codes[:, :2, :3] = 255  # clipped: the censored branches of start and the switches
    codes[:, -2:, :3] = 0
    return Recording(ev, SensorSize(h, w), Frames(codes, ft, ft, encoding="raw"))


def test_from_structured_in_parts_matches_the_columns(small_parts):
    rec = _rec()
    ev = rec.events
    ref = EventArrays.from_chunks([events_fields(ev)], (24, 30))
    for nw in (1, 3, 8):
        got = EventArrays.from_structured(ev, (24, 30), n_workers=nw)
        for a in "txyp":
            assert np.array_equal(getattr(got, a), getattr(ref, a)) and getattr(got, a).dtype == getattr(ref, a).dtype
    # a fault in any part is found, and the plain constructor names it
    bad = ev.copy()
    bad["t"][3001] = -1
    with pytest.raises(ValueError, match="non-decreasing; index 3001"):
        EventArrays.from_structured(bad, (24, 30), n_workers=4)
    bad = ev.copy()
    bad["y"][5999] = 24
    with pytest.raises(ValueError, match="exceed the sensor size"):
        EventArrays.from_structured(bad, (24, 30), n_workers=4)
    # a fault at a part's first event (compared with the event before it, in the part before)
    bad = ev.copy()
    bad["t"][3000] = bad["t"][2999] - 1
    with pytest.raises(ValueError, match="non-decreasing; index 3000"):
        EventArrays.from_structured(bad, (24, 30), n_workers=6)  # parts of 1,000 events


def test_parallel_reversal_equals_numpy(small_parts):
    ev = EventArrays.from_structured(_rec().events, (24, 30))
    m = 250_001
    for nw in (1, 4):
        r = reverse_events(ev, m, n_workers=nw)
        assert np.array_equal(r.t, (m - 1) - ev.t[::-1])
        assert np.array_equal(r.x, ev.x[::-1]) and np.array_equal(r.y, ev.y[::-1])
        assert np.array_equal(r.p, (-ev.p[::-1]).astype(np.int8)) and r.p.dtype == np.int8
        assert np.all(np.diff(r.t) >= 0)


def _start_reference(S, params, t_init):
    """The plain numpy start of the AKF (the column operations akf_start replaces)."""
    S[:, K.A_L] = S[:, K.A_LA]
    S[:, K.A_P] = params.initial_covariance
    cens = (S[:, K.A_BETA] == 0.0) & (S[:, K.A_KLOG] != 0.0)
    S[cens, K.A_P] = params.censored_initial_covariance
    dark = cens & (S[:, K.A_KLOG] < 0.0)
    w = S[dark, K.A_LA] - math.log(params.intensity_offset)
    S[dark, K.A_P] = np.maximum(w * w, params.initial_covariance)
    S[:, K.A_TU] = float(t_init)


@pytest.mark.parametrize("n_workers", [1, 3])
def test_akf_start_equals_the_numpy_initialisation(n_workers):
    rec = _rec()
    params = AKFParams()
    from hybridhdr.camera import default_profile
    m = FrameMeasurements(rec.frames, (24, 30), default_profile(), intensity_offset=params.intensity_offset,
                          saturation="bound")
    eng = AKFEngine((24, 30), m, params, n_workers=n_workers)
    t0 = eng.start(None)
    got = eng.S.copy()
    ref = got.copy()
    _start_reference(ref, params, t0)
    eng.close()
    assert np.array_equal(got.view(np.int64), ref.view(np.int64))  # bits, NaN included
    cens = (ref[:, K.A_BETA] == 0) & (ref[:, K.A_KLOG] != 0)
    assert cens.any() and (ref[:, K.A_KLOG] < 0).any()  # both censored branches were exercised


@pytest.mark.parametrize("method,mode", [("akf", "forward"), ("akf", "causal"), ("akf", "offline"), ("cf", "forward"),
                                         ("highpass", "forward")])
def test_every_parallel_path_gives_the_serial_bits(small_parts, method, mode):
    """1 worker against 2, 3 and 5 (row bands, parallel split, reversal, start, carried
    variance, fusion, per-band clamps and output collection), several chunks per run."""
    rec = _rec()
    runs = {}
    for nw in (1, 2, 3, 5):
        v = reconstruct(rec, method, fps=400.0, mode=mode, n_workers=nw, chunk_events=1700)
        runs[nw] = v
    ref = runs[1]
    assert len(ref) > 20
    for nw, v in runs.items():
        assert np.array_equal(v.frames, ref.frames), nw
        assert v.info.get("n_clamped") == ref.info.get("n_clamped")


def test_phase_timer_is_off_by_default_and_times_each_phase():
    rec = _rec()
    assert PH.ACTIVE is None
    plain = reconstruct(rec, "akf", fps=400.0, n_workers=2)
    with PH.timing() as pt:
        assert PH.ACTIVE is pt
        timed = reconstruct(rec, "akf", fps=400.0, n_workers=2)
    assert PH.ACTIVE is None
    assert np.array_equal(plain.frames, timed.frames)
    r = pt.report()
    ph = r["phases"]
    for name, kind in (("filter", "parallel"), ("output", "parallel"), ("fuse", "parallel"), ("reverse", "parallel"),
                       ("start", "parallel"), ("read_all", "parallel"), ("build", "serial")):
        assert ph[name]["kind"] == kind and ph[name]["calls"] >= 1 and ph[name]["s"] >= 0, name
    assert ph["output"]["calls"] == 2 * len(timed)  # each pass's estimates at each output
    assert ph["fuse"]["calls"] == len(timed)
    # the phases of the driving threads never exceed the wall time (both passes run at once with
    # 2 workers, so only the serial order's one thread is checked)
    with PH.timing() as pt1:
        reconstruct(rec, "akf", fps=400.0, n_workers=1)
    r1 = pt1.report()
    assert r1["parallel_s"] + r1["serial_s"] <= r1["wall_s"] * (1 + 1e-9)
    assert math.isclose(r1["untimed_s"], r1["wall_s"] - r1["parallel_s"] - r1["serial_s"], abs_tol=1e-9)


def test_phase_timer_rejects_a_phase_timed_as_two_kinds():
    pt = PH.PhaseTimer()
    pt.add("x", PH.now(), "parallel")
    with pytest.raises(ValueError, match="was timed as 'parallel'"):
        pt.add("x", PH.now(), "serial")
    with pytest.raises(ValueError, match="kind must be one of"):
        pt.add("y", PH.now(), "sideways")


@pytest.mark.parametrize("jit", [True, False])
@pytest.mark.parametrize("h,nb", [(30, 5), (30, 9), (12, 12), (40, 16)])
def test_band_split_lut_equals_band_select_per_band(jit, h, nb):
    """The look-up split (many bands, single-row bands included) = band_select of each band's
    rows and two ghost rows, in order."""
    from hybridhdr.reconstruct._engine import row_bands
    rng = np.random.default_rng(nb)
    y = rng.integers(0, h, 6_000).astype(np.uint16)
    bands = row_bands(h, nb)
    bor = np.empty(h, np.int32)
    edge = np.zeros(h, np.uint8)
    for b, (lo, hi) in enumerate(bands):
        bor[lo:hi] = b
        if b > 0:
            edge[lo] |= 1
        if b + 1 < len(bands):
            edge[hi - 1] |= 2
    fn = K.band_split_lut if jit else getattr(K.band_split_lut, "py_func")
    i0, j0, j1 = 100, 1_300, 5_100
    out = np.full((len(bands), j1 - j0), -1, np.int32)
    counts = np.full(len(bands), -5, np.int64)
    assert fn(y, i0, j0, j1, bor, edge, out, counts) == j1 - j0
    for b, (lo, hi) in enumerate(bands):
        idx = np.empty(j1 - j0, np.int32)
        m = K.band_select(y, j0, j1, lo - 1, hi + 1, idx)
        assert counts[b] == m
        np.testing.assert_array_equal(out[b, :m], idx[:m] + (j0 - i0))


@pytest.mark.parametrize("n_workers", [5, 8])
def test_many_band_engine_gives_the_serial_bits(n_workers):
    """The threaded AKF with more than SPLIT_LUT_MIN_BANDS bands (the look-up split), band
    edges moving between batches, against one worker."""
    from hybridhdr.camera import default_profile
    from hybridhdr.reconstruct import _engine as EN
    assert n_workers > EN.SPLIT_LUT_MIN_BANDS
    rec = _rec(n=90_000, h=40, w=30, seed=n_workers)
    ev = rec.events
    t, x, y, p = (np.ascontiguousarray(ev[k]) for k in ("t", "x", "y", "p"))
    y[: len(y) // 2] = np.minimum(y[: len(y) // 2], 9)  # first half clustered in 10 rows: edges move
    params = AKFParams()
    states = []
    for nw in (1, n_workers):
        m = FrameMeasurements(rec.frames, (40, 30), default_profile(), intensity_offset=params.intensity_offset)
        eng = AKFEngine((40, 30), m, params, n_workers=nw)
        eng.start(None)
        cuts = [0, 30_000, 45_000, 90_000]
        for a, b in zip(cuts[:-1], cuts[1:]):
            eng.process(t, x, y, p, a, b)
            if nw > 1:
                assert len(eng.bands) == nw
        states.append(eng.S.copy())
        eng.close()
    assert np.array_equal(states[0].view(np.int64), states[1].view(np.int64))


@pytest.mark.parametrize("n_workers", [4, 6])
def test_threaded_carried_variance_count_gives_the_serial_bits(monkeypatch, n_workers):
    """Two-sided with threaded row bands in each pass (the count split by band, waiting per part)
    against one worker; bands thread from 2,000 events or pixels on instead of 20,000."""
    from hybridhdr.reconstruct import _engine as EN
    from hybridhdr.reconstruct import smoother as SM
    rec = _rec(n=40_000, h=40, w=30, seed=3)
    ref = reconstruct(rec, "akf", fps=30.0, n_workers=1)
    monkeypatch.setattr(EN, "PARALLEL_MIN_WORK", 2000)
    calls = []
    real = SM._CarriedVariance._split_count

    def spy(self, *a, **k):
        calls.append(1)
        return real(self, *a, **k)
    monkeypatch.setattr(SM._CarriedVariance, "_split_count", spy)
    got = reconstruct(rec, "akf", fps=30.0, n_workers=n_workers)
    assert calls, "the threaded count did not run"
    assert np.array_equal(got.frames, ref.frames) and got.info["n_clamped"] == ref.info["n_clamped"]


def test_phase_context_manager_sync_and_nested_subtraction():
    """One context manager times every phase: off it is a shared no-op; with ``sync`` (the GPU's
    ``cuda.synchronize``) it calls it around the block and reports the host's share; ``less``
    subtracts the nested phases of a kind (a wait that holds timed work)."""
    import time
    assert PH.phase("x") is PH.phase("y")  # no timer: the shared no-op
    calls = []
    with PH.timing(sync=lambda: calls.append(1)) as pt:
        with PH.phase("outer", "serial", less="parallel"):
            with PH.phase("inner", "parallel"):
                time.sleep(0.02)
    r = pt.report()["phases"]
    assert len(calls) == 4  # around each of the two phases
    assert r["inner"]["s"] >= 0.02 and 0.0 <= r["inner"]["host_s"] <= r["inner"]["s"]
    assert r["outer"]["s"] < 0.02  # the nested parallel phase is not counted twice
    assert PH.ACTIVE is None
