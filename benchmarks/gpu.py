"""Benchmark the GPU paths: the CUDA AKF and CF (``hybridhdr.reconstruct.cuda``) and FireNet on PyTorch.

Usage: ``python benchmarks/gpu.py [--quick] [--profile] [--no-cpu] [--skip hd,agreement,firenet]
[--hd-events N] [--reps N]``. Prints progress on stderr, then ONE JSON object on the last stdout
line. ``--profile`` adds, for each resident case, a run with every phase synchronised and timed
(``hybridhdr._util.phases`` with the device synchronised: grouping steps, walks, frame switches, output kernels and
copies, fusion; the plain run stays the figure), the previous per-window grouping beside the
forward AKF, and host profiles (cProfile) of ``reconstruct`` and FireNet. Without a usable CUDA device (or without ``numba.cuda``) it prints
``{"skipped": "<why>"}`` and exits 0.

Measured (goals on an H100/H200):

* ``transfer_pageable`` / ``transfer_pinned``: host -> device copy of the events (13 bytes each),
  one pageable copy per column vs chunked through pinned staging buffers (what the package uses).
* ``walk_breakdown``: where the resident walk's time goes: the events grouped once, then
  simplified walks (events alone; plus process noise; plus frame fusion) and the package's walk
  (plus the isolated-pixel term, the refractory term, R's interpolation, censored bounds) over
  the same groups, in Gev/s, with each added term's share of the package's walk.
* ``end_to_end_file``: ``reconstruct(path, device="cuda")`` forward at 30 Hz from a container
  file against reading (decoding) the file's events alone (goal: >= 0.5x the decoder's rate).
* ``akf_forward_hd``: the forward AKF at 1280x720 on ``benchmarks/akf.py``'s ``synth_events_hd``
  stream (20 M events over 1 s; 5 M with --quick), 30 Hz frames and 30 Hz outputs copied back,
  events resident on the device: Mev/s (goal >= 1000). Beside it the same through
  ``reconstruct(..., device="cuda")`` end to end in memory (events uploaded window by window)
  and the CPU path (``n_workers`` = all cores) on the same stream.
* ``akf_two_sided_hd``: the default offline two-sided AKF, events resident (goal >= 400 Mev/s),
  end to end through ``reconstruct``, and the CPU beside it.
* ``cf_hd``: the complementary filter, events resident.
* ``agreement``: GPU vs CPU on a 346x260 case: float64 L̂ and P of the forward engine (relative,
  goal <= 1e-9) and the two-sided images through ``reconstruct`` (float32, relative).
* ``firenet``: ms per frame at 1280x720 and 346x260 on the GPU (voxel grids built on the device,
  network and recurrent state there, ``reconstruct`` end to end at 30 Hz; random seeded weights:
  speed only) and on the CPU (a few frames), plus the network step alone on the GPU (goal <= 5 ms
  at 1280x720), a one-frame call (checkpoint load and network build included) and the marginal
  time per further frame.

Each timing is the best of ``--reps`` runs after a warm-up that compiles the kernels (compile
time reported). Speed figures depend on the card: the JSON names it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def _best(fn, reps):
    best = float("inf")
    out = None
    for _ in range(reps):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _recording(t, x, y, p, frames, shape):
    from hybridhdr import Recording, SensorSize, make_events
    return Recording(make_events(t, x, y, p), SensorSize(*shape), frames)


def _make_engine_factory(shape, method="akf", params=None):
    """Engines as ``reconstruct`` builds them (measurements from the frames, built-in profile)."""
    from hybridhdr.camera.profile import load_profile
    from hybridhdr.reconstruct.api import ReconstructRequest, engine_for, make_params
    p = make_params(method, params)
    prof = load_profile(None)

    def make(fr, ev, backward, n_workers=1):
        pp = p.replace(contrast_threshold_on=p.c_off, contrast_threshold_off=p.c_on) if backward else p
        req = ReconstructRequest.build(method, pp, mode="forward", profile=prof, device="cuda")
        return engine_for(req, shape, fr, ev)
    return make, p


def _phases(fn):
    """``fn()`` once more under :func:`hybridhdr._util.phases.timing` with the device synchronised
    around every phase (slower than the plain run, which is the figure; this says where the time
    goes). Returns (seconds of the profiled run, phase table)."""
    from hybridhdr._util import phases as PH
    from hybridhdr.reconstruct.cuda import _cuda
    with PH.timing(sync=_cuda().synchronize) as tm:
        t0 = time.perf_counter()
        fn()
        el = time.perf_counter() - t0
    rows = tm.report()["phases"]
    tab = {k: {"calls": v["calls"], "total_s": round(v["s"], 5), "host_s": round(v.get("host_s", 0.0), 5)}
           for k, v in sorted(rows.items(), key=lambda kv: -kv[1]["s"])}
    tab["_unaccounted_s"] = round(el - sum(v["total_s"] for v in tab.values()), 5)
    return round(el, 4), tab


def _log_phases(name, el, tab):
    log(f"  phases of {name} (synchronised run, {el * 1e3:.1f} ms): phase calls total_ms host_ms")
    for k, v in tab.items():
        if isinstance(v, dict):
            log(f"    {k:18s} {v['calls']:6d} {v['total_s'] * 1e3:9.2f} {v['host_s'] * 1e3:9.2f}")
    log(f"    (outside the phases: {tab['_unaccounted_s'] * 1e3:.2f} ms: driver, Python, launches between phases)")


def _cprofile(fn, top=18):
    """Host-side profile of ``fn()`` (cProfile, no synchronisation added): the functions with the
    most own time, as lines ``tottime cumtime ncalls function``."""
    import cProfile
    import io
    import pstats
    pr = cProfile.Profile()
    pr.enable()
    try:
        fn()
    finally:
        pr.disable()
    st = pstats.Stats(pr, stream=io.StringIO())
    rows = []
    for (fname, line, func), (cc, nc, tt, ct, _) in st.stats.items():
        rows.append((tt, ct, nc, f"{Path(fname).name}:{line}({func})"))
    rows.sort(reverse=True)
    out = [f"{tt:.4f} {ct:.4f} {nc} {name}" for tt, ct, nc, name in rows[:top]]
    # and the toolkit's own functions by cumulative time (which step of reconstruct holds the time)
    own = sorted(((ct, tt, nc, f"{Path(fname).parent.name}/{Path(fname).name}:{line}({func})")
                  for (fname, line, func), (cc, nc, tt, ct, _) in st.stats.items() if "hybridhdr" in fname),
                 reverse=True)
    out.append("-- hybridhdr functions by cumulative time:")
    out += [f"{tt:.4f} {ct:.4f} {nc} {name}" for ct, tt, nc, name in own[:top]]
    return out


def gpu_akf_cf(t, x, y, p, frames, shape, reps, res_key, res, cpu_workers, run_cpu=True, profile=False):
    """Forward, two-sided and CF on the GPU (resident and end to end) and the CPU beside them;
    with ``profile``, each resident case once more with phase timings and ``reconstruct``'s host
    profile."""
    from numba import cuda

    from hybridhdr.reconstruct import reconstruct
    from hybridhdr.reconstruct.cuda import DeviceEvents, _run_pass_device, cuda_two_sided_iter
    from hybridhdr.reconstruct.event_arrays import EventArrays
    from hybridhdr.reconstruct.smoother import output_times
    n = t.shape[0]
    ev = EventArrays(t, x, y, p, shape)
    times = output_times(frames.t_mid_us, int(t[-1]), fps=30.0)
    out: dict = {"sensor": f"{shape[1]}x{shape[0]}", "n_events": int(n), "n_outputs": int(times.size)}

    def upload(pinned):
        d = DeviceEvents.upload(ev, pinned=pinned)
        cuda.synchronize()
        return d
    for pinned in (False, True):
        tr, dev = _best(lambda: upload(pinned), reps)
        key = "transfer_pinned" if pinned else "transfer_pageable"
        out[key] = {"seconds": round(tr, 4), "gb_per_s": round(13 * n / tr / 1e9, 2),
                    "mev_s": round(n / tr / 1e6, 1)}
        log(f"  transfer of {n} events, {'pinned, chunked' if pinned else 'pageable'}: {tr * 1e3:.1f} ms "
            f"({13 * n / tr / 1e9:.1f} GB/s, {n / tr / 1e6:.0f} Mev/s)")
    out["transfer"] = out["transfer_pinned"]

    make, params = _make_engine_factory(shape)

    def forward():
        eng = make(frames, None, False)
        for tt, _ in _run_pass_device(eng, dev, times, None):
            eng.output(tt)  # the linear image, computed on the device and copied back
        cuda.synchronize()
        return eng.n_events
    el, ne = _best(forward, reps)
    out["akf_forward_resident"] = {"seconds": round(el, 4), "mev_s": round(ne / el / 1e6, 1), "events": int(ne)}
    log(f"  AKF forward, events resident: {ne / el / 1e6:.1f} Mev/s ({el * 1e3:.1f} ms)")
    if profile:
        out["akf_forward_resident"]["phases_run_s"], out["akf_forward_resident"]["phases"] = pe = _phases(forward)
        _log_phases("the resident forward AKF", *pe)
        # the previous schedule beside it: resident events grouped window by window
        import hybridhdr.reconstruct.cuda as C
        keep, C.RESIDENT_CHUNK = C.RESIDENT_CHUNK, 0
        try:
            el_w, _ = _best(forward, reps)
            out["akf_forward_resident_per_window_grouping"] = {"seconds": round(el_w, 4),
                                                               "mev_s": round(ne / el_w / 1e6, 1)}
            log(f"  AKF forward, events resident, grouped per window (previous schedule): "
                f"{ne / el_w / 1e6:.1f} Mev/s ({el_w * 1e3:.1f} ms)")
            pe = _phases(forward)
            out["akf_forward_resident_per_window_grouping"]["phases"] = pe[1]
            _log_phases("the resident forward AKF grouped per window", *pe)
        finally:
            C.RESIDENT_CHUNK = keep

    from hybridhdr.camera import load_profile, profile_for_frames
    fprof = profile_for_frames(load_profile(None), frames)  # the engines' built-in profile
    # as reconstruct runs it: a clipped code does not restart its pixel's carried variance
    cens = (int(fprof.clip_low_code), int(fprof.clip_high_code)) if params.saturation == "bound" else None

    def two_sided():
        k = 0
        for _ in cuda_two_sided_iter(ev, frames, make, times, offset=params.intensity_offset,
                                     carried_variance=params.carried_variance(), device_events=dev,
                                     censored_codes=cens):
            k += 1
        cuda.synchronize()
        return k
    el2, k = _best(two_sided, reps)
    out["akf_two_sided_resident"] = {"seconds": round(el2, 4), "mev_s": round(n / el2 / 1e6, 1), "outputs": k}
    log(f"  AKF two-sided, events resident: {n / el2 / 1e6:.1f} Mev/s ({el2 * 1e3:.1f} ms)")
    if profile:
        out["akf_two_sided_resident"]["phases_run_s"], out["akf_two_sided_resident"]["phases"] = pe = \
            _phases(two_sided)
        _log_phases("the resident two-sided AKF", *pe)

    make_cf, _ = _make_engine_factory(shape, "cf")

    def cf():
        eng = make_cf(frames, None, False)
        for tt, _ in _run_pass_device(eng, dev, times, None):
            eng.output(tt)
        cuda.synchronize()
        return eng.n_events
    el3, ne3 = _best(cf, reps)
    out["cf_resident"] = {"seconds": round(el3, 4), "mev_s": round(ne3 / el3 / 1e6, 1)}
    log(f"  CF forward, events resident: {ne3 / el3 / 1e6:.1f} Mev/s ({el3 * 1e3:.1f} ms)")
    if profile:
        out["cf_resident"]["phases_run_s"], out["cf_resident"]["phases"] = pe = _phases(cf)
        _log_phases("the resident CF", *pe)

    section_breakdown(dev, shape, frames, out)
    rec = _recording(t, x, y, p, frames, shape)
    section_file(rec, n, out, reps)
    for mode, key in (("forward", "akf_forward"), ("offline", "akf_two_sided")):
        el, v = _best(lambda: reconstruct(rec, "akf", mode=mode, fps=30.0, device="cuda", thresholds="input"), 1)
        out[f"{key}_reconstruct_gpu"] = {"seconds": round(el, 3), "mev_s": round(n / el / 1e6, 1),
                                         "device_line": v.info.get("device")}
        log(f"  {key} through reconstruct on the GPU: {n / el / 1e6:.1f} Mev/s ({el * 1e3:.0f} ms)")
        if profile:
            rows = _cprofile(lambda: reconstruct(rec, "akf", mode=mode, fps=30.0, device="cuda", thresholds="input"))
            out[f"{key}_reconstruct_gpu"]["host_profile"] = rows
            log(f"  host profile of reconstruct {mode} on the GPU (tottime cumtime ncalls function):")
            for r in rows:
                log("    " + r)
        if run_cpu:
            el_c, _ = _best(lambda: reconstruct(rec, "akf", mode=mode, fps=30.0, n_workers=cpu_workers, thresholds="input"), 1)
            out[f"{key}_reconstruct_cpu"] = {"seconds": round(el_c, 3), "mev_s": round(n / el_c / 1e6, 1),
                                             "workers": cpu_workers}
            log(f"  {key} through reconstruct on the CPU ({cpu_workers} workers): {n / el_c / 1e6:.1f} Mev/s")
    res[res_key] = out
    return dev


def section_breakdown(dev, shape, frames, out):
    """Where the resident walk's time goes: the events grouped by pixel once (all of them, one
    window), then the package's walk and the simplified walks of :func:`_simple_walk_kernel` over
    the same groups, and one output kernel; each term's share is the time it adds over the
    simpler variant, as a share of the package's walk (:mod:`_gpu_simple`)."""
    import numpy as np
    from numba import cuda

    from hybridhdr.reconstruct.cuda import _grid, _Grouper
    H, W = shape
    n_pix = H * W
    n = min(dev.n, 1 << 24)
    make, params = _make_engine_factory(shape)
    eng = make(frames, None, False)
    eng.start(None)
    gr = _Grouper(n_pix)
    gr.group(dev.x, dev.y, 0, n, W)
    cuda.synchronize()
    S0 = eng.S.copy_to_host()
    from _gpu_simple import k_simple
    g = _grid(n_pix)
    pr = params

    def timed(fn, reps=3):
        best = float("inf")
        for _ in range(reps):
            eng.S.copy_to_device(S0)
            cuda.synchronize()
            t0 = time.perf_counter()
            fn()
            cuda.synchronize()
            best = min(best, time.perf_counter() - t0)
        return best
    rows = {}
    for level, name in ((0, "events"), (1, "events+process_noise"), (2, "events+process_noise+frame_fusion")):
        fn = (lambda lv=level: k_simple[g](dev.t, dev.p, gr.start, gr.grp, eng.S, lv, pr.c_on, pr.c_off,
                                             pr.process_noise_per_s, n_pix))
        fn()
        rows[name] = timed(fn)
    te_in = cuda.to_device(np.full(n_pix, int(frames.t_mid_us[0]), np.int64))
    te_out = cuda.device_array(n_pix, np.int64)

    def full():  # the package's walk, launched as CudaAKFEngine._walk launches it
        eng.ck.k_akf_walk[g](dev.t, dev.x, dev.y, dev.p, 0, H, W, gr.start, gr.grp, te_in, te_out, eng.S,
                              eng.has_la_step, eng.seg_t0, eng.seg_inv_t, pr.c_on, pr.c_off, pr.process_noise_per_s,
                              pr.isolated_noise_per_s, pr.refractory_noise, np.int64(pr.refractory_period_us),
                              eng.noise_form, eng.con_px, eng.coff_px, eng.ccount)
    full()
    rows["package_walk"] = timed(full)
    outl = cuda.device_array(n_pix, np.float32)
    e0 = cuda.device_array(0, np.float64)
    rows["one_output"] = timed(lambda: eng.ck.k_akf_output[g](eng.S, eng.seg_t0, eng.seg_inv_t,
                                                               float(frames.t_mid_us[-1]), outl, e0, e0, n_pix))
    tot = rows["package_walk"]
    prev = 0.0
    shares = {}
    for name in ("events", "events+process_noise", "events+process_noise+frame_fusion", "package_walk"):
        shares[name.split("+")[-1] if name != "package_walk" else "isolated_refractory_interpolation_bounds"] = \
            round((rows[name] - prev) / tot, 3)
        prev = rows[name]
    out["walk_breakdown"] = {"events": int(n), "seconds": {k: round(v, 5) for k, v in rows.items()},
                             "gev_s": {k: round(n / v / 1e9, 2) for k, v in rows.items() if k != "one_output"},
                             "share_of_package_walk": shares}
    log(f"  walk breakdown over {n} grouped events: " + ", ".join(f"{k} {n / v / 1e9:.2f} Gev/s"
                                                                 for k, v in rows.items() if k != "one_output")
        + f"; one output {rows['one_output'] * 1e3:.2f} ms; shares of the walk {shares}")


