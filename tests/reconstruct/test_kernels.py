"""Each Numba kernel equals its Python original; the row-band parallel AKF is bit-identical."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.events import events_fields
from hybridhdr.reconstruct import AKFParams, CFParams, reconstruct
from hybridhdr.reconstruct import _kernels as K

from .conftest import ideal_recording


def _py(f):
    """The Python original of a kernel (the function itself under NUMBA_DISABLE_JIT=1)."""
    return getattr(f, "py_func", f)


def _events(n=300, h=5, w=6, seed=1):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(1_000, 60_000, n)).astype(np.int64)
    t[10:14] = t[10]  # equal timestamps
    x = rng.integers(0, w, n).astype(np.uint16)
    y = rng.integers(0, h, n).astype(np.uint16)
    p = rng.choice(np.array([-1, 1], np.int8), n)
    return t, x, y, p


def _akf_state(n, seed=2, censored=False):
    """A random AKF state; ``censored``: some β = 0 pixels carry a bound direction (±1) in klog."""
    rng = np.random.default_rng(seed)
    S = K.aligned_state(n, K.AKF_FIELDS)
    S[:, K.A_L] = rng.normal(0, 0.3, n)
    S[:, K.A_P] = rng.uniform(0.005, 0.1, n)
    S[:, K.A_LA] = rng.normal(0, 0.3, n)
    S[:, K.A_RINV] = rng.uniform(10, 1e4, n)
    S[:, K.A_BETA] = np.where(rng.random(n) < 0.3, 0.0, rng.uniform(-0.5, 2.0, n))
    S[:, K.A_KLOG] = np.where(S[:, K.A_BETA] != 0, S[:, K.A_RINV] * 0.1 / np.where(S[:, K.A_BETA] != 0, S[:, K.A_BETA], 1), 0)
    S[:, K.A_TU] = 1_000.0
    S[:, K.A_LASTEP] = rng.uniform(0.05, 0.2, n)
    if censored:
        cz = rng.choice(np.array([-1.0, 0.0, 1.0]), n)
        S[:, K.A_KLOG] = np.where(S[:, K.A_BETA] == 0, cz, S[:, K.A_KLOG])
    return S


def _censor(n, seed):
    """Per-pixel (or per-code) censoring directions: +1, -1 or 0."""
    return np.random.default_rng(seed).choice(np.array([-1.0, 0.0, 0.0, 1.0]), n)


#: (censor?, discrete, s_proc, la_step): the published semantics first, then hybridhdr's
#: censored bounds, discrete frame update, process noise at the switch, and per-event L^A steps.
SWITCH_VARIANTS = [(False, False, 0.0, 0.0), (True, True, 0.05, 0.1), (True, False, 0.0, 0.0),
                   (False, True, 0.05, 0.0), (False, False, 0.05, 0.1)]


@pytest.mark.parametrize("per_pixel", [False, True])
@pytest.mark.parametrize("noise_form", [0, 1])
@pytest.mark.parametrize("has_la_step", [False, True, "follow"])
def test_akf_events_equals_py_func(noise_form, has_la_step, per_pixel):
    h, w = 5, 6
    t, x, y, p = _events(h=h, w=w)
    rng = np.random.default_rng(11)
    con = rng.uniform(0.08, 0.2, h * w) if per_pixel else np.empty(0)
    coff = rng.uniform(0.1, 0.3, h * w) if per_pixel else np.empty(0)
    outs = []
    # the compiled kernel and its Python source; int64 absolute last-event times and int32 ones
    # relative to te_base (as the engine keeps them): the same state and times bit for bit
    for fn, dtype, base in ((K.akf_events, np.int64, 0), (_py(K.akf_events), np.int64, 0),
                            (K.akf_events, np.int32, 1_000), (_py(K.akf_events), np.int32, 1_000)):
        S = _akf_state(h * w)
        if has_la_step == "follow":
            S[:, K.A_LASTEP] = -1.0
        te = K.padded_te(h, w, 1_000 - base, dtype)
        n = fn(t, x, y, p, 0, len(t), 0, h, w, h, S, te, np.int64(base), bool(has_la_step), 1_000.0,
               1.0 / 100_000, 0.12, 0.08, 5e-4, 0.03, 0.01, np.int64(10_000), noise_form, con, coff)
        outs.append((n, S.copy(), te.astype(np.int64) + base))
    for o in outs[1:]:
        assert o[0] == outs[0][0] == len(t)
        np.testing.assert_array_equal(o[1], outs[0][1])
        np.testing.assert_array_equal(o[2], outs[0][2])


@pytest.mark.parametrize("update_frame", [False, True])
@pytest.mark.parametrize("cens, discrete, s_proc, la_step", SWITCH_VARIANTS)
def test_akf_output_and_switch_equal_py_func(cens, discrete, s_proc, la_step, update_frame):
    n = 30
    rng = np.random.default_rng(5)
    lf, rinv = rng.normal(0, 0.3, n), rng.uniform(1e3, 1e6, n)
    beta = np.where(rng.random(n) < 0.5, 0.0, rng.uniform(-0.5, 2.0, n))
    censor = _censor(n, 9) if cens else np.empty(0)
    step = np.full(n, la_step) if la_step else np.empty(0)
    uf = lf + rng.normal(0, 0.05, n) if update_frame else np.empty(0)
    res = []
    for sw, outk in ((K.akf_switch, K.akf_output), (_py(K.akf_switch), _py(K.akf_output))):
        S = _akf_state(n, censored=cens)
        o = np.empty(n, np.float32); lg = np.empty(n); var = np.empty(n)
        outk(S, 1_000.0, 1.0 / 100_000, 77_777.0, o, lg, var, 0, n)
        sw(S, True, 1_000.0, 1.0 / 100_000, 50_000.0, lf, rinv, beta, step, censor, 0.03, discrete, s_proc, uf, 0, n)
        res.append((S.copy(), o, lg, var))
    for a, b in zip(*res):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(res[0][1], res[0][2].astype(np.float32))  # L̂ rounded to float32


def test_log_to_linear_single_precision():
    """exp(L̂) - offset in float32 (vectorised) is within a float32 rounding or two of float64's."""
    a = np.random.default_rng(6).uniform(-8, 8, 100_000).astype(np.float32)
    a64 = a.astype(np.float64)
    got = K.log_to_linear(a.copy(), 0.5)
    want = np.exp(a64) - 0.5
    assert got.dtype == np.float32
    # float32 eps 1.19e-7: exp within 2 eps of exp(L̂) (numpy's bound is a few ulp), then one
    # rounding of the difference, relative to the difference itself
    assert np.all(np.abs(got - want) <= 1.2e-7 * (2 * np.exp(a64) + np.abs(want)))


