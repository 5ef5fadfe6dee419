"""Row-band parallel filters: per-band event selection, and output bit-identical to the serial filter."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr import Frames
from hybridhdr.camera import default_profile
from hybridhdr.reconstruct import AKFParams, CFParams, FrameMeasurements
from hybridhdr.reconstruct import _kernels as K
from hybridhdr.reconstruct._engine import AKFEngine, CFEngine, row_bands


def _py(f):
    return getattr(f, "py_func", f)


def _stream(n, h, w, seed, t0=0, span=200_000, boundary_rows=()):
    """Random events; half of them on ``boundary_rows`` (band edges and their ghost rows)."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t0, t0 + span, n)).astype(np.int64)
    t[100:140] = t[100]  # equal timestamps
    x = rng.integers(0, w, n).astype(np.uint16)
    y = rng.integers(0, h, n).astype(np.uint16)
    if boundary_rows:
        sel = rng.random(n) < 0.5
        y[sel] = rng.choice(np.asarray(boundary_rows, np.uint16), int(sel.sum()))
    p = rng.choice(np.array([-1, 1], np.int8), n)
    return t, x, y, p


def _frames(h, w, times, seed=3):
    rng = np.random.default_rng(seed)
    codes = rng.integers(0, 256, (len(times), h, w)).astype(np.uint8)
    codes[:, :2, :3] = 255  # saturated corner: R changes between frames (eq. 7)
    t = np.asarray(times, np.int64)
    return Frames(codes, t, t, encoding="raw")


class _StepMeasurements:
    """A measurement provider with an event-driven L^A (la_step), as frame augmentation makes."""

    def __init__(self, inner):
        self.inner = inner
        self.times_us = inner.times_us

    def __len__(self):
        return len(self.inner)

    def segment(self, k):
        import dataclasses
        s = self.inner.segment(k)
        return dataclasses.replace(s, la_step=np.linspace(0.05, 0.15, s.log_frame.shape[0]))


class _SegmentOnly:
    """A provider with only ``segment`` (no ``segment_codes``): the AKF's generic load path."""

    def __init__(self, inner):
        self.inner = inner
        self.times_us = inner.times_us

    def __len__(self):
        return len(self.inner)

    def segment(self, k):
        return self.inner.segment(k)


def _run_akf(n_workers, t, x, y, p, fr, params, shape, step=False, batches=(0.3, 0.7), generic=False):
    h, w = shape
    m = FrameMeasurements(fr, shape, default_profile(), intensity_offset=params.intensity_offset,
                          interpolate_covariance=params.covariance_interpolation == "linear")
    if step:
        m = _StepMeasurements(m)
    elif generic:
        m = _SegmentOnly(m)
    eng = AKFEngine(shape, m, params, n_workers=n_workers)
    eng.start(None)
    outs = []
    n = t.shape[0]
    cuts = [0] + [int(f * n) for f in batches] + [n]
    for a, b in zip(cuts[:-1], cuts[1:]):
        # apply switches inside the batch at their event positions
        i = a
        while eng.next_switch_us() is not None and i < b and eng.next_switch_us() <= t[b - 1]:
            j = i + int(np.searchsorted(t[i:b], eng.next_switch_us(), side="left"))
            eng.process(t, x, y, p, i, j)
            eng.switch()
            i = j
        eng.process(t, x, y, p, i, b)
        outs.append(eng.output(int(t[b - 1]) + 1, with_state=True))
    S = eng.S.copy()
    eng.close()
    return S, outs, eng.n_events


@pytest.mark.parametrize("n_workers", [2, 3, 5])
@pytest.mark.parametrize("noise_model", ["paper", "reference_code"])
@pytest.mark.parametrize("cov", ["linear", "hold"])
def test_akf_parallel_bit_identical_threaded(n_workers, noise_model, cov):
    """Large batches (threaded path), many events on band edges and ghost rows."""
    h, w, n = 23, 17, 90_000
    edges = sorted({e for lo, hi in row_bands(h, n_workers) for e in (lo - 1, lo, hi - 1, hi) if 0 <= e < h})
    t, x, y, p = _stream(n, h, w, seed=n_workers, boundary_rows=edges)
    fr = _frames(h, w, [0, 70_000, 140_000, 210_000])
    params = AKFParams(noise_model=noise_model, covariance_interpolation=cov, frame_precision_scale=1e3)
    S1, o1, n1 = _run_akf(1, t, x, y, p, fr, params, (h, w))
    S2, o2, n2 = _run_akf(n_workers, t, x, y, p, fr, params, (h, w))
    assert n1 == n2 == n
    np.testing.assert_array_equal(S1, S2)
    for a, b in zip(o1, o2):
        for u, v in zip(a, b):
            np.testing.assert_array_equal(u, v)
    assert np.isfinite(S1).all()


