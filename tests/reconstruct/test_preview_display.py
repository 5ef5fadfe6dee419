"""One display map: ``reconstruct --png`` previews look as ``view`` shows them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hybridhdr.cli import main
from hybridhdr.formats import images as IM

from ..conftest import shared_file


def _png(path):
    from imageio.v3 import imread
    return np.asarray(imread(path))


def test_display_gamma_follows_the_frame_encoding():
    assert IM.display_gamma("gamma") == IM.display_gamma("srgb") == 2.2
    assert IM.display_gamma("linear") == IM.display_gamma("unknown") == IM.display_gamma(None) == 1.0


def test_centred_map_puts_the_median_at_mid_grey():
    """Events-only outputs: the median log intensity is code 128 (127.5 rounded), the map is
    symmetric, so a spot as far above the median as the 99th percentile is white."""
    m = IM.display_map_centred(-0.2, 0.0, 0.5)
    assert m["limits"] == (-0.5, 0.5) and m["centre"] == "median"
    u8 = IM.apply_display_map(np.exp(np.array([[0.0, 0.5, -0.5, 0.25]])), m)
    assert u8.tolist() == [[128, 255, 0, 191]]  # 255 * 0.75 = 191.25


def test_ecd_preview_mean_matches_the_frame(tmp_path, capsys):
    """The AKF preview of ecd_slider_depth at 0.1 s has the frame's brightness: within 4 codes of
    the frame at that time (was 126 vs 63 with the gamma-2.2 map on 'unknown'-encoded frames). The
    AKF output is the frame's linear intensity plus event detail, so the means agree to a few codes
    (measured 64.1 vs 62.7-63.3; 4 codes leaves room for the event detail, not for a gamma error).
    ``--thresholds input``: the preview's map is the subject, not the self-calibration, which took
    half of this test's time (with it the mean is 62.6)."""
    data = shared_file("ecd_slider_depth")
    out = tmp_path / "v"
    assert main(["reconstruct", str(data), "--method", "akf", "--fps", "300", "--out", str(out), "--png",
                 "--no-exr", "--no-progress", "--thresholds", "input"]) == 0
    capsys.readouterr()
    run = json.loads((out / "run.json").read_text())
    assert run["written"]["preview_display"] == {"mode": "linear", "hi": 1.0, "gamma": 1.0}
    t = [int(line.split()[0]) for line in (out / "timestamps.txt").read_text().splitlines()
         if line.strip() and not line.startswith("#")]
    import hybridhdr
    frames = hybridhdr.read(data).frames
    i = 30
    k = int(np.searchsorted(frames.t_end_us, t[i], side="right")) - 1  # the frame shown at that time
    prev = _png(out / "previews" / f"preview_{i:06d}.png").astype(float)
    assert abs(prev.mean() - frames.images[k].astype(float).mean()) < 4.0


def test_highpass_preview_of_sparklers_is_grey_not_saturated(tmp_path, capsys):
    """Events-only (high-pass) previews of the sparklers sample: mid-grey background under the
    centred log map, not white (were means 253-255): every preview's median is 128 and under 1 %
    of its pixels are at 255."""
    raw = shared_file("prophesee/sparklers_gen3_evt2.raw")
    out = tmp_path / "h"
    assert main(["reconstruct", str(raw), "--method", "highpass", "--fps", "100", "--out", str(out), "--png",
                 "--no-exr", "--no-progress"]) == 0
    capsys.readouterr()
    disp = json.loads((out / "run.json").read_text())["written"]["preview_display"]
    assert disp["mode"] == "log" and disp["centre"] == "median"
    pngs = sorted((out / "previews").glob("preview_*.png"))
    assert len(pngs) >= 5
    for p in pngs:
        u8 = _png(p)
        assert np.median(u8) == 128, p.name
        assert (u8 == 255).mean() < 0.01 and 100 < u8.mean() < 156, (p.name, u8.mean())


def test_view_uses_the_same_map_as_the_previews(tmp_path, capsys):
    """``view --recon`` on a reconstruct folder picks the map the previews used (run.json)."""
    from hybridhdr.view import _Recon
    raw = shared_file("prophesee/sparklers_gen3_evt2.raw")
    out = tmp_path / "h"
    assert main(["reconstruct", str(raw), "--method", "highpass", "--fps", "100", "--out", str(out), "--png",
                 "--no-progress"]) == 0
    capsys.readouterr()
    r = _Recon(out)
    assert r.events_only and r.display["centre"] == "median"
    d = json.loads((out / "run.json").read_text())["written"]["preview_display"]
    # view samples up to 64 outputs (here all 10): the same percentiles, up to the float32 keys'
    # interpolation in LogPercentiles vs np.percentile on float64 (1e-6 in log units)
    assert r.display["limits"] == pytest.approx(d["limits"], abs=1e-6)
