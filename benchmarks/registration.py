"""Benchmark HDR-reference registration (issue 6) and, as a peer check, CRF estimation.

Usage: ``python benchmarks/registration.py [--quick]``. Prints progress to stderr, then ONE JSON
object on the last stdout line.

Registration: a seeded textured HDR scene (``hybridhdr.calibrate._photometric_synth``), random
homographies (±3° rotation, ±3 % scale, ±8 px shift, small perspective) and frames rendered
through a gamma-2.2 response at exposures 4x below to 4x above the reference (0.5 DN noise).
For each method: mean time per frame (the whole :func:`register` call: photometric matching,
detection on both images, matching, MAGSAC) and the mean corner error against the true
homography. Methods: SURF (mahotas; OpenCV's non-free SURF when available -- the pip wheels
exclude it), SIFT (OpenCV), and each + ECC. The SURF/SIFT time ratio is printed.

CRF peer: our Debevec vs OpenCV's ``createCalibrateDebevec`` (8-bit 3-channel, as its guards
require) on synthetic gamma brackets; median log-irradiance error and time.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _loadavg():
    try:
        return float(Path("/proc/loadavg").read_text().split()[0])
    except OSError:
        return None


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def bench_registration(h, w, n_frames, seed=1):
    from hybridhdr.calibrate._photometric_synth import hdr_scene, random_homography, render_frame
    from hybridhdr.calibrate.hdr_reference import (RegistrationParams, corner_error, register,
                                                   surf_backend)
    rng = np.random.default_rng(seed)
    E = hdr_scene(h, w, seed=0)
    cases = []
    for _ in range(n_frames):
        H = random_homography(h, w, rng)
        cases.append((H, render_frame(E, H, 0.3 * 2.0 ** rng.uniform(-2, 2), rng)))
    out = {"image": f"{w}x{h}", "n_frames": n_frames, "surf_backend": surf_backend()}
    for feat in ("surf", "sift"):
        for ecc in (False, True):
            name = feat + ("+ecc" if ecc else "")
            errs, ts, inl = [], [], []
            for H, frame in cases:
                t0 = time.perf_counter()
                r = register(E, frame, RegistrationParams(features=feat, ecc=ecc))
                ts.append(time.perf_counter() - t0)
                errs.append(corner_error(r.homography, H, (h, w)))
                inl.append(r.n_inliers)
            out[name] = {"time_per_frame_s": float(np.mean(ts)), "corner_error_px_mean": float(np.mean(errs)),
                         "corner_error_px_max": float(np.max(errs)), "inliers_mean": float(np.mean(inl))}
            log(f"{name:9s} {np.mean(ts):6.2f} s/frame  corner error mean {np.mean(errs):.3f} px "
                f"max {np.max(errs):.3f} px  inliers {np.mean(inl):.0f}")
    out["surf_over_sift_time"] = out["surf"]["time_per_frame_s"] / out["sift"]["time_per_frame_s"]
    return out


def bench_crf(seed=0):
    import cv2

    from hybridhdr.calibrate.crf import debevec, robertson
    from hybridhdr.calibrate.hdr_reference import merge_brackets
    rng = np.random.default_rng(seed)
    h, w = 240, 320
    yy, xx = np.mgrid[0:h, 0:w]
    log_e = -5.0 + 7.0 * xx / (w - 1) + 0.4 * np.sin(yy / 6.0)
    ex = np.array([1 / 64, 1 / 16, 1 / 4, 1.0, 4.0], np.float32)
    imgs = []
    for t in ex:
        z = 255 * np.clip(np.exp(log_e) * t, 0, 1) ** (1 / 2.2) + rng.normal(0, 0.5, log_e.shape)
        g = np.clip(np.round(z), 0, 255).astype(np.uint8)
        imgs.append(np.stack([g, g, g], axis=-1))
    st = np.stack(imgs)[..., 0]
    good = ((st >= 10) & (st <= 245)).any(axis=0)

    def err(E):
        d = np.log(np.maximum(E[good], 1e-30)) - log_e[good]
        return float(np.median(np.abs(d - np.median(d))))

    res = {}
    for name, fn in (("ours_debevec", lambda: debevec(imgs, ex)), ("ours_robertson", lambda: robertson(imgs, ex))):
        t0 = time.perf_counter()
        crf = fn()
        dt = time.perf_counter() - t0
        res[name] = {"time_s": dt, "median_log_error": err(merge_brackets(imgs, ex, crf)[..., 1])}
    for name, make in (("opencv_debevec", lambda: cv2.createCalibrateDebevec()),
                       ("opencv_robertson", lambda: cv2.createCalibrateRobertson())):
        bgr = [np.ascontiguousarray(im) for im in imgs]  # 8-bit 3-channel only (calibration.md)
        t0 = time.perf_counter()
        resp = make().process(bgr, ex)  # (256, 1, 3) linear inverse response
        dt = time.perf_counter() - t0
        g = resp[:, 0, 1].astype(np.float64)
        n_nan = int(np.count_nonzero(~np.isfinite(g)))
        z = np.arange(256)
        ok = np.isfinite(g) & (g > 0)
        g = np.interp(z, z[ok], g[ok])
        from hybridhdr.calibrate.crf import CRF
        lg = np.maximum.accumulate(np.log(np.maximum(g, 1e-30)))
        crf = CRF(lg - lg[128])
        res[name] = {"time_s": dt, "median_log_error": err(merge_brackets([im[..., 1] for im in imgs], ex, crf)),
                     "nan_codes": n_nan}
    res["opencv_over_ours_debevec_time"] = res["opencv_debevec"]["time_s"] / res["ours_debevec"]["time_s"]
    for k, v in res.items():
        if isinstance(v, dict):
            log(f"{k:17s} {v['time_s']:.3f} s  median |dlog E| {v['median_log_error']:.4f}")
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="640x480, 3 frames (< 60 s)")
    args = ap.parse_args(argv)
    res = {"benchmark": "registration", "quick": args.quick, "cpu_count": os.cpu_count(),
           "loadavg_start": _loadavg()}
    t0 = time.perf_counter()
    if args.quick:
        res["registration"] = bench_registration(480, 640, 3)
    else:
        res["registration"] = bench_registration(600, 800, 10)
    res["crf"] = bench_crf()
    res["total_s"] = time.perf_counter() - t0
    res["loadavg_end"] = _loadavg()
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
