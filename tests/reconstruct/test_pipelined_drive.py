"""The pipelined driver (filter thread overlapped with the consumer): same outputs in the same
order, the consumer's engine reads between outputs unaffected, errors and early stops clean."""

import threading

import numpy as np
import pytest

import hybridhdr as hh
from hybridhdr.reconstruct import _engine as E
from hybridhdr.reconstruct import reconstruct


def _rec(seed=0, n=60_000, shape=(40, 50)):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 400_000, n))
    ev = hh.make_events(t, rng.integers(0, shape[1], n), rng.integers(0, shape[0], n), rng.choice([-1, 1], n))
    ft = np.arange(0, 420_000, 50_000)
    fr = hh.Frames(rng.integers(10, 250, (len(ft), *shape)).astype(np.uint8), ft, ft + 1000, encoding="raw")
    return hh.Recording(ev, shape, fr)


@pytest.mark.parametrize("mode", ["offline", "forward", "causal"])
@pytest.mark.parametrize("method", ["akf", "cf"])
def test_pipelined_equals_serial(mode, method, monkeypatch):
    if method == "cf" and mode != "offline":
        pytest.skip("modes are the AKF's")
    rec = _rec()
    kw = dict(fps=200, chunk_events=7_000) | ({"mode": mode} if method == "akf" else {})
    ref = reconstruct(rec, method, n_workers=1, **kw)
    for flag in (True, False):
        monkeypatch.setattr(E, "_pipelined", E._pipelined if flag else
                            (lambda engine, chunks, clock, **k: E._drive(engine, chunks, clock, **k)))
        got = reconstruct(rec, method, n_workers=2, **kw)
        assert np.array_equal(np.asarray(got.frames), np.asarray(ref.frames))
        assert np.array_equal(got.t_us, ref.t_us)


class _Probe(E.Engine):
    """A tiny engine whose output records the number of events seen so far."""

    def __init__(self, fail_at=None):
        super().__init__((1, 1), n_workers=2)
        self.seen = 0
        self.fail_at = fail_at
        self.last = None

    def start(self, t_start_us):
        return 0

    def process(self, t, x, y, p, i0, i1):
        if self.fail_at is not None and self.seen + (i1 - i0) > self.fail_at:
            raise RuntimeError("boom")
        self.seen += i1 - i0

    def output(self, t_us):
        self.last = self.seen
        return np.full((1, 1), float(self.seen))


def _chunks(n=1000, size=100):
    t = np.arange(n, dtype=np.int64) * 10
    z = np.zeros(n, np.uint16)
    p = np.ones(n, np.int8)
    return [(t[i:i + size], z[i:i + size], z[i:i + size], p[i:i + size]) for i in range(0, n, size)]


def test_consumer_reads_engine_state_of_the_output_it_got():
    eng = _Probe()
    clock = E.OutputClock(times_us=np.arange(5, 10_000, 95))
    for t, img in E.drive(eng, iter(_chunks()), clock, clamp=False, pipeline=True):
        assert eng.last == img[0, 0] == (t + 9) // 10  # events with timestamps < t
    assert not any(th.name == "hybridhdr-filter" for th in threading.enumerate())


def test_errors_reach_the_consumer_and_early_stop_joins_the_thread():
    eng = _Probe(fail_at=550)
    with pytest.raises(RuntimeError, match="boom"):
        for _ in E.drive(eng, iter(_chunks()), E.OutputClock(times_us=np.arange(5, 10_000, 95)), clamp=False,
                         pipeline=True):
            pass
    gen = E.drive(_Probe(), iter(_chunks()), E.OutputClock(times_us=np.arange(5, 10_000, 95)), clamp=False,
                  pipeline=True)
    next(gen)
    gen.close()
    assert not any(th.name == "hybridhdr-filter" for th in threading.enumerate())