@pytest.mark.parametrize("censored", [False, True])
def test_akf_switch_propagates_as_output_predicts(censored):
    """The switch's propagation (eqs. 17, 20) is the closed form akf_output evaluates, bit for bit;
    without ``propagate`` L̂, P and tu are untouched. ``censored``: the current segment holds
    censored bounds (no pull where the state satisfies them) and the new one loads some too
    (continuous frame update: the load does not touch L̂ or P)."""
    n = 50
    lf, rinv = np.full(n, 0.2), np.full(n, 5e3)
    censor = _censor(n, 4) if censored else np.empty(0)
    for fn in (K.akf_switch, _py(K.akf_switch)):
        S = _akf_state(n, censored=censored)
        lg = np.empty(n); var = np.empty(n)
        K.akf_output(S, 1_000.0, 1.0 / 100_000, 61_000.0, np.empty(n, np.float32), lg, var, 0, n)
        before = S.copy()
        fn(S, False, 1_000.0, 1.0 / 100_000, 61_000.0, lf, rinv, np.empty(0), np.empty(0), censor, 0.0, False, 0.0,
           np.empty(0), 0, n)
        for f in (K.A_L, K.A_P, K.A_TU):
            np.testing.assert_array_equal(S[:, f], before[:, f])
        S = before.copy()
        fn(S, True, 1_000.0, 1.0 / 100_000, 61_000.0, lf, rinv, np.empty(0), np.empty(0), censor, 0.0, False, 0.0,
           np.empty(0), 0, n)
        np.testing.assert_array_equal(S[:, K.A_L], lg)
        np.testing.assert_array_equal(S[:, K.A_P], var)
        assert (S[:, K.A_TU] == 61_000.0).all()


