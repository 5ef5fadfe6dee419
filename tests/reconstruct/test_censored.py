"""Saturation as a bound (censored frame measurements) and positive outputs.

A clipped frame code says "at least the clip level" (or "at most the dark level"); the AKF's
frame update acts only where the state violates that bound (``_kernels._pull_integral``,
``_kernels._frame_update``; docs/reconstruct.md, "Saturation as a bound").
"""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.events import EVENT_DTYPE, SensorSize
from hybridhdr.model import Frames, Recording
from hybridhdr.reconstruct import AKFParams, CFParams, reconstruct
from hybridhdr.reconstruct import _kernels as K
from hybridhdr.camera import CameraProfile, default_profile

H, W = 3, 4
PERIOD_US = 50_000  # 20 Hz frames
EXPO_US = 2_000


def _bright_object_recording(n_saturated=20, c=0.1, start=0.5, ratio_to_clip=5.0):
    """A uniform pixel patch at ``start`` (unclipped, frame 0), raised by ideal ON events to
    ``ratio_to_clip`` times the clip level (1.0) before frame 1; frames 1.. all clip (code 255)."""
    n_on = int(round(np.log(ratio_to_clip / start) / c))
    rec = _raised_then_clipped(1 + n_saturated, int(round(255 * start)), n_on, "linear")
    truth = (round(255 * start) / 255) * np.exp(n_on * c)
    return rec, rec.frames.t_start_us + EXPO_US // 2, truth


def _raised_then_clipped(k, first_code, n_on, encoding):
    """``k`` frames of a uniform patch, the first at ``first_code`` and the rest clipped (255);
    ``n_on`` ON events at every pixel between 10 and 30 ms (before frame 1)."""
    ts = np.arange(k, dtype=np.int64) * PERIOD_US
    img = np.full((k, H, W), 255, np.uint8)
    img[0] = first_code
    frames = Frames(img, ts, ts + EXPO_US, encoding=encoding)
    t_ev = np.linspace(10_000, 30_000, n_on).astype(np.int64)
    ev = np.zeros(n_on * H * W, EVENT_DTYPE)
    ev["t"] = np.repeat(t_ev, H * W)
    yy, xx = np.mgrid[0:H, 0:W]
    ev["x"] = np.tile(xx.ravel(), n_on)
    ev["y"] = np.tile(yy.ravel(), n_on)
    ev["p"] = 1
    return Recording(ev, SensorSize(H, W), frames)


@pytest.mark.parametrize("mode", ["causal", "offline"])
def test_bright_pixel_stays_above_the_clip_level_across_20_saturated_frames(mode):
    rec, t_mid, truth = _bright_object_recording()
    assert 4.9 < truth < 5.1  # 5x the clip level
    v = reconstruct(rec, "akf", times_us=t_mid[1:], mode=mode)
    err = np.abs(v.frames / truth - 1.0)
    assert err.max() < 0.02, f"worst relative error {err.max():.4f} over {len(v)} saturated frames"


def test_the_papers_reading_pulls_the_same_pixel_down_to_the_clip_value():
    """The published model (clipped code = a value) loses the HDR content this test guards."""
    rec, t_mid, truth = _bright_object_recording()
    v = reconstruct(rec, "akf", AKFParams.paper(), times_us=t_mid[1:], mode="causal")
    assert v.frames[-1].max() < 0.5 * truth


