"""Frame-camera model: exposure integration (blur, rolling shutter), noise, CRFs, auto-exposure."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridhdr.simulate.camera import (FrameCamera, FrameCameraParams, crf_forward, crf_inverse_table)


def cam(**kw):
    return FrameCamera(FrameCameraParams(**kw), (4, 5), seed=0)


def test_integrate_is_the_exact_time_average_of_piecewise_linear_radiance():
    c = cam()
    # radiance 1 at t=0, 3 at t=1000, 3 at t=2000: the mean over [500, 1500] is
    # (0.5*(2+3)*500 + 3*500)/1000 = 2.75
    s = [(0, np.ones((4, 5))), (1000, 3 * np.ones((4, 5))), (2000, 3 * np.ones((4, 5)))]
    np.testing.assert_allclose(c.integrate(s, 500, 1500), 2.75)
    np.testing.assert_allclose(c.integrate(s, 0, 2000), 2.5)
    with pytest.raises(ValueError, match="samples span"):
        c.integrate(s, 500, 2500)


def test_motion_blur_from_sub_renders_equals_dense_average():
    # a bright column moving 1 px per 100 µs; 2000 µs exposure: dense samples every 10 µs vs the
    # analytic trapezoid sum of the same piecewise-linear signal are identical; the blurred row
    # spreads the energy over ~20 px with the total conserved
    w = 40
    def img(t):
        x = np.arange(w)
        return (1.0 + 10.0 * np.exp(-0.5 * ((x - t / 100.0) / 0.7) ** 2))[None, :].repeat(2, 0)
    c = FrameCamera(FrameCameraParams(frame_rate_hz=100), (2, w))
    samples = [(t, img(t)) for t in range(0, 2001, 10)]
    m = c.integrate(samples, 0, 2000)
    dense = np.mean([0.5 * (img(t) + img(t + 10)) for t in range(0, 2000, 10)], axis=0)
    np.testing.assert_allclose(m, dense, rtol=1e-12)
    assert (m[0] > 1.2).sum() >= 18
    np.testing.assert_allclose((m[0] - 1).sum(), np.mean([(img(t)[0] - 1).sum() for t in range(0, 2001, 10)]),
                               rtol=0.02)


def test_rolling_shutter_shifts_each_row_window():
    # radiance grows linearly in time (1 + t/1000): row y's window is shifted by y*readout/H, so
    # its mean is 1 + (t_mid + y*readout/H)/1000
    h = 4
    c = FrameCamera(FrameCameraParams(frame_rate_hz=100, exposure_us=1000, rolling_shutter_readout_us=400), (h, 3))
    s = [(t, np.full((h, 3), 1 + t / 1000)) for t in (0, 500, 2000)]
    m = c.integrate(s, 0, 1000)
    expected = 1 + (500 + np.arange(h) * 400 / h) / 1000
    np.testing.assert_allclose(m[:, 0], expected, rtol=1e-12)


def test_noiseless_linear_capture_quantises_electrons():
    p = FrameCameraParams(exposure_us=10_000, full_well_e=10_000, electrons_per_radiance_s=5e5)
    c = FrameCamera(p, (1, 4))
    rad = np.array([[0.0, 0.5, 1.0, 5.0]])
    codes = c.capture(rad, 10_000)
    # e = rad * 0.01 s * 5e5 = 5000 rad; v = e / 1e4 = rad / 2 (clipped at 1); code = round(255 v)
    assert codes.dtype == np.uint8
    assert codes.tolist() == [[0, 64, 128, 255]]
    assert p.encoding == "linear"
    c12 = FrameCamera(p.replace(bit_depth=12), (1, 4))
    assert c12.capture(rad, 10_000).tolist() == [[0, 1024, 2048, 4095]]
    assert c12.capture(rad, 10_000).dtype == np.uint16


def test_shot_and_read_noise_statistics():
    # 1000 e- mean: Poisson variance 1000 e-^2, read noise 20 e- adds 400 -> std 37.4 e- =
    # 0.955 codes of a 10-bit camera whose full well is 10 000 e- (1023 codes). 40 000 pixels give
    # the std to ~0.35 % (1 sigma); allow 3 %.
    p = FrameCameraParams(exposure_us=10_000, bit_depth=10, shot_noise=True, read_noise_e=20.0)
    c = FrameCamera(p, (200, 200), seed=1)
    rad = np.full((200, 200), 1000 / (0.01 * 5e5))
    codes = c.capture(rad, 10_000).astype(np.float64)
    e_per_code = 10_000 / 1023
    assert codes.mean() * e_per_code == pytest.approx(1000, rel=0.005)
    assert codes.std() * e_per_code == pytest.approx(math.sqrt(1400), rel=0.03)
    a = FrameCamera(p, (20, 20), seed=5).capture(rad[:20, :20], 10_000)
    b = FrameCamera(p, (20, 20), seed=5).capture(rad[:20, :20], 10_000)
    np.testing.assert_array_equal(a, b)


def test_full_well_clips_before_read_noise():
    p = FrameCameraParams(full_well_e=1000, read_noise_e=0.0, gain=2.0)
    c = FrameCamera(p, (1, 3))
    # gain 2: the ADC saturates at half the full well
    codes = c.capture(np.array([[0.0, 0.05, 100.0]]), 10_000)
    # e = rad * 0.01 * 5e5 = 0, 250, 1000 (clipped); v = e * 2 / 1000 = 0, 0.5, 1
    assert codes.tolist() == [[0, 128, 255]]


@pytest.mark.parametrize("crf", ["linear", "gamma", "srgb", "akf_s_curve_30", "akf_s_curve_115"])
def test_crfs_are_monotone_onto_unit_interval_and_invert(crf):
    p = FrameCameraParams(crf=crf)
    v = np.linspace(0, 1, 1001)
    y = crf_forward(v, p)
    assert y[0] == pytest.approx(0, abs=1e-12) and y[-1] == pytest.approx(1, abs=1e-12)
    assert np.all(np.diff(y) >= -1e-15)
    inv = crf_inverse_table(p)
    assert inv.shape == (256,) and np.all(np.diff(inv) >= 0)
    # the inverse table maps each code back to a signal that quantises to the same code
    codes = np.arange(256)
    back = np.rint(crf_forward(inv, p) * 255)
    assert np.abs(back - codes).max() <= 1


def test_srgb_and_s_curve_values():
    p = FrameCameraParams(crf="srgb")
    # IEC 61966-2-1: 0.0031308 -> 0.04045, 0.5 -> 0.7354
    assert crf_forward(0.0031308, p) == pytest.approx(0.04045, abs=1e-5)
    assert crf_forward(0.5, p) == pytest.approx(0.735357, abs=1e-5)
    s = FrameCameraParams(crf="akf_s_curve_80")
    # inflection at code 80: the slope of the S-curve peaks at v = 80/255
    v = np.linspace(0, 1, 2551)
    assert v[np.argmax(np.gradient(crf_forward(v, s)))] == pytest.approx(80 / 255, abs=1e-3)
    assert FrameCameraParams(crf="gamma").encoding == "gamma"
    assert s.encoding == "unknown" and FrameCameraParams(crf="gamma", gamma=1.8).encoding == "unknown"


def test_table_crf_and_code_clip():
    inv = (np.arange(256) / 255.0) ** 2  # a measured-looking inverse CRF (square law)
    p = FrameCameraParams(crf="table", inverse_crf=tuple(inv))
    y = crf_forward(np.array([0.0, 0.25, 1.0]), p)
    # linear interpolation between table entries: |error| <= (1/255)^2 / 4 in code units at 0.25
    np.testing.assert_allclose(y, [0, 0.5, 1], atol=1e-5)
    np.testing.assert_allclose(crf_inverse_table(p), inv)
    q = FrameCameraParams(crf="gamma", code_clip=(100, 160))
    codes = FrameCamera(q, (1, 3)).capture(np.array([[0.001, 0.5, 50.0]]), 10_000)
    assert codes.min() == 100 and codes.max() == 160 and q.encoding == "unknown"
    table = crf_inverse_table(q)
    assert np.all(table[:100] == table[100]) and np.all(table[161:] == table[160])
    prof = FrameCamera(q, (1, 3)).camera_profile()
    assert prof.max_code == 255
    with pytest.raises(ValueError, match="inverse_crf"):
        FrameCameraParams(crf="table")
    with pytest.raises(ValueError, match="code_clip"):
        FrameCameraParams(code_clip=(200, 100))


def test_planned_exposures_and_streaming_frames():
    p = FrameCameraParams(frame_rate_hz=100, exposure_us=4000)
    c = FrameCamera(p, (2, 2), duration_us=30_000)
    ivs = c.pop_new_intervals()
    assert ivs == [(0, 4000), (10_000, 14_000), (20_000, 24_000)]
    assert c.mandatory_times(ivs[1]) == [10_000, 12_000, 14_000]
    frames = []
    for t in sorted({t for iv in ivs for t in c.mandatory_times(iv)} | {30_000}):
        frames += c.feed(t, np.full((2, 2), 0.5 + t / 1e5))
    assert [int(f.t_start_us[0]) for f in frames] == [0, 10_000, 20_000]
    assert all(f.exposure_us[0] == 4000 for f in frames)


def test_auto_exposure_converges_to_target():
    # constant radiance 2: with e = 10 ms the signal saturates (v = 2*0.01*5e5/1e4 = 1); AE must
    # bring the mean linear signal to 0.18 (within a code step) in a few frames
    p = FrameCameraParams(frame_rate_hz=50, exposure_us=10_000, auto_exposure=True, ae_damping=1.0)
    c = FrameCamera(p, (3, 3), duration_us=400_000)
    frames = []
    t = 0
    for _ in range(2000):
        for iv in c.pop_new_intervals():
            pass
        frames += c.feed(t, np.full((3, 3), 2.0))
        t += 500
        if t > 400_000:
            break
    assert len(frames) >= 15
    last = frames[-1]
    v = c.linear_signal(last.images[0]).mean()
    assert v == pytest.approx(0.18, abs=2 / 255)
    # e = 0.18 * 1e4 / (2 * 5e5) s = 1.8 ms
    assert last.exposure_us[0] == pytest.approx(1800, rel=0.03)


def test_params_validation():
    with pytest.raises(ValueError, match="bit_depth"):
        FrameCameraParams(bit_depth=9)
    with pytest.raises(ValueError, match="exceeds the frame period"):
        FrameCameraParams(frame_rate_hz=200, exposure_us=6000)
    with pytest.raises(ValueError, match="crf"):
        FrameCameraParams(crf="log")
    with pytest.raises(ValueError, match="read_noise_e"):
        FrameCameraParams(read_noise_e=-1)