def section_file(rec, n, out, reps):
    """End to end from a file: the container's events read (decoded) alone, then
    ``reconstruct(path, device="cuda")`` forward at 30 Hz; the ratio of the two rates."""
    import tempfile
    from hybridhdr.formats.container import RecordingFile, write_recording
    from hybridhdr.reconstruct import reconstruct
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "hd.h5"
        write_recording(rec, path)

        def decode():  # the columns as reconstruct reads them (RecordingFile.iter_event_columns)
            k = 0
            with RecordingFile(path) as f:
                for c in f.iter_event_columns(1 << 21):
                    k += len(c[0])
            return k
        el_d, k = _best(decode, reps)

        def e2e():
            with RecordingFile(path) as f:
                return reconstruct(f, "akf", mode="forward", fps=30.0, device="cuda", chunk_events=1 << 21, thresholds="input")
        e2e()
        el_e, v = _best(e2e, reps)
    out["end_to_end_file"] = {"decode_mev_s": round(n / el_d / 1e6, 1), "reconstruct_cuda_forward_mev_s":
                              round(n / el_e / 1e6, 1), "ratio_to_decoder": round(el_d / el_e, 2),
                              "device_line": v.info.get("device")}
    log(f"  end to end from a file: decoding alone {n / el_d / 1e6:.1f} Mev/s, reconstruct --device cuda "
        f"(forward, 30 Hz) {n / el_e / 1e6:.1f} Mev/s: {el_d / el_e:.2f}x the decoder's rate")


