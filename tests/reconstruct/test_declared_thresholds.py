"""Contrast thresholds a recording declares (CameraInfo.contrast_threshold_on/_off) are what the
reconstruction uses when it is given none; given ones and stored maps win."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hybridhdr.formats.container import RecordingFile, write_recording
from hybridhdr.model import CameraInfo, Metadata
from hybridhdr.reconstruct import reconstruct
from hybridhdr.simulate.procedural import procedural_recording


def test_camera_info_thresholds_validated_and_round_trip():
    c = CameraInfo(contrast_threshold_on=0.25, contrast_threshold_off=0.2)
    assert c.contrast_thresholds == (0.25, 0.2)
    assert CameraInfo(contrast_threshold_on=0.25).contrast_thresholds is None  # both or nothing
    assert "contrast_threshold_on" not in CameraInfo().to_dict()  # metadata without them unchanged
    assert CameraInfo.from_dict(c.to_dict()) == c
    for bad in (0.0, -0.1, float("nan"), float("inf"), True, "0.2"):
        with pytest.raises(ValueError, match="contrast_threshold_on"):
            CameraInfo(contrast_threshold_on=bad)


def _declaring(rec, on, off):
    md = dataclasses.replace(rec.metadata, event_camera=dataclasses.replace(
        rec.metadata.event_camera, contrast_threshold_on=on, contrast_threshold_off=off))
    return dataclasses.replace(rec, metadata=md)


def test_reconstruct_uses_the_declared_thresholds(tmp_path):
    rec, _ = procedural_recording((12, 16), 150_000)
    decl = _declaring(rec, 0.3, 0.2)
    write_recording(decl, tmp_path / "r.h5")
    times = np.array([50_000, 100_000], np.int64)
    with RecordingFile(tmp_path / "r.h5") as f:
        assert f.metadata.event_camera.contrast_thresholds == (0.3, 0.2)
    for src in (decl, tmp_path / "r.h5"):
        v = reconstruct(src, "akf", times_us=times)
        assert v.params["contrast_threshold_on"] == 0.3 and v.params["contrast_threshold_off"] == 0.2
        assert "declared by the recording" in v.info["thresholds"]
        # the same as giving them explicitly, bit for bit
        w = reconstruct(rec, "akf", {"contrast_threshold_on": 0.3, "contrast_threshold_off": 0.2}, times_us=times)
        assert w.frames.tobytes() == v.frames.tobytes()
    # given thresholds win; a recording without a declaration keeps the default
    g = reconstruct(decl, "akf", {"contrast_threshold": 0.15}, times_us=times)
    assert g.params["contrast_threshold"] == 0.15 and g.params["contrast_threshold_on"] is None
    assert "thresholds" not in g.info
    n = reconstruct(rec, "akf", times_us=times)
    assert n.params["contrast_threshold_on"] is None and "thresholds" not in n.info
    cf = reconstruct(decl, "cf", mode="causal", times_us=times)
    assert cf.params["contrast_threshold_on"] == 0.3


def test_old_simulated_files_declare_through_their_provenance():
    rec, _ = procedural_recording((12, 16), 150_000)
    prov = {"generator": "hybridhdr.simulate", "sensor": {"contrast_threshold_on": 0.22, "contrast_threshold_off": 0.18}}
    old = dataclasses.replace(rec, metadata=Metadata(rec.metadata.event_camera, rec.metadata.frame_camera,
                                                     provenance=prov))
    v = reconstruct(old, "akf", times_us=np.array([50_000], np.int64))
    assert (v.params["contrast_threshold_on"], v.params["contrast_threshold_off"]) == (0.22, 0.18)
    other = dataclasses.replace(rec, metadata=Metadata(provenance={**prov, "generator": "elsewhere"}))
    v = reconstruct(other, "akf", times_us=np.array([50_000], np.int64))
    assert v.params["contrast_threshold_on"] is None


def test_the_command_line_uses_the_declared_thresholds_unless_it_states_its_own(tmp_path, capsys):
    """`hybridhdr reconstruct` built a full Params from its flags, which the API counted as
    thresholds given: a recording's declared thresholds were ignored (c = 0.1 instead of 0.3)."""
    import json

    from hybridhdr.cli import main
    from hybridhdr.formats.images import read_exr
    rec, _ = procedural_recording((12, 16), 150_000)
    write_recording(_declaring(rec, 0.3, 0.2), tmp_path / "r.h5")
    write_recording(rec, tmp_path / "plain.h5")
    (tmp_path / "c.toml").write_text("contrast_threshold = 0.15\n")
    times = tmp_path / "t.txt"
    times.write_text("50000\n100000\n")

    def run(name, *extra, src="r.h5"):
        out = tmp_path / name
        assert main(["reconstruct", str(tmp_path / src), "--out", str(out), "--times-us", str(times),
                     "--no-progress", *extra]) == 0
        meta = json.loads((out / "run.json").read_text())
        return meta, np.stack([read_exr(f) for f in sorted(out.glob("*.exr"))])

    meta, imgs = run("declared")
    assert (meta["params"]["contrast_threshold_on"], meta["params"]["contrast_threshold_off"]) == (0.3, 0.2)
    assert "declared by the recording" in meta["thresholds"]
    want = reconstruct(tmp_path / "r.h5", "akf", times_us=np.array([50_000, 100_000], np.int64))
    assert imgs.tobytes() == want.frames.tobytes()
    for name, extra in (("flag", ("--contrast-threshold", "0.15")), ("set", ("--set", "contrast_threshold=0.15")),
                        ("config", ("--config", str(tmp_path / "c.toml")))):
        meta, _ = run(name, *extra)
        assert meta["params"]["contrast_threshold"] == 0.15 and meta["params"]["contrast_threshold_on"] is None, name
        assert meta["thresholds"] == "given on the command line", name
    meta, _ = run("preset", "--preset", "paper")  # a preset states no threshold: the declared ones apply
    assert meta["params"]["contrast_threshold_on"] == 0.3 and meta["params"]["saturation"] == "value"
    capsys.readouterr()
    meta, _ = run("plain", src="plain.h5")
    assert meta["params"]["contrast_threshold_on"] is None and meta["thresholds"].startswith("the method's default")
    assert "declares no contrast thresholds" in capsys.readouterr().err