def test_pixel_saturated_from_the_start_never_sits_below_the_clip_level():
    k = 12
    ts = np.arange(k, dtype=np.int64) * PERIOD_US
    frames = Frames(np.full((k, H, W), 255, np.uint8), ts, ts + EXPO_US, encoding="linear")
    # OFF events that a real brighter-than-clip object could emit while staying above the clip
    ev = np.zeros(3, EVENT_DTYPE)
    ev["t"] = [60_000, 61_000, 62_000]
    ev["p"] = -1
    rec = Recording(ev, SensorSize(H, W), frames)
    v = reconstruct(rec, "akf", times_us=ts[1:] + EXPO_US // 2, mode="causal")
    lo, hi = default_profile(8).bounds()
    # the update's gain P/(P + R) < 1 leaves R/(P + R) of a violation (here < 1e-3 relative,
    # under a quarter of one code step at the clip level, 1/255)
    assert v.frames.min() >= hi * (1 - 1e-3)
    # the scenario is not trivial: just after the OFF events, before the next frame, the
    # state is below the bound (the events are trusted), and the frames then restore it
    mid = reconstruct(rec, "akf", times_us=[62_001], mode="causal").frames[0, 0, 0]
    assert mid < 0.9 * hi


def test_censor_table_and_bounds_of_a_profile():
    p = CameraProfile(weighting=np.ones(256), clip_low_code=100, clip_high_code=160)
    cz = p.censor(np.arange(256))
    assert np.all(cz[:101] == -1) and np.all(cz[101:160] == 0) and np.all(cz[160:] == 1)
    lo, hi = p.bounds()
    assert lo == pytest.approx(100.5 / 255) and hi == pytest.approx(159.5 / 255)
    d = p.to_dict()
    q = CameraProfile.from_dict(d)
    assert (q.clip_low_code, q.clip_high_code) == (100, 160)
    with pytest.raises(ValueError, match="clip codes"):
        CameraProfile(weighting=np.ones(256), clip_low_code=200, clip_high_code=100)


def _random_recording(rng, h=6, w=8, n_frames=6):
    ts = np.arange(n_frames, dtype=np.int64) * 40_000
    img = rng.integers(0, 256, (n_frames, h, w)).astype(np.uint8)
    img[:, :2] = 255
    img[:, -1] = 0
    frames = Frames(img, ts, ts + 5_000, encoding=str(rng.choice(["linear", "gamma"])))
    n = int(rng.integers(50, 2000))
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, int(ts[-1]) + 20_000, n))
    ev["x"] = rng.integers(0, w, n)
    ev["y"] = rng.integers(0, h, n)
    ev["p"] = rng.choice([-1, 1], n)
    return Recording(ev, SensorSize(h, w), frames)


@pytest.mark.parametrize("seed", range(6))
def test_no_method_writes_a_non_positive_or_nan_intensity(seed):
    """Fuzzed parameters and adversarial events (long OFF runs, random polarities): every
    output of every method is finite and >= MIN_INTENSITY, and clamping is counted."""
    rng = np.random.default_rng(seed)
    rec = _random_recording(rng)
    akf = AKFParams(intensity_offset=float(10 ** rng.uniform(-5, 0)),
                    process_noise_per_s=float(10 ** rng.uniform(-5, 1)),
                    contrast_threshold=float(rng.uniform(0.05, 0.8)),
                    saturation=str(rng.choice(["bound", "value"])),
                    frame_update=str(rng.choice(["discrete", "continuous"])),
                    min_weighting=float(10 ** rng.uniform(-6, 0)))
    cf = CFParams(intensity_offset=float(10 ** rng.uniform(-5, 0)), cutoff_hz=float(rng.uniform(0, 20)),
                  contrast_threshold=float(rng.uniform(0.05, 0.8)))
    runs = [("akf", akf, "offline"), ("akf", akf, "causal"), ("akf", AKFParams.reference_code(), "causal"),
            ("cf", cf, "causal"), ("direct", None, "causal"), ("frames_zoh", None, "causal"),
            ("frames_linear", None, "offline"), ("edi", None, "offline")]
    for method, params, mode in runs:
        # the fuzzed parameters (or each method's defaults) as given: random events and noise
        # frames are nothing to self-calibrate from, and the calibration is not under test here
        v = reconstruct(rec, method, params, fps=200.0, mode=mode, thresholds="input")
        assert np.all(np.isfinite(v.frames)), method
        assert v.frames.min() >= np.float32(K.MIN_INTENSITY), (method, float(v.frames.min()))
        assert 0 <= v.info["n_clamped"] <= v.info["n_output_pixels"] == v.frames.size


def test_clamp_counts_and_raises_nan_and_negative():
    a = np.array([np.nan, -1.0, 0.0, 5e-7, 1e-6, 0.5], np.float32)
    assert K.clamp_linear(a) == 4
    assert np.all(a >= np.float32(K.MIN_INTENSITY)) and a[-1] == np.float32(0.5)


