"""Closed-form acceptance tests (akf.md §9 items 1-4, 7): the filter against cases with
an exact answer."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridhdr import make_events
from hybridhdr.camera import CameraProfile, default_profile
from hybridhdr.reconstruct import AKFParams, CFParams, FrameMeasurements, reconstruct
from hybridhdr.reconstruct._engine import AKFEngine, CFEngine
from hybridhdr.reconstruct.params import DEFAULT_INTENSITY_OFFSET, PUBLISHED_INTENSITY_OFFSET

from .conftest import constant_frames_recording, ideal_recording, shift_recording


def _akf_engine(rec, params, mode="offline", profile=None):
    prof = profile or default_profile()
    m = FrameMeasurements(rec.frames, rec.sensor_size.shape, prof, intensity_offset=params.intensity_offset,
                          bias_correction=params.bias_correction,
                          interpolate_covariance=(mode == "offline" and params.covariance_interpolation == "linear"),
                          precision_scale=params.frame_precision_scale, saturation=params.saturation,
                          min_weighting=params.min_weighting)
    return AKFEngine(rec.sensor_size.shape, m, params), m


def _run_to(eng, t_us):
    """Apply frame switches up to t_us, then read the state at t_us (no events)."""
    while eng.next_switch_us() is not None and eng.next_switch_us() <= t_us:
        eng.switch()
    return eng.output(t_us, with_state=True)


@pytest.mark.parametrize("preset", ["paper", "default"])
@pytest.mark.parametrize("mode", ["causal", "offline"])
def test_riccati_without_events(mode, preset):
    """No events: P follows eq. 20 and L̂ relaxes to the frame per eq. 17 (R of eq. 7 in offline mode).

    "paper": the frame acts only through the continuous pull after τ_k. "default"
    (``frame_update="discrete"``): at τ1 the new frame is also one discrete Kalman measurement,
    P ← P + σ²_proc·(τ1 - τ0) (no event updated the pixel since τ0), κ = P/(P + R1),
    L̂ ← L̂ + κ(L^F1 - L̂), P ← (1 - κ)P; the continuous eqs. 17 and 20 then continue from there.
    """
    make = AKFParams.paper if preset == "paper" else AKFParams
    params = make(initial_covariance=0.05, frame_precision_scale=50.0)
    assert params.frame_update == ("continuous" if preset == "paper" else "discrete")
    tau0, tau1 = 1_000, 41_000
    rec = constant_frames_recording([100, 250], [tau0, tau1])
    eng, m = _akf_engine(rec, params, mode)
    eng.start(None)
    s0, s1 = m.segment(0), m.segment(1)
    P0 = params.initial_covariance
    # segment 0: L̂ = L^A already, P decreases: 1/P = 1/P0 + ∫R⁻¹
    T = (tau1 - tau0) * 1e-6
    for t in (tau0, 11_000, 27_345, tau1 - 1):
        _, lg, var = _run_to(eng, t)
        dt = (t - tau0) * 1e-6
        b = s0.beta[0]
        integ = s0.rinv[0] * dt if b == 0 else s0.rinv[0] * T / b * math.log1p(b * dt / T)
        np.testing.assert_allclose(var, 1.0 / (1.0 / P0 + integ), rtol=1e-12)
        np.testing.assert_allclose(lg, s0.log_frame[0], rtol=1e-13)
    if mode == "offline":
        assert s0.beta[0] != 0.0  # eq. 7 is exercised
    P1 = 1.0 / (1.0 / P0 + (s0.rinv[0] * T if s0.beta[0] == 0 else s0.rinv[0] * T / s0.beta[0] * math.log1p(s0.beta[0])))
    L1 = s0.log_frame[0]
    if preset == "default":  # the discrete frame update at τ1
        Pq = P1 + params.process_noise_per_s * T
        kappa = Pq / (Pq + 1.0 / s1.rinv[0])
        L1 = L1 + kappa * (s1.log_frame[0] - L1)
        P1 = (1.0 - kappa) * Pq
    # segment 1 (last, R held): eqs. 17 and 20
    for t in (tau1, tau1 + 1, tau1 + 250, tau1 + 10_000, tau1 + 2_000_000):
        _, lg, var = _run_to(eng, t)
        P = 1.0 / (1.0 / P1 + s1.rinv[0] * (t - tau1) * 1e-6)
        np.testing.assert_allclose(var, P, rtol=1e-12)
        L = s1.log_frame[0] + (L1 - s1.log_frame[0]) * P / P1
        np.testing.assert_allclose(lg, L, rtol=1e-12, atol=1e-12)


def test_one_step_equals_1000_substeps():
    """Propagating through 1000 switch points of identical frames equals one closed-form step.

    A property of the paper's continuous frame pull (eqs. 17, 20), pinned here: with
    ``frame_update="discrete"`` every switch is also a discrete measurement, so 1000 identical
    frames carry more information than one (by design, see ``test_riccati_without_events``).
    """
    params = AKFParams(initial_covariance=0.05, frame_precision_scale=50.0, frame_update="continuous")
    times = 1_000 + 40 * np.arange(1002)
    codes = [60] + [180] * 1001
    rec = constant_frames_recording(codes, times)
    eng, m = _akf_engine(rec, params, "causal")
    eng.start(None)
    eng.switch()  # to the first 180 frame at times[1]
    _, l_a, p_a = eng.output(int(times[-1]), with_state=True)  # one step
    _, l_b, p_b = _run_to(eng, int(times[-1]))  # 1000 sub-steps
    np.testing.assert_allclose(l_b, l_a, rtol=1e-12)
    np.testing.assert_allclose(p_b, p_a, rtol=1e-12)


@pytest.mark.parametrize("form", ["paper", "reference_code"])
def test_zero_rinv_is_pure_integration(form):
    """R⁻¹ = 0: L̂ = L̂₀ + cΣσ exactly, and P = P₀ + ΣQ with Q computed by hand."""
    if form == "paper":
        params = AKFParams(frame_precision_scale=1e-300, bias_correction=False, contrast_threshold_on=0.13,
                           contrast_threshold_off=0.07)
    else:
        params = AKFParams.reference_code(frame_precision_scale=1e-300, contrast_threshold_on=0.13,
                                          contrast_threshold_off=0.07)
    ev = make_events([1_500, 1_600, 20_000, 20_100], [1, 2, 1, 1], [1, 1, 1, 1], [1, 1, -1, 1])
    rec = constant_frames_recording([128], [1_000], events=ev)
    v = reconstruct(rec, "akf", params, times_us=[1_000, 30_000], profile=default_profile())
    eng, m = _akf_engine(rec, params)
    eng.start(None)
    from hybridhdr.events import events_fields
    t, x, y, p = events_fields(ev)
    eng.process(t, x, y, p, 0, 4)
    _, lg, var = eng.output(30_000, with_state=True)
    L0 = math.log(128 / 255 + params.intensity_offset)
    assert lg[1, 1] == pytest.approx(L0 + 0.13 - 0.07 + 0.13, abs=1e-14)
    assert lg[1, 2] == pytest.approx(L0 + 0.13, abs=1e-14)
    assert v.frames[1, 1, 1] == pytest.approx(math.exp(L0 + 0.19) - params.intensity_offset, rel=1e-6)
    sp, si, sr = params.process_noise_per_s, params.isolated_noise_per_s, params.refractory_noise
    # pixel (1,1): events at 1500 (prev: start 1000), 20000 (neighbour 1600), 20100; ρ = 10 000 µs
    if form == "paper":
        q = (sp * 500e-6 + si * 500e-6 + sr) + (sp * 18500e-6 + si * 18400e-6) + (sp * 100e-6 + si * 100e-6 + sr)
    else:
        q = (sp * 500e-6 + si * 500e-6 + sr * 500e-6) + (sp * 18500e-6 + si * 18400e-6) + \
            (sp * 100e-6 + si * 100e-6 + sr * 100e-6)
    assert var[1, 1] == pytest.approx(params.initial_covariance + q, rel=1e-12)
    # a pixel without events keeps P0
    assert var[0, 0] == pytest.approx(params.initial_covariance, rel=1e-12)


@pytest.mark.parametrize("offset", [None, DEFAULT_INTENSITY_OFFSET])
@pytest.mark.parametrize("cutoff_hz", [0.5, 3.0, 0.0])
def test_cf_step_response(cutoff_hz, offset):
    """CF: L̂(t) = L^F + (L̂₀ - L^F) exp(-2π f_c t) after a frame step; f_c = 0 integrates.

    L^F = log(I + I0) with CF's default I0 (1, the published code's) and the AKF's 1e-3."""
    params = CFParams(cutoff_hz=cutoff_hz) if offset is None else CFParams(cutoff_hz=cutoff_hz, intensity_offset=offset)
    off = params.intensity_offset
    assert off == (PUBLISHED_INTENSITY_OFFSET if offset is None else offset)
    tau1 = 10_000
    rec = constant_frames_recording([40, 220], [0, tau1])
    times = np.array([tau1, tau1 + 1000, tau1 + 100_000, tau1 + 700_000])
    v = reconstruct(rec, "cf", params, times_us=times)
    lf0, lf1 = math.log(40 / 255 + off), math.log(220 / 255 + off)
    alpha = 2 * math.pi * cutoff_hz
    if cutoff_hz == 0.5:
        assert params.alpha_rad_per_s == pytest.approx(math.pi)
    for img, t in zip(v.frames, times):
        L = lf1 + (lf0 - lf1) * math.exp(-alpha * (t - tau1) * 1e-6)
        np.testing.assert_allclose(img, math.exp(L) - off, rtol=2e-7)
    # and the float64 state itself
    m = FrameMeasurements(rec.frames, (3, 3), default_profile(), intensity_offset=off, bias_correction=False,
                          interpolate_covariance=False)
    eng = CFEngine((3, 3), m, params, "cf")
    eng.start(None)
    eng.switch()
    from hybridhdr.reconstruct import _kernels as K
    eng.output(tau1 + 100_000)
    eng.switch  # no further switch exists
    eng_L = eng.C[:, K.C_L].copy()
    np.testing.assert_array_equal(eng_L, lf0)  # the state at τ1 is the old frame (continuity)
    out = np.empty(9, np.float32)
    getattr(K.cf_output, "py_func", K.cf_output)(eng.C, float(tau1 + 100_000), 0.0, out, 0, 9)
    np.testing.assert_allclose(np.log(out.astype(float)), lf1 + (lf0 - lf1) * math.exp(-alpha * 0.1), rtol=1e-6)


