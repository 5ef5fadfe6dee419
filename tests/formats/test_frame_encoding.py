"""Frame encodings: closed forms, luminance, the AKF .mat gamma/f_Q path, and every reader's
encoding through the container and ``convert --frame-encoding``."""

from __future__ import annotations

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.camera import CameraProfile
from hybridhdr.camera import encoding as E
from hybridhdr.formats import akf_mat as M
from hybridhdr.cli import main
from hybridhdr.formats.container import RecordingFile, write_recording
from hybridhdr.errors import FormatError

h5py = pytest.importorskip("h5py")

SS = hh.SensorSize(18, 24)
CODES = np.arange(256)


# ------------------------------------------------------------------------------------------------
# closed forms
# ------------------------------------------------------------------------------------------------

def test_names():
    assert E.ENCODING_CHOICES == ("linear", "gamma2.2", "srgb")
    assert [E.parse_frame_encoding(n) for n in E.ENCODING_CHOICES] == ["linear", "gamma", "srgb"]
    assert E.parse_frame_encoding(" SRGB ") == "srgb" and E.parse_frame_encoding("gamma") == "gamma"
    assert "srgb" in hh.model.FRAME_ENCODINGS
    for bad in ("gamma2.4", "log", "", None, 2.2):
        with pytest.raises(ValueError, match="frame encoding"):
            E.parse_frame_encoding(bad)


def test_srgb_closed_form():
    # IEC 61966-2-1: v <= 0.04045 -> v/12.92, else ((v+0.055)/1.055)^2.4
    assert E.decode(0, "srgb", 255) == 0.0
    assert E.decode(255, "srgb", 255) == 1.0
    assert E.decode(0.04045, "srgb", 1.0) == 0.04045 / 12.92
    assert E.decode(0.5, "srgb", 1.0) == pytest.approx(((0.5 + 0.055) / 1.055) ** 2.4, rel=1e-15)
    assert E.decode(0.04045, "srgb", 1.0) == pytest.approx(0.0031308, abs=1e-8)
    # the two pieces meet at the knee (within the standard's rounding of its constants)
    assert abs(((0.04045 + 0.055) / 1.055) ** 2.4 - 0.04045 / 12.92) < 1e-8
    assert E.encode(0.0031308, "srgb", 1.0) == pytest.approx(0.04045, abs=1e-7)
    assert E.encode(1.0, "srgb", 255) == pytest.approx(255.0, abs=1e-12)
    assert E.encode(0.0, "srgb", 255) == 0.0


def test_gamma_and_linear_closed_forms():
    np.testing.assert_allclose(E.decode(CODES, "gamma", 255), (CODES / 255.0) ** 2.2, rtol=0, atol=0)
    np.testing.assert_array_equal(E.decode(CODES, "linear", 255), CODES / 255.0)
    assert E.encode(0.5, "gamma", 255) == pytest.approx(255 * 0.5 ** (1 / 2.2), rel=1e-15)
    for enc in ("linear", "gamma", "srgb"):
        np.testing.assert_allclose(E.encode(E.decode(CODES, enc, 255), enc, 255), CODES, rtol=0, atol=1e-10)
        assert np.array_equal(E.encode(E.decode(CODES, enc, 255), enc, 255, dtype=np.uint8), CODES)
        d = E.decode(CODES, enc, 255)
        assert np.all(np.diff(d) > 0) and d[0] == 0 and d[-1] == 1
    # 16-bit codes and clipping
    assert E.decode(65535, "gamma", 65535) == 1.0 and E.decode(300, "linear", 255) == 1.0
    with pytest.raises(ValueError, match="unknown"):
        E.decode(CODES, "unknown", 255)
    with pytest.raises(ValueError, match="max_code"):
        E.decode(CODES, "linear", 0)


