"""Seeded mutation fuzzing of the AEDAT4 and AKF .mat v5 readers.

Every mutated input must either decode to valid data (sorted events inside the sensor, ±1
polarity, valid frames) or raise :class:`hybridhdr.errors.FormatError`; any other exception,
hang or silently invalid output fails the test.
"""

from __future__ import annotations

import datetime

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.errors import FormatError

N_MUTANTS = 1100  # per seed file; two seed files per reader -> 4400 inputs in all


def _mutate(data: bytes, rng: np.random.Generator, protect: int = 0) -> bytes:
    """One seeded mutation: bit flips, byte overwrites, truncation, or a duplicated/removed span."""
    b = bytearray(data)
    kind = int(rng.integers(0, 5))
    lo = protect
    if kind == 0:
        for _ in range(int(rng.integers(1, 9))):
            i = int(rng.integers(lo, len(b)))
            b[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1:
        i = int(rng.integers(lo, len(b)))
        k = int(rng.integers(1, 17))
        b[i:i + k] = rng.integers(0, 256, k, dtype=np.uint8).tobytes()
    elif kind == 2:
        b = b[:int(rng.integers(lo, len(b)))]
    elif kind == 3:
        i = int(rng.integers(lo, len(b)))
        b[i:i + 4] = rng.choice([b"\xff\xff\xff\x7f", b"\x00\x00\x00\x80", b"\x00\x00\x00\x00", b"\xff\xff\xff\xff"])
    else:
        i, j = sorted(int(v) for v in rng.integers(lo, len(b), 2))
        b = b[:i] + b[j:] if rng.random() < 0.5 else b[:j] + b[i:j] + b[j:]
    return bytes(b)


def _check_valid(rec: hh.Recording) -> None:
    ss = rec.sensor_size
    assert ss is not None
    hh.validate_events(rec.events, ss)  # sorted, ±1, inside the sensor
    hh.validate_triggers(rec.triggers)
    hh.validate_imu(rec.imu)  # sorted, finite or NaN
    if rec.frames is not None:
        assert isinstance(rec.frames, hh.Frames)
        assert np.all(rec.frames.t_end_us >= rec.frames.t_start_us)


def _fuzz(tmp_path, seed_bytes: bytes, fmt: str, seed: int, protect: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    path = tmp_path / f"fuzz.{fmt}"
    outcome = {"ok": 0, "FormatError": 0}
    for k in range(N_MUTANTS):
        data = _mutate(seed_bytes, rng, protect)
        path.write_bytes(data)
        try:
            with hh.open_reader(path, fmt) as r:
                rec = r.read()
                if fmt == "akf_mat":
                    r.read_hdr()
        except FormatError:
            outcome["FormatError"] += 1
            continue
        except Exception as exc:  # noqa: BLE001 - the point of the test
            raise AssertionError(f"mutant {k} (seed {seed}) raised {type(exc).__name__}: {exc}") from exc
        _check_valid(rec)
        outcome["ok"] += 1
    return outcome


# ------------------------------------------------------------------------------------------------
# AEDAT4
# ------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def aedat4_seeds(tmp_path_factory):
    dv = pytest.importorskip("dv_processing")
    rng = np.random.default_rng(11)
    out = {}
    for comp in ("LZ4", "NONE"):
        path = tmp_path_factory.mktemp("a4") / f"seed_{comp}.aedat4"
        cfg = dv.io.MonoCameraWriter.Config("Fuzz_1")
        cfg.addEventStream((32, 24))
        cfg.addFrameStream((32, 24))
        cfg.addTriggerStream()
        cfg.addImuStream()
        cfg.compression = getattr(dv.CompressionType, comp)
        w = dv.io.MonoCameraWriter(str(path), cfg)
        t = 1000
        for _ in range(4):
            store = dv.EventStore()
            for _ in range(60):
                t += int(rng.integers(0, 5))
                store.push_back(t, int(rng.integers(0, 32)), int(rng.integers(0, 24)), bool(rng.integers(0, 2)))
            w.writeEvents(store)
            f = dv.Frame(t, rng.integers(0, 256, (24, 32), dtype=np.uint8))
            f.exposure = datetime.timedelta(microseconds=100)
            w.writeFrame(f)
            w.writeTrigger(dv.Trigger(t, dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE))
            w.writeImu(dv.IMU(t, *[float(v) for v in rng.normal(0, 10, 10)]))
        del w
        out[comp] = path.read_bytes()
    return out


@pytest.mark.parametrize("comp, seed", [("LZ4", 101), ("NONE", 202)])
def test_fuzz_aedat4(tmp_path, aedat4_seeds, comp, seed):
    data = aedat4_seeds[comp]
    path = tmp_path / "seed.aedat4"
    path.write_bytes(data)
    base = hh.read(path)
    assert base.n_events == 240 and len(base.frames) == 4 and len(base.triggers) == 4 and len(base.imu) == 4
    outcome = _fuzz(tmp_path, data, "aedat4", seed, protect=len(b"#!AER-DAT4.0"))
    assert outcome["ok"] + outcome["FormatError"] == N_MUTANTS
    assert outcome["FormatError"] > 0 and outcome["ok"] > 0  # both paths exercised


# ------------------------------------------------------------------------------------------------
# AKF .mat v5
# ------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def mat_v5_seeds(tmp_path_factory):
    scipy_io = pytest.importorskip("scipy.io")
    rng = np.random.default_rng(12)
    n = 60
    t = np.sort(rng.integers(0, 10_000, n)).astype(float)
    events = np.c_[t, rng.integers(1, 13, n), rng.integers(1, 9, n), rng.integers(0, 2, n)].astype(float)
    d = {"events": events, "im_height": 8.0, "im_width": 12.0, "ct": 0.1, "f_Q": np.linspace(0, 1, 16),
         "image": rng.integers(0, 256, (8, 12, 2), dtype=np.uint8), "time_image": np.array([[100.0], [5000.0]]),
         "exposure": np.array([[50.0], [60.0]]), "HDR_mat": rng.random((8, 12, 3, 2))}
    out = {}
    for comp in (False, True):
        path = tmp_path_factory.mktemp("m5") / f"seed_{comp}.mat"
        scipy_io.savemat(path, d, do_compression=comp)
        out[comp] = path.read_bytes()
    return out


@pytest.mark.parametrize("compressed, seed", [(False, 303), (True, 404)])
def test_fuzz_akf_mat_v5(tmp_path, mat_v5_seeds, compressed, seed):
    data = mat_v5_seeds[compressed]
    path = tmp_path / "seed.mat"
    path.write_bytes(data)
    base = hh.read(path)
    assert base.n_events == 60 and len(base.frames) == 2
    outcome = _fuzz(tmp_path, data, "akf_mat", seed, protect=len(b"MATLAB 5.0 MAT-file"))
    assert outcome["ok"] + outcome["FormatError"] == N_MUTANTS
    assert outcome["FormatError"] > 0 and outcome["ok"] > 0
