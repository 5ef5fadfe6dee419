"""Dataset sessions: layout, manifest checksums, references, verification."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hybridhdr.formats.brackets import write_bracket_set
from hybridhdr.capture.session import create_session, sha256_file, verify_session
from hybridhdr.formats.container import write_recording
from hybridhdr.simulate.procedural import procedural_recording


@pytest.fixture
def parts(tmp_path):
    rec, _ = procedural_recording(duration_us=60_000, seed=1)
    write_recording(rec, tmp_path / "rec.h5")
    (tmp_path / "calib.json").write_text('{"R": [[1,0,0],[0,1,0],[0,0,1]]}')
    (tmp_path / "profile.json").write_text('{"contrast_threshold": 0.2}')
    imgs = [np.full((4, 5), v, np.uint8) for v in (10, 40, 160)]
    write_bracket_set(tmp_path / "br_A", imgs, [0.001, 0.004, 0.016], encoding="gamma")
    return tmp_path, rec


def test_create_and_verify(parts):
    d, rec = parts
    out = create_session(d / "seq01", d / "rec.h5", calibration=d / "calib.json",
                         camera_profile=d / "profile.json", brackets=[d / "br_A"], notes="test")
    m = json.loads((out / "manifest.json").read_text())
    assert m["format"] == "hybridhdr-session" and m["recording"] == "recording.h5"
    assert m["calibration"] == "calibration/calib.json" and m["camera_profile"] == "profile/profile.json"
    assert m["brackets"] == ["brackets/br_A"] and m["summary"]["events"] == len(rec.events)
    paths = {e["path"]: e for e in m["files"]}
    assert {"recording.h5", "brackets/br_A/brackets.json", "brackets/br_A/exp_000.png"} <= set(paths)
    assert paths["recording.h5"]["sha256"] == sha256_file(d / "rec.h5")  # a byte-exact copy
    assert paths["calibration/calib.json"]["size"] == (d / "calib.json").stat().st_size
    res = verify_session(out)
    assert res["ok"] and res["checked"] == len(m["files"]) and not res["unlisted"]
    assert not (d / "seq01.partial").exists()
    # tamper: one changed byte, one deleted file, one extra file
    p = out / "brackets/br_A/exp_001.png"
    b = bytearray(p.read_bytes())
    b[-1] ^= 1
    p.write_bytes(bytes(b))
    (out / "profile/profile.json").unlink()
    (out / "stray.txt").write_text("x")
    res = verify_session(out)
    assert not res["ok"] and res["missing"] == ["profile/profile.json"]
    assert res["changed"] == [{"path": "brackets/br_A/exp_001.png", "why": "sha256 differs"}]
    assert res["unlisted"] == ["stray.txt"]


def test_referenced_calibration(parts):
    d, _ = parts
    out = create_session(d / "sessions" / "seq02", d / "rec.h5", calibration=d / "calib.json", reference=True)
    m = json.loads((out / "manifest.json").read_text())
    assert m["calibration"] == "../../calib.json" and not (out / "calibration").exists()
    assert verify_session(out)["ok"]
    (d / "calib.json").write_text("{}")  # the shared calibration changed after the session was made
    res = verify_session(out)
    assert not res["ok"] and res["changed"][0]["path"] == "../../calib.json"


def test_errors(parts):
    d, _ = parts
    with pytest.raises(FileNotFoundError, match="recording not found"):
        create_session(d / "s", d / "nope.h5")
    with pytest.raises(ValueError, match="not a bracket-set folder"):
        create_session(d / "s", d / "rec.h5", brackets=[d])
    create_session(d / "s", d / "rec.h5")
    with pytest.raises(FileExistsError):
        create_session(d / "s", d / "rec.h5")
    with pytest.raises(FileNotFoundError, match="no manifest.json"):
        verify_session(d)
