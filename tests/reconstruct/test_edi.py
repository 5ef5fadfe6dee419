"""EDI deblurring (Pan et al. 2019): exact recovery, threshold search, kernels, method 'edi'."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from hybridhdr import SensorSize, make_events, Recording, Frames
from hybridhdr.reconstruct import reconstruct
from hybridhdr.reconstruct import _augment_kernels as AK
from hybridhdr.reconstruct.edi import (EDIParams, edi_integral, edi_latent, edi_log_latent, estimate_threshold,
                                       golden_section_minimize, sharpness_energy)
from hybridhdr.reconstruct.event_arrays import EventArrays

from hybridhdr.reconstruct.params import DEFAULT_INTENSITY_OFFSET, PUBLISHED_INTENSITY_OFFSET

from .blur_data import shifted_sequence


def py(f):
    """The Python original of a kernel (the function itself under NUMBA_DISABLE_JIT=1)."""
    return getattr(f, "py_func", f)


def _ev(t, x, y, p, shape):
    return EventArrays(np.asarray(t, np.int64), np.asarray(x, np.uint16), np.asarray(y, np.uint16),
                       np.asarray(p, np.int8), shape)


# -- akf.md §9 test 5 -------------------------------------------------------------------------

def test_single_pixel_exact_recovery():
    """Known L(t_s), c and events; B analytic; EDI recovers L(t_s) to 1e-12."""
    c, I0, Ls, T = 0.15, 1.0, 0.37, 10_000
    t_ev = [1_000, 2_500, 4_000, 7_000]
    p_ev = [1, 1, -1, 1]
    # E(t) piecewise constant: 0 on [0,1000), 1, 2, 1, 2 on [7000, 10000)
    levels, cuts = [0, 1, 2, 1, 2], [0] + t_ev + [T]
    B = sum((Ls + I0) * math.exp(c * e) * (b - a) for e, a, b in zip(levels, cuts[:-1], cuts[1:])) / T - I0
    ev = _ev(t_ev, [0] * 4, [0] * 4, p_ev, (1, 1))
    got = edi_latent(np.array([[B]]), ev, 0, T, c, 0, intensity_offset=I0)[0, 0]
    assert abs(got - Ls) < 1e-12
    # at any time in the exposure: L(t) = L(t_s) exp(c E(t)) in the offset domain
    got_mid = edi_latent(np.array([[B]]), ev, 0, T, c, 5_000, intensity_offset=I0)[0, 0]
    assert abs(got_mid - ((Ls + I0) * math.exp(c) - I0)) < 1e-12


def test_single_event_normalisation_by_true_exposure():
    """One event: normalising by the event span (zero here) instead of T would fail."""
    c, I0, Ls, T, te = 0.2, 1.0, 0.5, 8_000, 6_000
    B = (Ls + I0) * (te + (T - te) * math.exp(c)) / T - I0
    ev = _ev([te], [1], [0], [1], (1, 2))
    img = np.array([[0.3, B]])
    got = edi_latent(img, ev, 0, T, c, 0, intensity_offset=I0)
    assert abs(got[0, 1] - Ls) < 1e-12
    assert got[0, 0] == pytest.approx(0.3, abs=1e-15)  # no events: the frame itself
    J, cnt = edi_integral(ev, 0, T, c)
    assert J[1] == pytest.approx((te + (T - te) * math.exp(c)) / T, rel=1e-15)
    assert cnt.tolist() == [0, 1]


def test_zero_exposure_and_errors():
    ev = _ev([5], [0], [0], [1], (1, 1))
    J, cnt = edi_integral(ev, 10, 10, 0.1)
    assert J.tolist() == [1.0] and cnt.tolist() == [0]
    with pytest.raises(ValueError, match="t_end_us >= t_start_us"):
        edi_integral(ev, 10, 5, 0.1)
    with pytest.raises(TypeError, match="int"):
        edi_integral(ev, 0.5, 5, 0.1)
    with pytest.raises(ValueError, match="at_us must lie"):
        edi_latent(np.zeros((1, 1)), ev, 0, 10, 0.1, 11)
    with pytest.raises(ValueError, match="non-decreasing"):
        _ev([5, 4], [0, 0], [0, 0], [1, 1], (1, 1))
    with pytest.raises(ValueError, match="sensor size"):
        _ev([5], [3], [0], [1], (1, 1))
    with pytest.raises(ValueError, match="threshold_min"):
        EDIParams(threshold_min=0.5, threshold_max=0.1)


# -- blurred image, known motion --------------------------------------------------------------

@pytest.mark.parametrize("I0", [None, PUBLISHED_INTENSITY_OFFSET])
@pytest.mark.parametrize("seed", [0, 1])
def test_blurred_image_recovered_exactly(seed, I0):
    """A quantised image shifted by 1 px per ms, exposed 8 ms: EDI with the true c recovers the
    sharp image at any time in the exposure. The model is exact for this motion (log intensity
    piecewise constant, changing by multiples of c at event times), so the tolerance is rounding:
    1e-12 relative. The events are level crossings of log(I + I0) for EDI's I0 (None: the
    default, 1e-3; and the published 1)."""
    off = DEFAULT_INTENSITY_OFFSET if I0 is None else I0
    kw = {} if I0 is None else {"intensity_offset": I0}
    rec, truth = shifted_sequence(seed=seed, I0=off)
    ev = EventArrays.from_structured(rec.events, rec.sensor_size.shape)
    B = rec.frames.images[0]
    for at in (0, 2_500, 4_000, 7_999, 8_000):
        got = edi_latent(B, ev, 0, 8_000, 0.2, at, **kw)
        want = truth(at - 1) if at > 0 else truth(0)  # the state at t excludes events at t
        np.testing.assert_allclose(got + off, want + off, rtol=1e-12)
    assert np.abs(B - truth(4_000)).max() > 0.3  # the frame really is blurred


@pytest.mark.parametrize("I0", [None, PUBLISHED_INTENSITY_OFFSET])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_threshold_search_within_5_percent(seed, I0):
    """Data exact for EDI's I0 (None: the default)."""
    rec, _ = shifted_sequence(seed=seed, I0=DEFAULT_INTENSITY_OFFSET if I0 is None else I0)
    ev = EventArrays.from_structured(rec.events, rec.sensor_size.shape)
    kw = {} if I0 is None else {"intensity_offset": I0}
    c, _ = estimate_threshold(rec.frames.images[0], ev, 0, 8_000, bounds=(0.05, 0.5), **kw)
    assert abs(c - 0.2) / 0.2 < 0.05


