"""calibrate sensor: round trip through the simulator, the profile file, simulate's use of it, ECD."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from hybridhdr.calibrate.camera_model import GridEdgeWarning
from hybridhdr.calibrate.sensor_profile import (
    estimate_sensor_profile,
    isi_lower_edge,
    poisson_ci,
)
from hybridhdr.formats.sensor_profile import (
    SIMULATOR_FIELDS,
    SensorProfile,
    SensorProfileError,
    load_sensor_profile,
)
from hybridhdr.simulate.procedural import sensor_calibration_recording
from hybridhdr.simulate.sensor import (
    EventSensorParams,
    sensor_from_profile,
    sensor_preset,
)

TRUE = EventSensorParams(contrast_threshold_on=0.25, contrast_threshold_off=0.2, threshold_mismatch_sigma=0.03,
                         refractory_period_us=300, shot_noise_rate_hz=3.0, leak_rate_hz=0.5)


@pytest.fixture(scope="module")
def roundtrip():
    # 1 s, 2 kHz renders of a 32x64 scene: 24 frame intervals over 1152 texture pixels, 504 static
    # pixels (504 pixel-seconds), 25 flicker bursts
    rec, scene, _ = sensor_calibration_recording(TRUE, seed=1, duration_us=1_000_000, render_rate_hz=2000.0)
    return rec, scene, estimate_sensor_profile(rec, n_boot=50, seed=0)


def test_roundtrip_every_identifiable_parameter(roundtrip):
    rec, scene, prof = roundtrip
    e = prof.estimates
    # threshold means: 5 %. Measured errors -2.9 % to +1.8 % (seeds 0-4, 1 s): the quantisation
    # residual of each interval, and pooling, which weights low-threshold pixels up by about
    # sigma^2/C^2 = 1.4 % ON, 2.3 % OFF; bootstrap SE 0.5 %
    for k in ("contrast_threshold_on", "contrast_threshold_off"):
        assert e[k]["identifiable"]
        assert abs(e[k]["value"] / getattr(TRUE, k) - 1) < 0.05, (k, e[k]["value"])
        assert e[k]["ci95"][0] <= e[k]["value"] <= e[k]["ci95"][1]
    # mismatch sigma: 12 %. Sampling: the realised SD of 1152 pixels' thresholds differs from sigma by
    # sigma/sqrt(2n) = 2 %, the split-half covariance has a bootstrap SE of 2-3 % at 12 intervals per
    # half; measured errors -2.5 % to +7.6 % (seeds 0-4, 1 s)
    s = e["threshold_mismatch_sigma"]
    assert s["identifiable"] and abs(s["value"] / TRUE.threshold_mismatch_sigma - 1) < 0.12, s
    assert s["pixels_both_halves"] >= 30 and s["ci95"][0] <= s["value"] <= s["ci95"][1]
    # shot noise and leak: 4 Poisson standard errors (OFF count and ON-OFF difference at 504 pixel-s),
    # plus 3 % on the leak for Jensen: a mismatched pixel leaks at leak*C/c, mean (1 + sigma^2/C^2)
    sh, lk = e["shot_noise_rate_hz"], e["leak_rate_hz"]
    assert sh["identifiable"] and abs(sh["value"] - TRUE.shot_noise_rate_hz) < 4 * sh["std"], sh
    assert lk["identifiable"] and abs(lk["value"] - TRUE.leak_rate_hz) < 4 * lk["std"] + 0.03 * TRUE.leak_rate_hz, lk
    # refractory: the lower ISI edge lies at R + c/slope, the flicker's log slope being 12 ln / 1.5 ms;
    # c at most C_on + 3 sigma; +2 us for timestamp rounding
    r = e["refractory_period_us"]
    slope = scene.flicker_ln / (scene.ramp_us * 1e-6)
    hi = TRUE.refractory_period_us + (TRUE.contrast_threshold_on + 3 * TRUE.threshold_mismatch_sigma) / slope * 1e6 + 2
    assert r["identifiable"] and TRUE.refractory_period_us - 2 <= r["value"] <= hi, (r["value"], hi)
    for k in ("photoreceptor_cutoff_hz", "timestamp_jitter_us"):
        assert not e[k]["identifiable"] and e[k]["value"] is None and e[k]["reason"]
    # the simulator reads back what was identified
    p = sensor_from_profile(prof)
    assert p.refractory_period_us == int(round(r["value"]))
    assert p.contrast_threshold_on == e["contrast_threshold_on"]["value"]
    assert p.photoreceptor_cutoff_hz is None


def test_refractory_upper_bound_without_pileup():
    # a pixel whose intervals rise gradually from their edge: a bound, not an estimate
    rng = np.random.default_rng(0)
    isi = np.sort(2000 + rng.gamma(3.0, 1500.0, 5000))
    edge = isi_lower_edge(isi)
    assert 2000 <= edge < 2600
    m1 = np.count_nonzero((isi >= edge) & (isi < 1.5 * edge))
    m2 = np.count_nonzero((isi >= 1.5 * edge) & (isi < 2 * edge))
    assert m1 < m2  # the rule calibrate sensor uses to call it a bound
    # a noise floor below the edge does not pull it down: 5 per 1000 ISIs spread over [0, 300)
    sig = np.sort(np.concatenate([300 + rng.exponential(20.0, 20000), rng.uniform(0, 300, 100)]))
    assert 300 <= isi_lower_edge(sig, noise_rate_hz=100 / 20100 / 300e-6) <= 305


def test_poisson_ci_closed_form():
    # n = 0: upper limit -ln(0.025) = 3.689 (exact for a Poisson mean)
    lo, hi = poisson_ci(0)
    assert lo == 0 and math.isclose(hi, -math.log(0.025), rel_tol=1e-9)
    lo, hi = poisson_ci(100)
    assert 81.3 < lo < 81.4 and 121.6 < hi < 121.7  # Garwood table values 81.36, 121.63


def test_profile_file_roundtrip_and_errors(roundtrip, tmp_path):
    _, _, prof = roundtrip
    p = prof.save(tmp_path / "profile.json")
    back = load_sensor_profile(p)
    assert back.simulator_params == prof.simulator_params and back.estimates.keys() == prof.estimates.keys()
    assert not list(tmp_path.glob("*.partial"))
    assert sensor_preset(str(p)) == sensor_from_profile(prof)
    d = json.loads(p.read_text())
    for bad, msg in (({**d, "version": 2}, "expected version 1, found 2"),
                     ({**d, "format": "x"}, "expected format"),
                     ({**d, "simulator_params": {"leak_rate_hz": -1}}, "leak_rate_hz must be a finite number >= 0"),
                     ({**d, "simulator_params": {"refractory_period_us": 1.5}}, "integer >= 0"),
                     ({**d, "simulator_params": {"bogus_hz": 1}}, "unknown simulator_params ['bogus_hz']")):
        q = tmp_path / "bad.json"
        q.write_text(json.dumps(bad))
        with pytest.raises(SensorProfileError, match=msg.replace("[", r"\[").replace("]", r"\]")):
            load_sensor_profile(q)
    q = tmp_path / "nan.json"
    q.write_text(json.dumps({**d, "simulator_params": {"shot_noise_rate_hz": float("nan")}}))  # NaN in the JSON
    with pytest.raises(SensorProfileError, match="shot_noise_rate_hz must be a finite number"):
        load_sensor_profile(q)
    q.write_text("{not json")
    with pytest.raises(SensorProfileError, match="not valid JSON"):
        load_sensor_profile(q)
    with pytest.raises(ValueError, match="unknown event-sensor preset"):
        sensor_preset("nonsense")
    with pytest.raises(ValueError, match="unknown built-in sensor profile"):
        sensor_preset("builtin:nope")
    with pytest.raises(SensorProfileError, match="cannot read"):
        sensor_preset(str(tmp_path / "missing.json"))


def test_simulator_fields_match_event_sensor_params():
    assert set(SIMULATOR_FIELDS) == {f.name for f in dataclasses.fields(EventSensorParams)}


def test_builtin_profile_and_cli_precedence():
    from hybridhdr.cli import build_parser
    from hybridhdr.simulate.cli import sensor_params
    p = sensor_preset("builtin:davis240c")
    prof = SensorProfile.from_dict(json.loads((__import__("pathlib").Path(__import__("hybridhdr").simulate.__file__)
                                               .with_name("profiles") / "davis240c_ecd.json").read_text()))
    assert p.contrast_threshold_on == prof.simulator_params["contrast_threshold_on"]
    assert p.refractory_period_us == 0  # not identified on the ECD excerpt: the ideal base keeps it off
    parser = build_parser()
    a = parser.parse_args(["simulate", "builtin:slow_static", "--out", "x.h5", "--sensor", "builtin:davis240c",
                           "--pos-thres", "0.3"])
    s = sensor_params(a)
    assert s.contrast_threshold_on == 0.3 and s.contrast_threshold_off == p.contrast_threshold_off
    a = parser.parse_args(["simulate", "builtin:slow_static", "--out", "x.h5", "--sensor", "builtin:davis240c",
                           "--preset", "clean"])
    s = sensor_params(a)
    assert s.refractory_period_us == 500 and s.shot_noise_rate_hz == p.shot_noise_rate_hz
    plain = parser.parse_args(["simulate", "builtin:slow_static", "--out", "x.h5"])
    assert sensor_params(plain) == sensor_preset("clean")  # without --sensor the default preset is unchanged


def test_ecd_profile(shared_data):
    path = shared_data("ecd_slider_depth")
    # the excerpt has two usable frame intervals: the next-frame criterion keeps falling as the log
    # offset grows, so the estimator must say that the recording does not bound I0 (never silently)
    with pytest.warns(GridEdgeWarning, match="log offset I0 .* upper edge"):
        prof = estimate_sensor_profile(path, n_boot=30)
    e = prof.estimates
    # identified: the threshold means, shot noise (and a leak consistent with 0); not: sigma (3 frame
    # intervals), refractory (the ISIs rise gradually from ~2.6 ms: a bound), photoreceptor, jitter
    assert e["contrast_threshold_on"]["identifiable"] and e["contrast_threshold_off"]["identifiable"]
    assert not e["threshold_mismatch_sigma"]["identifiable"]
    assert not e["refractory_period_us"]["identifiable"] and 2000 < e["refractory_period_us"]["upper_bound_us"] < 3500
    assert e["shot_noise_rate_hz"]["identifiable"] and 0.3 < e["shot_noise_rate_hz"]["value"] < 1.5
    # same seed, same profile (the bootstrap is seeded; nothing time-dependent is stored)
    with pytest.warns(GridEdgeWarning):
        assert estimate_sensor_profile(path, n_boot=30).to_dict() == prof.to_dict()
    # the shipped preset is the profile file shipped with the simulator (an earlier estimate on this
    # recording, kept fixed so that the synthetic suites do not move with the estimator): the preset
    # must be exactly that file's values, and the file must be a profile of this recording
    ship = sensor_preset("builtin:davis240c")
    shipped = json.loads((__import__("pathlib").Path(__import__("hybridhdr").simulate.__file__)
                          .with_name("profiles") / "davis240c_ecd.json").read_text())
    assert ship.contrast_threshold_on == shipped["simulator_params"]["contrast_threshold_on"]
    assert ship.shot_noise_rate_hz == shipped["simulator_params"]["shot_noise_rate_hz"]
    assert "ecd_slider_depth" in json.dumps(shipped.get("provenance", {}))


@pytest.mark.filterwarnings("ignore::hybridhdr.calibrate.camera_model.GridEdgeWarning")  # ECD: I0 unbounded (test_ecd_profile)
def test_cli_json_and_errors(shared_data, tmp_path, capsys):
    from hybridhdr.cli import main
    ecd = shared_data("ecd_slider_depth")
    out = tmp_path / "p" / "profile.json"
    assert main(["calibrate", "sensor", str(ecd), "--out", str(out), "--bootstrap", "20", "--json"]) == 0
    cap = capsys.readouterr()
    assert cap.out.count("\n") == 1
    obj = json.loads(cap.out)
    assert obj["written"] == str(out) and load_sensor_profile(out).simulator_params == obj["simulator_params"]
    assert obj["provenance"]["input"] == str(ecd) and obj["provenance"]["command"][0] == "hybridhdr"
    # a recording without frames: a clear error, nothing written
    bad_out = tmp_path / "none.json"
    # a recording that lacks what the verb needs is an input mismatch: a usage error (exit 2)
    assert main(["calibrate", "sensor", str(shared_data("aedat4/sample.aedat4")), "--out", str(bad_out)]) == 2
    assert "at least two frames; found 0" in capsys.readouterr().err and not bad_out.exists()
