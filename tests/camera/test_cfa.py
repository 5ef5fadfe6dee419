"""CFA pattern handling for all four Bayer layouts: names, channels, mosaic, demosaic."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.camera.cfa import (CFA_PATTERNS, DEMOSAIC_METHODS, channel_index, channel_masks, crop_pattern,
                                  demosaic, mosaic, mosaic_frames, parse_cfa)
from hybridhdr.model import Frames

TILES = {"RGGB": [[0, 1], [1, 2]], "BGGR": [[2, 1], [1, 0]], "GRBG": [[1, 0], [2, 1]], "GBRG": [[1, 2], [0, 1]]}


def test_parse():
    assert parse_cfa(" rggb ") == "RGGB"
    for n in (None, "", "none", "NONE", "mono"):
        assert parse_cfa(n) is None
    for bad in ("RGBG", "RGB", "xyz", 3):
        with pytest.raises(ValueError):
            parse_cfa(bad)


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_channel_layout(pattern):
    ch = channel_index(pattern, (5, 7))  # odd sizes: partial tiles at the far edges
    assert ch.shape == (5, 7)
    for y in range(5):
        for x in range(7):
            assert ch[y, x] == TILES[pattern][y % 2][x % 2]
    m = channel_masks(pattern, (4, 6))
    assert m.sum(axis=2).tolist() == np.ones((4, 6), int).tolist()
    assert m[..., 1].sum() == 12 and m[..., 0].sum() == 6 and m[..., 2].sum() == 6
    # the tile read from (0, 0) spells the name
    assert "".join("RGB"[c] for c in ch[:2, :2].ravel()) == pattern


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_crop_pattern(pattern):
    ch = channel_index(pattern, (6, 6))
    for y0 in range(2):
        for x0 in range(2):
            assert np.array_equal(channel_index(crop_pattern(pattern, y0, x0), (4, 4)), ch[y0:y0 + 4, x0:x0 + 4])


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_mosaic_takes_own_channel(pattern):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (3, 6, 8, 3)).astype(np.uint8)
    m = mosaic(rgb, pattern)
    assert m.shape == (3, 6, 8) and m.dtype == np.uint8
    ch = channel_index(pattern, (6, 8))
    yy, xx = np.mgrid[0:6, 0:8]
    assert np.array_equal(m, rgb[:, yy, xx, ch])
    assert np.array_equal(mosaic(rgb[0], pattern), m[0])


@pytest.mark.parametrize("method", DEMOSAIC_METHODS)
@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_demosaic_flat_and_own_channel(pattern, method):
    # a flat colour is reproduced exactly everywhere, borders included
    rgb = np.broadcast_to(np.array([0.3, 2.0, 0.05], np.float32), (7, 9, 3))
    out = demosaic(mosaic(rgb, pattern), pattern, method)
    assert out.dtype == np.float32 and out.shape == (7, 9, 3)
    np.testing.assert_allclose(out, rgb, rtol=1e-6)
    # each pixel's own channel is the measurement, bit for bit
    rng = np.random.default_rng(1)
    m = rng.lognormal(0, 2, (2, 7, 9)).astype(np.float32)
    d = demosaic(m, pattern, method)
    assert np.array_equal(mosaic(d, pattern), m)
    assert (d > 0).all()


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_demosaic_linear_ramp(pattern):
    # bilinear interpolation is exact on a linear ramp away from the border
    yy, xx = np.mgrid[0:10, 0:12].astype(np.float64)
    rgb = np.stack([1 + xx, 2 + yy, 3 + xx + yy], axis=-1)
    out = demosaic(mosaic(rgb, pattern), pattern, "bilinear")
    np.testing.assert_allclose(out[1:-1, 1:-1], rgb[1:-1, 1:-1], rtol=1e-6)


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_log_cubic_exact_on_quadratic_log_intensity(pattern):
    # Keys' cubic reproduces polynomials up to degree 2 (tensor products too), G along rows and
    # columns and the log ratios R/G, B/G on their quarter grid: a radiance whose log is quadratic
    # in x and y is recovered exactly away from the border (6 pixels: the cubic reaches 3 pixels,
    # and the ratios at R and B sites use G interpolated 3 pixels further); bilinear is not
    yy, xx = np.mgrid[0:20, 0:22].astype(np.float64) / 8.0
    logs = [0.5 + xx - 0.7 * yy + 0.9 * xx * xx, -1 + 0.4 * yy * yy + xx * yy, 2 - xx * xx + 0.3 * yy]
    rgb = np.exp(np.stack(logs, axis=-1))
    out = demosaic(mosaic(rgb, pattern), pattern, "log_cubic")
    inner = (slice(6, -6), slice(6, -6))
    np.testing.assert_allclose(out[inner], rgb[inner], rtol=1e-5)
    lb = demosaic(mosaic(rgb, pattern), pattern, "log_bilinear")
    assert np.abs(np.log(lb[inner]) - np.log(rgb[inner])).max() > 1e-3


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_edge_aware_keeps_a_vertical_edge(pattern):
    rgb = np.ones((8, 10, 3))
    rgb[:, 5:] = 100.0  # grey edge: 1 | 100
    b = demosaic(mosaic(rgb, pattern), pattern, "bilinear")
    e = demosaic(mosaic(rgb, pattern), pattern, "edge_aware")
    err = lambda o: np.abs(np.log(o[1:-1]) - np.log(rgb[1:-1])).max()  # noqa: E731
    assert err(e) < 1e-6 < err(b)


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_mosaic_frames(pattern):
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, (2, 4, 6, 3)).astype(np.uint8)
    f = Frames(rgb, [0, 10], [5, 15], encoding="srgb")
    m = mosaic_frames(f, pattern)
    assert m.images.dtype == np.uint8 and m.encoding == "srgb" and np.array_equal(m.images, mosaic(rgb, pattern))
    raw = Frames(m.images, [0, 10], [5, 15], encoding="raw")
    assert mosaic_frames(raw, pattern, pattern) is raw
    with pytest.raises(ValueError, match="declare"):
        mosaic_frames(raw, pattern, None)
    other = next(p for p in CFA_PATTERNS if p != pattern)
    flat = Frames(mosaic(np.broadcast_to(np.array([10.0, 20.0, 30.0]), (1, 4, 6, 3)), other), [0], [5])
    np.testing.assert_allclose(mosaic_frames(flat, pattern, other).images,
                               mosaic(np.broadcast_to(np.array([10.0, 20.0, 30.0]), (1, 4, 6, 3)), pattern))