@pytest.mark.parametrize("cens, discrete, s_proc, la_step", SWITCH_VARIANTS)
@pytest.mark.parametrize("jit", [True, False])
def test_akf_switch_lut_equals_lut_segment_then_switch(jit, cens, discrete, s_proc, la_step):
    """The one-pass LUT switch loads exactly what lut_segment + akf_switch load (codes clipped),
    also with a per-code censor table (β = 0 where frame k or k+1 is censored, the direction in
    klog), the discrete frame update with process noise, and a per-event L^A step."""
    n = 400
    rng = np.random.default_rng(13)
    max_code = 255
    inten_l, rbar_l, logf_l, rinv_l = (rng.uniform(0.1, 2.0, max_code + 1) for _ in range(4))
    cens_l = _censor(max_code + 1, 14) if cens else np.empty(0)
    code = rng.integers(-3, 300, n).astype(np.int16)
    nxt = rng.integers(0, 256, n).astype(np.int16)
    censor = cens_l[np.clip(code, 0, max_code)] if cens else np.empty(0)
    step = np.full(n, la_step) if la_step else np.empty(0)
    fn = K.akf_switch_lut if jit else _py(K.akf_switch_lut)
    for has_next in (True, False):
        for seg_t_s in (0.0333, 0.0):
            for prop in (True, False):
                nx = nxt if has_next else nxt[:0]
                lf, it, ri, be = (np.empty(n) for _ in range(4))
                K.lut_segment(code, nx, max_code, inten_l, rbar_l, logf_l, rinv_l, cens_l, lf, it, ri, be)
                want = _akf_state(n, censored=cens)
                K.akf_switch(want, prop, 1_000.0, 1.0 / 100_000, 40_000.0, lf, ri, be, step, censor, seg_t_s,
                             discrete, s_proc, np.empty(0), 0, n)
                got = _akf_state(n, censored=cens)
                fn(got, prop, 1_000.0, 1.0 / 100_000, 40_000.0, code, nx, max_code, rbar_l, logf_l, rinv_l,
                   cens_l, la_step, seg_t_s, discrete, s_proc, 0, n)
                np.testing.assert_array_equal(got, want)
                if cens:
                    cz = censor != 0
                    assert cz.any() and not got[cz, K.A_BETA].any()
                    np.testing.assert_array_equal(got[cz, K.A_KLOG], censor[cz])


def test_cf_kernels_equal_py_func():
    h, w = 5, 6
    t, x, y, p = _events(h=h, w=w)
    res = []
    for ev, prop, outk in ((K.cf_events, K.cf_propagate, K.cf_output),
                           (_py(K.cf_events), _py(K.cf_propagate), _py(K.cf_output))):
        rng = np.random.default_rng(3)
        C = K.aligned_state(h * w, K.CF_FIELDS)
        C[:, K.C_LF] = rng.normal(0, 0.3, h * w)
        C[:, K.C_ALPHA] = rng.uniform(0, 20, h * w)
        C[:, K.C_TU] = 1_000.0
        ev(t, x, y, p, 0, len(t), 0, h, w, C, 0.1, 0.12, 0.01, np.empty(0), np.empty(0))
        o = np.empty(h * w, np.float32)
        outk(C, 70_000.0, 1.0, o, 0, h * w)
        prop(C, 80_000.0, 0, h * w)
        res.append((C.copy(), o))
    for a, b in zip(*res):
        np.testing.assert_array_equal(a, b)


def test_rinv_integral_series_and_log_branches_agree():
    # x just below and above the series threshold give the same integral to 1e-15
    for beta in (0.3, -0.4, 1e-9):
        for du in (0.0333333, 0.0333334, 1e-6, 0.9):
            a = _py(K.rinv_integral)(5.0, beta, 5.0 * 1.0 / beta, 0.0, du * 1e6, 0.0, 1e-6)
            exact = 5.0 / beta * np.log1p(beta * du)
            assert a == pytest.approx(exact, rel=1e-13)


