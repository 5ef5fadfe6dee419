"""simulate's ``cfa`` option: a Bayer event sensor and frame camera on an RGB source."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.camera.cfa import CFA_PATTERNS, channel_index
from hybridhdr.simulate.camera import FrameCameraParams
from hybridhdr.simulate.pipeline import simulate, simulate_to_file
from tests.simulate._sources import BlobSource


class RedBlobSource(BlobSource):
    """The blob in red only: G and B are a static grey, so only R pixels see any change."""

    def render(self, t_us):
        r = super().render(t_us).astype(np.float64)
        g = np.full_like(r, self.background)
        return np.stack([r, g, 0.5 * g], axis=-1).astype(np.float32)


CAM = FrameCameraParams(frame_rate_hz=50.0, exposure_us=2_000)


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_red_blob_fires_only_red_pixels(pattern):
    src = RedBlobSource(height=12, width=16, duration_us=60_000, speed_px_s=60.0)
    res = simulate(src, sensor="ideal", camera=CAM, progress=False, cfa=pattern)
    rec = res.recording
    ev = rec.events
    assert len(ev) > 100
    ch = channel_index(pattern, (12, 16))
    assert set(np.unique(ch[ev["y"], ev["x"]])) == {0}  # every event at a red pixel
    assert rec.frames.images.ndim == 3  # the raw mosaic
    assert rec.hdr.images.shape[1:] == (12, 16, 3)
    assert rec.metadata.event_camera.cfa == pattern and rec.metadata.frame_camera.cfa == pattern
    assert rec.metadata.provenance["source"]["cfa"] == pattern
    # G and B pixels of the frames see the static grey: the same code in every frame
    for c in (1, 2):
        px = rec.frames.images[:, ch == c]
        assert (px == px[0]).all()


def test_grey_source_through_bayer_equals_mono(tmp_path):
    """A grey scene through a Bayer filter is the monochrome simulation, bit for bit (the mosaic
    of a grey image is that image); only the metadata names the pattern."""
    mono = simulate(BlobSource(height=10, width=12, duration_us=40_000), sensor="clean", camera=CAM,
                    progress=False, seed=3).recording
    col = simulate(BlobSource(height=10, width=12, duration_us=40_000), sensor="clean", camera=CAM,
                   progress=False, seed=3, cfa="GRBG").recording
    for k in ("t", "x", "y", "p"):
        assert np.array_equal(mono.events[k], col.events[k])
    assert mono.frames.images.tobytes() == col.frames.images.tobytes()
    assert mono.metadata.event_camera.cfa is None and col.metadata.event_camera.cfa == "GRBG"
    res = simulate_to_file(RedBlobSource(height=10, width=12, duration_us=40_000), tmp_path / "c.h5",
                           sensor="ideal", camera=CAM, progress=False, cfa="RGGB")
    from hybridhdr.formats.container import RecordingFile
    with RecordingFile(res.path) as f:
        assert f.metadata.event_camera.cfa == "RGGB" and f.metadata.frame_camera.cfa == "RGGB"
        assert f.read().hdr.images.shape[-1] == 3
        # the sensor's nominal thresholds are stated, for the reconstruction to use
        assert f.metadata.event_camera.contrast_thresholds == (0.2, 0.2)
        assert f.metadata.frame_camera.contrast_thresholds is None
