"""Two-sided offline AKF (hybridhdr.reconstruct.smoother): reversal, fusion, determinism."""

from __future__ import annotations


import numpy as np
import pytest

from hybridhdr.events import EVENT_DTYPE, SensorSize
from hybridhdr.model import Frames, Recording
from hybridhdr.reconstruct import AKFParams, reconstruct
from hybridhdr.reconstruct.event_arrays import EventArrays
from hybridhdr.reconstruct.smoother import fuse, output_times, reverse_events, reverse_frames


def _rec(seed=0, h=5, w=7, k=6):
    rng = np.random.default_rng(seed)
    ts = np.arange(k, dtype=np.int64) * 40_000 + 1_000
    img = rng.integers(20, 230, (k, h, w)).astype(np.uint8)
    frames = Frames(img, ts, ts + 3_001, encoding="linear")  # odd exposure: mid rounding matters
    n = 3000
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, int(ts[-1]) + 10_000, n))
    ev["x"], ev["y"] = rng.integers(0, w, n), rng.integers(0, h, n)
    ev["p"] = rng.choice([-1, 1], n)
    return Recording(ev, SensorSize(h, w), frames)


def test_fuse_is_inverse_covariance_weighting():
    l, p = fuse([0.0, 1.0], [1.0, 3.0], [2.0, 1.0], [3.0, 1e-12])
    assert l == pytest.approx([0.5, 1.0]) and p == pytest.approx([0.75, 1e-12], rel=1e-6)


def test_reversal_is_an_involution_and_keeps_mid_exposure_times():
    rec = _rec()
    ev = EventArrays.from_structured(rec.events, rec.sensor_size.shape)
    m = 123_457
    back = reverse_events(reverse_events(ev, m), m)
    for a in "txyp":
        assert np.array_equal(getattr(back, a), getattr(ev, a))
    r = reverse_events(ev, m)
    assert np.all(np.diff(r.t) >= 0) and np.array_equal(r.p, -ev.p[::-1])
    fr = reverse_frames(rec.frames, m)
    assert np.array_equal(fr.t_mid_us, (m - 1) - rec.frames.t_mid_us[::-1])
    assert np.array_equal(fr.exposure_us, rec.frames.exposure_us[::-1])
    assert np.array_equal(reverse_frames(fr, m).t_mid_us, rec.frames.t_mid_us)


def test_static_scene_without_events_gives_the_frames():
    rec = _rec()
    still = Frames(np.repeat(rec.frames.images[:1], len(rec.frames), 0), rec.frames.t_start_us,
                   rec.frames.t_end_us, encoding="linear")
    r = Recording(np.zeros(0, EVENT_DTYPE), rec.sensor_size, still)
    v = reconstruct(r, "akf", AKFParams(bias_correction=False), fps=100.0)
    want = still.images[0] / 255.0
    assert np.allclose(v.frames, want, rtol=2e-6), np.abs(v.frames - want).max()
    assert v.info["two_sided"]["outputs_fused"] > 0


def test_two_sided_uses_the_future_frame():
    """A pixel steps up between frames k and k+1 with no events: at τ_{k+1} - 1 µs the forward
    filter still says frame k, the two-sided one leans towards frame k+1."""
    rec = _rec()
    k = len(rec.frames)
    img = np.full((k, 5, 7), 50, np.uint8)
    img[3:] = 200
    fr = Frames(img, rec.frames.t_start_us, rec.frames.t_end_us, encoding="linear")
    r = Recording(np.zeros(0, EVENT_DTYPE), rec.sensor_size, fr)
    t = int(fr.t_mid_us[3]) - 1
    fwd = reconstruct(r, "akf", times_us=[t], mode="causal").frames[0, 0, 0]
    two = reconstruct(r, "akf", times_us=[t]).frames[0, 0, 0]
    assert fwd == pytest.approx(50 / 255, rel=1e-3)
    assert two > 100 / 255