def agreement(res):
    """GPU vs CPU: the forward engine's float64 state, and two-sided images through reconstruct."""
    from akf import H, W, synth_events, synth_frames
    from hybridhdr.camera import default_profile
    from hybridhdr.reconstruct import AKFParams, FrameMeasurements, reconstruct
    from hybridhdr.reconstruct._engine import AKFEngine
    from hybridhdr.reconstruct.cuda import CudaAKFEngine
    t, x, y, p, dur = synth_events(300_000, rate_mev_s=3.0)
    fr = synth_frames(dur)
    params = AKFParams()
    outs = []
    for cls in (AKFEngine, CudaAKFEngine):
        m = FrameMeasurements(fr, (H, W), default_profile(), intensity_offset=params.intensity_offset)
        eng = cls((H, W), m, params)
        eng.start(None)
        o = []
        n = t.shape[0]
        for a, b in zip([0, n // 3, 2 * n // 3], [n // 3, 2 * n // 3, n]):
            i = a
            while eng.next_switch_us() is not None and eng.next_switch_us() <= t[b - 1]:
                j = i + int(np.searchsorted(t[i:b], eng.next_switch_us(), side="left"))
                eng.process(t, x, y, p, i, j)
                eng.switch()
                i = j
            eng.process(t, x, y, p, i, b)
            o.append(eng.output(int(t[b - 1]) + 1, with_state=True))
        outs.append(o)
        eng.close()

    def rel(a, b):
        return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)))
    r_l = max(rel(g[1], c[1]) for c, g in zip(*outs))
    r_p = max(rel(g[2], c[2]) for c, g in zip(*outs))
    rec = _recording(t, x, y, p, fr, (H, W))
    a = reconstruct(rec, "akf", fps=100.0, thresholds="input")
    b = reconstruct(rec, "akf", fps=100.0, device="cuda", thresholds="input")
    r_img = rel(b.frames, a.frames) if a.frames.shape == b.frames.shape else float("inf")
    res["agreement"] = {"case": f"{W}x{H}, {t.shape[0]} events", "forward_L_max_rel": r_l, "forward_P_max_rel": r_p,
                        "state_goal": 1e-9, "state_met": bool(max(r_l, r_p) <= 1e-9),
                        "two_sided_images_max_rel": r_img, "images": len(a)}
    log(f"  agreement: L {r_l:.2e}, P {r_p:.2e}, two-sided images {r_img:.2e}")


