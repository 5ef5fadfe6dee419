"""ECD folders of colour images and the colour filter arrays of ``cfa.txt``."""

from __future__ import annotations

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.errors import FormatError

SS = hh.SensorSize(20, 30)


def _events(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return hh.make_events(np.sort(rng.integers(0, 1_000_000, n)), rng.integers(0, SS.width, n),
                          rng.integers(0, SS.height, n), rng.integers(0, 2, n))


def _folder(tmp_path, images, name="seq", metadata=None):
    fr = hh.Frames(images, [10, 20], [10, 20])
    p = tmp_path / name
    hh.write(hh.Recording(_events(), SS, fr, metadata=metadata or hh.Metadata()), p, "ecd")
    return p


def test_rgb_images_give_rgb_frames_and_no_pattern(tmp_path):
    rgb = np.random.default_rng(1).integers(0, 256, (2,) + SS.shape + (3,), dtype=np.uint8)
    p = _folder(tmp_path, rgb)
    assert not (p / "cfa.txt").exists()
    with hh.open_reader(p) as r:
        md = r.metadata
        fr = r.read_frames()
    np.testing.assert_array_equal(fr.images, rgb)
    assert md.frame_camera.cfa is None and md.event_camera.cfa is None
    assert md.provenance["frame_colour"].startswith("rgb")
    assert "--cfa" in md.provenance["cfa_source"]


def test_grey_images_declare_nothing(tmp_path):
    grey = np.random.default_rng(2).integers(0, 256, (2,) + SS.shape, dtype=np.uint8)
    p = _folder(tmp_path, grey)
    md = hh.open_reader(p).metadata
    assert md.frame_camera.cfa is None and md.event_camera.cfa is None
    assert md.provenance["frame_colour"].startswith("grey")


def test_sample_folder_is_grey(shared_data):
    md = hh.open_reader(shared_data("ecd_slider_depth")).metadata
    assert md.provenance["frame_colour"].startswith("grey")
    assert md.event_camera.cfa is None and md.frame_camera.cfa is None


@pytest.mark.parametrize("event_cfa,frame_cfa", [("RGGB", "RGGB"), ("GBRG", None), (None, "BGGR")])
def test_cfa_round_trip_through_ecd_and_the_container(tmp_path, event_cfa, frame_cfa):
    from hybridhdr.formats.container import RecordingFile, write_recording
    mosaic = np.random.default_rng(3).integers(0, 256, (2,) + SS.shape, dtype=np.uint8)
    md = hh.Metadata(event_camera=hh.CameraInfo(SS, cfa=event_cfa), frame_camera=hh.CameraInfo(SS, cfa=frame_cfa))
    p = _folder(tmp_path, mosaic, metadata=md)
    assert (p / "cfa.txt").read_text() == (f"event_camera {event_cfa or 'none'}\n"
                                           f"frame_camera {frame_cfa or 'none'}\n")
    rec = hh.read(p)
    assert rec.metadata.event_camera.cfa == event_cfa and rec.metadata.frame_camera.cfa == frame_cfa
    assert "cfa.txt" in rec.metadata.provenance["cfa_source"]
    out = write_recording(rec, tmp_path / "r.h5")
    with RecordingFile(out) as f:
        assert f.metadata.event_camera.cfa == event_cfa and f.metadata.frame_camera.cfa == frame_cfa
        np.testing.assert_array_equal(f.read_frames().images, mosaic)


@pytest.mark.parametrize("text,match", [
    ("event_camera RGGX\n", "unknown colour filter array 'RGGX'"),
    ("camera RGGB\n", "expected '<camera> <pattern>'"),
    ("event_camera\n", "expected '<camera> <pattern>'"),
    ("event_camera RGGB\nevent_camera BGGR\n", "event_camera given twice"),
    ("frame_camera \xff\n", "expected '<camera> <pattern>'"),
])
def test_bad_cfa_file(tmp_path, text, match):
    grey = np.zeros((2,) + SS.shape, np.uint8)
    p = _folder(tmp_path, grey)
    (p / "cfa.txt").write_bytes(text.encode("latin-1"))
    with pytest.raises(FormatError, match=match):
        hh.open_reader(p)


def test_cfa_file_comments_and_case(tmp_path):
    p = _folder(tmp_path, np.zeros((2,) + SS.shape, np.uint8))
    (p / "cfa.txt").write_text("# written by hand\n\nframe_camera grbg  # lower case\n")
    md = hh.open_reader(p).metadata
    assert md.frame_camera.cfa == "GRBG" and md.event_camera.cfa is None
    (p / "cfa.txt").write_bytes(b"#" * 5000)
    with pytest.raises(FormatError, match="a cfa.txt holds two short lines"):
        hh.open_reader(p)