def test_two_sided_is_deterministic_and_bit_identical_across_workers():
    rec = _rec(3, h=40, w=9)
    # the default parameters as given (the self-calibration is not under test here)
    a = reconstruct(rec, "akf", fps=250.0, n_workers=1, thresholds="input")
    b = reconstruct(rec, "akf", fps=250.0, n_workers=2, thresholds="input")
    c = reconstruct(rec, "akf", fps=250.0, n_workers=1, thresholds="input")
    assert np.array_equal(a.frames, b.frames) and np.array_equal(a.frames, c.frames)
    assert np.array_equal(a.t_us, b.t_us)


def test_output_times_match_the_forward_driver():
    rec = _rec()
    fwd = reconstruct(rec, "akf", fps=300.0, mode="forward", thresholds="input")
    t = output_times(rec.frames.t_mid_us, int(rec.events["t"][-1]), fps=300.0)
    assert np.array_equal(t, fwd.t_us)
    two = reconstruct(rec, "akf", fps=300.0, thresholds="input")
    assert np.array_equal(two.t_us, fwd.t_us)


@pytest.mark.parametrize("c_on, c_off", [(0.1, 0.1), (0.12, 0.2)])
def test_reversing_the_recording_reverses_the_output(c_on, c_off):
    """Two-sided AKF on the reversed recording (thresholds swapped: a forward ON event is a
    backward OFF event of the same size) at the reversed times gives the same frames, reversed."""
    rec = _rec(5)
    ev = EventArrays.from_structured(rec.events, rec.sensor_size.shape)
    fr = rec.frames
    t_lo = min(int(ev.t[0]), int(fr.t_start_us[0]))
    t_hi = max(int(ev.t[-1]), int(fr.t_end_us[-1]))
    m = t_lo + t_hi + 1
    rev = reverse_events(ev, m)
    rev_ev = np.zeros(len(rev), EVENT_DTYPE)
    rev_ev["t"], rev_ev["x"], rev_ev["y"], rev_ev["p"] = rev.t, rev.x, rev.y, rev.p
    r2 = Recording(rev_ev, rec.sensor_size, reverse_frames(fr, m))
    times = np.arange(int(fr.t_mid_us[0]) + 7, int(fr.t_mid_us[-1]), 4_999, dtype=np.int64)
    a = reconstruct(rec, "akf", AKFParams(contrast_threshold_on=c_on, contrast_threshold_off=c_off), times_us=times)
    b = reconstruct(r2, "akf", AKFParams(contrast_threshold_on=c_off, contrast_threshold_off=c_on),
                    times_us=(m - times)[::-1])
    np.testing.assert_array_equal(a.frames, b.frames[::-1])


def test_fused_estimate_equals_the_closed_form_two_filter_solution():
    """One pixel, no events, two frames: each pass is a closed-form Kalman filter of its frames;
    the output equals (L_f/P_f + L_b/P_b)/(1/P_f + 1/P_b) of the passes' own outputs."""
    h, w = 1, 1
    ts = np.array([0, 50_000], np.int64)
    img = np.array([[[60]], [[120]]], np.uint8)
    fr = Frames(img, ts, ts + 2_000, encoding="linear")
    r = Recording(np.zeros(0, EVENT_DTYPE), SensorSize(h, w), fr)
    t = np.array([1_000, 20_000, 40_000, 51_000 - 1], np.int64)
    p = AKFParams()
    from hybridhdr.reconstruct import _engine as E
    from hybridhdr.reconstruct.api import ReconstructRequest, engine_for
    from hybridhdr.reconstruct.smoother import _run_pass
    ev = EventArrays.from_structured(r.events, (h, w))
    mk = lambda f: engine_for(ReconstructRequest.build("akf", p, mode="forward"), (h, w), f, ev)  # noqa: E731
    q, s = p.carried_variance()  # each pass: P plus what its carried frame accumulated
    fwd = {tt: (lg.item(), var.item()) for tt, lg, var in
           _run_pass(lambda: mk(fr), ev, t, 1 << 20, None, (fr.t_mid_us, q, s))}
    m = 0 + 52_000 + 1
    rf = reverse_frames(fr, m)
    bwd = {m - tt: (lg.item(), var.item()) for tt, lg, var in
           _run_pass(lambda: mk(rf), reverse_events(ev, m), (m - t)[::-1], 1 << 20, None, (rf.t_mid_us, q, s))}
    got = reconstruct(r, "akf", p, times_us=t).frames[:, 0, 0]
    for i, tt in enumerate(t):
        (lf, pf), (lb, pb) = fwd[int(tt)], bwd[int(tt)]
        want = np.exp((lf / pf + lb / pb) / (1 / pf + 1 / pb)) - p.intensity_offset
        assert got[i] == pytest.approx(want, rel=1e-6)
        assert min(lf, lb) - 1e-9 <= np.log(got[i] + p.intensity_offset) <= max(lf, lb) + 1e-9


