"""The HDR-VDP 3 bridge, run through GNU Octave against a test stand-in ``hdrvdp3.m``.

The stand-in (tests/evaluate/data/hdrvdp_standin/) is NOT HDR-VDP: it computes
Q = 10 - mean((log10 max(test, 1e-3) - log10 max(ref, 1e-3))²) + 0.001·ppd, which these tests
reproduce in NumPy. It proves that the images, the luminance scale, task, encoding and ppd
reach ``hdrvdp3`` and that Q and the version come back.
"""

import shutil
from pathlib import Path

import numpy as np
import pytest

from hybridhdr.evaluate import metrics as M

STANDIN = Path(__file__).parent / "data" / "hdrvdp_standin"
needs_octave = pytest.mark.skipif(shutil.which("octave") is None,
                                  reason="GNU Octave not installed (apt-get install octave); the HDR-VDP bridge "
                                         "runs hdrvdp3.m through it")


def _standin_q(t, r, ppd):
    d = np.log10(np.maximum(t, 1e-3)) - np.log10(np.maximum(r, 1e-3))
    return 10 - np.mean(d ** 2) + 0.001 * ppd


@needs_octave
def test_bridge_returns_standin_q_and_settings():
    rng = np.random.default_rng(0)
    ref = rng.random((12, 16)) * 0.9 + 0.05
    test = np.clip(ref * (1 + 0.2 * rng.standard_normal(ref.shape)), 0, 1)
    res = M.hdrvdp_q(test, ref, hdrvdp_dir=STANDIN, engine="octave", luminance_scale_cd_m2=200.0)
    want = _standin_q(test * 200, ref * 200, M.pixels_per_degree())
    # the .mat file carries float64 and Octave prints %.17g, so agreement is to rounding
    assert res.q == pytest.approx(want, abs=1e-12)
    assert res.version == "3.0.6-standin"
    assert (res.task, res.color_encoding, res.engine) == ("side-by-side", "luminance", "octave")
    assert res.luminance_scale_cd_m2 == 200.0 and res.pixels_per_degree == pytest.approx(26.3986, abs=1e-4)


@needs_octave
def test_bridge_env_variable_ppd_and_errors(monkeypatch):
    monkeypatch.setenv("HYBRIDHDR_HDRVDP_DIR", str(STANDIN))
    ref = np.full((4, 5), 0.5)
    res = M.hdrvdp_q(ref, ref, pixels_per_degree=40.0)
    assert res.q == pytest.approx(10.04, abs=1e-12)
    with pytest.raises(RuntimeError, match="supports task side-by-side only"):
        M.hdrvdp_q(ref, ref, task="flicker")


def test_bridge_clear_message_when_absent(monkeypatch, tmp_path):
    monkeypatch.delenv("HYBRIDHDR_HDRVDP_DIR", raising=False)
    with pytest.raises(M.HDRVDPNotFound, match="HYBRIDHDR_HDRVDP_DIR"):
        M.hdrvdp_q(np.ones((4, 4)), np.ones((4, 4)))
    with pytest.raises(M.HDRVDPNotFound, match="hdrvdp3.m"):
        M.hdrvdp_q(np.ones((4, 4)), np.ones((4, 4)), hdrvdp_dir=tmp_path)
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(M.HDRVDPNotFound, match="no matlab executable"):
        M.hdrvdp_q(np.ones((4, 4)), np.ones((4, 4)), hdrvdp_dir=STANDIN, engine="matlab")


@needs_octave
def test_score_video_with_hdrvdp():
    rng = np.random.default_rng(1)
    ref = rng.random((2, 12, 12)) + 0.1
    # a pure gain, removed by the named gain fit: the stand-in then sees identical images
    s = M.score_video(ref * 0.5, ref, normalise="scale", hdrvdp={"hdrvdp_dir": STANDIN, "engine": "octave"})
    assert s["q"] == pytest.approx(10 + 0.001 * M.pixels_per_degree(), abs=1e-9)
    assert s["q_version"] == "3.0.6-standin" and s["q_luminance_scale_cd_m2"] == 4000.0


@needs_octave
def test_bridge_scores_a_stack_in_one_session():
    rng = np.random.default_rng(5)
    ref = rng.random((3, 6, 7)) + 0.05
    test = ref * np.array([1.0, 1.5, 3.0])[:, None, None]
    res = M.hdrvdp_q(test, ref, hdrvdp_dir=STANDIN, engine="octave", luminance_scale_cd_m2=100.0,
                     pixels_per_degree=30.0)
    # frame k: 10 - log10(factor)² + 0.03 (no pixel falls below the 1e-3 floor: ref >= 5 cd/m²)
    want = [10 - np.log10(f) ** 2 + 0.03 for f in (1.0, 1.5, 3.0)]
    np.testing.assert_allclose(res.q_frames, want, atol=1e-12)
    assert res.q == pytest.approx(np.mean(want), abs=1e-12)


@needs_octave
def test_bench_rows_carry_q_and_its_settings(tmp_path):
    from hybridhdr.evaluate import bench as B
    b = B.parse_bench({"bench": {"warmup": False, "hdrvdp_dir": str(STANDIN), "strips": 0},
                       "datasets": [{"kind": "procedural", "name": "p", "width": 24, "height": 16,
                                     "duration_us": 120_000}],
                       "methods": [{"method": "frames", "normalise": "scale"}]})
    rows = B.run_bench(b, workers=0, progress=False)
    r = rows[0]
    assert r["status"] == "ok" and 9 < r["q"] < 10.1
    assert r["q_version"] == "3.0.6-standin" and r["q_task"] == "side-by-side"
    w = B.write_results(rows, tmp_path, b)
    line = [ln for ln in w["report_md"].read_text().splitlines() if ln.startswith("| p | frames (fitted: scale) |")][0]
    assert f"| {r['q']:.2f} |" in line  # the Q column of the results table
