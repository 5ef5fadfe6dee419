"""``calibrate rig --events`` on a simulated single camera: compared with the camera the
recording's provenance states, no stereo baseline claimed, few views warned."""

from __future__ import annotations

import types

import numpy as np
import pytest

from hybridhdr.calibrate._cli_rig import FEW_VIEWS, compare_with_truth, simulated_camera


def test_simulated_camera_from_provenance():
    K = [[194.22, 0.0, 172.5], [0.0, 194.22, 129.5], [0.0, 0.0, 1.0]]
    prov = {"source": {"source": "mitsuba", "scene": "blinking_checkerboard", "width": 346, "height": 260, "K": K}}
    t = simulated_camera(prov)
    assert t["K"] == K and t["width"] == 346
    assert simulated_camera({}) is None and simulated_camera({"source": {"K": [[1, 2]]}}) is None
    assert simulated_camera(None) is None  # a real recording: no ground truth


def test_compare_with_truth_reports_errors_and_zero_baseline():
    K = [[200.0, 0.0, 170.0], [0.0, 200.0, 130.0], [0.0, 0.0, 1.0]]
    est = np.array([[195.57, 0, 171.0], [0, 191.62, 128.5], [0, 0, 1]])
    cam = types.SimpleNamespace(K=est, views=[0, 1, 2, 3])
    stereo = types.SimpleNamespace(baseline_m=0.01117, rotation_deg=0.4)
    r = compare_with_truth({"K": K}, {"frame": cam, "event": cam}, stereo)
    e = r["cameras"]["frame"]
    assert e["fx_error_pct"] == pytest.approx(100 * (195.57 / 200 - 1))
    assert e["cy_error_px"] == pytest.approx(-1.5) and e["views_used"] == 4 < FEW_VIEWS
    assert r["true_baseline_m"] == 0.0 and r["estimated_baseline_m"] == pytest.approx(0.01117)