def test_per_pixel_threshold_map_equal_to_the_scalars_changes_nothing():
    rec = _rec(2)
    shape = rec.sensor_size.shape
    for mode in ("offline", "causal"):
        for method in ("akf", "cf", "direct"):
            a = reconstruct(rec, method, fps=200.0, mode=mode, thresholds="input")  # the scalar default, no calibration
            b = reconstruct(rec, method, fps=200.0, mode=mode,
                            thresholds=(np.full(shape, 0.1), np.full(shape, 0.1)))
            np.testing.assert_array_equal(a.frames, b.frames)


def test_per_pixel_thresholds_track_an_asymmetric_sensor():
    """A pixel with c_on = 0.15, c_off = 0.25: 10 ON then 6 OFF ideal events from a known start;
    with the map the causal AKF ends at start·exp(10·0.15 - 6·0.25) = start; with the scalar
    0.1 it does not."""
    h, w = 2, 2
    ts = np.array([0, 100_000], np.int64)
    img = np.full((2, h, w), 40, np.uint8)
    fr = Frames(img, ts, ts + 1_000, encoding="linear")
    n_on, n_off = 10, 6
    ev = np.zeros(n_on + n_off, EVENT_DTYPE)
    ev["t"] = np.linspace(10_000, 20_000, n_on + n_off).astype(np.int64)
    ev["p"] = [1] * n_on + [-1] * n_off
    r = Recording(ev, SensorSize(h, w), fr)
    thr = (np.full((h, w), 0.15), np.full((h, w), 0.25))
    start = 40 / 255
    v = reconstruct(r, "akf", times_us=[20_001], mode="causal", thresholds=thr)
    assert v.frames[0, 0, 0] == pytest.approx(start, rel=0.02)
    v0 = reconstruct(r, "akf", times_us=[20_001], mode="causal")
    assert abs(v0.frames[0, 0, 0] / start - 1) > 0.3


def test_backward_estimates_spilled_to_a_file_give_the_same_frames(monkeypatch):
    import hybridhdr.reconstruct.smoother as sm
    rec = _rec(4)
    a = reconstruct(rec, "akf", fps=500.0)
    monkeypatch.setattr(sm, "MEMORY_LIMIT_BYTES", 1)
    b = reconstruct(rec, "akf", fps=500.0)
    assert b.info["two_sided"]["spilled_to_disk"] and not a.info["two_sided"]["spilled_to_disk"]
    np.testing.assert_array_equal(a.frames, b.frames)


