"""``--sensor-profile FILE``: the camera model a run uses is exactly the profile's, with no re-estimation,
on the command line and in the API, and it is recorded in run.json / ``Video.info``."""

from __future__ import annotations

import json

import pytest

import hybridhdr
from hybridhdr.calibrate import camera_model as CM
from hybridhdr.cli import main
from hybridhdr.reconstruct import reconstruct

pytestmark = pytest.mark.filterwarnings("ignore::hybridhdr.calibrate.camera_model.GridEdgeWarning")


@pytest.fixture(scope="module")
def ecd_profile(tmp_path_factory):
    from tests.conftest import shared_file
    ecd = shared_file("ecd_slider_depth")
    out = tmp_path_factory.mktemp("prof") / "p.json"
    assert main(["calibrate", "sensor", str(ecd), "--out", str(out), "--bootstrap", "20", "-q"]) == 0
    return ecd, out


def _no_estimation(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("the camera model was re-estimated although a sensor profile was given")
    # every module that binds the name, imported BEFORE the patch: one first imported while
    # camera_model is patched would bind ``refuse`` and keep it after the test (later tests failed)
    import hybridhdr.calibrate.selfcal as SC
    import hybridhdr.calibrate.sensor_profile as SP
    for mod in (CM, SC, SP):
        monkeypatch.setattr(mod, "estimate_camera_model", refuse)


def test_reconstruct_uses_the_profile_exactly(ecd_profile, tmp_path, monkeypatch):
    ecd, path = ecd_profile
    prof = json.loads(path.read_text())
    est = prof["estimates"]
    _no_estimation(monkeypatch)
    out = tmp_path / "out"
    assert main(["reconstruct", str(ecd), "--method", "akf", "--sensor-profile", str(path), "--out", str(out),
                 "--no-progress", "-q"]) == 0
    run = json.loads((out / "run.json").read_text())
    cm = run["camera_model"]
    assert cm["source"] == "profile" and cm["sensor_profile"] == str(path)
    assert cm["c_on"] == prof["simulator_params"]["contrast_threshold_on"]
    assert cm["c_off"] == prof["simulator_params"]["contrast_threshold_off"]
    assert cm["intensity_offset"] == est["intensity_offset"]["value"]
    assert cm["frame_time_offset_us"] == est["time_offset_us"]["value"]
    assert cm["estimates"]["contrast_threshold_on"]["std"] == est["contrast_threshold_on"]["std"]  # uncertainties kept
    assert run["params"]["contrast_threshold_on"] == cm["c_on"] and run["params"]["intensity_offset"] == cm["intensity_offset"]
    assert "self_calibration" not in run
    # the API: the same values, the same record
    v = reconstruct(hybridhdr.read(ecd), "akf", thresholds=path)
    assert v.info["camera_model"]["c_on"] == cm["c_on"] and v.info["frame_time_offset_us"] == cm["frame_time_offset_us"]
    assert v.params["intensity_offset"] == cm["intensity_offset"]


def test_sensor_profile_flag_errors(ecd_profile, tmp_path, capsys):
    ecd, path = ecd_profile
    for verb in (["reconstruct", str(ecd), "--method", "akf", "--out", str(tmp_path / "a")],
                 ["evaluate", "holdout", str(ecd), "--method", "akf"],
                 ["evaluate", "overexpose", str(ecd), "--gain", "4", "--method", "akf", "--out", str(tmp_path / "c")]):
        assert main([*verb, "--sensor-profile", str(path), "--thresholds", "selfcal"]) == 2  # a usage error
        assert "both give the camera model" in capsys.readouterr().err
        # reconstruct reports any error found while reading its arguments as a usage error (2), evaluate a missing file as 1
        assert main([*verb, "--sensor-profile", str(tmp_path / "missing.json")]) in (1, 2)
        assert "does not exist" in capsys.readouterr().err
        assert main([*verb, "--sensor-profile", str(tmp_path / "map.npz")]) == 2
        assert "expected a sensor profile .json" in capsys.readouterr().err


def test_simulate_reads_the_same_file(ecd_profile):
    """``simulate --sensor p.json`` takes the same file's event model (ON/OFF, noise)."""
    from hybridhdr.cli import build_parser
    from hybridhdr.simulate.cli import sensor_params
    _, path = ecd_profile
    sp = json.loads(path.read_text())["simulator_params"]
    s = sensor_params(build_parser().parse_args(["simulate", "builtin:slow_static", "--out", "x.h5", "--sensor", str(path)]))
    assert (s.contrast_threshold_on, s.contrast_threshold_off) == (sp["contrast_threshold_on"], sp["contrast_threshold_off"])
    assert s.shot_noise_rate_hz == sp["shot_noise_rate_hz"]


def test_overexposed_input_scales_the_profiles_dark_offset(ecd_profile, monkeypatch):
    """``evaluate overexpose`` with a sensor profile: the over-exposed input's frames read ``gain`` times
    brighter, so the AKF's I0 is the profile's × gain (ln(I + I0) shifts by the constant ln gain and the
    thresholds hold); a method with its own log model keeps its own I0. Nothing is re-estimated."""
    from hybridhdr.evaluate import overexpose as O
    ecd, path = ecd_profile
    i0 = json.loads(path.read_text())["estimates"]["intensity_offset"]["value"]
    _no_estimation(monkeypatch)
    over, _ = O.overexpose_recording(hybridhdr.read(ecd), 4.0)
    got = O._profile_at_gain(path, O.OverexposeSpec("akf_causal", "akf", "causal"), over)
    assert got.source == "profile" and got.intensity_offset == pytest.approx(4.0 * i0, rel=1e-12)
    assert "× 4" in got.note
    t = int(over.frames.t_mid_us[3])
    v = reconstruct(over, "akf", thresholds=got, times_us=[t], mode="causal")
    assert v.params["intensity_offset"] == pytest.approx(4.0 * i0, rel=1e-12)
    assert v.info["camera_model"]["source"] == "profile"
    assert O._profile_at_gain(path, O.OverexposeSpec("cf_causal", "cf", "causal"), over).intensity_offset is None
