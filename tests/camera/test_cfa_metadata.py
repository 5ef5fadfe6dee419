"""CameraInfo.cfa: validated, canonical, absent from monochrome metadata, kept by the container."""

from __future__ import annotations

import dataclasses

import pytest

from hybridhdr.formats.container import RecordingFile, write_recording
from hybridhdr.model import CameraInfo, Metadata
from hybridhdr.simulate.procedural import procedural_recording


def test_camera_info_cfa():
    assert CameraInfo(cfa="gbrg").cfa == "GBRG"
    assert CameraInfo(cfa="none").cfa is None
    assert "cfa" not in CameraInfo().to_dict()  # monochrome metadata unchanged
    with pytest.raises(ValueError):
        CameraInfo(cfa="RGBW")
    md = Metadata(CameraInfo(cfa="BGGR"), CameraInfo(cfa="RGGB"))
    assert Metadata.from_dict(md.to_dict()) == md


@pytest.mark.parametrize("ev_cfa,fr_cfa", [("RGGB", "RGGB"), ("GRBG", None), (None, None)])
def test_container_round_trip(tmp_path, ev_cfa, fr_cfa):
    rec, _ = procedural_recording((6, 8), 60_000)
    md = dataclasses.replace(rec.metadata, event_camera=dataclasses.replace(rec.metadata.event_camera, cfa=ev_cfa),
                             frame_camera=dataclasses.replace(rec.metadata.frame_camera, cfa=fr_cfa))
    write_recording(dataclasses.replace(rec, metadata=md), tmp_path / "r.h5")
    with RecordingFile(tmp_path / "r.h5") as f:
        assert f.metadata.event_camera.cfa == ev_cfa and f.metadata.frame_camera.cfa == fr_cfa
        assert f.read().metadata.event_camera.cfa == ev_cfa