def test_each_pass_reports_p_plus_the_variance_its_carried_frame_accumulated():
    """Closed form of the carried variance: at t, a pass reports P + q·n + s·Δt, n the pixel's
    events since the pass's last frame and Δt the time since it; the fused output weighs the
    nearer frame more than P alone does (a frame 45 ms old against one 5 ms away)."""
    from hybridhdr.reconstruct.api import ReconstructRequest, engine_for
    from hybridhdr.reconstruct.smoother import _run_pass
    h, w = 1, 2
    ts = np.array([0, 50_000], np.int64)
    img = np.array([[[60, 60]], [[120, 120]]], np.uint8)
    fr = Frames(img, ts, ts + 2_000, encoding="linear")
    ev = np.zeros(8, EVENT_DTYPE)  # pixel 0 fires 8 ON events in the first 30 ms; pixel 1 none
    ev["t"] = np.arange(8) * 3_000 + 2_000
    ev["p"] = 1
    r = Recording(ev, SensorSize(h, w), fr)
    p = AKFParams(contrast_threshold=0.0866)  # 8 events: log(120/60) = 0.693
    q, s = p.carried_variance()
    assert (q, s) == (p.refractory_noise, p.process_noise_per_s)
    ea = EventArrays.from_structured(r.events, (h, w))
    t = np.array([1_000, 20_000, 46_000], np.int64)
    mk = lambda: engine_for(ReconstructRequest.build("akf", p, mode="forward"), (h, w), fr, ea)  # noqa: E731
    raw = {tt: var.copy() for tt, _, var in _run_pass(mk, ea, t, 1 << 20, None)}
    got = {tt: var for tt, _, var in _run_pass(mk, ea, t, 1 << 20, None, (fr.t_mid_us, q, s))}
    for tt in t:
        n0 = int(np.sum((ea.t >= 1_000) & (ea.t < tt)))  # frame 0's mid-exposure is 1 000 µs
        want = raw[int(tt)].astype(np.float64) + q * np.array([n0, 0]) + s * (tt - 1_000) * 1e-6
        np.testing.assert_allclose(got[int(tt)], want, rtol=1e-6)
    # the fused estimate at 46 ms (45 ms after frame 0, 5 ms before frame 1) leans to frame 1
    # more with the carried variance than with P alone, on the pixel without events too
    on = reconstruct(r, "akf", p, times_us=[46_000]).frames[0, 0]
    off = reconstruct(r, "akf", p.replace(fusion_carried_variance=False), times_us=[46_000]).frames[0, 0]
    assert abs(on[1] - 120 / 255) < abs(off[1] - 120 / 255)
    assert AKFParams.paper().carried_variance() is None and AKFParams.reference_code().carried_variance() is None



def test_a_frame_that_clips_a_pixel_does_not_restart_its_carried_variance():
    """A clipped code is a censored bound, not a measurement: the pixel's carried variance keeps
    running from its last unclipped frame (n and Δt since that frame), while a pixel the frame
    measures restarts there. Without the rule both restarted at the clipped frame, so the fusion
    weighed an estimate carried through clipped frames as if the clipped frame had measured it."""
    from hybridhdr.reconstruct.api import ReconstructRequest, engine_for
    from hybridhdr.reconstruct.smoother import _run_pass, frames_measure
    h, w = 1, 2
    ts = np.array([0, 40_000, 80_000], np.int64)
    img = np.array([[[100, 100]], [[255, 120]], [[110, 110]]], np.uint8)  # frame 1 clips pixel 0
    fr = Frames(img, ts, ts + 2_000, encoding="linear")  # mid-exposures 1, 41, 81 ms
    ev = np.zeros(12, EVENT_DTYPE)  # pixel 0: an ON event every 5 ms from 3 ms; pixel 1: none
    ev["t"] = np.arange(12) * 5_000 + 3_000
    ev["p"] = 1
    r = Recording(ev, SensorSize(h, w), fr)
    p = AKFParams(contrast_threshold=0.1)
    q, s = p.carried_variance()
    ea = EventArrays.from_structured(r.events, (h, w))
    t = np.array([20_000, 60_000, 90_000], np.int64)
    mk = lambda: engine_for(ReconstructRequest.build("akf", p, mode="forward"), (h, w), fr, ea)  # noqa: E731
    raw = {tt: var.copy() for tt, _, var in _run_pass(mk, ea, t, 1 << 20, None)}
    measured = frames_measure(fr, (0, 255))
    assert measured(1).tolist() == [False, True] and measured(0).all() and measured(2).all()
    got = {tt: var.copy() for tt, _, var in _run_pass(mk, ea, t, 1 << 20, None, (fr.t_mid_us, q, s, measured))}
    plain = {tt: var.copy() for tt, _, var in _run_pass(mk, ea, t, 1 << 20, None, (fr.t_mid_us, q, s))}
    mids = fr.t_mid_us
    # (output time, pixel 0's reference frame with the rule, without it); pixel 1 always the last frame
    for tt, ref0, last in ((20_000, 0, 0), (60_000, 0, 1), (90_000, 2, 2)):
        def want(ref, pix):
            n = int(np.sum((ea.t >= mids[ref]) & (ea.t < tt) & (ea.x == pix)))
            return float(raw[tt][pix]) + q * n + s * (tt - int(mids[ref])) * 1e-6
        np.testing.assert_allclose(got[tt], [want(ref0, 0), want(last, 1)], rtol=1e-6)
        np.testing.assert_allclose(plain[tt], [want(last, 0), want(last, 1)], rtol=1e-6)
    # at 60 ms pixel 0 has carried 12 events (3..58 ms) since frame 0, not 4 (43..58 ms) since frame 1
    assert got[60_000][0] - plain[60_000][0] == pytest.approx(q * 8 + s * 0.040, rel=1e-5)
    # the two-sided reconstruction reads the clip codes of its profile ("bound": the default)
    from hybridhdr.camera import load_profile
    from hybridhdr.reconstruct.api import _censored_codes
    pr = load_profile(None)  # the built-in 8-bit profile: clip codes 0 and 255
    assert _censored_codes(p, pr, fr) == (0, 255)
    assert _censored_codes(p.replace(saturation="value"), pr, fr) is None