def test_the_command_line_estimates_thresholds_with_auto(tmp_path):
    import json

    from hybridhdr.calibrate.thresholds import pooled_thresholds
    from hybridhdr.cli import main
    rec, _ = procedural_recording((48, 64), 600_000)  # ideal events at c = 0.2; declares nothing
    assert rec.metadata.event_camera.contrast_thresholds is None
    write_recording(rec, tmp_path / "r.h5")
    out = tmp_path / "o"
    assert main(["reconstruct", str(tmp_path / "r.h5"), "--out", str(out), "--fps", "50", "--no-exr",
                 "--no-progress", "--contrast-threshold", "auto"]) == 0
    meta = json.loads((out / "run.json").read_text())
    on, off, _ = pooled_thresholds(rec, intensity_offset=meta["params"]["intensity_offset"])
    assert (meta["params"]["contrast_threshold_on"], meta["params"]["contrast_threshold_off"]) == (on, off)
    assert meta["thresholds"].startswith("estimated from the recording")
    assert abs(on - 0.2) < 0.03 and abs(off - 0.2) < 0.03  # the simulated sensor's c (measured 0.207, 0.206)
    # a recording that cannot tell its thresholds (one frame) is a usage error, nothing written
    one = dataclasses.replace(rec, frames=rec.frames.select(np.array([0])))
    write_recording(one, tmp_path / "one.h5")
    assert main(["reconstruct", str(tmp_path / "one.h5"), "--out", str(tmp_path / "o1"), "--fps", "50",
                 "--no-exr", "--no-progress", "--contrast-threshold", "auto"]) == 2
    assert not (tmp_path / "o1").exists()
    # not with a per-pixel map as well, nor for a method without thresholds
    assert main(["reconstruct", str(tmp_path / "r.h5"), "--out", str(tmp_path / "o3"), "--no-exr", "--no-progress",
                 "--contrast-threshold", "auto", "--thresholds", str(tmp_path / "none.npz")]) == 2
    assert main(["reconstruct", str(tmp_path / "r.h5"), "--out", str(tmp_path / "o2"), "--method", "frames",
                 "--no-exr", "--no-progress", "--contrast-threshold", "auto"]) == 2
