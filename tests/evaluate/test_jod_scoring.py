"""ColorVideoVDP JOD in score_video: bounded, evenly spaced frames; n/a (never a crash) without cvvdp."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridhdr.evaluate import metrics as M


def _seq(k=12, h=24, w=32, seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    base = 0.02 + np.exp(2 * np.sin(xx / 5.0) * np.cos(yy / 7.0)) / 8.0
    return np.stack([base * (1 + 0.05 * i) for i in range(k)]), rng


def test_jod_frame_indices():
    assert M.jod_frame_indices(20, 8).tolist() == [0, 3, 5, 8, 11, 14, 16, 19]
    assert M.jod_frame_indices(3, 8).tolist() == [0, 1, 2]
    assert M.jod_frame_indices(1, 8).tolist() == [0] and M.jod_frame_indices(0).size == 0
    with pytest.raises(ValueError):
        M.jod_frame_indices(5, 0)


def test_jod_not_installed_is_na(monkeypatch):
    from hybridhdr.evaluate import cvvdp_metric as cv

    def missing(*a, **k):
        raise cv.CVVDPNotAvailable("no cvvdp")
    monkeypatch.setattr(cv, "cvvdp_jod", missing)
    ref, _ = _seq(4)
    s = M.score_video(ref * 0.9, ref, jod=True)
    assert math.isnan(s["jod"]) and s["jod_note"] == M.JOD_NA == "n/a (install hybridhdr[evaluate])"
    assert np.isfinite(s["mse"])                      # the other metrics are unaffected
    assert "jod" not in M.score_video(ref, ref)       # off unless asked


def test_jod_scores_bounded_frames_with_the_display_stated():
    cv = pytest.importorskip("hybridhdr.evaluate.cvvdp_metric")
    if not cv.cvvdp_available():
        pytest.skip("cvvdp not installed")
    ref, rng = _seq(12)
    same = M.score_video(ref, ref, jod={"max_frames": 3})
    assert same["jod"] == pytest.approx(10.0, abs=1e-3) and same["jod_frames"] == 3
    assert "standard_hdr_linear" in same["jod_display_line"] and "viewing distance 0.7472 m" in same["jod_display_line"]
    noisy = M.score_video(ref * np.exp(0.3 * rng.standard_normal(ref.shape)), ref, jod=True)
    assert noisy["jod_frames"] == 8 and noisy["jod"] < same["jod"] - 0.2
    # NaN pixels: the JOD is NaN too (a numerical failure is never hidden)
    bad = ref.copy()
    bad[0, 0, 0] = np.nan
    assert math.isnan(M.score_video(bad, ref, jod=True)["jod"])