# -- the faster paths against the serial order, bit for bit ------------------------------------

def _fuse_numpy(l_f, p_f, l_b, p_b, offset, floor, out):
    """The fusion written with numpy: the reference of ``fuse_to_linear``. L̂ in float64 from the
    float32 pass estimates, rounded to float32, numpy's float32 exp, minus the offset in float32,
    clamped at the floor (NaN too)."""
    pf, pb = p_f.astype(np.float64), p_b.astype(np.float64)
    with np.errstate(all="ignore"):
        lg = ((l_f.astype(np.float64) * pb + l_b.astype(np.float64) * pf) / (pf + pb)).astype(np.float32)
        v = np.exp(lg) - np.float32(offset)
    bad = ~(v >= np.float32(floor))
    v[bad] = np.float32(floor)
    out[:] = v
    return int(bad.sum())


@pytest.mark.parametrize("n", [0, 1, 1023, 1024, 1025, 5000])
def test_fusion_kernel_gives_the_numpy_fusions_bits(n):
    from hybridhdr.reconstruct import _kernels as K
    rng = np.random.default_rng(n)
    lf = rng.normal(-1, 4, n).astype(np.float32)
    lb = (lf + rng.normal(0, 1, n)).astype(np.float32)
    pf = rng.uniform(0, 0.1, n).astype(np.float32)
    pb = rng.uniform(1e-6, 0.1, n).astype(np.float32)
    pf[::7] = 0.0
    lf[::11] = np.nan
    pb[::13] = np.inf
    lb[::17] = 200.0  # exp overflows
    for off in (1.0, 0.0, 1e-3):
        want = np.full(n, -1.0, np.float32)
        got = np.full(n, -2.0, np.float32)
        c_want = _fuse_numpy(lf, pf, lb, pb, off, K.MIN_INTENSITY, want)
        with np.errstate(all="ignore"):
            assert K.fuse_to_linear(lf, pf, lb, pb, off, K.MIN_INTENSITY, got) == c_want
        np.testing.assert_array_equal(got.view(np.int32), want.view(np.int32))
        # the weighting's Python body (NumPy scalars) gives the compiled kernel's bits
        lg, lg_py = np.empty(n, np.float32), np.empty(n, np.float32)
        K.fuse_log32(lf, pf, lb, pb, lg)
        with np.errstate(all="ignore"):
            K.fuse_log32.py_func(lf, pf, lb, pb, lg_py)
        np.testing.assert_array_equal(lg.view(np.int32), lg_py.view(np.int32))


