"""Bracket-set folders: brackets.json round trip, list files, EXIF, RAW errors, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hybridhdr.formats.brackets import (BracketSet, colour_mask, exif_exposure_s, parse_exposure,
                                        read_bracket_set, write_bracket_set)
from hybridhdr.errors import FormatError


def _imgs(k=3, shape=(12, 16, 3), dtype=np.uint8, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype) for _ in range(k)]


def test_roundtrip_json(tmp_path):
    imgs = _imgs()
    out = write_bracket_set(tmp_path / "b", imgs, [0.001, 0.004, 0.016], encoding="gamma",
                            camera={"name": "cam"}, iso=[100, 100, 100], t_us=[0, 10, 20])
    assert not (tmp_path / "b.partial").exists()
    d = json.loads((out / "brackets.json").read_text())
    assert d["format"] == "hybridhdr-brackets" and d["camera"]["bit_depth"] == 8
    bs = read_bracket_set(out)
    assert bs.encoding == "gamma" and bs.files == ["exp_000.png", "exp_001.png", "exp_002.png"]
    np.testing.assert_array_equal(bs.exposures_s, [0.001, 0.004, 0.016])
    np.testing.assert_array_equal(bs.t_us, [0, 10, 20])
    assert bs.gain is None
    for a, b in zip(imgs, bs.images):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(FileExistsError):
        write_bracket_set(out, imgs, [1, 2, 3], encoding="gamma")


def test_uint16_raw_linear_stack(tmp_path):
    imgs = [np.full((4, 5), v, np.uint16) for v in (64, 576, 1023)]
    out = write_bracket_set(tmp_path / "r", imgs, [1e-3, 2e-3, 4e-3], encoding="raw",
                            camera={"bit_depth": 10, "black_level": 64, "white_level": 1023})
    bs = read_bracket_set(out)
    assert bs.max_code == 1023
    lin = bs.linear_stack()
    # (576 - 64) / (1023 - 64) = 0.533889...
    np.testing.assert_allclose(lin[:, 0, 0], [0.0, 512 / 959, 1.0], rtol=1e-6)
    assert bs.saturated()[2].all() and not bs.saturated()[1].any()
    with pytest.raises(ValueError, match="linear_stack"):
        BracketSet(imgs, [1, 2, 3], "gamma").linear_stack()


def test_list_file_and_fractions(tmp_path):
    import imageio.v3 as iio
    for i, im in enumerate(_imgs(2)):
        iio.imwrite(tmp_path / f"a{i}.png", im)
    (tmp_path / "exposures.txt").write_text("# file exposure\na0.png 1/250\na1.png 0.016 extra\n")
    bs = read_bracket_set(tmp_path)
    np.testing.assert_allclose(bs.exposures_s, [0.004, 0.016])
    assert parse_exposure("1/1024") == 1 / 1024
    with pytest.raises(ValueError, match="1/N"):
        parse_exposure("fast")


def test_exif_exposure_jpeg_and_tiff(tmp_path):
    from PIL import Image
    for ext in ("jpg", "tiff"):
        im = Image.fromarray(_imgs(1)[0])
        exif = Image.Exif()
        exif[0x829A] = 0.004  # ExposureTime; Pillow stores it as a rational
        p = tmp_path / f"e.{ext}"
        im.save(p, exif=exif)
        assert exif_exposure_s(p) == pytest.approx(0.004, rel=1e-6)
    p = tmp_path / "noexif.png"
    Image.fromarray(_imgs(1)[0]).save(p)
    assert exif_exposure_s(p) is None
    with pytest.raises(FormatError, match="no EXIF ExposureTime"):
        read_bracket_set(tmp_path)


@pytest.mark.parametrize("ext", [".dng", ".cr2"])
def test_unreadable_raw_names_file(tmp_path, ext):
    rng = np.random.default_rng(1)
    for i in range(2):
        (tmp_path / f"x{i}{ext}").write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    (tmp_path / "exposures.txt").write_text(f"x0{ext} 0.01\nx1{ext} 0.02\n")
    with pytest.raises(FormatError, match=f"x0\\{ext}: cannot decode as a RAW file"):
        read_bracket_set(tmp_path)


def test_mismatched_sizes(tmp_path):
    with pytest.raises(ValueError, match="same size"):
        BracketSet([np.zeros((4, 4), np.uint8), np.zeros((4, 5), np.uint8)], [1, 2])
    import imageio.v3 as iio
    iio.imwrite(tmp_path / "a.png", np.zeros((4, 4), np.uint8))
    iio.imwrite(tmp_path / "b.png", np.zeros((5, 4), np.uint8))
    (tmp_path / "exposures.txt").write_text("a.png 1\nb.png 2\n")
    with pytest.raises(ValueError, match=r"a.png: \(4, 4\), b.png: \(5, 4\)"):
        read_bracket_set(tmp_path)


def test_bad_exposures_and_json(tmp_path):
    with pytest.raises(ValueError, match="> 0 s"):
        BracketSet(_imgs(2), [0.01, 0.0])
    with pytest.raises(ValueError, match="one per image"):
        BracketSet(_imgs(2), [0.01])
    (tmp_path / "brackets.json").write_text('{"format": "other"}')
    with pytest.raises(FormatError, match="hybridhdr-brackets"):
        read_bracket_set(tmp_path)
    with pytest.raises(FileNotFoundError):
        read_bracket_set(tmp_path / "nope")


def test_sorted_and_colour_mask():
    imgs = _imgs(3)
    imgs[1][2, 3] = (0, 0, 255)
    bs = BracketSet(imgs, [4.0, 1.0, 2.0], "unknown", files=["a", "b", "c"]).sorted()
    assert bs.files == ["b", "c", "a"]
    m = colour_mask(bs.images, (0, 0, 255))
    assert m[2, 3] and m.sum() >= 1