def firenet(res, quick, reps=2, profile=False):
    import torch

    from akf import synth_events, synth_events_hd, synth_frames
    from hybridhdr.reconstruct import reconstruct
    from hybridhdr.reconstruct.learned.engine import Reconstructor, load_network
    from hybridhdr.reconstruct.learned.networks import FireNet
    from hybridhdr.reconstruct.learned.params import FireNetParams
    from hybridhdr.reconstruct.learned.voxel import voxel_grid_torch
    torch.backends.cudnn.benchmark = True
    out: dict = {}
    with tempfile.TemporaryDirectory() as d:
        torch.manual_seed(0)
        net = FireNet()
        path = Path(d) / "firenet.pth.tar"
        torch.save({"arch": "FireNet", "model": net.config, "state_dict": net.state_dict()}, path)
        for (h, w), synth, n in (((720, 1280), synth_events_hd, 2_000_000 if quick else 6_000_000),
                                 ((260, 346), synth_events, 300_000 if quick else 1_000_000)):
            t, x, y, p, dur = synth(n) if synth is synth_events_hd else synth(n, rate_mev_s=1.0)
            fr = synth_frames(dur, h=h, w=w)
            rec = _recording(t, x, y, p, fr, (h, w))
            times = np.arange(int(t[0]) + 33_333, int(t[-1]), 33_333, dtype=np.int64)
            key = f"{w}x{h}"
            o: dict = {"n_events": n, "frames": int(times.size)}
            reconstruct(rec, "firenet", {"weights": str(path), "device": "cuda"}, times_us=times[:3])  # warm-up
            torch.cuda.synchronize()
            el, v = _best(lambda: reconstruct(rec, "firenet", {"weights": str(path), "device": "cuda"},
                                              times_us=times), reps)
            o["gpu_end_to_end_ms_per_frame"] = round(1e3 * el / len(v), 2)
            # fixed costs (checkpoint load, network build, first window) apart from the per-frame
            # cost: one frame alone, and the marginal time per further frame
            el1, _ = _best(lambda: reconstruct(rec, "firenet", {"weights": str(path), "device": "cuda"},
                                               times_us=times[:1]), reps)
            o["gpu_one_frame_call_ms"] = round(1e3 * el1, 2)
            if len(v) > 1:
                o["gpu_marginal_ms_per_frame"] = round(1e3 * (el - el1) / (len(v) - 1), 2)
            if profile:
                rows = _cprofile(lambda: reconstruct(rec, "firenet", {"weights": str(path), "device": "cuda"},
                                                     times_us=times))
                o["host_profile"] = rows
                log(f"  host profile of FireNet {w}x{h} on the GPU, {times.size} frames "
                    "(tottime cumtime ncalls function):")
                for r in rows:
                    log("    " + r)
            # the network step alone on a device voxel grid (the recurrent state kept on the device)
            netd, dev = load_network("firenet", FireNetParams(weights=str(path), device="cuda"))
            r = Reconstructor(netd, dev, (h, w), clip=True)
            i1 = int(np.searchsorted(t, times[0]))
            g = voxel_grid_torch(*(torch.from_numpy(a[:i1].astype(np.int64)).cuda() for a in (t, x, y, p)), 5, (h, w))
            for _ in range(3):
                r.step(g)
            torch.cuda.synchronize()
            k = 20
            t0 = time.perf_counter()
            for _ in range(k):
                r.step(g)
            torch.cuda.synchronize()
            o["gpu_network_step_ms"] = round(1e3 * (time.perf_counter() - t0) / k, 2)
            k_cpu = min(times.size, 3 if h == 720 else 10)
            el_c, vc = _best(lambda: reconstruct(rec, "firenet", {"weights": str(path), "device": "cpu"},
                                                 times_us=times[:k_cpu]), 1)
            o["cpu_end_to_end_ms_per_frame"] = round(1e3 * el_c / len(vc), 1)
            o["cpu_threads"] = torch.get_num_threads()
            out[key] = o
            log(f"  FireNet {key}: GPU {o['gpu_end_to_end_ms_per_frame']} ms/frame end to end "
                f"({o['gpu_one_frame_call_ms']} ms for a 1-frame call, marginal "
                f"{o.get('gpu_marginal_ms_per_frame')} ms per further frame), "
                f"{o['gpu_network_step_ms']} ms network step; CPU {o['cpu_end_to_end_ms_per_frame']} ms/frame")
    out["goal_ms_per_frame_1280x720"] = 5.0
    out["cudnn_benchmark"] = True  # set by this script (the library leaves PyTorch's global flags alone)
    res["firenet"] = out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller streams, one repetition")
    ap.add_argument("--reps", type=int, default=None, help="repetitions per timing (best kept)")
    ap.add_argument("--skip", default="", help="comma-separated parts to skip: hd, agreement, firenet")
    ap.add_argument("--hd-events", type=int, default=None,
                    help="events of the 1280x720 stream (default 20 M; 5 M with --quick)")
    ap.add_argument("--profile", action="store_true",
                    help="also time each phase (synchronised runs) and profile reconstruct's host side")
    ap.add_argument("--no-cpu", action="store_true", help="skip the CPU reconstruct runs beside the GPU ones")
    ap.add_argument("--firenet-reps", type=int, default=2, help="repetitions of FireNet's end-to-end timing")
    args = ap.parse_args(argv)
    skip = set(filter(None, args.skip.split(",")))
    from hybridhdr.reconstruct.cuda import cuda_unavailable_reason, device_name
    why = cuda_unavailable_reason()
    if why is None and os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        why = "NUMBA_ENABLE_CUDASIM=1: the simulator has no meaningful speed"
    if why is not None:
        print(json.dumps({"skipped": why}))
        return 0
    import numba
    res: dict = {"device": device_name(), "quick": bool(args.quick), "numba": numba.__version__,
                 "cpu_count": os.cpu_count()}
    try:
        import numba_cuda
        res["numba_cuda"] = getattr(numba_cuda, "__version__", "?")
    except ImportError:
        res["numba_cuda"] = None
    reps = args.reps or (1 if args.quick else 2)
    from akf import HD_H, HD_W, synth_events_hd, synth_frames
    t_all = time.perf_counter()
    # warm-up: compile every kernel on a small case (reported: numba.cuda compiles on first launch)
    def section(name, fn):
        """Run one part; an error is reported in the JSON (the other parts still run)."""
        try:
            fn()
        except Exception as e:  # noqa: BLE001 - reported, not hidden
            import traceback
            res.setdefault("errors", {})[name] = f"{type(e).__name__}: {e}"
            log(f"ERROR in {name}:\n{traceback.format_exc()}")

    def warmup():
        log("compiling the kernels (small case) ...")
        t0 = time.perf_counter()
        tw, xw, yw, pw, durw = synth_events_hd(200_000)
        frw = synth_frames(durw, h=HD_H, w=HD_W)
        gpu_akf_cf(tw, xw, yw, pw, frw, (HD_H, HD_W), 1, "warmup", {}, 1, run_cpu=False)
        res["compile_and_warmup_s"] = round(time.perf_counter() - t0, 1)
    section("warmup", warmup)
    if "agreement" not in skip:
        log("agreement with the CPU path ...")
        section("agreement", lambda: agreement(res))

    def hd_part():
        n = args.hd_events or (5_000_000 if args.quick else 20_000_000)
        log(f"1280x720: {n} events ...")
        t, x, y, p, dur = synth_events_hd(n)
        fr = synth_frames(dur, h=HD_H, w=HD_W)
        gpu_akf_cf(t, x, y, p, fr, (HD_H, HD_W), reps, "hd", res, min(16, os.cpu_count() or 1),
                   run_cpu=not args.no_cpu, profile=args.profile)
        hd = res["hd"]
        res["goals"] = {"akf_forward_hd_mev_s": 1000, "akf_two_sided_hd_mev_s": 400,
                        "forward_met": hd["akf_forward_resident"]["mev_s"] >= 1000,
                        "two_sided_met": hd["akf_two_sided_resident"]["mev_s"] >= 400}
    if "hd" not in skip:
        section("hd", hd_part)
    if "firenet" not in skip:
        try:
            import torch
            if torch.cuda.is_available():
                log("FireNet ...")
                section("firenet", lambda: firenet(res, args.quick, args.firenet_reps, args.profile))
            else:
                res["firenet"] = {"skipped": "PyTorch sees no CUDA device"}
        except ImportError as e:
            res["firenet"] = {"skipped": f"PyTorch missing ({e})"}
    res["total_s"] = round(time.perf_counter() - t_all, 1)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
