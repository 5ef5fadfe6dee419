"""Fuzz the Prophesee readers with seeded mutations of small valid files.

Every mutated input must either decode to a valid event array (sorted, inside the sensor,
polarity ±1) or raise FormatError (a ValueError). Any other exception fails the test; the readers
have no unbounded loops, so a hang cannot pass silently either (pytest would time out).
"""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr import FormatError, make_events, make_triggers
from hybridhdr.formats import prophesee as P

N_MUTANTS = 2000


def _seed_events(rng, n=40, h=8, w=24, t_step=3000):
    t = np.sort(rng.integers(0, t_step * n, n))
    x = rng.integers(0, w, n)
    x[5:10] = np.arange(3, 8)  # a same-row run for EVT3 vectors
    t[5:10] = t[5]
    y = rng.integers(0, h, n)
    y[5:10] = y[5]
    p = np.where(rng.random(n) < 0.5, 1, -1)
    p[5:10] = 1
    return make_events(t, x, y, p)


def _valid_file(fmt, tmp_path, rng) -> bytes:
    ev = _seed_events(rng)
    if fmt == "evt21":
        body = P._encode_evt21(ev, legacy=bool(rng.integers(0, 2)))
        return b"% evt 2.1\n% format EVT21;height=8;width=24\n% end\n" + body
    path = tmp_path / f"seed.{fmt}"
    with P.WRITERS[fmt](path, sensor_size=(8, 24)) as w:
        w.write_events(ev)
        if fmt != "dat":
            w.write_triggers(make_triggers([int(ev["t"][3]), int(ev["t"][-1])], [1, 2], [1, -1]))
    return path.read_bytes()


def _mutate(data: bytes, rng) -> bytes:
    b = bytearray(data)
    hdr = data.find(b"% end\n")
    hdr = hdr + 6 if hdr >= 0 else 60
    for _ in range(int(rng.integers(1, 4))):
        kind = int(rng.integers(0, 6))
        if not b:
            b = bytearray(rng.integers(0, 256, 4, dtype=np.uint8).tobytes())
        i = int(rng.integers(0, len(b)))
        if kind == 0:  # bit flip
            b[i] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:  # byte overwrite
            b[i] = int(rng.integers(0, 256))
        elif kind == 2:  # truncation
            del b[int(rng.integers(0, len(b) + 1)):]
        elif kind == 3:  # insertion
            k = int(rng.integers(1, 9))
            b[i:i] = rng.integers(0, 256, k, dtype=np.uint8).tobytes()
        elif kind == 4:  # header damage
            j = int(rng.integers(0, min(hdr, len(b))))
            b[j] = int(rng.choice([0x25, 0x0A, 0x00, 0x20, 0x39, 0x78, 0x3B, 0x3D, int(rng.integers(0, 256))]))
        else:  # overwrite a whole data word with random bits
            j = hdr + int(rng.integers(0, max(1, len(b) - hdr)))
            b[j:j + 4] = rng.integers(0, 256, 4, dtype=np.uint8).tobytes()
    return bytes(b)


def _check(fmt, path, stream: bool):
    try:
        r = P.READERS[fmt](path)
        if stream:
            chunks = list(r.iter_chunks(7))
            ev = np.concatenate([c.events for c in chunks]) if chunks else np.zeros(0, r.read_all().events.dtype)
        else:
            ev = r.read_all().events
    except FormatError:
        return "error"
    ss = r.sensor_size
    lim_w, lim_h = (ss.width, ss.height) if ss is not None else (r._max_coord, r._max_coord)
    assert np.all(np.diff(ev["t"]) >= 0)
    assert np.all(ev["t"] >= 0)
    assert np.all(ev["x"] < lim_w) and np.all(ev["y"] < lim_h)
    assert np.all((ev["p"] == 1) | (ev["p"] == -1))
    return "ok"


@pytest.mark.parametrize("fmt", ["evt2", "evt21", "evt3", "dat"])
def test_fuzz_reader(fmt, tmp_path):
    rng = np.random.default_rng({"evt2": 11, "evt21": 12, "evt3": 13, "dat": 14}[fmt])
    seeds = [_valid_file(fmt, tmp_path, rng) for _ in range(4)]
    for s in seeds:  # the unmutated seeds decode
        p = tmp_path / f"s.{fmt}"
        p.write_bytes(s)
        assert _check(fmt, p, False) == "ok"
    outcomes = {"ok": 0, "error": 0}
    path = tmp_path / f"m.{'dat' if fmt == 'dat' else 'raw'}"
    for k in range(N_MUTANTS):
        data = _mutate(seeds[k % len(seeds)], rng)
        path.write_bytes(data)
        P.sniff(path, data[:4096])  # must not raise
        try:
            outcomes[_check(fmt, path, stream=(k % 5 == 0))] += 1
        except AssertionError:
            raise AssertionError(f"{fmt} mutant {k} decoded to invalid events: {data!r}") from None
        except FormatError:
            raise
        except Exception as e:  # noqa: BLE001
            raise AssertionError(f"{fmt} mutant {k} raised {type(e).__name__}: {e}; input {data!r}") from e
    # both outcomes occur: the fuzzer reaches the decoders, not only the header checks
    assert outcomes["ok"] > 50 and outcomes["error"] > 50, outcomes
