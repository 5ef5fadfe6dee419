"""Benchmark the learned events-only baselines (E2VID, FireNet) beside the AKF, and ColorVideoVDP.

Usage: ``python benchmarks/learned.py [--quick]``. Prints progress, then ONE JSON object on the last line.

Same synthetic stream as ``benchmarks/akf.py`` (346×260 sensor, drifting Gaussian blobs, about
1 Mev/s here (about 33k events per 30 Hz window), frames every 1/30 s). In one run: E2VID and FireNet end to end through
``reconstruct`` at 30 Hz output (voxel grids + network, PyTorch on ``--device``: the CPU here, a GPU where PyTorch sees one, with the voxel grids built there; ``torch`` threads
= its default), reported as events/s and ms per output frame, and the AKF (``mode="forward"``,
one worker) on the same events and output times. The networks' weights are **random**
(seeded), written by this script in the released checkpoints' layout: speed does not depend on
the values, quality numbers would be meaningless and none are reported. Then ColorVideoVDP's
seconds per frame pair at 346×260 (``standard_hdr_linear`` display), as images and as a 30 Hz
video. The machine is a shared 2-core VM: timings vary by tens of percent from run to run.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from akf import H, W, synth_events, synth_frames  # noqa: E402


def _recording(n, rate_mev_s):
    from hybridhdr import Recording, SensorSize, make_events
    t, x, y, p, dur = synth_events(n, rate_mev_s=rate_mev_s)
    frames = synth_frames(dur)
    return Recording(make_events(t, x, y, p), SensorSize(H, W), frames), dur


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a short stream (finishes in under 60 s)")
    ap.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                    help="PyTorch device of the networks (auto: CUDA when PyTorch sees it); on a GPU the voxel grids "
                         "are built there too (learned.voxel.voxel_grid_torch)")
    args = ap.parse_args(argv)
    import torch

    from hybridhdr.reconstruct.learned.engine import torch_device
    device = torch_device(args.device)
    dev_name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"

    from hybridhdr.reconstruct import reconstruct
    from hybridhdr.reconstruct.learned.networks import E2VIDRecurrent, FireNet
    n = 250_000 if args.quick else 3_000_000
    rate = 1.0  # Mev/s: ~33k events per 30 Hz window
    rec, dur = _recording(n, rate)
    fps = 30.0
    times = np.arange(int(rec.frames.t_mid_us[0]) + int(1e6 / fps), int(rec.events["t"][-1]), int(1e6 / fps),
                      dtype=np.int64)
    res: dict = {"sensor": f"{W}x{H}", "n_events": n, "rate_mev_s": rate, "duration_s": dur / 1e6, "quick": bool(args.quick),
                 "output_hz": fps, "n_outputs": int(len(times)), "cpu_count": os.cpu_count(),
                 "torch": torch.__version__, "torch_threads": torch.get_num_threads(), "device": str(device),
                 "device_name": dev_name,
                 "weights": "random (seeded, written by this script in the released layout): speed only"}
    print(f"{n} events over {dur / 1e6:.2f} s, {len(times)} outputs at {fps:g} Hz", file=sys.stderr)
    with tempfile.TemporaryDirectory() as d:
        for method, cls, arch in (("firenet", FireNet, "FireNet"), ("e2vid", E2VIDRecurrent, "E2VIDRecurrent")):
            torch.manual_seed(0)
            net = cls()
            path = Path(d) / f"{method}.pth.tar"
            torch.save({"arch": arch, "model": net.config, "state_dict": net.state_dict()}, path)
            if device.type == "cuda":  # warm-up: CUDA context, cuDNN autotuning
                reconstruct(rec, method, {"weights": str(path), "device": str(device)}, times_us=times[:3])
            t0 = time.perf_counter()
            v = reconstruct(rec, method, {"weights": str(path), "device": str(device)}, times_us=times)
            el = time.perf_counter() - t0
            ne = int(v.info["n_events_used"])
            res[method] = {"seconds": round(el, 3), "events_per_s": round(ne / el), "ms_per_frame": round(1e3 * el / len(v), 2),
                           "n_frames": len(v), "n_params": int(sum(p.numel() for p in net.parameters()))}
            print(f"{method} on {device}: {ne / el / 1e6:.3f} Mev/s, {1e3 * el / len(v):.1f} ms/frame", file=sys.stderr)
    t0 = time.perf_counter()
    v = reconstruct(rec, "akf", None, times_us=times, mode="forward", thresholds="input")
    el = time.perf_counter() - t0
    res["akf"] = {"seconds": round(el, 3), "events_per_s": round(int(v.info["n_events_used"]) / el),
                  "ms_per_frame": round(1e3 * el / len(v), 2), "n_frames": len(v), "mode": "forward", "workers": 1}
    print(f"akf: {v.info['n_events_used'] / el / 1e6:.3f} Mev/s, {1e3 * el / len(v):.1f} ms/frame", file=sys.stderr)
    try:
        from hybridhdr.evaluate.cvvdp_metric import cvvdp_available, cvvdp_jod
        ok = cvvdp_available()
    except ImportError:
        ok = False
    if ok:
        k = 4 if args.quick else 16
        ref = np.clip(v.frames[-k:], 1e-4, None)
        test = ref * np.exp(0.05 * np.random.default_rng(0).standard_normal(ref.shape))
        cvvdp_jod(test[:1], ref[:1])  # warm-up (loads the CSF tables)
        r_img = cvvdp_jod(test, ref)
        r_vid = cvvdp_jod(test, ref, fps=fps)
        res["cvvdp"] = {"s_per_frame_pair_images": round(r_img.seconds / k, 4),
                        "s_per_frame_pair_video": round(r_vid.seconds / k, 4), "frames": k,
                        "display": r_img.display_line()}
        print(f"cvvdp: {r_img.seconds / k:.3f} s/pair (images), {r_vid.seconds / k:.3f} s/pair (video)",
              file=sys.stderr)
    else:
        res["cvvdp"] = None
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
