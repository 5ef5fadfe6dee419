"""`make demo` installs no PyTorch: the perceptual score (ColorVideoVDP JOD) is then skipped, said
once by the demo, and every scored row carries an "n/a" JOD instead of failing."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from hybridhdr.evaluate import cvvdp_metric, demo, metrics
from hybridhdr.evaluate.report import jod_label


@pytest.fixture
def no_torch(monkeypatch):
    """`import torch` fails (None in sys.modules), as in the demo's venv; restored afterwards."""
    monkeypatch.setitem(sys.modules, "torch", None)
    monkeypatch.setitem(sys.modules, "pycvvdp", None)


def test_cvvdp_says_not_available_without_torch(no_torch):
    assert cvvdp_metric.cvvdp_available() is False
    ref = np.ones((2, 8, 8))
    with pytest.raises(cvvdp_metric.CVVDPNotAvailable, match=r"hybridhdr\[evaluate\]"):
        cvvdp_metric.cvvdp_jod(ref, ref)


def test_scores_carry_na_jod_without_torch(no_torch):
    rng = np.random.default_rng(0)
    ref = rng.random((3, 12, 16))
    s = metrics.score_video(ref * 1.1, ref, jod={"max_frames": 2})
    assert math.isnan(s["jod"]) and s["jod_note"] == metrics.JOD_NA
    assert math.isfinite(s["ssim"])   # the other metrics are unaffected
    assert jod_label([s]) == f"JOD (ColorVideoVDP) {metrics.JOD_NA}"


def test_demo_note_says_the_perceptual_score_was_skipped(no_torch):
    note = demo.perceptual_score_note()
    assert note is not None and note.startswith("perceptual score skipped") and "[evaluate]" in note


def test_demo_note_is_silent_when_cvvdp_is_available(monkeypatch):
    monkeypatch.setattr(cvvdp_metric, "cvvdp_available", lambda: True)
    assert demo.perceptual_score_note() is None


def _jod_rows(note, jods):
    return [{"dataset": "d", "method_name": m, "status": "ok", "ds.noise": x, "jod": j, "jod_note": note,
             "n_nonfinite": 0} for m in ("akf", "cf") for x, j in enumerate(jods)]


def test_stability_of_an_uncomputed_jod_is_na_not_a_failure(tmp_path):
    from hybridhdr.evaluate import charts

    na = charts.stability_curves(_jod_rows(metrics.JOD_NA, [math.nan] * 3), dataset="d", axis="noise",
                                 metric="jod", relative_bound=0.8)
    assert all(c["failed_at"] is None and c["reason"] == metrics.JOD_NA for c in na.values()), na
    fig, ax = charts.plot_stability(_jod_rows(metrics.JOD_NA, [math.nan] * 3), dataset="d", axis="noise",
                                    metric="jod", relative_bound=0.8)
    assert any(metrics.JOD_NA in t.get_text() for t in ax.texts) and not ax.lines   # said, not drawn
    fig.savefig(tmp_path / "na.png")
    # a JOD that was computed and came out NaN (non-finite pixels) is still a failure, at its point
    bad = charts.stability_curves(_jod_rows("non-finite pixels", [9.5, math.nan, 9.0]), dataset="d",
                                  axis="noise", metric="jod", relative_bound=0.8)
    assert all(c["failed_at"] == 1 for c in bad.values()), bad