def test_luminance_weights_and_grey():
    w = E.LUMINANCE_WEIGHTS
    assert w == (0.2126, 0.7152, 0.0722) and sum(w) == pytest.approx(1.0, abs=1e-15)
    grey = np.repeat(CODES[:, None], 3, axis=1).astype(np.uint8)
    for enc in ("linear", "gamma", "srgb", "unknown"):
        np.testing.assert_allclose(E.to_luminance(grey, enc), CODES, rtol=0, atol=1e-10)
        assert np.array_equal(E.to_luminance(grey, enc, dtype=np.uint8), CODES)
    # weights apply to linear values: pure green in sRGB codes
    g = np.array([0, 255, 0], np.uint8)
    assert E.to_luminance(g, "linear") == pytest.approx(0.7152 * 255)
    assert E.to_luminance(g, "srgb") == pytest.approx(E.encode(0.7152, "srgb", 255), rel=1e-12)
    assert E.to_luminance(g, "gamma") == pytest.approx(255 * 0.7152 ** (1 / 2.2), rel=1e-12)
    with pytest.raises(ValueError, match="last axis of 3"):
        E.to_luminance(np.zeros((2, 4)), "linear")


def test_luminance_frames_and_with_encoding():
    rng = np.random.default_rng(0)
    fr = hh.Frames(rng.integers(0, 256, (2, 4, 5, 3), dtype=np.uint8), [0, 10], [5, 15], encoding="srgb")
    y = E.luminance_frames(fr)
    assert y.images.shape == (2, 4, 5) and y.images.dtype == np.uint8 and y.encoding == "srgb"
    np.testing.assert_array_equal(y.t_end_us, fr.t_end_us)
    assert E.luminance_frames(y) is y
    g = E.with_encoding(y, "gamma2.2")
    assert g.encoding == "gamma" and g.images is y.images
    assert E.with_encoding(y, None) is y and E.with_encoding(None, "srgb") is None


# ------------------------------------------------------------------------------------------------
# AKF .mat: gamma / f_Q
# ------------------------------------------------------------------------------------------------

def _akf_f_q():
    """The authors' construction, f_Q = 7e5 * max(f_w, 0.09), with a bell-shaped f_w."""
    fw = np.exp(-0.5 * ((CODES - 127.5) / 50.0) ** 2)
    return 7e5 * np.maximum(fw, 0.09)


def _events(n=200, seed=0):
    rng = np.random.default_rng(seed)
    return hh.make_events(np.sort(rng.integers(0, 1_000_000, n)), rng.integers(0, SS.width, n),
                          rng.integers(0, SS.height, n), rng.integers(0, 2, n))


def _frames(k=3, seed=1, encoding="unknown"):
    rng = np.random.default_rng(seed)
    ts = np.array([100_000, 400_000, 700_000][:k])
    return hh.Frames(rng.integers(0, 256, (k, SS.height, SS.width), dtype=np.uint8), ts, ts + 5000,
                     encoding=encoding)


def _check_profile(prov, f_q, inverse_crf):
    prof = CameraProfile.from_dict(prov["camera_profile"])
    assert prof.name == "akf .mat f_Q" and prof.max_code == 255
    assert prof.frame_precision_scale == pytest.approx(f_q.max(), rel=1e-12)
    np.testing.assert_allclose(prof.weighting, f_q / f_q.max(), rtol=1e-12, atol=0)
    assert prof.min_weighting == pytest.approx((f_q / f_q.max()).min(), rel=1e-12)
    # eq. 6: R̄ = 1 / f_Q at every code
    np.testing.assert_allclose(1.0 / prof.variance(CODES), f_q, rtol=1e-12, atol=0)
    np.testing.assert_allclose(M.f_q_from_profile(prof), f_q, rtol=1e-12, atol=0)
    if inverse_crf is None:
        assert prof.inverse_crf is None
    else:
        np.testing.assert_allclose(prof.inverse_crf, inverse_crf, rtol=1e-15, atol=0)
    return prof


def test_mat_v73_f_q_and_default_encoding(tmp_path):
    f_q = _akf_f_q()
    path = tmp_path / "a.mat"
    hh.write(hh.Recording(_events(), SS, _frames()), path, f_Q=f_q, ct=0.1)
    rec = hh.read(path)
    # the file states no transfer function; the authors' code reads image/255 linearly
    assert rec.frames.encoding == "unknown"
    prov = rec.metadata.provenance
    assert prov["frame_encoding"] == "unknown" and "linear" in prov["frame_encoding_source"]
    _check_profile(prov, f_q, None)
    np.testing.assert_array_equal(prov["akf_mat"]["f_Q"], f_q)