@pytest.mark.parametrize("method", ["akf", "cf", "direct", "highpass", "frames_linear"])
def test_output_rate_independence(method):
    """fps 30 and fps 1000 give identical frames at their shared times."""
    rec, _ = ideal_recording(height=6, width=8, duration_us=610_000, grid_us=100)
    a = reconstruct(rec, method, fps=30)
    b = reconstruct(rec, method, fps=1000)
    shared, ia, ib = np.intersect1d(a.t_us, b.t_us, return_indices=True)
    assert len(shared) >= 6
    np.testing.assert_array_equal(a.frames[ia], b.frames[ib])


def test_output_does_not_change_state():
    rec, _ = ideal_recording()
    v1 = reconstruct(rec, "akf", times_us=[150_000])
    t_many = np.arange(5_000, 150_001, 137)
    t_many[-1] = 150_000
    v2 = reconstruct(rec, "akf", times_us=np.unique(t_many))
    np.testing.assert_array_equal(v1.frames[0], v2.frames[-1])


@pytest.mark.parametrize("method", ["akf", "cf", "highpass"])
@pytest.mark.parametrize("offset", [10**12, 2**40])
def test_timestamp_offset_changes_nothing(method, offset):
    rec, _ = ideal_recording()
    a = reconstruct(rec, method, fps=200)
    b = reconstruct(shift_recording(rec, offset), method, fps=200)
    np.testing.assert_array_equal(b.t_us - a.t_us, offset)
    np.testing.assert_allclose(b.frames, a.frames, rtol=1e-12, atol=0)


