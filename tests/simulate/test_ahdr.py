"""AHDR builder: image readers, image-motion source, artificial saturation, real data."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridhdr.errors import FormatError
from hybridhdr.simulate import _kernels as K
from hybridhdr.simulate.ahdr import (AHDR_SATURATION, ImageMotionSource, ImageSequenceSource, MotionParams,
                                     build_ahdr, load_linear_image, read_rgbe)


def _rgbe_bytes(rgb, rle: bool) -> bytes:
    """Tiny test encoder of Radiance RGBE (flat or new-style RLE with literal runs only plus one
    repeated run per channel)."""
    h, w, _ = rgb.shape
    m = rgb.max(axis=2)
    e = np.where(m > 0, np.floor(np.log2(np.maximum(m, 1e-30))) + 1, 0).astype(int)
    mant = np.where(m[..., None] > 0, np.floor(rgb / np.ldexp(1.0, e)[..., None] * 256), 0).astype(np.uint8)
    px = np.concatenate([mant, np.where(m > 0, e + 128, 0).astype(np.uint8)[..., None]], axis=2)
    out = bytearray(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {h} +X {w}\n".encode())
    for y in range(h):
        if not rle:
            out += px[y].tobytes()
            continue
        out += bytes([2, 2, w >> 8, w & 255])
        for c in range(4):
            row = px[y, :, c]
            out += bytes([128 + 3, row[0]])  # a run of 3 equal values (the test rows start so)
            rest = row[3:]
            for i in range(0, len(rest), 128):
                chunk = rest[i:i + 128]
                out += bytes([len(chunk)]) + chunk.tobytes()
    return bytes(out)


@pytest.mark.parametrize("rle", [False, True])
def test_read_rgbe_roundtrip(tmp_path, rle):
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.01, 500.0, (5, 140, 3))
    rgb[:, 1:3] = rgb[:, :1]  # first three pixels equal (encoded as a run)
    p = tmp_path / "x.hdr"
    p.write_bytes(_rgbe_bytes(rgb, rle))
    im = read_rgbe(p)
    assert im.shape == (5, 140, 3) and im.dtype == np.float32
    # RGBE keeps 8 mantissa bits of the largest channel: relative error <= 1/256 of that channel
    assert np.all(np.abs(im - rgb) <= rgb.max(axis=2, keepdims=True) / 256 + 1e-6)
    bad = tmp_path / "bad.hdr"
    bad.write_bytes(_rgbe_bytes(rgb, rle)[:-40])
    with pytest.raises(FormatError, match="truncated"):
        read_rgbe(bad)
    notrgbe = tmp_path / "n.hdr"
    notrgbe.write_bytes(b"hello\n\n-Y 1 +X 1\n0000")
    with pytest.raises(FormatError, match="signature"):
        read_rgbe(notrgbe)


def test_decode_rgbe_kernel_matches_py_func(tmp_path):
    rng = np.random.default_rng(1)
    rgb = rng.uniform(0.1, 10.0, (3, 20, 3))
    rgb[:, 1:3] = rgb[:, :1]
    raw = np.frombuffer(_rgbe_bytes(rgb, True), np.uint8)
    start = raw.tobytes().find(b"+X 20\n") + 6
    a, b = np.zeros((3, 20, 4), np.uint8), np.zeros((3, 20, 4), np.uint8)
    assert K.decode_rgbe(raw, start, 3, 20, a) == K.decode_rgbe.py_func(raw, start, 3, 20, b) == len(raw)
    np.testing.assert_array_equal(a, b)


def test_image_motion_source_pan_and_exact_speed_bound():
    # a horizontal ramp image; pure pan of 20 px with the cosine profile over 1 s: the view
    # moves by s(t) * 20 px; the speed bound is pi/2 * 20 px/s at mid-time (the true maximum)
    img = np.tile(np.linspace(1.0, 5.0, 400, dtype=np.float32), (300, 1))
    src = ImageMotionSource(img, (30, 40), duration_us=1_000_000, motion=MotionParams(pan_x_px=20.0, view_fraction=0.5),
                            radiance_scale=1.0)
    a, b = src.render(0), src.render(1_000_000)
    # the resampled ramp has slope 4/399 per source px * (resample factor f) per image px
    f = 0.5 * min(300 / 30, 400 / 40)
    slope = 4.0 / 399 * f
    np.testing.assert_allclose((b - a)[5:-5, 5:-5], 20 * slope, rtol=1e-3)
    assert src.max_image_speed_px_per_s(0, 1_000_000) == pytest.approx(math.pi / 2 * 20)
    assert src.max_image_speed_px_per_s(0, 1000) < 1.0  # at rest at the start
    z = ImageMotionSource(img, (30, 40), duration_us=500_000,
                          motion=MotionParams(pan_x_px=0, zoom=1.5, rotation_deg=10, view_fraction=0.5))
    # numerical check: the sensor corner's image-plane speed never exceeds the bound
    for t in range(0, 500_000, 50_000):
        m0, m1 = z._affine(t), z._affine(t + 1000)
        corner = np.array([0.0, 0.0, 1.0])
        # image point under the corner at t, where is it on the sensor at t + 1 ms?
        p = m0 @ corner
        a1 = np.vstack([m1, [0, 0, 1]])
        q = np.linalg.solve(a1, np.append(p, 1.0))[:2]
        v = np.hypot(*q) / 1e-3
        assert v <= z.max_image_speed_px_per_s(t, t + 1000) * 1.001 + 1e-9


def test_build_ahdr_saturates_frames_and_keeps_hdr_reference():
    yy, xx = np.mgrid[0:120, 0:160]
    img = np.exp(3.0 * np.sin(xx / 7.0) * np.cos(yy / 9.0)).astype(np.float32)  # e^±3: 8.7 stops
    rec = build_ahdr(img, sensor_size=(40, 50), duration_us=120_000, frame_rate_hz=25, exposure_us=5000,
                     motion=MotionParams(pan_x_px=10), sensor="ideal", seed=1)
    f = rec.frames
    assert len(f) == 3 and f.images.dtype == np.uint8 and f.encoding == "unknown"
    assert f.images.min() == AHDR_SATURATION[0] and f.images.max() == AHDR_SATURATION[1]
    # both clips are active on a sizeable share of the pixels (the point of AHDR)
    assert (f.images == 100).mean() > 0.05 and (f.images == 160).mean() > 0.05
    np.testing.assert_array_equal(rec.hdr.t_us, f.t_mid_us)
    src = ImageMotionSource(img, (40, 50), duration_us=120_000, motion=MotionParams(pan_x_px=10))
    np.testing.assert_array_equal(rec.hdr.images[1], src.render(int(f.t_mid_us[1])))
    assert rec.n_events > 100
    assert tuple(rec.metadata.provenance["camera"]["code_clip"]) == (100, 160)


def test_image_sequence_source_interpolates(tmp_path):
    a = np.full((8, 10), 1.0, np.float32)
    b = np.full((8, 10), 3.0, np.float32)
    s = ImageSequenceSource([a, b, a], frame_rate_hz=10, radiance_scale=1.0)
    assert s.duration_us == 200_000
    np.testing.assert_allclose(s.render(50_000), 2.0)
    np.testing.assert_allclose(s.render(150_000), 2.0)
    assert math.isinf(s.max_image_speed_px_per_s(0, 10))


def test_ahdr_on_real_memorial_png(shared_data):
    # a real well-exposed image (memorial0068.png, 1/4 s) linearised with sRGB, panned and
    # zoomed over 100 ms on a 60x80 sensor
    p = shared_data("brackets/memorial/memorial0068.png")
    im = load_linear_image(p)
    assert im.shape == (768, 512, 3) and 0 <= im.min() and im.max() <= 1
    rec = build_ahdr(p, sensor_size=(60, 80), duration_us=100_000, frame_rate_hz=20, exposure_us=5000,
                     motion=MotionParams(pan_x_px=8, zoom=1.05), sensor="clean", seed=0)
    assert len(rec.frames) == 2 and rec.n_events > 500
    assert rec.frames.images.min() >= 100 and rec.frames.images.max() == 160
    assert len(rec.hdr) == 2 and rec.hdr.images.dtype == np.float32