@pytest.mark.parametrize("version", ["7.3", "5"])
def test_mat_gamma_f_q_path(tmp_path, version):
    """Declared gamma 2.2: encoding "gamma", profile inverse CRF (code/255)^2.2, f_Q reproduced."""
    f_q = _akf_f_q()
    fr = _frames()
    path = tmp_path / f"g{version}.mat"
    if version == "7.3":
        hh.write(hh.Recording(_events(), SS, fr), path, f_Q=f_q)
    else:
        from tests.formats.test_akf_mat import write_v5
        write_v5(path, _events(), fr, extra={"f_Q": f_q.reshape(-1, 1)})
    with hh.open_reader(path, frame_encoding="gamma2.2") as r:
        assert r.version == version
        rec = r.read()
    assert rec.frames.encoding == "gamma"
    np.testing.assert_array_equal(rec.frames.images, fr.images)
    prov = rec.metadata.provenance
    assert prov["frame_encoding"] == "gamma" and prov["frame_encoding_source"].startswith("declared")
    prof = _check_profile(prov, f_q, (CODES / 255.0) ** 2.2)
    assert prof.source == str(path)
    # sRGB declared: the IEC curve as inverse CRF
    srgb = hh.read(path, frame_encoding="srgb")
    assert srgb.frames.encoding == "srgb"
    _check_profile(srgb.metadata.provenance, f_q, E.decode(CODES, "srgb", 255))


def test_mat_writer_writes_f_q_from_profile(tmp_path):
    f_q = _akf_f_q()
    prof = M.profile_from_f_q(f_q, "gamma", source="test")
    md = hh.Metadata(provenance={"camera_profile": prof.to_dict()})
    path = tmp_path / "p.mat"
    hh.write(hh.Recording(_events(), SS, _frames(encoding="gamma"), metadata=md), path)
    with h5py.File(path, "r") as f:
        np.testing.assert_allclose(f["f_Q"][()].reshape(-1), f_q, rtol=1e-12, atol=0)
    back = hh.read(path, frame_encoding="gamma2.2")
    _check_profile(back.metadata.provenance, f_q, (CODES / 255.0) ** 2.2)
    # .mat -> container -> .mat keeps f_Q
    h5 = write_recording(back, tmp_path / "p.h5")
    again = tmp_path / "again.mat"
    hh.write(hh.read(h5), again)
    with h5py.File(again, "r") as f:
        np.testing.assert_allclose(f["f_Q"][()].reshape(-1), f_q, rtol=1e-12, atol=0)


def test_mat_unusable_f_q_is_noted_not_fatal(tmp_path):
    path = tmp_path / "z.mat"
    hh.write(hh.Recording(_events(), SS, _frames()), path, f_Q=np.zeros(256))
    prov = hh.read(path).metadata.provenance
    assert "camera_profile" not in prov and "positive maximum" in prov["camera_profile_note"]
    # a zero entry (R̄ = ∞) gets the least precision of the table
    f_q = _akf_f_q()
    f_q[0] = 0.0
    prof = M.profile_from_f_q(f_q)
    assert prof.min_weighting == pytest.approx(0.09 * 7e5 / f_q.max())
    assert prof.extra["f_Q_zero_codes"] == 1


# ------------------------------------------------------------------------------------------------
# every reader's encoding through the container
# ------------------------------------------------------------------------------------------------

def _through_container(rec, tmp_path, name):
    p = write_recording(rec, tmp_path / f"{name}.h5")
    with RecordingFile(p) as rf:
        fr = rf.read_frames()
    assert fr.encoding == rec.frames.encoding
    assert hh.read(p).frames.encoding == rec.frames.encoding
    np.testing.assert_array_equal(fr.images, rec.frames.images)
    return p


def _ecd(tmp_path):
    p = tmp_path / "ecd"
    hh.write(hh.Recording(_events(), SS, _frames()), p, "ecd")
    return p, "unknown"


def _mat(tmp_path):
    p = tmp_path / "m.mat"
    hh.write(hh.Recording(_events(), SS, _frames()), p, f_Q=_akf_f_q())
    return p, "unknown"


def _monash(tmp_path):
    from tests.formats.test_hdf5_layouts import _cols, write_monash
    return write_monash(tmp_path / "mo.h5", *_cols(500)), "unknown"


def _aedat4(tmp_path):
    from tests.formats.test_aedat4 import make_aedat4
    img = np.arange(24 * 32, dtype=np.uint8).reshape(24, 32)
    ev = hh.make_events([5, 9], [1, 2], [1, 3], [1, -1])
    return make_aedat4(tmp_path / "a.aedat4", ev, frames=[(10, 4, img), (40, 4, img)]), "raw"


