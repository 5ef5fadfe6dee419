"""End to end on real DAVIS240C data (ecd_slider_depth): AKF and CF from the ECD folder."""

from __future__ import annotations

import numpy as np
import pytest

import hybridhdr
from hybridhdr.reconstruct import reconstruct


def test_ecd_slider_depth_mse(shared_data, record_property, capsys):
    """Predict APS frame k+1 at τ_{k+1} - 1 µs (before the filter sees it) from frame k + events.

    Bound: the MSE must beat the trivial prediction "frame k held" (zero-order hold), i.e. the
    events must add information. Frames are scaled to [0, 1] by 255 and the output clipped.
    """
    folder = shared_data("ecd_slider_depth")
    rec = hybridhdr.read(folder)
    fr = rec.frames
    t_last_ev = int(rec.events["t"][-1])
    k = np.flatnonzero(fr.t_mid_us[1:] <= t_last_ev) + 1  # frames inside the event span
    assert len(k) >= 3
    times = fr.t_mid_us[k] - 1
    gt = fr.images[k].astype(np.float64) / 255.0
    zoh = fr.images[k - 1].astype(np.float64) / 255.0
    mse_zoh = float(np.mean((zoh - gt) ** 2))
    results = {"frames_zoh": mse_zoh}
    for method in ("akf", "cf"):
        for mode in ("offline", "causal"):
            v = reconstruct(folder, method, times_us=times, mode=mode)
            assert v.frames.shape == gt.shape and np.isfinite(v.frames).all()
            results[f"{method}_{mode}"] = float(np.mean((np.clip(v.frames, 0, 1) - gt) ** 2))
    for name, val in results.items():
        record_property(f"mse_{name}", val)
    with capsys.disabled():
        print("\necd_slider_depth MSE vs APS frame k+1: " + ", ".join(f"{k} {v:.5f}" for k, v in results.items()))
    for name, val in results.items():
        if name != "frames_zoh":
            assert np.isfinite(val) and val < mse_zoh, (name, val, mse_zoh)
