"""``hybridhdr calibrate crf`` and ``hybridhdr calibrate hdr-reference`` (see docs/calibrate.md).

Heavy imports happen inside the command functions.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import sys
import time
from pathlib import Path

from .._util.atomic import atomic_path, write_json_atomic
from .._util.cliargs import COMMON_NO_JSON, HelpFormatter, json_command, nonneg_float, positive_float, positive_int


def register(steps) -> None:
    """Add the ``crf`` and ``hdr-reference`` steps to ``hybridhdr calibrate``."""
    p = steps.add_parser(
        "crf", help="camera response (Debevec/Robertson) and the AKF noise profile from exposure brackets",
        formatter_class=HelpFormatter, parents=[COMMON_NO_JSON],
        description="Estimate the camera response function from a bracket set (docs/brackets.md), then the "
                    "certainty/weighting function f_w, the noise level sigma^2_im and the covariance lookup "
                    "R(code) = sigma^2_im / f_w (AKF eqs. 4-6). Writes OUT/crf.json, OUT/camera_profile.json "
                    "(read by 'hybridhdr reconstruct --profile'), OUT/report.json and OUT/crf_profile.png.")
    p.add_argument("brackets", type=Path, metavar="BRACKETS_DIR",
                   help="bracket set folder: brackets.json, or images + exposures.txt, or EXIF exposures")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the files a previous run wrote in a non-empty --out (refused without it)")
    p.add_argument("--method", default="debevec", choices=["debevec", "robertson"], help="CRF estimator")
    p.add_argument("--smoothness", type=nonneg_float, default=10.0,
                   help="Debevec smoothness lambda (scaled by sqrt(samples*images/codes))")
    p.add_argument("--samples", type=positive_int, default=400, help="Debevec: pixels sampled per channel")
    p.add_argument("--seed", type=int, default=0, help="seed of the pixel sampling")
    p.add_argument("--sigma2-im", type=positive_float, default=None,
                   help="frame noise variance in intensity^2 (I in [0,1], top code = 1); default: estimated "
                        "(temporal from equal exposures, else spatial Immerkaer)")
    p.add_argument("--floor", type=float, default=0.09, help="floor of f_w (eq. 6 saturation; AKF code 0.09)")
    p.add_argument("--domain", default="log", choices=["log", "linear"],
                   help="certainty as the CRF slope w.r.t. log exposure (default) or linear exposure (eq. 4)")
    p.add_argument("--ignore-colour", default=None, metavar="R,G,B",
                   help="exclude pixels of this exact colour in any image (e.g. 0,0,255 for Debevec's scans)")
    p.add_argument("--name", default="", help="camera name stored in the profile")
    p.set_defaults(func=run_crf)

    q = steps.add_parser(
        "hdr-reference", help="merge brackets into an HDR reference (EXR); register it to a recording's frames",
        formatter_class=HelpFormatter, parents=[COMMON_NO_JSON],
        description="Merge a bracket set into float32 relative radiance weighted by the certainty function "
                    "(log domain with a CRF; Poisson ML in the linear domain for RAW/linear brackets) and write "
                    "OpenEXR. With --register, register the reference to every frame of a recording (SURF or "
                    "SIFT keypoints, ratio test, MAGSAC homography, optional ECC) and write a NEW recording with "
                    "the warped references. Writes OUT.json (report) and OUT.png (the tone-mapped reference at "
                    "full size; with --register: reference, frame, overlay).")
    q.add_argument("brackets", type=Path, metavar="BRACKETS_DIR", help="bracket set folder")
    q.add_argument("--crf", type=Path, default=None,
                   help="crf.json from 'calibrate crf' (default: estimated here with Debevec for coded images)")
    q.add_argument("--out", type=Path, required=True, help="output EXR file (RGB or Y, float32)")
    q.add_argument("--weighting", default="certainty", choices=["certainty", "hat"], help="merge weight per code")
    q.add_argument("--ignore-colour", default=None, metavar="R,G,B", help="pixels of this colour are not sampled")
    q.add_argument("--register", type=Path, default=None, metavar="REC", help="recording whose frames to register to")
    q.add_argument("--out-recording", type=Path, default=None, metavar="REC2",
                   help="new recording (hybridhdr HDF5) with the warped references; required with --register")
    q.add_argument("--overwrite", action="store_true",
                   help="replace an existing --out EXR (and its .json/.png beside it) and --out-recording")
    q.add_argument("--features", default="surf", choices=["surf", "sift"],
                   help="keypoints: SURF (mahotas, or OpenCV non-free when present) or SIFT")
    q.add_argument("--ecc", action=argparse.BooleanOptionalAction, default=True,
                   help="ECC refinement in the frame's grid, kept only when it lowers the residual")
    q.add_argument("--align", action=argparse.BooleanOptionalAction, default=True,
                   help="align the brackets to each other before merging (AlignMTB, then a keypoint homography; "
                        "each kept only when it lowers the residual, so tripod brackets stay as they are)")
    q.add_argument("--ratio", type=positive_float, default=0.75, help="Lowe ratio-test threshold")
    q.add_argument("--ransac-px", type=positive_float, default=3.0, help="MAGSAC/RANSAC inlier threshold in pixels")
    q.set_defaults(func=run_hdr_reference)


def _write_json(path: Path, obj) -> None:
    write_json_atomic(path, obj, default=_default)


def _default(o):
    import numpy as np
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _colour(text):
    if text is None:
        return None
    try:
        vals = tuple(int(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 3:
        raise ValueError(f"--ignore-colour must be R,G,B integers, got {text!r}")
    return vals


def _mask(bs, colour):
    if colour is None:
        return None
    from ..formats.brackets import colour_mask
    if bs.n_channels != 3:
        raise ValueError("--ignore-colour needs RGB brackets")
    return ~colour_mask(bs.images, colour)


@json_command
def run_crf(args) -> int:
    from ..formats.brackets import read_bracket_set
    from .crf import DebevecParams, RobertsonParams, estimate_crf
    from .noise_profile import estimate_sigma2_im, noise_profile, plot_profile

    from .._util.atomic import check_outputs
    check_outputs({"--out": args.out},
                  [args.brackets] + (sorted(Path(args.brackets).iterdir()) if Path(args.brackets).is_dir() else []),
                  overwrite=args.overwrite, command="calibrate crf")
    t0 = time.perf_counter()
    bs = read_bracket_set(args.brackets)
    if bs.encoding in ("raw", "linear"):
        print(f"note: {args.brackets} is '{bs.encoding}' (linear); the CRF estimate checks that linearity",
              file=sys.stderr)
    mask = _mask(bs, _colour(args.ignore_colour))
    params = (DebevecParams(n_samples=args.samples, smoothness=args.smoothness, seed=args.seed)
              if args.method == "debevec" else RobertsonParams(seed=args.seed))
    h, w = bs.shape[:2]
    colour = "RGB" if bs.n_channels == 3 else "grey"
    print(f"{args.method}: {len(bs)} images {w}x{h} {colour}, exposures {bs.exposures_s.min():g}..{bs.exposures_s.max():g} s",
          file=sys.stderr)
    crf = estimate_crf(bs, None, args.method, params, mask=mask, progress=not args.no_progress)
    if args.sigma2_im is None:
        s2, noise = estimate_sigma2_im(bs.images, bs.exposures_s, crf)
    else:
        s2, noise = float(args.sigma2_im), {"estimator": "given (--sigma2-im)"}
    src = f"hybridhdr calibrate crf {args.method}, {len(bs)} exposures from {args.brackets.name}"
    prof = noise_profile(crf, sigma2_im=s2, floor=args.floor, domain=args.domain, name=args.name, source=src,
                         extra={"noise": noise})
    out = args.out
    # the four files appear together or not at all (a full disk used to leave crf.json alone)
    with _staged(out, last=("report.json",)) as stage:
        crf.save(stage / "crf.json")
        prof.save(stage / "camera_profile.json")
        plot_profile(crf, prof, stage / "crf_profile.png")
        report = _write_crf_report(stage, args, bs, crf, prof, s2, noise, t0)
    print(f"crf ({args.method}): sigma2_im {s2:.3g} (precision {prof.frame_precision_scale:.3g}) -> {out}")
    args.emit_json({**report, "out": str(out)})
    return 0


def _write_crf_report(out, args, bs, crf, prof, s2, noise, t0) -> None:
    import numpy as np

    from .._version import __version__
    z = np.arange(crf.max_code + 1)
    report = {"hybridhdr_version": __version__, "command": sys.argv, "brackets": str(args.brackets),
              "n_images": len(bs), "shape": list(bs.shape), "encoding": bs.encoding,
              "exposures_s": bs.exposures_s.tolist(), "method": args.method, "crf_info": crf.info,
              "sigma2_im": s2, "frame_precision_scale": prof.frame_precision_scale, "noise": noise,
              "floor": args.floor, "certainty_domain": args.domain,
              "weighting_at": {int(c): float(prof.weighting[c]) for c in z[:: max(1, len(z) // 8)]},
              "time_s": time.perf_counter() - t0,
              "written": ["crf.json", "camera_profile.json", "crf_profile.png", "report.json"]}
    _write_json(out / "report.json", report)
    return report


@contextlib.contextmanager
def _staged(folder, last=()):
    """All-or-none outputs in ``folder`` (:func:`~hybridhdr._util.atomic.atomic_outputs`); a writer
    library's ``RuntimeError`` (OpenEXR, libpng on a full disk) becomes one ``OSError`` line."""
    from .._util.atomic import atomic_outputs
    try:
        with atomic_outputs(folder, last=tuple(last)) as stage:
            yield stage
    except RuntimeError as e:
        raise OSError(errno.EIO, f"cannot write the outputs in {folder}: {str(e).splitlines()[0] if str(e) else e!r}; "
                                 f"nothing was written") from None