def test_first_and_last_frames_used():
    rec = constant_frames_recording([10, 20, 250], [5_000, 45_000, 85_000])
    # the forward filter (the two-sided one smooths frame 0 with the later frames: no events
    # say the scene changed, test_smoother.py)
    v = reconstruct(rec, "akf", times_us=[5_000, 85_000, 1_000_000_000], mode="forward")
    i0 = 10 / 255
    assert v.frames[0, 0, 0] == pytest.approx(i0, rel=1e-3)  # initialised from the first frame
    assert v.frames[-1, 0, 0] == pytest.approx(250 / 255, rel=1e-3)  # converges as 1/t without events


def test_akf_tracks_ideal_signal():
    """With ideal events and frames the AKF stays close to the true log intensity."""
    rec, logi = ideal_recording()
    t = np.arange(25_000, 200_000, 10_000)
    # ZOH frames with the paper's 7e5 precision pin L̂ to the stale frame (time constant ~1 ms);
    # with a lower frame precision the events carry the signal between frames.
    v = reconstruct(rec, "akf", AKFParams(intensity_offset=1e-3, frame_precision_scale=100.0), times_us=t)
    truth = np.exp(logi(t))
    err = np.abs(v.frames - truth).mean()
    zoh = reconstruct(rec, "frames_zoh", times_us=t)
    assert np.isfinite(v.frames).all()
    assert err < np.abs(zoh.frames - truth).mean()
