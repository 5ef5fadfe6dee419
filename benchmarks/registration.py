"""Benchmark HDR-reference registration and, as a peer check, CRF estimation.

Usage: ``python benchmarks/registration.py [--quick]``. Prints progress to stderr, then ONE JSON
object on the last stdout line.

Registration: a seeded textured HDR scene (``hybridhdr.simulate.procedural.hdr_scene``), random
homographies (±3° rotation, ±3 % scale, ±8 px shift, small perspective) and frames rendered
through a gamma-2.2 response at exposures 4x below to 4x above the reference (0.5 DN noise).
For each method: mean time per frame (the whole :func:`register` call: photometric matching,
detection on both images, matching, MAGSAC) and the mean corner error against the true
homography. Methods: SURF (mahotas; OpenCV's non-free SURF when available -- the pip wheels
exclude it), SIFT (OpenCV), and each + ECC. The SURF/SIFT time ratio is printed.

Real brackets: Debevec's Memorial Church film scans (``../shared/data/brackets/memorial``)
are aligned to each other (:func:`align_brackets`: the scans are off by up to ~2 px from one another
as published), merged into the HDR reference, and single brackets are warped by known
homographies (rotation up to 5 degrees, scale 0.85-1.0, perspective up to 1e-4/px, shift up to 6 px)
into frames of sizes other than the reference's (360x600, 400x560, 352x576 against 512x768).
Corner error = mean distance, in frame pixels, between the frame's four corners and where the
estimated homography puts the reference points the true one maps there. Reported per method
before ECC (keypoints) and after ECC (refinement kept only when it lowers the residual), with the
ground-truth floor: each aligned bracket registered at identity to the reference (same size).

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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED_DATA, loadavg  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))



def log(*a):
    print(*a, file=sys.stderr, flush=True)


def bench_registration(h, w, n_frames, seed=1):
    from hybridhdr.simulate.procedural import hdr_scene, random_homography, render_frame
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


def _frame_corner_error(H_est, H_true, frame_shape):
    import cv2
    fh, fw = frame_shape[:2]
    c = np.array([[0, 0], [fw - 1, 0], [fw - 1, fh - 1], [0, fh - 1]], np.float64).reshape(-1, 1, 2)
    r = cv2.perspectiveTransform(c, np.linalg.inv(H_true))
    return float(np.mean(np.linalg.norm(cv2.perspectiveTransform(r, np.asarray(H_est, np.float64)) - c, axis=2)))


def _known_homography(rng, ref_hw, frame_wh):
    h, w = ref_hw
    fw, fh = frame_wh
    a = np.deg2rad(rng.uniform(-5, 5))
    c, s = np.cos(a), np.sin(a)
    k = rng.uniform(0.85, 1.0)
    T1 = np.array([[1, 0, -w / 2], [0, 1, -h / 2], [0, 0, 1.0]])
    T2 = np.array([[1, 0, fw / 2 + rng.uniform(-6, 6)], [0, 1, fh / 2 + rng.uniform(-6, 6)], [0, 0, 1.0]])
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    P = np.array([[1, 0, 0], [0, 1, 0], [rng.uniform(-1e-4, 1e-4), rng.uniform(-1e-4, 1e-4), 1.0]])
    H = T2 @ P @ R @ np.diag([k, k, 1.0]) @ T1
    return H / H[2, 2]


def bench_real_brackets(quick: bool, seed: int = 0):
    import cv2

    from hybridhdr.calibrate.crf import debevec
    from hybridhdr.calibrate.hdr_reference import (RegistrationParams, align_brackets, corner_error,
                                                   merge_brackets, register, surf_backend)
    from hybridhdr.formats.brackets import colour_mask, read_bracket_set
    folder = SHARED_DATA
    folder = folder / "brackets" / "memorial"
    if not folder.exists():
        log(f"real brackets: {folder} not found, skipped")
        return {"skipped": f"{folder} not found"}
    t0 = time.perf_counter()
    bs = read_bracket_set(folder)
    ainfo: dict = {}
    al = align_brackets(bs, info=ainfo)
    t_align = time.perf_counter() - t0
    valid = ~colour_mask(al.images, (0, 0, 255))
    E = merge_brackets(al, None, debevec(al, None, mask=valid))
    h, w = E.shape[:2]
    log(f"memorial: {len(bs)} brackets aligned in {t_align:.1f} s "
        f"({ainfo['n_moved']} moved, anchor {bs.files[ainfo['anchor']]}), merged {w}x{h}")
    to_anchor = {d["image"]: np.asarray(d["homography_to_anchor"]) for d in ainfo["pairs"]}
    ks = [2, 4, 6, 8, 10, 12] if quick else list(range(2, 13))
    sizes = [(360, 600), (400, 560), (352, 576)]
    rng = np.random.default_rng(seed)
    cases = []
    for i, k in enumerate(ks * (1 if quick else 2)):
        fw, fh = sizes[i % len(sizes)]
        H = _known_homography(rng, (h, w), (fw, fh))
        A = to_anchor.get(k, np.eye(3))  # one resampling: original bracket -> anchor grid -> frame
        frame = cv2.warpPerspective(np.asarray(bs.images[k]), H @ A, (fw, fh), flags=cv2.INTER_LINEAR)
        cases.append((k, H, frame))
    out = {"data": "brackets/memorial", "reference": f"{w}x{h}", "n_cases": len(cases),
           "surf_backend": surf_backend(), "align_time_s": t_align, "brackets_moved": ainfo["n_moved"]}
    for feat in ("sift", "surf"):
        p = RegistrationParams(features=feat, ecc=True)
        floor = []
        for k in sorted(set(ks)):
            r = register(E, al.images[k], p, valid=valid)
            floor.append(corner_error(r.homography, np.eye(3), (h, w)))
        kp, ecc, ts, status, rows = [], [], [], [], []
        for k, H, frame in cases:
            t1 = time.perf_counter()
            try:
                r = register(E, frame, p, valid=valid)
            except ValueError as e:
                log(f"{feat} bracket {k}: {e}")
                kp.append(np.inf), ecc.append(np.inf), status.append("error")
                continue
            ts.append(time.perf_counter() - t1)
            kp.append(_frame_corner_error(r.info["homography_keypoints"], H, frame.shape))
            ecc.append(_frame_corner_error(r.homography, H, frame.shape))
            status.append(r.info["ecc"]["status"])
            rows.append({"bracket": bs.files[k], "frame": f"{frame.shape[1]}x{frame.shape[0]}",
                         "keypoints_px": kp[-1], "ecc_px": ecc[-1], "ecc": status[-1], "inliers": r.n_inliers})
        out[feat] = {"corner_error_px_median_keypoints": float(np.median(kp)),
                     "corner_error_px_median_ecc": float(np.median(ecc)),
                     "corner_error_px_max_keypoints": float(np.max(kp)), "corner_error_px_max_ecc": float(np.max(ecc)),
                     "identity_floor_px_median": float(np.median(floor)),
                     "ecc_kept": status.count("kept"), "ecc_rejected": status.count("rejected"),
                     "ecc_failed": status.count("failed"), "errors": status.count("error"),
                     "time_per_frame_s": float(np.mean(ts)) if ts else None, "cases": rows}
    log("| features | median corner error, keypoints | after ECC | max after ECC | ECC kept/rejected/failed "
        "| identity floor (reference corners) | s/frame |")
    log("|---|---|---|---|---|---|---|")
    for feat in ("sift", "surf"):
        o = out[feat]
        name = feat.upper() + (" (mahotas)" if feat == "surf" and out["surf_backend"] == "mahotas" else "")
        log(f"| {name} | {o['corner_error_px_median_keypoints']:.3f} px | {o['corner_error_px_median_ecc']:.3f} px "
            f"| {o['corner_error_px_max_ecc']:.3f} px | {o['ecc_kept']}/{o['ecc_rejected']}/{o['ecc_failed']} "
            f"| {o['identity_floor_px_median']:.3f} px | {o['time_per_frame_s']:.2f} |")
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
    ap.add_argument("--quick", action="store_true",
                    help="real brackets: 6 frames; synthetic registration skipped (< 60 s)")
    args = ap.parse_args(argv)
    res = {"benchmark": "registration", "quick": args.quick, "cpu_count": os.cpu_count(),
           "loadavg_start": loadavg()}
    t0 = time.perf_counter()
    import cv2
    res["opencv"] = cv2.__version__
    res["real_brackets"] = bench_real_brackets(args.quick)
    if not args.quick:
        res["registration"] = bench_registration(600, 800, 10)
    res["crf"] = bench_crf()
    res["total_s"] = time.perf_counter() - t0
    res["loadavg_end"] = loadavg()
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
