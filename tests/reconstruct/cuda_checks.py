"""Agreement checks of the CUDA AKF/CF path with the CPU path (run by ``test_cuda.py`` in a child process).

Usage: ``python tests/reconstruct/cuda_checks.py [--real] [NAME ...]``. Without ``--real`` it sets
``NUMBA_ENABLE_CUDASIM=1`` before Numba is imported (Numba's CUDA simulator: the kernels run as
Python threads on the CPU), so the process that runs the other tests never sees it. With
``--real`` the kernels run on the GPU (``benchmarks/device_run.sh``). Prints one JSON object per
check: ``{"check", "ok", "max_rel", "tol", "detail"}``, or ``{"skip": reason}`` when numba.cuda
cannot run.

What is compared, and why these tolerances:

* Engine checks compare the filter state itself, float64 L̂ and P at every output time
  (``output(t, with_state=True)``), relative error <= 1e-9: the GPU runs the same float64
  operations in the same order; a GPU may fuse a*b+c into one rounding and its ``log1p`` may
  differ in the last bit, a few 1e-16 per operation, and the filter is contractive between
  events, so these stay many orders of magnitude below 1e-9.
* End-to-end checks (``reconstruct(..., device=...)``) compare the float32 linear images the
  user gets. Both round L̂ to float32; the CPU takes numpy's float32 exp, the GPU the correctly
  rounded float32 of a float64 exp (numpy's is within about an ulp of it: 1.6e-7 relative seen
  in the simulator), and a 1e-15 difference in L̂ can at most flip the float32 rounding of L̂
  (2**-24 relative of |L̂| <= 8, i.e. up to 5e-7 after exp): relative tolerance 2e-6.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

REAL = "--real" in sys.argv
if not REAL:
    os.environ["NUMBA_ENABLE_CUDASIM"] = "1"
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

STATE_TOL = 1e-9
IMAGE_TOL = 2e-6


def _rel(a, b):
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300))) if a.size else 0.0


def _stream(n, h, w, seed, span=200_000):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, span, n)).astype(np.int64)
    t[100:140] = t[100]  # equal timestamps: stream order, not time, decides t*
    x = rng.integers(0, w, n).astype(np.uint16)
    y = rng.integers(0, h, n).astype(np.uint16)
    hot = rng.random(n) < 0.1  # a hot pixel: a long group (the shell sort path)
    x[hot], y[hot] = 3, 4
    p = rng.choice(np.array([-1, 1], np.int8), n)
    return t, x, y, p


def _frames(h, w, times, seed=3):
    from hybridhdr import Frames
    rng = np.random.default_rng(seed)
    codes = rng.integers(0, 256, (len(times), h, w)).astype(np.uint8)
    codes[:, :2, :3] = 255  # saturated corner: censored bound, R changing between frames (eq. 7)
    codes[:, -1, -2:] = 0
    t = np.asarray(times, np.int64)
    return Frames(codes, t, t, encoding="raw")


class _Step:
    """An event-driven L^A (la_step) through the generic segment path, as frame augmentation."""

    def __init__(self, inner):
        self.inner = inner
        self.times_us = inner.times_us

    def __len__(self):
        return len(self.inner)

    def segment(self, k):
        import dataclasses
        s = self.inner.segment(k)
        return dataclasses.replace(s, la_step=np.linspace(0.05, 0.15, s.log_frame.shape[0]))


def _resident(t, x, y, p):
    """The events on the device (``cuda.DeviceEvents``), for the resident path."""
    import types

    from hybridhdr.reconstruct.cuda import DeviceEvents
    return DeviceEvents.upload(types.SimpleNamespace(t=t, x=x, y=y, p=p))


def _drive_engines(make, t, x, y, p, cuts, resident=False):
    """Drive a CPU and a GPU engine through the same batches (switches inside), outputs with state;
    ``resident``: the GPU engine takes its windows from resident events (``process_resident``)."""
    res = []
    for dev in ("cpu", "cuda"):
        eng = make(dev)
        eng.start(None)
        outs = []
        if dev == "cuda" and resident:
            d = _resident(t, x, y, p)

            def proc(t_, x_, y_, p_, i, j):
                eng.process_resident(d, i, j)
        else:
            proc = eng.process
        for a, b in zip(cuts[:-1], cuts[1:]):
            i = a
            while eng.next_switch_us() is not None and eng.next_switch_us() <= t[b - 1]:
                j = i + int(np.searchsorted(t[i:b], eng.next_switch_us(), side="left"))
                proc(t, x, y, p, i, j)
                eng.switch()
                i = j
            proc(t, x, y, p, i, b)
            outs.append(eng.output(int(t[b - 1]) + 1, with_state=True))
        res.append((outs, eng.n_events))
        eng.close()
    return res


def check_akf_engine(noise_model="paper", cov="linear", frame_update="continuous", step=False, thresholds=False,
                     max_window=None, resident_chunk=None):
    from hybridhdr.camera import default_profile
    from hybridhdr.reconstruct import AKFParams, FrameMeasurements
    from hybridhdr.reconstruct._engine import AKFEngine
    from hybridhdr.reconstruct.cuda import CudaAKFEngine
    h, w = 12, 16
    t, x, y, p = _stream(900, h, w, seed=7)
    fr = _frames(h, w, [0, 70_000, 140_000, 210_000])
    params = AKFParams(noise_model=noise_model, covariance_interpolation=cov, frame_precision_scale=1e3,
                       frame_update=frame_update)
    rng = np.random.default_rng(5)
    thr = (rng.uniform(0.08, 0.3, (h, w)), rng.uniform(0.08, 0.3, (h, w))) if thresholds else None

    def make(dev):
        m = FrameMeasurements(fr, (h, w), default_profile(), intensity_offset=params.intensity_offset,
                              interpolate_covariance=cov == "linear", saturation=params.saturation)
        if step:
            m = _Step(m)
        e = AKFEngine((h, w), m, params) if dev == "cpu" else CudaAKFEngine((h, w), m, params)
        if thr is not None:
            e.set_thresholds(*thr)
        return e
    n = t.shape[0]
    import hybridhdr.reconstruct.cuda as C
    if max_window is not None:  # windows split inside the engine (staging and grouping limits)
        C.MAX_WINDOW = max_window
    if resident_chunk is not None:  # resident events, grouped once per chunk of this many
        C.RESIDENT_CHUNK = resident_chunk
    try:
        (cpu, n_cpu), (gpu, n_gpu) = _drive_engines(make, t, x, y, p, [0, n // 3, 2 * n // 3, n],
                                                    resident=resident_chunk is not None)
    finally:
        C.MAX_WINDOW = 1 << 24
        C.RESIDENT_CHUNK = 1 << 25
    rel = max(max(_rel(g[1], c[1]), _rel(g[2], c[2])) for c, g in zip(cpu, gpu))
    return rel, STATE_TOL, f"L and P at {len(cpu)} outputs; events {n_gpu} vs {n_cpu}", n_cpu == n_gpu


def check_cf_engine(mode="cf", generic=False, adaptive=False, resident_chunk=None):
    from hybridhdr.camera import default_profile
    from hybridhdr.reconstruct import CFParams, FrameMeasurements, HighPassParams
    from hybridhdr.reconstruct._engine import CFEngine
    from hybridhdr.reconstruct.cuda import CudaCFEngine
    h, w = 12, 16
    t, x, y, p = _stream(900, h, w, seed=9)
    fr = _frames(h, w, [0, 70_000, 140_000, 210_000])
    from hybridhdr.reconstruct import DirectParams
    params = {"highpass": HighPassParams(), "direct": DirectParams()}.get(mode) or \
        CFParams(cutoff_hz=4.0, adaptive_gain=adaptive, adaptive_low=0.2, adaptive_high=0.8)

    def make(dev):
        m = None if mode == "highpass" else FrameMeasurements(fr, (h, w), default_profile(), intensity_offset=1.0,
                                                              bias_correction=False, interpolate_covariance=False)
        if generic:  # no segment_codes: the per-pixel segment path (not the per-code tables)
            m = _Step(m)
        return CFEngine((h, w), m, params, mode) if dev == "cpu" else CudaCFEngine((h, w), m, params, mode)
    import hybridhdr.reconstruct.cuda as CU
    try:
        res = _cf_runs(make, t, x, y, p, resident_chunk)
    finally:
        CU.RESIDENT_CHUNK = 1 << 25
    rel = max(_rel(g[1], c[1]) for c, g in zip(*res))
    rel_img = max(_rel(g[0], c[0]) for c, g in zip(*res))
    return max(rel, rel_img / IMAGE_TOL * STATE_TOL), STATE_TOL, f"L (float64) and images ({rel_img:.2e})", True


def _cf_runs(make, t, x, y, p, resident_chunk):
    """The CPU and GPU CF engines through the same windows: [(image, float64 L̂) per output] each."""
    import hybridhdr.reconstruct.cuda as CU
    res = []
    for dev in ("cpu", "cuda"):
        e = make(dev)
        e.start(int(t[0]))
        outs = []
        n = t.shape[0]
        proc = e.process
        if dev == "cuda" and resident_chunk is not None:
            CU.RESIDENT_CHUNK = resident_chunk
            d = _resident(t, x, y, p)

            def proc(t_, x_, y_, p_, i, j):
                e.process_resident(d, i, j)
        for a, b in zip([0, n // 2], [n // 2, n]):
            i = a
            while e.next_switch_us() is not None and e.next_switch_us() <= t[b - 1]:
                j = i + int(np.searchsorted(t[i:b], e.next_switch_us(), side="left"))
                proc(t, x, y, p, i, j)
                e.switch()
                i = j
            proc(t, x, y, p, i, b)
            tt = int(t[b - 1]) + 1
            if dev == "cpu":  # the CPU kernel's float64 L̂ (cf_output only writes the linear value)
                from hybridhdr.reconstruct import _kernels as K
                C = e.C
                lg = C[:, K.C_LF] + (C[:, K.C_L] - C[:, K.C_LF]) * np.exp(-C[:, K.C_ALPHA] * ((tt - C[:, K.C_TU]) * 1e-6))
                outs.append((e.output(tt), lg))
            else:
                img, lg = e.output(tt, with_state=True)
                outs.append((img, lg.reshape(-1)))
        res.append(outs)
    return res


def check_reconstruct(mode="offline", augment=False, spill=False, stream=False, fps=None, resident_chunk=None,
                      clip=False):
    import hybridhdr.reconstruct.cuda as C
    from conftest import ideal_recording
    from hybridhdr.reconstruct import reconstruct
    rec, _ = ideal_recording(height=8, width=10, duration_us=80_000, frame_period_us=30_000, noise_events=40)
    if clip:  # a block clipped in every other frame: the carried variance runs from its last unclipped frame
        import dataclasses
        from hybridhdr import Frames
        f = rec.frames
        codes = np.array(f.images, copy=True)
        top = np.iinfo(codes.dtype).max if codes.dtype.kind in "ui" else 1.0
        codes[1::2, 2:5, 3:7] = top
        rec = dataclasses.replace(rec, frames=Frames(codes, f.t_start_us, f.t_end_us, f.gain, f.iso, f.encoding))
    if spill:
        C.DEVICE_STORE_BYTES = 0
    if stream:
        C.DEVICE_EVENTS_BYTES = 0
    if resident_chunk is not None:
        C.RESIDENT_CHUNK = resident_chunk
    try:
        kw = dict(mode=mode, augment=augment, fps=fps)
        a = reconstruct(rec, "akf", **kw, device="cpu")
        b = reconstruct(rec, "akf", **kw, device="cuda")
    finally:
        C.DEVICE_STORE_BYTES = 2 << 30
        C.DEVICE_EVENTS_BYTES = 4 << 30
        C.RESIDENT_CHUNK = 1 << 25
    same_t = a.t_us.shape == b.t_us.shape and bool(np.all(a.t_us == b.t_us))
    rel = _rel(b.frames, a.frames) if same_t else float("inf")
    ok_info = b.info.get("device", "").startswith("device: cuda") and a.info.get("n_clamped") == b.info.get("n_clamped")
    if mode == "offline":
        ok_info = ok_info and {k: v for k, v in a.info["two_sided"].items() if k != "spilled_to_disk"} == \
            {k: v for k, v in b.info["two_sided"].items() if k != "spilled_to_host"}
    return rel, IMAGE_TOL, f"{len(a)} images; {b.info.get('device')}; {len(rec.events)} events", same_t and ok_info


CHECKS = {
    "akf_paper_linear": lambda: check_akf_engine(),
    "akf_reference_hold": lambda: check_akf_engine("reference_code", "hold"),
    "akf_discrete_thresholds": lambda: check_akf_engine(frame_update="discrete", thresholds=True),
    "akf_la_step_generic": lambda: check_akf_engine(step=True, thresholds=True),
    "akf_windows_split": lambda: check_akf_engine(max_window=97),
    "akf_resident": lambda: check_akf_engine(thresholds=True, resident_chunk=1 << 25),
    "akf_resident_chunks": lambda: check_akf_engine(step=True, thresholds=True, resident_chunk=97),
    "cf": lambda: check_cf_engine("cf"),
    "cf_adaptive": lambda: check_cf_engine("cf", adaptive=True),
    "cf_generic": lambda: check_cf_engine("cf", generic=True, adaptive=True),
    "cf_resident_chunks": lambda: check_cf_engine("cf", resident_chunk=97),
    "highpass": lambda: check_cf_engine("highpass"),
    "direct": lambda: check_cf_engine("direct"),
    "reconstruct_forward": lambda: check_reconstruct("forward", fps=100.0),
    "reconstruct_causal": lambda: check_reconstruct("causal"),
    "reconstruct_two_sided": lambda: check_reconstruct("offline", fps=100.0),
    "reconstruct_two_sided_chunks": lambda: check_reconstruct("offline", fps=100.0, resident_chunk=11),
    "reconstruct_two_sided_per_window": lambda: check_reconstruct("offline", fps=100.0, resident_chunk=0),
    "reconstruct_two_sided_spill_stream": lambda: check_reconstruct("offline", spill=True, stream=True),
    "reconstruct_two_sided_augmented": lambda: check_reconstruct("offline", augment=True),
    "reconstruct_two_sided_clipped": lambda: check_reconstruct("offline", fps=100.0, clip=True),
}


def main() -> int:
    names = [a for a in sys.argv[1:] if not a.startswith("--")] or list(CHECKS)
    from hybridhdr.reconstruct.cuda import cuda_unavailable_reason
    why = cuda_unavailable_reason()
    if why is not None:
        print(json.dumps({"skip": why}))
        return 0
    for name in names:
        try:
            rel, tol, detail, extra_ok = CHECKS[name]()
            print(json.dumps({"check": name, "ok": bool(rel <= tol and extra_ok), "max_rel": rel, "tol": tol,
                              "detail": detail, "simulator": not REAL}), flush=True)
        except Exception as e:  # noqa: BLE001 - reported to the test as a failed check
            import traceback
            print(json.dumps({"check": name, "ok": False, "error": f"{type(e).__name__}: {e}",
                              "trace": traceback.format_exc()[-2000:]}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