@pytest.mark.parametrize("method", ["akf", "cf"])
@pytest.mark.parametrize("n_workers", [2, 3])
def test_parallel_bit_identical(method, n_workers):
    """Row bands with ghost rows reproduce the serial filter exactly (events on band boundaries)."""
    rec, _ = ideal_recording(height=12, width=16, noise_events=400)
    params = AKFParams(frame_precision_scale=100.0) if method == "akf" else CFParams(cutoff_hz=2.0)
    a = reconstruct(rec, method, params, fps=250, n_workers=1)
    b = reconstruct(rec, method, params, fps=250, n_workers=n_workers, chunk_events=10**6)
    np.testing.assert_array_equal(a.frames, b.frames)
    assert a.info["n_events_used"] == b.info["n_events_used"] == len(rec.events)


def test_parallel_threads_bit_identical_on_large_chunk():
    """Large batches take the threaded path (>= 20 000 events per call)."""
    from hybridhdr.reconstruct._engine import AKFEngine
    from hybridhdr.camera import default_profile
    from hybridhdr.reconstruct import FrameMeasurements
    rng = np.random.default_rng(5)
    h, w, n = 20, 24, 60_000
    t = np.sort(rng.integers(0, 200_000, n)).astype(np.int64)
    x = rng.integers(0, w, n).astype(np.uint16); y = rng.integers(0, h, n).astype(np.uint16)
    p = rng.choice(np.array([-1, 1], np.int8), n)
    from hybridhdr import Frames
    codes = rng.integers(0, 256, (2, h, w)).astype(np.uint8)
    fr = Frames(codes, np.array([0, 300_000]), np.array([0, 300_000]))
    states = []
    for nw in (1, 2):
        m = FrameMeasurements(fr, (h, w), default_profile(), intensity_offset=1.0)
        eng = AKFEngine((h, w), m, AKFParams(), n_workers=nw)
        eng.start(None)
        eng.process(t, x, y, p, 0, n)
        states.append(eng.S.copy())
        eng.close()
    np.testing.assert_array_equal(states[0], states[1])


def test_akf_switch_load_equals_py_func_and_numpy():
    n = 40
    rng = np.random.default_rng(8)
    lf, rinv = rng.normal(0, 0.3, n), rng.uniform(1e3, 1e6, n)
    beta = np.where(rng.random(n) < 0.5, 0.0, rng.uniform(-0.5, 2.0, n))
    step = rng.uniform(0.05, 0.2, n)
    cens = _censor(n, 10)
    T_s = 0.0333
    res = []
    e = np.empty(0)
    for fn in (K.akf_switch, _py(K.akf_switch)):
        for b, st, cz, ts in ((beta, step, e, T_s), (e, e, e, T_s), (beta, step, e, 0.0), (beta, step, cens, T_s)):
            S = _akf_state(n)
            fn(S, False, 0.0, 0.0, 0.0, lf, rinv, b, st, cz, ts, False, 0.0, e, 0, n)
            res.append(S.copy())
    for a, b in zip(res[:4], res[4:]):
        np.testing.assert_array_equal(a, b)
    S = res[0]
    np.testing.assert_array_equal(S[:, K.A_LA], lf)
    np.testing.assert_array_equal(S[:, K.A_KLOG], np.where(beta != 0, rinv * T_s / np.where(beta != 0, beta, 1), 0))
    assert not res[1][:, K.A_BETA].any() and not res[1][:, K.A_LASTEP].any()
    assert not res[2][:, K.A_BETA].any() and not res[2][:, K.A_KLOG].any()
    # a censored pixel holds R (β = 0) and keeps its bound's direction in klog
    S = res[3]
    cz = cens != 0
    np.testing.assert_array_equal(S[:, K.A_BETA], np.where(cz, 0.0, res[0][:, K.A_BETA]))
    np.testing.assert_array_equal(S[:, K.A_KLOG], np.where(cz, cens, res[0][:, K.A_KLOG]))
    np.testing.assert_array_equal(S[:, K.A_LA], lf)