def test_pixel_dark_clipped_at_the_start_keeps_the_level_the_events_give_it():
    """A black pixel (code 0 of a gamma-2.2 frame) raised by 40 ideal ON events (c = 0.2) to
    3x the clip level, then clipped bright in 10 frames. The dark code bounds ln(I + I0) on both
    sides (ln I0 <= L <= ln(I_dark + I0), 1e-3 wide), so the forward pass knows the level
    (P = initial_covariance), while the backward pass starts from the bright bound knowing
    nothing above it (P = 1e3): the two-sided output follows the forward pass. With P = 1e3 at
    the dark start too, the fusion averaged the two (about 1.7 instead of 2.98)."""
    k, c, n_on = 11, 0.2, 40
    rec = _raised_then_clipped(k, 0, n_on, "gamma")
    ts = rec.frames.t_start_us
    p = AKFParams(contrast_threshold=c)
    truth = np.exp(np.log(p.intensity_offset) + n_on * c) - p.intensity_offset  # from I = 0
    assert 2.9 < truth < 3.1
    t_out = ts[1:] + EXPO_US // 2
    for mode in ("offline", "forward"):
        v = reconstruct(rec, "akf", p, times_us=t_out, mode=mode)
        err = np.abs(v.frames / truth - 1.0)
        assert err.max() < 0.02, f"{mode}: worst relative error {err.max():.4f}"


# -- the Tobit update of a censored frame -------------------------------------------------------

def test_inverse_mills_matches_the_normal_distribution():
    from scipy.stats import norm

    from hybridhdr.reconstruct._kernels import inverse_mills
    for a in (0.0, 0.5, 1.0, 3.0, 10.0, 24.9):
        assert inverse_mills(a) == pytest.approx(norm.pdf(a) / norm.sf(a), rel=1e-12)
    for a in (25.1, 40.0, 1e3):  # the asymptote a + 1/a beyond 25: 1 - 2/a^4 relative (< 1e-5)
        assert inverse_mills(a) == pytest.approx(a + 1 / a - 2 / a ** 3, rel=1e-5)


def test_censored_frame_moves_a_violating_state_to_its_conditional_mean():
    """Closed form (Allik et al. 2016): state N(μ, P), measurement z = L + v, v ~ N(0, R), a lower
    bound b (z >= b): E[L | z >= b] = μ + P/s λ((b - μ)/s), s = √(P + R); P unchanged. A state
    that satisfies the bound is untouched; an upper bound mirrors it; a state of P >= TOBIT_MAX_P
    (never seen unclipped) takes the plain update towards the bound."""
    from scipy.stats import norm

    from hybridhdr.reconstruct import _kernels as K

    def run(L, P, R, cz, b):
        S = np.zeros((1, 8))
        S[0, K.A_L], S[0, K.A_P] = L, P
        K.akf_switch(S, False, 0.0, 0.0, 0.0, np.array([b]), np.array([1.0 / R]), np.zeros(0), np.zeros(0),
                     np.array([float(cz)]), 0.0, True, 0.0, np.zeros(0), 0, 1)
        return S[0, K.A_L], S[0, K.A_P]

    mu, P, R, b = 0.0, 0.04, 0.01, 0.1
    s = np.sqrt(P + R)
    a = (b - mu) / s
    want = mu + P / s * norm.pdf(a) / norm.sf(a)
    L, P1 = run(mu, P, R, +1, b)
    assert L == pytest.approx(want, rel=1e-12) and L > b and P1 == P
    L, P1 = run(-mu, P, R, -1, -b)  # the mirror image: an upper bound
    assert L == pytest.approx(-want, rel=1e-12) and P1 == P
    assert run(0.3, P, R, +1, b) == (0.3, P)  # the bound holds: nothing to do
    big = K.TOBIT_MAX_P * 2
    L, _ = run(mu, big, R, +1, b)
    assert L == pytest.approx(mu + big / (big + R) * (b - mu), rel=1e-12) and L < b
