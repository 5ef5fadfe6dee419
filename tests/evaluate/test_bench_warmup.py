"""The bench's timings exclude compilation: its warm-up call is the timed call's kind, so no
Numba kernel meets a new signature inside the timed region. (A kernel compiled there made plain
"akf" look slower than "akf augmented" in the speed-accuracy chart.) Checked by counting the
kernels' compiled signatures around each call, not by timing."""

from __future__ import annotations

import sys

import pytest


def _signatures():
    from numba.core.registry import CPUDispatcher
    out = set()
    for m in list(sys.modules.values()):
        if m is None or not getattr(m, "__name__", "").startswith("hybridhdr"):
            continue
        for n, v in list(vars(m).items()):
            if isinstance(v, CPUDispatcher):
                out |= {(m.__name__, n, str(s)) for s in v.signatures}
    return out


def test_timed_runs_compile_nothing(monkeypatch):
    import hybridhdr.evaluate.bench as B
    bench = B.load_bench("speed_accuracy")
    opts = B._bench_opts(bench)
    opts["jod"] = False
    ds_name, spec, gv, runs = B.expand(bench)[0]
    spec = dict(spec, width=32, height=24, duration_us=200_000)  # small: the kernels' types are the same
    runs = [r for r in runs if r.label in ("akf", "akf augmented", "akf causal", "cf")]
    assert len(runs) == 4
    real, real_warm = B.reconstruct, B._warmup
    in_warm, compiled = [False], []

    def warm(*a, **k):
        in_warm[0] = True
        try:
            return real_warm(*a, **k)
        finally:
            in_warm[0] = False

    def timed(*a, **k):
        before = _signatures()
        out = real(*a, **k)
        if not in_warm[0]:
            compiled.append((a[1], k.get("augment"), k.get("mode"), sorted(_signatures() - before)))
        return out

    monkeypatch.setattr(B, "_WARM", set())
    monkeypatch.setattr(B, "_warmup", warm)
    monkeypatch.setattr(B, "reconstruct", timed)
    rows = B.run_task((ds_name, spec, gv, runs), opts)
    assert [r["status"] for r in rows] == ["ok"] * 4, [r.get("status") for r in rows]
    assert len(compiled) == 4
    assert all(not new for *_, new in compiled), [c for c in compiled if c[-1]]