def test_fusion_of_one_pass_with_itself_gives_the_forward_outputs_bits():
    # (L, P) fused with itself is L: the same float32 exp as the forward filter's outputs
    from hybridhdr.reconstruct import _kernels as K
    rng = np.random.default_rng(3)
    lg = rng.normal(-2, 3, 4000).astype(np.float32)
    pv = rng.uniform(1e-4, 1.0, 4000).astype(np.float32)
    got = np.empty(4000, np.float32)
    K.fuse_to_linear(lg, pv, lg, pv, 1e-3, K.MIN_INTENSITY, got)
    want = K.log_to_linear(lg.copy(), 1e-3)
    K.clamp_linear(want)
    np.testing.assert_array_equal(got.view(np.int32), want.view(np.int32))


def test_fusion_kernel_raises_on_a_zero_variance_sum():
    from hybridhdr.reconstruct import _kernels as K
    z = np.zeros(3000, np.float32)
    pb = np.ones(3000, np.float32)
    pb[2500] = 0.0
    with pytest.raises(ZeroDivisionError):
        K.fuse_to_linear(z, z, z, pb, 1.0, K.MIN_INTENSITY, np.empty(3000, np.float32))
    with pytest.raises(ZeroDivisionError), np.errstate(all="ignore"):
        K.fuse_log32.py_func(z, z, z, pb, np.empty(3000, np.float32))


def _serial_reference(rec, p, times):
    """The two-sided filter in the serial order with the first kernels: the backward pass kept in
    full, then the forward pass fused output by output with the numpy fusion (one worker)."""
    from hybridhdr.reconstruct import _kernels as K
    from hybridhdr.reconstruct.api import ReconstructRequest, engine_for
    from hybridhdr.reconstruct.smoother import _run_pass, frames_measure
    shape = rec.sensor_size.shape
    ev, fr = EventArrays.from_structured(rec.events, shape), rec.frames
    cc = (0, 255) if p.saturation == "bound" else None  # the built-in 8-bit profile's clip codes
    m = min(int(ev.t[0]), int(fr.t_start_us[0])) + max(int(ev.t[-1]), int(fr.t_end_us[-1])) + 1
    q_s = p.carried_variance()
    rev_p = p.replace(contrast_threshold_on=p.c_off, contrast_threshold_off=p.c_on)
    rf, re = reverse_frames(fr, m), reverse_events(ev, m)
    mk = lambda pp, f, e: engine_for(ReconstructRequest.build("akf", pp, mode="forward"), shape, f, e)  # noqa: E731
    bwd = {int(m - t): (lg.copy(), var.copy()) for t, lg, var in
           _run_pass(lambda: mk(rev_p, rf, re), re, (m - times)[::-1], 1 << 20, None, (rf.t_mid_us,) + q_s + (frames_measure(rf, cc),))}
    fwd = {int(t): (lg.copy(), var.copy()) for t, lg, var in
           _run_pass(lambda: mk(p, fr, ev), ev, times, 1 << 20, None, (fr.t_mid_us,) + q_s + (frames_measure(fr, cc),))}
    out = []
    n_clamped = 0
    for t in times:
        f, b = fwd.get(int(t)), bwd.get(int(t))
        f, b = f or b, b or f
        img = np.empty(shape[0] * shape[1], np.float32)
        n_clamped += _fuse_numpy(f[0], f[1], b[0], b[1], p.intensity_offset, K.MIN_INTENSITY, img)
        out.append(img.reshape(shape))
    return np.stack(out), n_clamped