@json_command
def run_hdr_reference(args) -> int:
    import numpy as np

    from .._version import __version__
    from ..formats.brackets import read_bracket_set
    from .crf import CRF, debevec
    from .hdr_reference import RegistrationParams, align_brackets, merge_brackets, register_recording, write_exr

    t0 = time.perf_counter()
    if args.out.suffix.lower() in (".png", ".json"):
        raise ValueError(f"--out {args.out}: the reference is an EXR (its .json report and .png plot are written "
                         f"beside it); give a name ending in .exr")
    from .._util.atomic import check_outputs
    check_outputs({"--out": args.out, "--out-recording": args.out_recording},
                  [args.brackets, args.crf, args.register]
                  + (sorted(Path(args.brackets).iterdir()) if Path(args.brackets).is_dir() else []),
                  overwrite=args.overwrite, command="calibrate hdr-reference")
    # the report and plot beside the EXR are replaced with it: never an input
    check_outputs({"--out (report)": args.out.with_suffix(".json"), "--out (plot)": args.out.with_suffix(".png")},
                  [args.brackets, args.crf, args.register]
                  + (sorted(Path(args.brackets).iterdir()) if Path(args.brackets).is_dir() else []), overwrite=True)
    if args.register is not None and args.out_recording is None:
        raise ValueError("--register needs --out-recording (the input recording is never modified)")
    if args.out_recording is not None and args.register is None:
        raise ValueError("--out-recording needs --register REC")
    bs = read_bracket_set(args.brackets)
    mask = _mask(bs, _colour(args.ignore_colour))
    crf = None
    crf_src = None
    if args.crf is not None:
        crf = CRF.load(args.crf)
        crf_src = str(args.crf)
    align: dict = {"enabled": bool(args.align)}
    if args.align and len(bs) > 1:
        bs = align_brackets(bs, features="sift", info=align)
        mask = _mask(bs, _colour(args.ignore_colour))
        align["moved"] = [bs.files[d["image"]] for d in align["pairs"] if d["method"] != "identity"]
        print(f"align: {len(align['moved'])} of {len(bs) - 1} brackets moved to {bs.files[align['anchor']]}",
              file=sys.stderr)
    if crf is None and bs.encoding not in ("raw", "linear"):
        crf = debevec(bs, None, mask=mask)
        crf_src = "estimated here (Debevec)"
    info: dict = {}
    E = merge_brackets(bs, None, crf, weighting=args.weighting, info=info)
    report = {"hybridhdr_version": __version__, "command": sys.argv, "brackets": str(args.brackets),
              "reference": str(args.out), "shape": list(E.shape), "crf": crf_src, "merge": info,
              "alignment": align, "radiance_range": [float(np.nanmin(E)), float(np.nanmax(E))], "warnings": []}
    frame = H = None
    if args.register is not None:
        # registered before anything is written: a failure leaves no EXR, JSON, PNG or recording
        p = RegistrationParams(features=args.features, ecc=args.ecc, ratio=args.ratio, ransac_px=args.ransac_px)
        out_rec, frames = register_recording(E, args.register, args.out_recording, p, progress=not args.no_progress,
                                             valid=mask)
        for f in frames:
            for w in f.get("warnings", []):
                report["warnings"].append(f"frame {f['frame']}: {w}")
                print(f"warning: frame {f['frame']}: {w}", file=sys.stderr)
        report.update(recording=str(args.register), out_recording=str(out_rec), registration=frames,
                      features=args.features, ecc=args.ecc,
                      mean_time_s=float(np.mean([f["time_s"] for f in frames])),
                      mean_reprojection_px=float(np.mean([f["reprojection_px"] for f in frames])))
        from ..formats.container import RecordingFile
        with RecordingFile(args.register) as r:
            fr = r.read_frames()
        frame = fr.images[frames[0]["frame"]]
        H = np.asarray(frames[0]["homography"])
    report["time_s"] = time.perf_counter() - t0
    # EXR, JSON and PNG together or not at all (a full disk used to leave the EXR and JSON alone)
    with _staged(args.out.parent or Path("."), last=(args.out.name,)) as stage:
        write_exr(stage / args.out.name, E)
        _write_json(stage / args.out.with_suffix(".json").name, report)
        _plot_reference(E, frame, H, stage / args.out.with_suffix(".png").name, valid=mask)
    msg = (f"hdr-reference: {E.shape[1]}x{E.shape[0]} {'RGB' if E.ndim == 3 else 'grey'}, radiance "
           f"{report['radiance_range'][0]:.3g}..{report['radiance_range'][1]:.3g} -> {args.out} "
           f"(preview {args.out.with_suffix('.png')})")
    if args.register is not None:
        msg += (f"; {len(report['registration'])} frames registered (mean {report['mean_time_s']:.2f} s/frame) "
                f"-> {args.out_recording}")
    print(msg)
    args.emit_json(report)
    return 0