@pytest.mark.parametrize("cov", ["linear", "hold"])
def test_akf_lut_switch_equals_generic_segment_path(cov):
    """Frame switches built from codes and tables in the kernel (segment_codes) give the same
    filter, bit for bit, as loading FrameMeasurements.segment's arrays, serial and parallel."""
    h, w, n = 19, 14, 60_000
    t, x, y, p = _stream(n, h, w, seed=21, boundary_rows=(8, 9, 10))
    fr = _frames(h, w, [0, 50_000, 100_000, 150_000])
    params = AKFParams(covariance_interpolation=cov, frame_precision_scale=1e3)
    S_ref, o_ref, _ = _run_akf(1, t, x, y, p, fr, params, (h, w), generic=True)
    for nw in (1, 2):
        S, o, _ = _run_akf(nw, t, x, y, p, fr, params, (h, w))
        np.testing.assert_array_equal(S, S_ref)
        for a, b in zip(o, o_ref):
            for u, v in zip(a, b):
                np.testing.assert_array_equal(u, v)


def test_akf_parallel_bit_identical_with_la_step():
    h, w, n = 16, 11, 40_000
    t, x, y, p = _stream(n, h, w, seed=9, boundary_rows=(7, 8))
    fr = _frames(h, w, [0, 100_000, 200_000])
    S1, _, _ = _run_akf(1, t, x, y, p, fr, AKFParams(), (h, w), step=True)
    S2, _, _ = _run_akf(2, t, x, y, p, fr, AKFParams(), (h, w), step=True)
    np.testing.assert_array_equal(S1, S2)


def test_akf_more_workers_than_rows_and_timestamps_past_2_31():
    h, w, n = 3, 40, 30_000
    t, x, y, p = _stream(n, h, w, seed=4, t0=(1 << 33) + 5)
    fr = _frames(h, w, [(1 << 33), (1 << 33) + 300_000])
    S1, _, _ = _run_akf(1, t, x, y, p, fr, AKFParams(), (h, w))
    S8, _, _ = _run_akf(8, t, x, y, p, fr, AKFParams(), (h, w))  # clamped to 3 one-row bands
    np.testing.assert_array_equal(S1, S8)


@pytest.mark.parametrize("n_workers", [1, 3])
def test_int32_last_event_times_widen_to_int64_with_the_same_bits(monkeypatch, n_workers):
    """The engine keeps the last-event times in int32 relative to the start and turns them into
    int64 absolute times once the events pass int32's reach (about 35 minutes; shortened here
    to 150 ms): the state and outputs equal those of int64 throughout, bit for bit."""
    import hybridhdr.reconstruct._engine as E
    h, w, n = 17, 13, 50_000
    t0 = (1 << 33) + 11
    t, x, y, p = _stream(n, h, w, seed=40 + n_workers, t0=t0, span=300_000, boundary_rows=(5, 6, 11))
    fr = _frames(h, w, [t0 - 11, t0 + 100_000, t0 + 200_000, t0 + 299_000])
    params = AKFParams(frame_precision_scale=1e3)
    dtypes = []
    fit = E.AKFEngine._te_fit

    def spy(self, a, b):
        fit(self, a, b)
        dtypes.append(self.te[0].dtype)
    monkeypatch.setattr(E.AKFEngine, "_te_fit", spy)
    orig = K.padded_te
    monkeypatch.setattr(K, "padded_te", lambda hh, ww, ti, dtype=np.int64: orig(hh, ww, ti, np.int64))
    S_ref, o_ref, _ = _run_akf(n_workers, t, x, y, p, fr, params, (h, w))
    assert set(dtypes) == {np.dtype(np.int64)}
    monkeypatch.setattr(K, "padded_te", orig)
    for limit, widened in ((1 << 31) - 1, False), (150_000, True):
        monkeypatch.setattr(E, "TE32_MAX", limit)
        dtypes.clear()
        S, o, _ = _run_akf(n_workers, t, x, y, p, fr, params, (h, w))
        assert dtypes[0] == np.int32 and (dtypes[-1] == np.int64) == widened, (limit, dtypes)
        np.testing.assert_array_equal(S, S_ref)
        for a, b in zip(o, o_ref):
            for u, v in zip(a, b):
                np.testing.assert_array_equal(u, v)