@pytest.mark.parametrize("n_workers", [1, 2, 3, 4])
@pytest.mark.parametrize("spill", [False, True])
def test_two_sided_paths_give_the_serial_orders_bits(monkeypatch, n_workers, spill):
    """1 worker: the passes in turn; 2 or more: both passes at once (one thread each, the workers
    shared between them). Every frame is bit for bit the serial reference's, in memory or spilled."""
    import hybridhdr.reconstruct.smoother as sm
    rec = _rec(6, h=30, w=11, k=7)
    rec.frames.images[:, :6] = 0  # black rows and an offset of 1: some outputs clamp (n_clamped)
    p = AKFParams(intensity_offset=1.0)
    times = output_times(rec.frames.t_mid_us, int(rec.events["t"][-1]), fps=700.0)
    assert times[-1] > rec.frames.t_mid_us[-1]  # some outputs after the last frame: the forward pass only
    want, n_clamped = _serial_reference(rec, p, times)
    if spill:
        monkeypatch.setattr(sm, "MEMORY_LIMIT_BYTES", 1)
    v = reconstruct(rec, "akf", p, times_us=times, n_workers=n_workers)
    np.testing.assert_array_equal(v.frames.view(np.int32), want.view(np.int32))
    ts = v.info["two_sided"]
    assert ts["spilled_to_disk"] == spill
    n_after = int(np.sum(times > rec.frames.t_mid_us[-1]))
    assert (ts["outputs_one_pass"], ts["outputs_fused"]) == (n_after, times.size - n_after)
    assert v.info["n_output_pixels"] == want.size
    assert v.info["n_clamped"] == n_clamped > 0


def test_concurrent_passes_storing_the_same_output_at_once_fuse_it_once(monkeypatch):
    """Both passes reach one output together, neither finds the other's estimate, both store
    theirs: the later mark fuses it (forced with a barrier in the store); the same bits."""
    import threading

    import hybridhdr.reconstruct.smoother as sm
    rec = _rec(7, h=12, w=9)
    times = output_times(rec.frames.t_mid_us, int(rec.events["t"][-1]), fps=400.0)
    k = times.size // 2
    bar = threading.Barrier(2)
    met = []
    put = sm._Store.put

    def put_meeting(self, i, *a):
        if self.fields == 2 and i == k:
            bar.wait(timeout=20)  # both passes at output k before either marks it
            met.append(i)
        put(self, i, *a)
    monkeypatch.setattr(sm._Store, "put", put_meeting)
    got = reconstruct(rec, "akf", times_us=times, n_workers=2, thresholds="input")  # AKFParams(), as the reference
    assert met == [k, k]
    np.testing.assert_array_equal(got.frames, _serial_reference(rec, AKFParams(), times)[0])


def test_an_error_in_a_concurrent_pass_is_raised_and_no_thread_outlives_the_call(monkeypatch):
    import threading

    import hybridhdr.reconstruct.smoother as sm
    rec = _rec(8)
    before = threading.active_count()

    def boom(self, t_us, var, engine=None):
        raise RuntimeError("boom in a pass")
    monkeypatch.setattr(sm._CarriedVariance, "add_to", boom)
    with pytest.raises(RuntimeError, match="boom in a pass"):
        reconstruct(rec, "akf", fps=300.0, n_workers=2, thresholds="input")
    assert threading.active_count() == before


def test_augmented_two_sided_passes_at_once_give_the_same_frames_and_stats():
    """Frame augmentation (EDI deblur and calibration per pass) with the passes at once: the same
    frames and the same per-pass statistics, each under its own pass."""
    rec = _rec(6, h=30, w=11, k=7)
    thr = (np.full((30, 11), 0.12), np.full((30, 11), 0.2))
    a = reconstruct(rec, "akf", fps=500.0, augment=True, n_workers=1, thresholds=thr)
    b = reconstruct(rec, "akf", fps=500.0, augment=True, n_workers=2, thresholds=thr)
    np.testing.assert_array_equal(a.frames, b.frames)
    assert a.info["augmentation"] == b.info["augmentation"] and "backward" in a.info["augmentation"]
