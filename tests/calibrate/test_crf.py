"""Camera response: Debevec and Robertson on synthetic brackets, Memorial Church, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.calibrate.crf import (CRF, DebevecParams, RobertsonParams, check_brackets, debevec, estimate_crf,
                                     gamma_crf, robertson)
from hybridhdr.calibrate.hdr_reference import merge_brackets


def s_curve_codes(log_x: np.ndarray) -> np.ndarray:
    """A film-like S-curve: z = 255 * sigmoid(1.2 * (ln X + 1)), before quantisation."""
    return 255.0 / (1.0 + np.exp(-1.2 * (log_x + 1.0)))


def synth_brackets(curve, exposures, noise_dn=0.5, shape=(90, 120), seed=0):
    """Brackets of a smooth HDR scene (ln E spans 7 natural-log units) through ``curve``."""
    rng = np.random.default_rng(seed)
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    log_e = -5.0 + 7.0 * xx / (w - 1) + 0.4 * np.sin(yy / 6.0)
    imgs = []
    for t in exposures:
        z = curve(log_e + np.log(t)) + rng.normal(0.0, noise_dn, log_e.shape)
        imgs.append(np.clip(np.round(z), 0, 255).astype(np.uint8))
    return imgs, log_e


def gamma_codes(log_x):
    return 255.0 * np.clip(np.exp(log_x / 2.2), 0, 1)


def log_error(E, log_e, imgs):
    """Median |ln E_est - ln E_true| after removing the global scale (the median difference),
    on well-exposed pixels (codes in 10..245 in at least one exposure)."""
    st = np.stack(imgs)
    good = ((st >= 10) & (st <= 245)).any(axis=0)
    d = np.log(E[good]) - log_e[good]
    return float(np.median(np.abs(d - np.median(d))))


@pytest.mark.parametrize("curve,name", [(gamma_codes, "gamma"), (s_curve_codes, "s-curve")])
def test_debevec_synthetic_log_error(curve, name):
    ex = np.array([1 / 64, 1 / 16, 1 / 4, 1.0, 4.0])
    imgs, log_e = synth_brackets(curve, ex)
    crf = debevec(imgs, ex)
    E = merge_brackets(imgs, ex, crf)
    err = log_error(E, log_e, imgs)
    # target: median log-irradiance error <= 0.02 (0.5 DN noise: calibration.md measured 0.0094)
    assert err <= 0.02, (name, err)
    # the curve itself: g(z) vs the true ln f^-1(z) on codes 20..235, offset removed
    if name == "gamma":
        d = (crf.log_inverse[0] - gamma_crf())[20:236]
        assert np.median(np.abs(d - np.median(d))) < 0.01


def test_robertson_synthetic_and_monotone():
    ex = np.array([1 / 64, 1 / 16, 1 / 4, 1.0, 4.0])
    imgs, log_e = synth_brackets(gamma_codes, ex)
    crf = robertson(imgs, ex, RobertsonParams(max_pixels=20_000))
    assert np.all(np.diff(crf.log_inverse[0]) >= 0)
    err = log_error(merge_brackets(imgs, ex, crf), log_e, imgs)
    # Robertson has no smoothness prior: with one-stop-ratio chains of codes it is ~10x less
    # accurate than Debevec (calibration.md: 0.092 vs 0.0094 on a gamma CRF); we measured 0.10
    # (gamma) and 0.12 (S-curve) here at 0.5 DN noise, so the bound is a sanity check, not Debevec's 0.02 target.
    assert err < 0.3, err
    assert crf.info["channels"][0]["unseen_codes"] >= 0


def test_colour_and_save_load(tmp_path):
    ex = np.array([1 / 16, 1 / 4, 1.0])
    imgs, _ = synth_brackets(gamma_codes, ex, shape=(40, 50))
    rgb = [np.stack([im, im, im], axis=-1) for im in imgs]
    crf = estimate_crf(rgb, ex, "debevec", DebevecParams(n_samples=150, seed=3))
    assert crf.log_inverse.shape == (3, 256)
    assert crf.log_inverse[:, 128].tolist() == [0.0, 0.0, 0.0]
    back = CRF.load(crf.save(tmp_path / "crf.json"))
    np.testing.assert_array_equal(back.log_inverse, crf.log_inverse)
    np.testing.assert_array_equal(back.observed, crf.observed)
    # same seed, same bits
    again = estimate_crf(rgb, ex, "debevec", DebevecParams(n_samples=150, seed=3))
    np.testing.assert_array_equal(again.log_inverse, crf.log_inverse)
    # forward(g(z)) gives z back where g is strictly increasing
    z = np.arange(20, 240)
    np.testing.assert_allclose(crf.forward(crf.log_inverse[0][z]), z, atol=1e-6)


def test_bad_input():
    im = np.zeros((8, 8), np.uint8)
    with pytest.raises(ValueError, match="exposures must differ: all 3 images have exposure 0.01"):
        debevec([im, im, im], [0.01, 0.01, 0.01])
    with pytest.raises(ValueError, match="at least 2 exposures, got 1"):
        debevec([im], [0.01])
    with pytest.raises(ValueError, match="same shape"):
        robertson([im, np.zeros((8, 9), np.uint8)], [0.01, 0.02])
    with pytest.raises(TypeError, match="integer codes"):
        check_brackets([im.astype(np.float32)] * 2, [1, 2])
    with pytest.raises(ValueError, match="one exposure time per image"):
        check_brackets([im, im], [1.0])
    with pytest.raises(ValueError, match="method must be one of"):
        estimate_crf([im, im], [1, 2], "mertens")
    with pytest.raises(ValueError, match="non-decreasing"):
        CRF(np.array([0.0, -1.0, 2.0]))


@pytest.mark.slow
def test_memorial_church_against_published_map(shared_data):
    """Debevec & Malik's own brackets: our CRF + certainty-weighted merge vs ``memorial.hdr``."""
    from hybridhdr.formats.rgbe import read_rgbe
    from hybridhdr.formats.brackets import colour_mask, read_bracket_set
    folder = shared_data("brackets/memorial")
    bs = read_bracket_set(folder)  # exposures from image_list.txt (32 s ... 1/1024 s)
    assert len(bs) == 16 and bs.exposures_s[0] == 32.0 and bs.exposures_s[-1] == 1 / 1024
    valid = ~colour_mask(bs.images, (0, 0, 255))  # the README: pure blue = shifted border
    crf = debevec(bs, None, mask=valid)
    E = merge_brackets(bs, None, crf)
    ref = read_rgbe(folder / "memorial.hdr")  # the shared copy is newline-damaged; repaired on read
    assert ref.shape == E.shape == (768, 512, 3)
    st = bs.stack()
    well = ((st >= 25) & (st <= 230)).all(axis=-1).sum(axis=0) >= 2
    well &= valid & (ref > 0).all(axis=-1)
    d = np.log(E[well]) - np.log(ref[well])
    d -= np.median(d, axis=0)  # scale (and white balance) fit per channel
    ad = np.abs(d)
    med, mean = float(np.median(ad)), float(ad.mean())
    print(f"memorial: {well.sum()} well-exposed px, |dlog| median {med:.4f} mean {mean:.4f}")
    # Measured: median 0.044, mean 0.11. The published map was made by the authors from these
    # film scans with their own curve and weights; ours has a ~10 % smaller log slope in G and B
    # (film), so dark regions differ most. 0.08 / 0.2 bound a correct pipeline with margin;
    # merging with a linear CRF (g = ln z) instead gives median 0.46, mean 0.83.
    assert med < 0.08 and mean < 0.2


def test_isotonic_monotone_fit():
    from hybridhdr.calibrate.crf import _isotonic, _monotone
    y = np.array([1.0, 3.0, 2.0, 4.0, 0.0, 5.0])
    # pool adjacent violators: [3, 2, 4, 0] pools to their mean 2.25 (worked by hand)
    np.testing.assert_allclose(_isotonic(y, np.ones(6)), [1, 2.25, 2.25, 2.25, 2.25, 5])
    g = np.linspace(-3, 1, 256)
    np.testing.assert_array_equal(_monotone(g)[0], g)  # already monotone: unchanged, ends linear
    bad = g.copy()
    bad[3] = 5.0  # one rarely seen, noisy dark code
    w = np.full(256, 1000.0)
    w[3] = 1.0
    fixed, n = _monotone(bad, w)
    assert np.all(np.diff(fixed) >= 0) and n >= 2
    # a running maximum would flatten codes 3..~200 to 5.0; the weighted fit moves little
    assert np.abs(fixed[10:] - g[10:]).max() < 0.01
