"""Stability sweeps: every stress axis maps onto the generator, runs, and our methods never produce
NaN/Inf, however hard a stress axis is pushed."""

import numpy as np
import pytest

from hybridhdr.evaluate import bench as B
from hybridhdr.evaluate import sweeps as S
from hybridhdr.evaluate.datasets import load_dataset


def test_axes_cover_every_stress_the_stability_bench_names():
    names = set(S.STRESS_AXES)
    assert {"noise_rate", "threshold_mismatch", "refractory", "threshold_under", "threshold_over", "under_exposure",
            "over_exposure", "motion_speed", "frame_rate"} == names
    for a in S.STRESS_AXES.values():
        assert a.stress in ("increasing", "decreasing") and a.target in ("dataset", "method")
        assert len(a.values) >= 5
    with pytest.raises(ValueError, match="unknown stress axis"):
        S.stability_bench(["nope"])


def test_bundled_stability_bench_is_the_generated_one():
    b = B.load_bench("stability")
    gen = B.parse_bench(S.stability_bench(), "gen")
    assert b.datasets == gen.datasets and b.methods == gen.methods and b.charts == gen.charts


def test_stresses_change_the_data_as_stated():
    base = {"kind": "procedural", "width": 32, "height": 24, "duration_us": 150_000}
    n0 = len(load_dataset(base).recording.events)
    noisy = load_dataset({**base, "noise_rate_hz": 100.0}).recording.events
    # 768 px · 100 Hz · 0.15 s = 11520 expected noise events (Poisson sd 107)
    assert abs(len(noisy) - n0 - 11_520) < 600
    refr = load_dataset({**base, "refractory_period_us": 20_000}).recording.events
    assert len(refr) < 0.9 * n0
    for px in np.unique(refr["y"].astype(np.int64) * 32 + refr["x"])[:50]:
        t = refr["t"][(refr["y"].astype(np.int64) * 32 + refr["x"]) == px]
        assert np.all(np.diff(t) >= 20_000)  # the refractory period holds at every pixel
    over = load_dataset({**base, "exposure_scale": 4.0}).recording.frames.images
    under = load_dataset({**base, "exposure_scale": 0.05}).recording.frames.images
    nominal = load_dataset(base).recording.frames.images
    # measured on this scene: saturated fraction 0.56 nominal, 0.88 at 4x, 0.37 at 0.05x
    assert (over == 255).mean() > (nominal == 255).mean() + 0.25
    assert (under == 255).mean() < (nominal == 255).mean() - 0.1
    assert under.mean() < 0.75 * nominal.mean()


@pytest.mark.slow
def test_quick_sweep_has_no_numerical_failures():
    # every axis, 3 values each, all six methods, in this process. JOD (ColorVideoVDP) is scored
    # for every run, as by default, but on one frame per run instead of 8: a failing JOD would still
    # fail its run (status not "ok"), and 8 frames made JOD nearly 90 % of this test's time
    d = S.stability_bench(quick=True)
    d["bench"]["jod_frames"] = 1
    b = B.parse_bench(d, "quick")
    rows = B.run_bench(b, workers=0, progress=False)
    assert len(rows) == 7 * 3 * 6 + 2 * 3 * 6  # 7 dataset axes x 3 values, 2 method axes x 3 values; 6 methods
    bad = [(r["dataset"], r["method_label"], r["status"]) for r in rows if r["status"] != "ok"]
    assert not bad
    ours = [r for r in rows if r["method"] in ("akf", "cf", "highpass", "direct", "edi", "frames_zoh")]
    assert sum(r["n_nonfinite"] for r in ours) == 0
    assert all(np.isfinite(r["mse"]) and np.isfinite(r["log_ssim"]) for r in ours)
    assert all(r["jod_frames"] == 1 and "jod" in r for r in rows)  # JOD was scored in every run
