"""The one thresholds resolver: what each choice gives, where it comes from, and that the words
and keys are written once in the package."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from hybridhdr.calibrate.resolve import (DEFAULT_THRESHOLDS, THRESHOLD_KEYS, THRESHOLD_WORDS, ResolvedThresholds,
                                         declared_thresholds, recording_declares_thresholds, resolve_thresholds,
                                         thresholds_stated)
from hybridhdr.formats.container import RecordingFile, store_thresholds, write_recording
from hybridhdr.simulate.procedural import edge_sweep_recording, procedural_recording

PACKAGE = Path(__file__).resolve().parents[2] / "hybridhdr"


def _declaring(rec, on, off):
    md = dataclasses.replace(rec.metadata, event_camera=dataclasses.replace(
        rec.metadata.event_camera, contrast_threshold_on=on, contrast_threshold_off=off))
    return dataclasses.replace(rec, metadata=md)


def _bare(rec):
    """The recording without any threshold declaration (the simulator states its sensor's)."""
    from hybridhdr.model import Metadata
    return dataclasses.replace(rec, metadata=Metadata(dataclasses.replace(
        rec.metadata.event_camera, contrast_threshold_on=None, contrast_threshold_off=None),
        rec.metadata.frame_camera))


def test_the_words_and_keys_are_written_once():
    """No module but calibrate/resolve.py spells the four words or the three keys as a tuple."""
    words, keys = set(THRESHOLD_WORDS), set(THRESHOLD_KEYS)
    found = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.Tuple, ast.List, ast.Set)) and all(
                    isinstance(e, ast.Constant) for e in node.elts):
                vals = {e.value for e in node.elts}
                if vals in (words, keys) and path.name != "resolve.py":
                    found.append(f"{path.relative_to(PACKAGE)}:{node.lineno}")
    assert not found, found
    assert DEFAULT_THRESHOLDS in THRESHOLD_WORDS


def test_input_takes_the_declared_thresholds_unless_the_params_state_them():
    rec, _ = procedural_recording((12, 16), 150_000)
    decl = _declaring(rec, 0.3, 0.2)
    got = resolve_thresholds(decl, "input")
    assert (got.source, got.c_on, got.c_off, got.maps) == ("declared", 0.3, 0.2, None)
    assert got.note == "declared by the recording: ON 0.3, OFF 0.2 (log units)"
    assert got.overrides() == {"contrast_threshold_on": 0.3, "contrast_threshold_off": 0.2}
    assert resolve_thresholds(decl, "input", stated=True).source == "params"
    bare = resolve_thresholds(_bare(rec), "input")
    assert bare.source == "params" and bare.overrides() == {} and bare.note is None
    assert recording_declares_thresholds(decl) and not recording_declares_thresholds(_bare(rec))
    assert resolve_thresholds(decl, "params").source == "params"


def test_a_stored_map_wins_even_over_stated_params(tmp_path):
    from hybridhdr.formats.thresholds import ThresholdMap
    rec, _ = procedural_recording((12, 16), 150_000)
    write_recording(_bare(rec), tmp_path / "r.h5")
    c_on = np.full((12, 16), 0.21)
    c_off = np.full((12, 16), 0.17)
    store_thresholds(tmp_path / "r.h5", ThresholdMap(c_on=c_on, c_off=c_off, fallback_on=0.2, fallback_off=0.3))
    with RecordingFile(tmp_path / "r.h5") as f:
        for stated in (False, True):
            got = resolve_thresholds(f, "input", stated=stated)
            assert got.source == "stored" and got.note == "per-pixel map stored in the recording"
            assert np.array_equal(got.maps[0], c_on) and np.array_equal(got.maps[1], c_off)
        assert resolve_thresholds(f, "input", maps=False).source == "params"
        assert recording_declares_thresholds(f)


def test_a_map_choice():
    pair = (np.full((2, 3), 0.2), np.full((2, 3), 0.25))
    got = resolve_thresholds(None, pair)
    assert got.source == "map" and got.maps[1][0, 0] == 0.25 and got.overrides() == {}
    assert resolve_thresholds(None, {"c_on": pair[0], "c_off": pair[1]}).maps[0][1, 2] == 0.2
    with pytest.raises(ValueError, match="not a thresholds .npz file"):
        resolve_thresholds(None, "no/such/thresholds.npz")  # a str that is no word is a path
    with pytest.raises(TypeError, match="thresholds must be a threshold map"):
        resolve_thresholds(None, 0.2)


def test_auto_is_the_pooled_estimate():
    from hybridhdr.calibrate.thresholds import pooled_thresholds
    rec, _ = edge_sweep_recording(0, duration_us=300_000)
    got = resolve_thresholds(rec, "auto", intensity_offset=1e-3)
    on, off, record = pooled_thresholds(rec, intensity_offset=1e-3)
    assert (got.source, got.c_on, got.c_off, got.record) == ("auto", on, off, record)
    assert got.frame_time_offset_us == 0 and got.intensity_offset is None
    assert got.note.startswith("estimated from the recording: ON ")


def test_selfcal_is_the_self_calibration():
    from hybridhdr.calibrate.selfcal import self_calibration
    rec, _ = edge_sweep_recording(0, duration_us=400_000)
    rec = _bare(rec)
    cal = self_calibration(rec)
    got = resolve_thresholds(rec, "selfcal")
    assert (got.c_on, got.c_off, got.intensity_offset) == (cal["c_on"], cal["c_off"], cal["intensity_offset"])
    assert got.frame_time_offset_us == cal["time_offset_us"] and got.record["r2"] == cal["r2"]
    assert got.note.startswith("self-calibrated from the recording: frames stand for their stamp")
    assert set(got.overrides()) == {"contrast_threshold_on", "contrast_threshold_off", "intensity_offset"}
    own = resolve_thresholds(rec, "selfcal", intensity_offset=1.0)  # a fixed log model: I0 not replaced
    assert own.intensity_offset is None and "ln(I + 1)" in own.note
    assert set(own.overrides()) == {"contrast_threshold_on", "contrast_threshold_off"}


def test_selfcal_on_a_recording_that_cannot_tell_raises():
    rec, _ = procedural_recording((12, 16), 60_000)
    short = dataclasses.replace(rec, frames=rec.frames.select(slice(0, 1)))
    with pytest.raises(ValueError):
        resolve_thresholds(short, "selfcal")


def test_result_is_frozen_and_helpers():
    r = ResolvedThresholds("params")
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.source = "auto"
    assert not thresholds_stated(None) and not thresholds_stated({"cutoff_hz": 1.0})
    assert thresholds_stated({"contrast_threshold": 0.2}) and thresholds_stated("akf.toml")
    assert declared_thresholds(object()) is None