@pytest.mark.parametrize("n_workers", [2, 4])
def test_cf_parallel_bit_identical_threaded(n_workers):
    h, w, n = 20, 13, 60_000
    t, x, y, p = _stream(n, h, w, seed=7)
    fr = _frames(h, w, [0, 100_000, 200_000])
    states = []
    for nw in (1, n_workers):
        m = FrameMeasurements(fr, (h, w), default_profile(), intensity_offset=1.0, bias_correction=False,
                              interpolate_covariance=False)
        eng = CFEngine((h, w), m, CFParams(cutoff_hz=3.0), "cf", n_workers=nw)
        eng.start(None)
        eng.process(t, x, y, p, 0, n // 2)
        o = eng.output(int(t[n // 2]))
        eng.switch()
        eng.process(t, x, y, p, n // 2, n)
        states.append((eng.C.copy(), o, eng.output(int(t[-1]) + 10), eng.n_events))
        eng.close()
    for a, b in zip(*states):
        np.testing.assert_array_equal(a, b)


# -- kernels ---------------------------------------------------------------------------------

@pytest.mark.parametrize("lo,hi", [(0, 5), (-1, 3), (2, 4), (4, 6), (3, 3)])
def test_band_select_matches_numpy_and_py_func(lo, hi):
    rng = np.random.default_rng(1)
    y = rng.integers(0, 5, 200).astype(np.uint16)
    want = np.flatnonzero((y[7:180] >= lo) & (y[7:180] < hi))
    for fn in (K.band_select, _py(K.band_select)):
        out = np.full(200, -7, np.int32)
        m = fn(y, 7, 180, lo, hi, out)
        assert m == want.size
        np.testing.assert_array_equal(out[:m], want)
    assert K.band_select(y, 5, 5, 0, 5, np.empty(0, np.int32)) == 0


def test_indexed_kernels_equal_py_func_and_scan_kernels():
    """akf_events_indexed over band_select equals akf_events on the same band (and its py_func)."""
    h, w, n = 6, 5, 400
    t, x, y, p = _stream(n, h, w, seed=2, span=50_000)
    rng = np.random.default_rng(0)

    def state():
        S = K.aligned_state(h * w, K.AKF_FIELDS)
        S[:, K.A_L] = rng.normal(0, 0.3, h * w)
        S[:, K.A_P] = 0.05
        S[:, K.A_LA] = 0.1
        S[:, K.A_RINV] = 500.0
        S[:, K.A_BETA] = np.where(np.arange(h * w) % 3 == 0, 0.4, 0.0)
        S[:, K.A_KLOG] = np.where(S[:, K.A_BETA] != 0, 500.0 * 0.1 / 0.4, 0.0)
        S[:, K.A_TU] = 0.0
        S[:, K.A_LASTEP] = 0.07
        return S

    con = np.linspace(0.08, 0.2, h * w)
    args = (True, 0.0, 1.0 / 100_000, 0.12, 0.08, 5e-4, 0.03, 0.01, np.int64(10_000), 0, con, con[::-1].copy())
    lo, hi = 2, 4
    res = []
    S0 = state()
    for kind in ("scan", "indexed", "indexed_py"):
        S = S0.copy()
        te = K.padded_te(h, w, 0)
        if kind == "scan":
            c = K.akf_events(t, x, y, p, 3, n, lo, hi, w, h, S, te, np.int64(0), *args)
        else:
            fn = K.akf_events_indexed if kind == "indexed" else _py(K.akf_events_indexed)
            idx = np.empty(n, np.int32)
            m = K.band_select(y, 3, n, lo - 1, hi + 1, idx)
            c = fn(t, x, y, p, 3, idx, m, lo, hi, w, h, S, te, np.int64(0), *args)
        res.append((c, S.copy(), K.te_view(te, h, w)[lo - 1:hi + 1].copy()))
    for r in res[1:]:
        assert r[0] == res[0][0] == int(((y[3:] >= lo) & (y[3:] < hi)).sum())
        np.testing.assert_array_equal(r[1], res[0][1])
        np.testing.assert_array_equal(r[2], res[0][2])

    # CF indexed kernel against its py_func and the scanning kernel
    cres = []
    for kind in ("scan", "indexed", "indexed_py"):
        C = K.aligned_state(h * w, K.CF_FIELDS)
        C[:, K.C_LF] = np.linspace(-1, 0.5, h * w)
        C[:, K.C_ALPHA] = 7.0
        if kind == "scan":
            K.cf_events(t, x, y, p, 0, n, lo, hi, w, C, 0.1, 0.12, 0.0, con, con[::-1].copy())
        else:
            fn = K.cf_events_indexed if kind == "indexed" else _py(K.cf_events_indexed)
            idx = np.empty(n, np.int32)
            m = K.band_select(y, 0, n, lo, hi, idx)
            fn(t, x, y, p, 0, idx, m, w, C, 0.1, 0.12, 0.0, con, con[::-1].copy())
        cres.append(C.copy())
    for c in cres[1:]:
        np.testing.assert_array_equal(c, cres[0])


@pytest.mark.parametrize("n_workers", [2, 3])
def test_akf_rebalanced_bands_stay_bit_identical(n_workers, monkeypatch):
    """Events crowd the top rows, then the bottom rows: the band edges follow the events (so the
    workers share the work), the last-event-time rows are handed over exactly, and the result
    still equals the serial filter bit for bit."""
    h, w, n = 40, 13, 120_000
    rng = np.random.default_rng(21)
    t = np.sort(rng.integers(0, 300_000, n)).astype(np.int64)
    x = rng.integers(0, w, n).astype(np.uint16)
    frac = np.arange(n) / n  # the event cloud drifts from rows ~3 to rows ~36
    y = np.clip(np.round(3 + 33 * frac + rng.normal(0, 2.5, n)), 0, h - 1).astype(np.uint16)
    p = rng.choice(np.array([-1, 1], np.int8), n)
    fr = _frames(h, w, [0, 100_000, 200_000, 300_000])
    params = AKFParams(frame_precision_scale=1e3)
    seen = []
    orig = AKFEngine._rebalance

    def spy(self, yy):
        orig(self, yy)
        seen.append(list(self.bands))
    monkeypatch.setattr(AKFEngine, "_rebalance", spy)
    S1, o1, _ = _run_akf(1, t, x, y, p, fr, params, (h, w), batches=(0.2, 0.4, 0.6, 0.8))
    S2, o2, _ = _run_akf(n_workers, t, x, y, p, fr, params, (h, w), batches=(0.2, 0.4, 0.6, 0.8))
    firsts = [b[0][1] for b in seen]  # the first band's upper edge per batch
    assert len(set(firsts)) >= 3 and firsts[-1] > firsts[0] + 10, seen
    np.testing.assert_array_equal(S1, S2)
    for a, b in zip(o1, o2):
        for u, v in zip(a, b):
            np.testing.assert_array_equal(u, v)


@pytest.mark.parametrize("jit", [True, False])
def test_row_histogram_equals_bincount(jit):
    rng = np.random.default_rng(30)
    y = rng.integers(0, 50, 10_001).astype(np.uint16)
    y[::97] = 60  # rows past the histogram are not counted
    fn = K.row_histogram if jit else _py(K.row_histogram)
    hist = np.full(50, 7, np.int64)
    for i0, i1, step in ((0, 10_001, 1), (13, 9_000, 8), (5, 5, 3)):
        sub = y[i0:i1:step]
        want = np.bincount(sub[sub < 50], minlength=50)
        np.testing.assert_array_equal(fn(y, i0, i1, step, hist), want)


@pytest.mark.parametrize("n_workers", [1, 2])
def test_akf_deferred_switch_equals_immediate(n_workers):
    """A frame switch is applied inside the next parallel call (events or output); reading the
    state forces it. Back-to-back switches with no event between, an output straight after a
    switch, and a forced switch after every frame all give the same filter, bit for bit."""
    h, w, n = 21, 12, 50_000
    t, x, y, p = _stream(n, h, w, seed=31, span=200_000, boundary_rows=(9, 10, 11))
    t[(t >= 60_000) & (t < 90_000)] = 59_999  # no event between the frames at 60, 70 and 80 ms
    t = np.sort(t)
    fr = _frames(h, w, [0, 60_000, 70_000, 80_000, 150_000])
    params = AKFParams(frame_precision_scale=1e3)
    res = []
    for force in (False, True):
        m = FrameMeasurements(fr, (h, w), default_profile(), intensity_offset=params.intensity_offset)
        eng = AKFEngine((h, w), m, params, n_workers=n_workers)
        eng.start(None)
        outs = []
        i = k = 0
        while eng.next_switch_us() is not None:
            j = int(np.searchsorted(t, eng.next_switch_us(), side="left"))
            eng.process(t, x, y, p, i, j)
            ts = eng.next_switch_us()
            eng.switch()
            if force:
                eng.S  # noqa: B018 - the property applies the pending switch
                assert eng._pending is None
            else:
                assert eng._pending is not None
            if k % 2:  # an output after every other switch only: back-to-back switches too
                outs.append(eng.output(ts + 1))
            k += 1
            i = j
        eng.process(t, x, y, p, i, n)
        res.append((eng.S.copy(), outs))
        eng.close()
    np.testing.assert_array_equal(res[0][0], res[1][0])
    for a, b in zip(res[0][1], res[1][1]):
        np.testing.assert_array_equal(a, b)
    # the serial filter agrees too
    S1, _, _ = _run_akf(1, t, x, y, p, fr, params, (h, w))
    np.testing.assert_array_equal(res[0][0], S1)


@pytest.mark.parametrize("jit", [True, False])
@pytest.mark.parametrize("nb", [2, 3])
def test_band_split_equals_band_select_per_band(jit, nb):
    """Splitting a part of a batch for all bands at once = band_select per band on that part."""
    rng = np.random.default_rng(40 + nb)
    y = rng.integers(0, 30, 5_000).astype(np.uint16)
    edges = np.linspace(0, 30, nb + 1).astype(int)
    los = np.array([e - 1 for e in edges[:-1]], np.int64)
    his = np.array([e + 1 for e in edges[1:]], np.int64)
    fn = K.band_split if jit else _py(K.band_split)
    i0, j0, j1 = 100, 1_300, 4_100
    out = np.full((nb, j1 - j0), -1, np.int32)
    counts = np.full(nb, -5, np.int64)
    assert fn(y, i0, j0, j1, los, his, out, counts) == j1 - j0
    for b in range(nb):
        idx = np.empty(j1 - j0, np.int32)
        m = K.band_select(y, j0, j1, los[b], his[b], idx)
        assert counts[b] == m
        np.testing.assert_array_equal(out[b, :m], idx[:m] + (j0 - i0))


def test_akf_worker_error_does_not_hang_the_other_workers(monkeypatch):
    """If one worker fails in its split, the others (waiting for its part) are released and the error is raised."""
    import threading
    h, w, n = 20, 10, 60_000
    t, x, y, p = _stream(n, h, w, seed=41)
    fr = _frames(h, w, [0, 300_000])
    m = FrameMeasurements(fr, (h, w), default_profile(), intensity_offset=1.0)
    eng = AKFEngine((h, w), m, AKFParams(), n_workers=3)
    eng.start(None)
    real = K.band_split

    def failing(y_, i0, j0, *a):
        if j0 == i0:  # the first part's worker fails
            raise RuntimeError("simulated worker failure")
        return real(y_, i0, j0, *a)
    monkeypatch.setattr(K, "band_split", failing)
    errors = []

    def run():
        try:
            eng.process(t, x, y, p, 0, n)
        except BaseException as e:  # noqa: BLE001 - the test inspects it
            errors.append(e)
    th = threading.Thread(target=run, daemon=True)
    th.start()
    th.join(timeout=30)
    assert not th.is_alive(), "the workers hung at the barrier"
    assert len(errors) == 1 and isinstance(errors[0], RuntimeError), errors  # the cause, not the barrier's
    eng.close()


@pytest.mark.parametrize("n_workers", [1, 2])
def test_akf_measurement_lookahead_is_sequential_and_changes_nothing(n_workers):
    """A generic provider's next segment is computed in the background, but its calls stay
    one at a time and in order, and the filter equals the one without look-ahead bit for bit."""
    import threading
    import time

    class Recorder(_StepMeasurements):
        def __init__(self, inner):
            super().__init__(inner)
            self.calls, self.threads = [], set()
            self._busy = threading.Lock()

        def segment(self, k):
            assert self._busy.acquire(blocking=False), "segment() called concurrently"
            try:
                self.calls.append(k)
                self.threads.add(threading.get_ident())
                time.sleep(0.002)
                return super().segment(k)
            finally:
                self._busy.release()

    h, w, n = 18, 11, 40_000
    t, x, y, p = _stream(n, h, w, seed=50, boundary_rows=(8, 9))
    fr = _frames(h, w, [0, 40_000, 80_000, 120_000, 160_000])
    res = []
    for ahead in (True, False):
        m = Recorder(FrameMeasurements(fr, (h, w), default_profile(), intensity_offset=1.0))
        eng = AKFEngine((h, w), m, AKFParams(), n_workers=n_workers)
        eng.lookahead = ahead
        eng.start(None)
        i = 0
        while eng.next_switch_us() is not None:
            j = int(np.searchsorted(t, eng.next_switch_us(), side="left"))
            eng.process(t, x, y, p, i, j)
            eng.switch()
            i = j
        eng.process(t, x, y, p, i, n)
        out = eng.output(int(t[-1]) + 1)
        eng.close()
        assert m.calls == list(range(len(fr))), m.calls
        assert (len(m.threads) > 1) == ahead
        res.append((eng.S.copy(), out))
    np.testing.assert_array_equal(res[0][0], res[1][0])
    np.testing.assert_array_equal(res[0][1], res[1][1])