def _preview_reference(E, valid=None, *, saturation: float = 0.6):
    """Full-size 8-bit preview of a merged reference: the log tone map of its luminance (0.5th and
    99.5th percentiles of the valid pixels to black and white) with its colour ratios to the power
    ``saturation``; pixels outside ``valid`` (e.g. the Memorial scans' pure-blue borders, not
    image data) black. Returns (uint8 image, log limits)."""
    import numpy as np

    from ..formats.images import tone_map
    from .hdr_reference import to_grey
    L = np.asarray(to_grey(E), np.float64)
    ok = np.ones(L.shape, bool) if valid is None else np.asarray(valid, bool)
    if valid is not None and not ok.all():
        # aligned brackets are resampled: the marked border bleeds about a pixel into its
        # neighbours (thin blue lines), so 2 px more are left out
        from scipy.ndimage import binary_erosion
        ok = binary_erosion(ok, iterations=2, border_value=1)
    _, lim = tone_map(np.where(ok, L, np.nan)[None], low_percentile=0.5, high_percentile=99.5)
    v = tone_map(L[None], limits=lim)[0][0] / 255.0
    if E.ndim == 3:
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.clip(np.nan_to_num(E / np.maximum(L, 1e-12)[..., None]), 0, None) ** saturation
        out = np.clip(v[..., None] * ratio, 0, 1)
    else:
        out = v
    out = np.where(ok[..., None] if out.ndim == 3 else ok, out, 0.0)
    return np.round(255 * out).astype(np.uint8), lim