def test_golden_section():
    x, fx, n = golden_section_minimize(lambda v: (v - 0.3) ** 2, 0.0, 1.0, 1e-6)
    assert abs(x - 0.3) < 1e-6 and n < 40
    x, _, _ = golden_section_minimize(lambda v: v, 0.1, 0.5, 1e-3)  # monotone: boundary
    assert x == 0.1
    with pytest.raises(ValueError, match="hi > lo"):
        golden_section_minimize(lambda v: v, 1.0, 1.0, 1e-3)


def test_sharpness_energy_flat():
    assert sharpness_energy(np.zeros((4, 4)), np.zeros((4, 4))) == 0.0


# -- kernels against their Python originals ----------------------------------------------------

def test_kernels_match_py_func():
    rng = np.random.default_rng(3)
    n, H, W = 200, 5, 7
    t = np.sort(rng.integers(0, 1000, n)).astype(np.int64)
    x = rng.integers(0, W, n).astype(np.uint16)
    y = rng.integers(0, H, n).astype(np.uint16)
    p = rng.choice(np.array([-1, 1], np.int8), n)
    outs = []
    for f in (AK.edi_walk, py(AK.edi_walk)):
        cnt = np.zeros(H * W, np.int64); tl = np.zeros(H * W); acc = np.zeros(H * W)
        r = f(t, x, y, p, 10, 180, W, 0, 1000, 0.13, cnt, tl, acc)
        outs.append((r, cnt, acc))
    assert outs[0][0] == outs[1][0]
    np.testing.assert_array_equal(outs[0][1], outs[1][1])
    np.testing.assert_allclose(outs[0][2], outs[1][2], rtol=1e-15)
    outs = []
    for f in (AK.event_counts, py(AK.event_counts)):
        s = np.zeros(H * W, np.int64); a = np.zeros(H * W, np.int64)
        f(x, y, p, 0, n, W, s, a)
        outs.append((s, a))
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_array_equal(outs[0][1], outs[1][1])


# -- method 'edi' ------------------------------------------------------------------------------

def _as_codes(rec):
    fr = rec.frames
    codes = np.clip(np.round(fr.images * 255), 0, 255).astype(np.uint8)
    return Recording(rec.events, rec.sensor_size, Frames(codes, fr.t_start_us, fr.t_end_us, encoding="linear"))


@pytest.mark.parametrize("I0, base", [(None, np.log(0.25)), (PUBLISHED_INTENSITY_OFFSET, np.log(1.05))])
def test_method_edi_video(I0, base):
    """The events are level crossings of log(I + I0) for the method's I0 (None: the default 1e-3,
    with the scene 0.25..0.41 of the clip level; the published I0 = 1 with 0.05..0.73)."""
    rec, truth = shifted_sequence(c=0.1, base=base, I0=DEFAULT_INTENSITY_OFFSET if I0 is None else I0)
    rec8 = _as_codes(rec)
    times = np.array([1_500, 4_500, 7_500, 12_500, 21_500, 27_500], np.int64)
    kw = {} if I0 is None else {"intensity_offset": I0}
    v = reconstruct(rec8, "edi", {"contrast_threshold": 0.1, **kw}, times_us=times)
    assert v.frames.shape == (6, 16, 48) and v.method == "edi"
    assert v.info["edi_thresholds"] == {0: 0.1, 1: 0.1}
    err = np.abs(v.frames - np.stack([truth(t) for t in times]) / 1.0)
    assert err.max() < 0.02  # 8-bit quantisation of B, amplified by at most exp(c|E|)
    z = reconstruct(rec8, "frames", times_us=times[2:])  # zero-order hold starts at τ_0 = 4 ms
    assert np.abs(z.frames - np.stack([truth(t) for t in times[2:]])).mean() > 5 * err[2:].mean()
    v2 = reconstruct(rec8, "edi", kw, times_us=times[:3])  # threshold search
    assert all(abs(c - 0.1) < 0.02 for c in v2.info["edi_thresholds"].values())
    with pytest.raises(ValueError, match="causal"):
        reconstruct(rec8, "edi", mode="causal")


def test_event_arrays_reject_decreasing_time_naming_the_index():
    from hybridhdr.reconstruct.event_arrays import EventArrays
    t = np.array([5, 7, 7, 6, 9], np.int64)
    z = np.zeros(5, np.uint16)
    with pytest.raises(ValueError, match="index 3 has 6 after 7"):
        EventArrays(t, z, z, np.ones(5, np.int8), (2, 2))
    EventArrays(np.sort(t), z, z, np.ones(5, np.int8), (2, 2))  # sorted: accepted
