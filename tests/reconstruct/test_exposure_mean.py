"""Frames read as the mean of the intensity over their exposure (the AKF's ``exposure_mean``).

Closed forms of :func:`hybridhdr.reconstruct.edi.exposure_log_corrections` (the double integral of
EDI taken at mid-exposure), and the AKF on exactly blurred frames: with the exposure model the
state at a frame's mid-exposure is the sharp image there; without it the frame's blur is read as
the intensity at mid-exposure.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridhdr import Frames, Recording, make_events
from hybridhdr.reconstruct import reconstruct
from hybridhdr.reconstruct.edi import exposure_log_corrections
from hybridhdr.reconstruct.event_arrays import EventArrays
from hybridhdr.reconstruct.measurement import FrameMeasurements
from hybridhdr.reconstruct.params import DEFAULT_INTENSITY_OFFSET, AKFParams
from hybridhdr.camera import load_profile

from .blur_data import shifted_sequence


def _frames(starts, ends, shape=(1, 2)):
    k = len(starts)
    return Frames(np.full((k, *shape), 100, np.uint8), np.asarray(starts, np.int64), np.asarray(ends, np.int64),
                  encoding="linear")


def test_corrections_closed_form_one_event_each_side_of_mid_exposure():
    """Exposure [0, 1000), τ = 500. Pixel 0: one ON event at 250, so E(τ, t) = -c_on before it and 0
    after: J = (250 e^{-c_on} + 750)/1000. Pixel 1: one OFF event at 750: J = (750 + 250 e^{-c_off})/1000.
    The correction is -ln J; a frame without an exposure and a pixel without events get none."""
    ev = EventArrays(np.array([250, 750, 5000], np.int64), np.array([0, 1, 0], np.uint16),
                     np.zeros(3, np.uint16), np.array([1, -1, 1], np.int8), (1, 2))
    c_on, c_off = 0.1, 0.3
    out = exposure_log_corrections(_frames([0, 4000, 6000], [1000, 4000, 7000]), ev, c_on, c_off)
    assert set(out) == {0}  # frame 1: no exposure; frame 2: no event inside [6000, 7000)
    pix, corr = out[0]
    assert pix.tolist() == [0, 1]
    j0 = (250 * math.exp(-c_on) + 750) / 1000
    j1 = (750 + 250 * math.exp(-c_off)) / 1000
    np.testing.assert_allclose(corr, [-math.log(j0), -math.log(j1)], rtol=0, atol=1e-14)


def test_corrections_symmetric_ramp_cancels_to_first_order():
    """Events evenly spread around τ (one ON at 250 and one at 750 of [0, 1000)): the log latent at
    τ is within c²/8 of the log mean (J = (e^{-c} + 2 + e^{c})/4 = cosh²(c/2), -ln J ≈ -c²/4)."""
    c = 0.2
    ev = EventArrays(np.array([250, 750], np.int64), np.zeros(2, np.uint16), np.zeros(2, np.uint16),
                     np.ones(2, np.int8), (1, 1))
    pix, corr = exposure_log_corrections(_frames([0], [1000], (1, 1)), ev, c, c)[0]
    np.testing.assert_allclose(corr, [-2 * math.log(math.cosh(c / 2))], rtol=0, atol=1e-14)


def test_corrections_reject_bad_thresholds():
    ev = EventArrays(np.array([1], np.int64), np.zeros(1, np.uint16), np.zeros(1, np.uint16),
                     np.ones(1, np.int8), (1, 1))
    with pytest.raises(ValueError, match="c_on and c_off must be finite and > 0"):
        exposure_log_corrections(_frames([0], [10], (1, 1)), ev, 0.0, 0.1)


def test_frame_measurements_add_corrections_to_log_frame_and_bound():
    """L^F of a corrected frame is the plain one plus the correction at the listed pixels (a
    clipped code's bound too); the per-code path is left for that frame only."""
    im = np.array([[[100, 255]], [[100, 255]]], np.uint8)
    fr = Frames(im, np.array([0, 1000], np.int64), np.array([500, 1500], np.int64), encoding="linear")
    prof = load_profile(None)
    kw = dict(intensity_offset=DEFAULT_INTENSITY_OFFSET, saturation="bound", event_step=-1.0)
    plain = FrameMeasurements(fr, (1, 2), prof, **kw)
    corr = FrameMeasurements(fr, (1, 2), prof, log_corrections={1: (np.array([0, 1]), np.array([0.05, -0.02]))}, **kw)
    assert corr.segment_codes(0) is not None and corr.segment_codes(1) is None
    np.testing.assert_array_equal(corr.segment(0).log_frame, plain.segment(0).log_frame)
    np.testing.assert_allclose(corr.segment(1).log_frame - plain.segment(1).log_frame, [0.05, -0.02], atol=1e-15)
    np.testing.assert_array_equal(corr.segment(1).censor, plain.segment(1).censor)
    with pytest.raises(ValueError, match="frame index 2 is not among the 2 frames"):
        FrameMeasurements(fr, (1, 2), prof, log_corrections={2: (np.array([0]), np.array([0.1]))}, **kw)
    with pytest.raises(ValueError, match="equal-length 1-D pixel indices"):
        FrameMeasurements(fr, (1, 2), prof, log_corrections={0: (np.array([0, 2]), np.array([0.1, 0.1]))}, **kw)


@pytest.mark.parametrize("mode", ["offline", "causal"])
def test_akf_reads_blurred_frames_as_exposure_means(mode):
    """Exactly blurred frames (8 ms exposures of a pattern moving one pixel per ms, events exact,
    c = 0.1, intensities 0.25-0.41 of the clip level as 8-bit linear codes 64-105): at each
    frame's mid-exposure the AKF with the exposure model is within the codes' rounding of the sharp
    image (half a code in 64: 0.008 ln, times at most e^{0.5} through J); read as the intensity at
    τ_k the blur stays (the blurred frame's log differs from the sharp one by 0.1-0.2 ln at the
    bars' edges)."""
    rec, truth = shifted_sequence(c=0.1, base=np.log(0.25), I0=DEFAULT_INTENSITY_OFFSET,
                                  frame_starts=(500, 20_500), exposure_us=8_000)
    fr = rec.frames
    codes = np.clip(np.round(fr.images * 255), 0, 255).astype(np.uint8)
    rec = Recording(rec.events, rec.sensor_size, Frames(codes, fr.t_start_us, fr.t_end_us, encoding="linear"))
    tau = rec.frames.t_mid_us
    ref = np.log(np.stack([truth(int(t) - 1) for t in tau]) + DEFAULT_INTENSITY_OFFSET)  # events at t < τ
    errs = {}
    for on in (True, False):
        p = AKFParams(contrast_threshold=0.1, exposure_mean=on, exposure_min_events=0)  # exact events: every pixel
        v = reconstruct(rec, "akf", p, times_us=tau, mode=mode, augment=False)
        errs[on] = np.abs(np.log(v.frames + DEFAULT_INTENSITY_OFFSET) - ref)
    assert errs[True].max() < 0.015, errs[True].max()
    assert errs[False].max() > 0.1 and errs[False].mean() > 3 * errs[True].mean(), (errs[False].mean(),
                                                                                     errs[True].mean())


def test_exposure_mean_changes_nothing_without_exposures():
    """Frames without an exposure (t_end == t_start, as the ECD layout gives) are read as before,
    bit for bit."""
    rec, _ = shifted_sequence(c=0.1, base=np.log(0.25), I0=DEFAULT_INTENSITY_OFFSET, frame_starts=(500, 20_500))
    codes = np.clip(np.round(rec.frames.images * 255), 0, 255).astype(np.uint8)
    mid = rec.frames.t_mid_us
    fr = Frames(codes, mid, mid, encoding="linear")  # one stamp per frame, no exposure
    r8 = Recording(rec.events, rec.sensor_size, fr)
    a = reconstruct(r8, "akf", AKFParams(contrast_threshold=0.1), fps=500)
    b = reconstruct(r8, "akf", AKFParams(contrast_threshold=0.1, exposure_mean=False), fps=500)
    np.testing.assert_array_equal(a.frames, b.frames)


def test_pixels_with_few_events_in_the_exposure_are_left_alone():
    """By default a pixel is corrected only with n* = ceil(sqrt(24 / (√12 c))) events in the exposure
    (9 at c = 0.1): the corrected pixels are exactly those, and their values match the
    every-pixel run there."""
    rec, _ = shifted_sequence(c=0.1, base=np.log(0.25), I0=DEFAULT_INTENSITY_OFFSET, frame_starts=(500, 20_500),
                              exposure_us=8_000)
    ev = EventArrays.from_structured(rec.events, (16, 48))
    every = exposure_log_corrections(rec.frames, ev, 0.1, 0.1)
    some = exposure_log_corrections(rec.frames, ev, 0.1, 0.1, min_events=9)
    for k, (pix, corr) in every.items():
        s, e = int(rec.frames.t_start_us[k]), int(rec.frames.t_end_us[k])
        _, n = ev.counts(s, e)
        want = np.flatnonzero(n >= 9)
        got = some.get(k, (np.zeros(0, np.int64), np.zeros(0)))
        np.testing.assert_array_equal(got[0], want)
        np.testing.assert_array_equal(got[1], corr[np.isin(pix, want)])
    assert sum(len(v[0]) for v in some.values()) < sum(len(v[0]) for v in every.values())
    with pytest.raises(ValueError, match="min_events must be an int >= 0"):
        exposure_log_corrections(rec.frames, ev, 0.1, 0.1, min_events=-1)
    with pytest.raises(ValueError, match="exposure_min_events must be None or an int >= 0"):
        AKFParams(exposure_min_events=-2)
