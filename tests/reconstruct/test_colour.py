"""Colour event cameras (colour filter mosaic): the mosaic path of the reconstruction."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hybridhdr.reconstruct import reconstruct
from tests.reconstruct.data.make_mono_reference import RUNS, recordings

REFERENCE = Path(__file__).parent / "data" / "mono_reference.npz"


@pytest.fixture(scope="module")
def mono_recordings():
    return recordings()


@pytest.mark.parametrize("frames_kind", ["grey", "rgb"])
@pytest.mark.parametrize("method,mode,kw", RUNS, ids=[f"{m}-{mo}{'-aug' if kw else ''}" for m, mo, kw in RUNS])
def test_monochrome_outputs_unchanged(mono_recordings, frames_kind, method, mode, kw):
    """No CFA: every method gives, bit for bit, the outputs committed before the colour path
    existed (grey frames, and colour frames reduced to luminance)."""
    rec = mono_recordings[0 if frames_kind == "grey" else 1]
    key = f"{frames_kind}_{method}_{mode}" + ("_aug" if kw else "")
    with np.load(REFERENCE) as ref:
        want, want_t = ref[key], ref[key + "_t"]
    # the span the references were committed with (the default span is now the command line's:
    # up to the last event for the event methods, the last frame for the frames-only ones)
    v = reconstruct(rec, method, mode=mode, fps=100, t_end_us=int(want_t[-1]) + 1, **kw)
    assert v.frames.dtype == np.float32 and v.frames.shape == want.shape
    np.testing.assert_array_equal(v.t_us, want_t)
    assert v.frames.tobytes() == want.tobytes()


# -- the colour path ------------------------------------------------------------------------------

import dataclasses  # noqa: E402

from hybridhdr.camera.cfa import CFA_PATTERNS, channel_masks, mosaic  # noqa: E402
from hybridhdr.formats.container import write_recording  # noqa: E402
from hybridhdr.model import Frames  # noqa: E402


def _grey_as_colour(rec, pattern, frames="rgb"):
    """The grey recording as a colour camera would record a grey scene: same events, frames
    RGB with R = G = B (or the raw mosaic, which for grey is the grey frame)."""
    f = rec.frames
    if frames == "rgb":
        f = Frames(np.repeat(f.images[..., None], 3, axis=-1), f.t_start_us, f.t_end_us, encoding=f.encoding)
    ec = dataclasses.replace(rec.metadata.event_camera, cfa=pattern)
    fc = dataclasses.replace(rec.metadata.frame_camera, cfa=pattern)
    return dataclasses.replace(rec, frames=f, metadata=dataclasses.replace(rec.metadata, event_camera=ec,
                                                                         frame_camera=fc))


@pytest.mark.parametrize("method,mode,kw", RUNS, ids=[f"{m}-{mo}{'-aug' if kw else ''}" for m, mo, kw in RUNS])
def test_grey_scene_through_colour_path(mono_recordings, method, mode, kw):
    """A grey scene seen by a Bayer camera: at every pixel, its own channel of the colour output
    is the monochrome output, bit for bit, for every method (the filters run unchanged on the
    mosaic; demosaicking keeps each pixel's measurement)."""
    rec = mono_recordings[0]
    mono = reconstruct(rec, method, mode=mode, fps=100, **kw)
    pattern = CFA_PATTERNS[len(method) % 4]
    col = reconstruct(_grey_as_colour(rec, pattern), method, mode=mode, fps=100, **kw)
    assert col.is_colour and col.frames.shape == mono.frames.shape + (3,) and col.frames.dtype == np.float32
    np.testing.assert_array_equal(col.t_us, mono.t_us)
    assert mosaic(col.frames, pattern).tobytes() == mono.frames.tobytes()
    assert col.info["cfa"]["event"] == pattern and col.info["cfa"]["demosaic"] == "log_cubic"
    assert col.luminance().shape == mono.frames.shape


def test_cfa_argument_and_sources(mono_recordings, tmp_path):
    rec = mono_recordings[0]
    mono = reconstruct(rec, "akf", fps=100)
    # cfa= on a recording that declares none; raw-mosaic grey frames
    a = reconstruct(rec, "akf", fps=100, cfa="gbrg")
    assert mosaic(a.frames, "GBRG").tobytes() == mono.frames.tobytes()
    # "none" forces the monochrome path on a colour recording
    col = _grey_as_colour(rec, "RGGB")
    assert reconstruct(col, "akf", fps=100, cfa="none").frames.tobytes() == mono.frames.tobytes()
    # from a container path: the CFA comes from the stored metadata
    write_recording(col, tmp_path / "c.h5")
    b = reconstruct(tmp_path / "c.h5", "akf", fps=100, demosaic="edge_aware")
    assert b.info["cfa"] == {"event": "RGGB", "frames": "RGB frames, each pixel's RGGB channel",
                             "demosaic": "edge_aware"}
    assert mosaic(b.frames, "RGGB").tobytes() == mono.frames.tobytes()
    # grey frames of a colour event camera that declare no frame CFA are refused
    ec = dataclasses.replace(rec.metadata.event_camera, cfa="RGGB")
    bad = dataclasses.replace(rec, metadata=dataclasses.replace(rec.metadata, event_camera=ec))
    with pytest.raises(ValueError, match="declare the frames' CFA"):
        reconstruct(bad, "akf", fps=100)
    with pytest.raises(ValueError):
        reconstruct(rec, "akf", fps=100, cfa="RGBW")


def test_colour_edge_sweep_accuracy_and_no_bleeding():
    """benchmarks/colour.py in small: a Bayer camera on the band-limited colour edge sweep (a
    saturated red object, G = B = R/50, sweeping over a colour-textured background). The filter
    on its own channels is as accurate as the monochrome AKF on luminance; after demosaicking
    the RGB error is within 1.25x (measured 1.14x with the default log-bilinear demosaic; the
    demosaicking of the true radiance alone costs 0.83x); inside the red object G and B stay at
    their true level (no red leaks into them)."""
    from scipy.ndimage import binary_erosion

    from hybridhdr.simulate.procedural import colour_edge_sweep_recording

    def lr(x, t):
        e = np.log(np.maximum(x, 1e-6)) - np.log(t)
        return float(np.sqrt(np.mean(e * e)))
    col, scene = colour_edge_sweep_recording(0, cfa="RGGB", band_limited=True, duration_us=500_000)
    mono, _ = colour_edge_sweep_recording(0, cfa=None, band_limited=True, duration_us=500_000)
    tm = col.frames.t_mid_us
    times = np.arange(int(tm[0]), int(tm[-1]) + 1, 10_000, dtype=np.int64)
    tex = scene._tex()
    rgb = np.stack([scene.rgb(t, tex) for t in times])
    vm = reconstruct(mono, "akf", times_us=times, thresholds="input")  # the simulated sensor, not a calibration
    vc = reconstruct(col, "akf", times_us=times, thresholds="input")
    e_mono = lr(vm.frames, rgb @ np.array([0.2126, 0.7152, 0.0722]))
    assert lr(mosaic(vc.frames, "RGGB"), mosaic(rgb, "RGGB")) <= 1.0 * e_mono
    assert lr(vc.frames, rgb) <= 1.25 * e_mono
    inside = np.stack([binary_erosion(scene.object_mask(t), iterations=2) for t in times])
    assert inside.sum() > 1000
    for c in (1, 2):
        assert abs(vc.frames[..., c][inside].mean() / rgb[..., c][inside].mean() - 1) < 0.02
