"""Frames of unequal exposure are read in one unit: each frame's linear intensity times
``median(T·g) / (T_k·g_k)`` (:meth:`hybridhdr.model.Frames.exposure_scale`), by the filters as by
the camera model, and the held-out and over-exposure scores compare in each frame's own units.

A frame records the mean intensity over its exposure times the exposure (and the gain): a scene
of constant brightness shot at 1, 2 and 4 ms gives codes in the ratio 1:2:4 and one intensity.
"""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.camera import default_profile
from hybridhdr.events import SensorSize
from hybridhdr.model import CameraInfo, Frames, Metadata, Recording
from hybridhdr.reconstruct import FrameMeasurements, reconstruct
from hybridhdr.simulate.procedural import ideal_events

H, W = 16, 20
PERIOD_US = 20_000
T_REF_US = 2_000  # the median exposure of the bracketed frames below


def _scene(seed=0):
    """ln I(t) = L0 + r t per pixel (frame-linear units of a 2 ms exposure), I within 0.1-0.3."""
    rng = np.random.default_rng(seed)
    L0 = np.log(rng.uniform(0.1, 0.2, (H, W)))
    r = (np.log(rng.uniform(0.2, 0.3, (H, W))) - L0) / 0.1
    return lambda t_us: L0 + r * (t_us * 1e-6)


def _recording(exposures_us, c=0.04, seed=0):
    """Frames every 20 ms exposed for ``exposures_us`` (cycled), codes = round(255 · I(mid) · T / 2 ms)
    (12-bit-free: 8-bit raw codes; the scene stays below the clip level at 4 ms), ideal events."""
    L = _scene(seed)
    n = 6
    ex = np.resize(np.asarray(exposures_us, np.int64), n)
    t0 = np.arange(n, dtype=np.int64) * PERIOD_US + 1_000
    mid = t0 + ex // 2
    codes = np.stack([np.round(255 * np.exp(L(int(m))) * e / T_REF_US) for m, e in zip(mid, ex)]).astype(np.uint8)
    ev = ideal_events(L, np.arange(0, n * PERIOD_US + 1, 50, dtype=np.int64), c)
    ss = SensorSize(H, W)
    return Recording(ev, ss, Frames(codes, t0, t0 + ex, encoding="linear"),
                     metadata=Metadata(CameraInfo(ss), CameraInfo(ss))), L, mid


def test_exposure_scale_rule():
    """median(T·g) / (T_k·g_k); ones for equal exposures or any frame without one; gain counts."""
    t = np.array([0, 100, 200])
    img = np.zeros((3, 2, 2), np.uint8)
    np.testing.assert_array_equal(Frames(img, t, t + [1000, 2000, 4000]).exposure_scale(), [2.0, 1.0, 0.5])
    np.testing.assert_array_equal(Frames(img, t, t + 500).exposure_scale(), [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(Frames(img, t, t + [0, 2000, 4000]).exposure_scale(), [1.0, 1.0, 1.0])
    fr = Frames(img, t, t + 1000, gain=np.array([1.0, 2.0, 4.0]))
    np.testing.assert_array_equal(fr.exposure_scale(), [2.0, 1.0, 0.5])
    assert fr.reference_exposure() == 2000.0 and fr.units_factor(2, 2000.0) == 2.0
    assert Frames(img, t, t).reference_exposure() is None and Frames(img, t, t).units_factor(0, None) == 1.0


def test_measurements_read_bracketed_frames_in_one_unit():
    """The same scene at 1, 2 and 4 ms: one intensity (to the 8-bit quantisation of the 1 ms
    frame, 0.5/12.75 at least: 4 % relative), where the codes differ by 2x and 4x; equal exposures
    keep the per-code tables (the same path and bits as before)."""
    rec, L, mid = _recording([1_000, 2_000, 4_000])
    m = FrameMeasurements(rec.frames, (H, W), default_profile(), intensity_offset=1e-3)
    truth = [np.exp(L(int(t))).ravel() for t in mid]
    for k in range(len(m)):
        assert m.segment_codes(k) is None  # unequal exposures: the per-pixel path
        got = m.segment(k).intensity
        np.testing.assert_allclose(got, truth[k], rtol=0.045)
    raw = rec.frames.images[0].ravel() / 255.0  # read as it is: half the intensity at 1 ms
    assert np.median(raw / truth[0]) == pytest.approx(0.5, rel=0.05)
    same, _, _ = _recording([2_000])
    m2 = FrameMeasurements(same.frames, (H, W), default_profile(), intensity_offset=1e-3)
    assert all(m2.segment_codes(k) is not None for k in range(len(m2)))


@pytest.mark.parametrize("mode", ["offline", "causal"])
def test_akf_on_bracketed_frames_equals_constant_exposure(mode):
    """The AKF on frames bracketed 1/2/4 ms gives the image it gives on the same scene at a
    constant 2 ms, to the quantisation of the short frames (median |Δ ln| well below 0.02, where
    reading the codes as they are would put the 1 ms frames ln 2 = 0.69 too dark)."""
    rec_b, L, mid = _recording([1_000, 2_000, 4_000])
    rec_c, _, mid_c = _recording([2_000])
    t = np.array([45_000, 71_000, 95_000], np.int64)
    kw = dict(mode=mode, times_us=t, thresholds="params", frame_time_offset_us=0)
    a = np.asarray(reconstruct(rec_b, "akf", {"contrast_threshold": 0.04}, **kw).frames, np.float64)
    b = np.asarray(reconstruct(rec_c, "akf", {"contrast_threshold": 0.04}, **kw).frames, np.float64)
    assert np.all(a > 0) and np.all(b > 0)
    d = np.abs(np.log(a) - np.log(b))
    assert np.median(d) < 0.02, np.median(d)
    truth = np.stack([np.exp(L(int(v))) for v in t])
    assert np.median(np.abs(np.log(a) - np.log(truth))) < 0.05


def test_holdout_scores_in_each_frames_own_units():
    """Leave-one-out on the bracketed recording: the reconstruction of frame k is compared in frame
    k's units, so hold-previous (the previous frame, 20 ms and a few % of brightening earlier)
    errs as on the constant-exposure recording, not by the exposure ratio."""
    from hybridhdr.evaluate.realdata import HoldoutSpec, evaluate_holdout
    specs = [HoldoutSpec("akf", "akf", "offline", {"contrast_threshold": 0.04})]
    out = {}
    for name, ex in (("bracketed", [1_000, 2_000, 4_000]), ("constant", [2_000])):
        rec, _, _ = _recording(ex)
        res = evaluate_holdout(rec, specs, tasks=("leave_one_out",), thresholds="params")
        out[name] = {lab: row["mean"]["mse"] for lab, row in res["leave_one_out"]["methods"].items() if "mean" in row}
    for lab in ("akf", "hold_previous"):
        assert out["bracketed"][lab] < 2.0 * out["constant"][lab] + 1e-6, (lab, out)