def _plot_reference(E, frame, H, path: Path, valid=None) -> None:
    """The tone-mapped reference at full size (:func:`_preview_reference`); with a registration a
    figure of it, the frame and a red/cyan overlay."""
    import numpy as np

    from ..formats.images import write_png, tone_map
    from .hdr_reference import to_grey, warp_reference

    ref8, lim = _preview_reference(E, valid)
    if frame is None:
        with atomic_path(path, ".png") as tmp:
            write_png(tmp, ref8)
        return
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    panels = [("HDR reference (log tone map)", ref8)]
    if frame is not None:
        f = to_grey(frame)
        warped = warp_reference(to_grey(E).astype(np.float32), H, f.shape)
        wt, _ = tone_map(np.nan_to_num(warped, nan=1e-6)[None], limits=lim)
        fn = np.clip(f / max(f.max(), 1e-9), 0, 1)
        over = np.stack([wt[0] / 255.0, fn, fn], axis=-1)
        panels += [("frame", f), ("overlay: red = warped reference, cyan = frame", over)]
    fig, ax = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 4))
    ax = np.atleast_1d(ax)
    for a, (title, img) in zip(ax, panels):
        a.imshow(img, cmap=None if img.ndim == 3 else "gray")
        a.set_title(title, fontsize=9)
        a.axis("off")
    fig.tight_layout()
    try:
        with atomic_path(path, ".png") as tmp:
            fig.savefig(tmp, dpi=100, format="png")
    finally:
        plt.close(fig)