@pytest.mark.parametrize("discrete", [True, False])
@pytest.mark.parametrize("jit", [True, False])
def test_akf_switch_discrete_update_closed_form(jit, discrete):
    """After the propagation to τ (akf_output's closed form) a switch adds the process noise,
    P ← P + σ²_proc(τ - tu); with ``discrete`` it then applies one Kalman update with the new
    frame (``update_frame`` when given, else L^F): κ = P/(P + 1/rinv), L̂ ← L̂ + κ(L^F - L̂),
    P ← (1 - κ)P. A censored frame leaves a state that satisfies its bound untouched and moves
    one that violates it by the same κ but keeps P (a projection: P only gains the process noise)."""
    n = 60
    rng = np.random.default_rng(21)
    lf, rinv = rng.normal(0, 0.3, n), rng.uniform(10, 1e4, n)
    cens = _censor(n, 22)
    uf_vals = lf + rng.normal(0, 0.1, n)
    fn = K.akf_switch if jit else _py(K.akf_switch)
    t_to, s_proc = 50_000.0, 0.05
    for censor, uf in ((np.empty(0), np.empty(0)), (cens, np.empty(0)), (cens, uf_vals)):
        S = _akf_state(n, censored=True)
        lg = np.empty(n); var = np.empty(n)
        K.akf_output(S, 1_000.0, 1.0 / 100_000, t_to, np.empty(n, np.float32), lg, var, 0, n)
        tu = S[:, K.A_TU].copy()
        fn(S, True, 1_000.0, 1.0 / 100_000, t_to, lf, rinv, np.empty(0), np.empty(0), censor, 0.03, discrete, s_proc,
           uf, 0, n)
        Pq = var + s_proc * (t_to - tu) * 1e-6
        if discrete:
            z = uf if uf.shape[0] else lf
            kappa = Pq / (Pq + 1.0 / rinv)
            L = lg + kappa * (z - lg)
            P = (1.0 - kappa) * Pq
            if censor.shape[0]:
                hold = censor * (lg - z) > 0
                assert hold.any() and (~hold & (censor != 0)).any()
                # a violated bound: the Tobit update's conditional mean beyond it (P < TOBIT_MAX_P),
                # else the plain update towards it
                from scipy.stats import norm
                sd = np.sqrt(Pq + 1.0 / rinv)
                a = censor * (z - lg) / sd
                tobit = lg + censor * (Pq / sd) * norm.pdf(a) / norm.sf(a)
                viol = (censor != 0) & ~hold
                L = np.where(viol & (Pq < K.TOBIT_MAX_P), tobit, L)
                L = np.where(hold, lg, L)
                P = np.where(censor != 0, Pq, P)
        else:
            L, P = lg, Pq
        np.testing.assert_allclose(S[:, K.A_L], L, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(S[:, K.A_P], P, rtol=1e-13)
        np.testing.assert_array_equal(S[:, K.A_LA], lf)  # L^A is the segment's, not the update's frame
        assert (S[:, K.A_TU] == t_to).all()


@pytest.mark.parametrize("jit", [True, False])
def test_isolated_noise_window_clipped_at_border(jit):
    """t* (eq. 2, §3.1.1) is the latest event time in the 3×3 window clipped at the sensor border.

    With R⁻¹ = 0 (no propagation) and only σ²_iso non-zero, each event adds exactly
    σ²_iso·(t_i − t*)·1e-6 to P, so P reveals which neighbour times the kernel saw. The padded
    last-event-time array must behave like the clipped window at corners and edges, and a
    neighbour just outside the window must not count.
    """
    h, w = 4, 5
    fn = K.akf_events if jit else _py(K.akf_events)
    # (x, y, t) in time order; the corner (0,0) sees (1,1); the edge pixel (4,2) sees (3,3) but
    # not (2,2), one column outside its window; (4,0) sees nobody
    ev = [(1, 1, 1_500), (3, 3, 1_700), (2, 2, 1_800), (0, 0, 2_000), (4, 2, 2_500), (4, 0, 3_000)]
    t = np.array([e[2] for e in ev], np.int64)
    x = np.array([e[0] for e in ev], np.uint16)
    y = np.array([e[1] for e in ev], np.uint16)
    p = np.ones(len(ev), np.int8)
    S = K.aligned_state(h * w, K.AKF_FIELDS)
    S[:, K.A_TU] = 1_000.0
    te = K.padded_te(h, w, 1_000)
    s_iso = 1e3
    fn(t, x, y, p, 0, len(t), 0, h, w, h, S, te, np.int64(0), False, 1_000.0, 0.0, 0.1, 0.1, 0.0, s_iso, 0.0,
       np.int64(0), 0, np.empty(0), np.empty(0))
    P = S[:, K.A_P].reshape(h, w)
    # t_i − t*, keyed (y, x); the start time 1000 counts as every pixel's last event time
    expect = {(1, 1): 500, (3, 3): 700, (2, 2): 100, (0, 0): 500, (2, 4): 800, (0, 4): 2_000}
    for (yy, xx), dt in expect.items():
        assert P[yy, xx] == pytest.approx(s_iso * dt * 1e-6, rel=1e-12, abs=1e-15), (yy, xx)
    np.testing.assert_array_equal(K.te_view(te, h, w)[y.astype(int), x.astype(int)], t)
    assert (te.reshape(h + 2, w + 2)[[0, -1]] == 1_000).all()  # the border is never written


@pytest.mark.parametrize("cens", [False, True])
@pytest.mark.parametrize("jit", [True, False])
def test_lut_segment_equals_numpy_tables(jit, cens):
    """One-pass segment builder = the per-code tables gathered with numpy (codes clipped); with a
    censor table β is 0 where frame k's or k+1's code is censored."""
    rng = np.random.default_rng(12)
    max_code = 255
    tabs = [rng.uniform(0.1, 2.0, max_code + 1) for _ in range(4)]  # intensity, rbar, logf, rinv
    cens_l = _censor(max_code + 1, 15) if cens else np.empty(0)
    code = rng.integers(-3, 300, 500).astype(np.int32)
    nxt = rng.integers(0, 256, 500).astype(np.int32)
    fn = K.lut_segment if jit else _py(K.lut_segment)
    c = np.clip(code, 0, max_code)
    c1 = np.clip(nxt, 0, max_code)
    for has_next in (True, False):
        out = [np.full(500, np.nan) for _ in range(4)]
        fn(code, nxt if has_next else nxt[:0], max_code, *tabs, cens_l, *out)
        np.testing.assert_array_equal(out[0], tabs[2][c])
        np.testing.assert_array_equal(out[1], tabs[0][c])
        np.testing.assert_array_equal(out[2], tabs[3][c])
        want_beta = tabs[1][c1] / tabs[1][c] - 1.0 if has_next else np.zeros(500)
        if cens:
            cz = (cens_l[c] != 0) | (cens_l[c1] != 0)
            assert cz.any() and (~cz).any()
            want_beta = np.where(cz, 0.0, want_beta)
        np.testing.assert_array_equal(out[3], want_beta)


def test_pixel_functions_compile_for_another_target():
    """The per-pixel arithmetic is one source compiled per target: compiled with an identity "jit"
    (plain Python calling plain Python, as the CUDA simulator runs it) it gives the CPU kernels'
    bits for an event step, a frame switch and an output."""
    py = K.compile_pixel_functions(lambda f: f)
    assert set(py) == {f.__name__ for f in K.PIXEL_FUNCTIONS}
    rng = np.random.default_rng(5)
    for _ in range(200):
        lh, pp, la = rng.normal(0, 0.3), rng.uniform(0.005, 0.1), rng.normal(0, 0.3)
        rinv, beta = rng.uniform(10, 1e4), (0.0 if rng.random() < 0.3 else rng.uniform(-0.5, 2.0))
        klog = rinv * 0.1 / beta if beta else float(rng.choice([-1.0, 0.0, 1.0]))
        args = (lh, pp, la, 1_000.0, int(rng.integers(1_000, 90_000)), int(rng.integers(0, 20_000)),
                int(rng.integers(0, 20_000)), bool(rng.random() < 0.5), rinv, beta, klog, rng.uniform(-0.1, 0.2),
                bool(rng.random() < 0.5), 0.0, 1e-5, 0.12, -0.09, 0.05, 0.03, 0.01, np.int64(10_000),
                int(rng.integers(0, 2)))
        assert K.akf_event_step(*args) == py["akf_event_step"](*args)
        out = (lh, pp, la, rinv, beta, klog, 1_000.0, 60_000.0, 0.0, 1e-5)
        assert K.output_pixel(*out) == py["output_pixel"](*out)
    S = _akf_state(40, censored=True)
    S2 = S.copy()
    for pix in range(40):
        a = (pix, True, 1_000.0, 1e-5, 50_000.0, 0.05, 0.1, 200.0, 0.3, float(pix % 3 - 1), 0.1, 0.08, True, 0.2)
        K.akf_switch_pixel(S, *a)
        py["akf_switch_pixel"](S2, *a)
    np.testing.assert_array_equal(S, S2)