def _container(tmp_path):
    return write_recording(hh.Recording(_events(), SS, _frames(encoding="srgb")), tmp_path / "c.h5"), "srgb"


@pytest.mark.parametrize("make", [_ecd, _mat, _monash, _aedat4, _container],
                         ids=["ecd", "akf_mat", "monash", "aedat4", "hybridhdr"])
@pytest.mark.parametrize("declared", [None, "linear", "gamma2.2", "srgb"])
def test_reader_encoding_round_trips(tmp_path, make, declared):
    path, default = make(tmp_path)
    opts = {} if declared is None else {"frame_encoding": declared}
    rec = hh.read(path, **opts)
    want = default if declared is None else E.parse_frame_encoding(declared)
    assert rec.frames.encoding == want
    _through_container(rec, tmp_path, "out")


def test_ecd_sample_declared_srgb(shared_data, tmp_path):
    folder = shared_data("ecd_slider_depth")
    rec = hh.read(folder)
    assert rec.frames.encoding == "unknown"
    assert rec.metadata.provenance["frame_encoding"] == "unknown"
    rec = hh.read(folder, frame_encoding="srgb", t_end_us=50_000)
    assert rec.frames.encoding == "srgb"
    assert rec.metadata.provenance["frame_encoding_source"].startswith("declared")
    _through_container(rec, tmp_path, "ecd_srgb")


def test_container_unknown_stored_encoding(tmp_path):
    p = write_recording(hh.Recording(_events(), SS, _frames(encoding="gamma")), tmp_path / "u.h5")
    with h5py.File(p, "r+") as f:
        f["frames"].attrs["encoding"] = "pq"
    with pytest.raises(FormatError, match="encoding 'pq'.*not know"):
        hh.read(p)
    assert hh.read(p, frame_encoding="srgb").frames.encoding == "srgb"


def test_reader_rejects_bad_declared_encoding(tmp_path):
    path, _ = _ecd(tmp_path)
    with pytest.raises(ValueError, match="unknown frame encoding"):
        hh.open_reader(path, frame_encoding="gamma1.8")


# ------------------------------------------------------------------------------------------------
# convert --frame-encoding
# ------------------------------------------------------------------------------------------------

def test_convert_frame_encoding_srgb_on_ecd(tmp_path, capsys):
    src, _ = _ecd(tmp_path)
    out = tmp_path / "o.h5"
    assert main(["convert", str(src), str(out), "--frame-encoding", "srgb", "--no-progress"]) == 0
    assert "frames encoded srgb" in capsys.readouterr().out
    with RecordingFile(out) as rf:
        assert rf.read_frames().encoding == "srgb"
        assert rf.metadata.provenance["frame_encoding"] == "srgb"
    # without the flag the reader's statement is kept
    out2 = tmp_path / "o2.h5"
    assert main(["convert", str(src), str(out2), "--no-progress"]) == 0
    assert hh.read(out2).frames.encoding == "unknown"


def test_convert_frame_encoding_ecd_sample(shared_data, tmp_path, capsys):
    folder = shared_data("ecd_slider_depth")
    out = tmp_path / "s.h5"
    assert main(["convert", str(folder), str(out), "--frame-encoding", "srgb", "--end-us", "100000",
                 "--no-progress"]) == 0
    fr = hh.read(out).frames
    assert fr.encoding == "srgb" and len(fr) == 3


def test_convert_frame_encoding_mat_profile_follows(tmp_path, capsys):
    src, _ = _mat(tmp_path)
    out = tmp_path / "m.h5"
    assert main(["convert", str(src), str(out), "--frame-encoding", "gamma2.2", "--no-progress"]) == 0
    rec = hh.read(out)
    assert rec.frames.encoding == "gamma"
    _check_profile(rec.metadata.provenance, _akf_f_q(), (CODES / 255.0) ** 2.2)


def test_convert_frame_encoding_choices(tmp_path, capsys):
    src, _ = _ecd(tmp_path)
    # main returns argparse's usage status (2) instead of exiting (callers keep control)
    assert main(["convert", str(src), str(tmp_path / "x.h5"), "--frame-encoding", "gamma"]) == 2
    assert "invalid choice" in capsys.readouterr().err
