"""``hybridhdr calibrate rig``: stereo calibration of an event/frame rig (or two frame cameras).

Heavy imports (cv2, matplotlib, the readers) happen inside :func:`run`.
"""

from __future__ import annotations

import glob
import sys
from pathlib import Path

from .._util.atomic import atomic_path, write_json_atomic
from .._util.cliargs import COMMON_NO_JSON, HelpFormatter, json_command, nonneg_float, positive_float, positive_int
from .._version import __version__

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm")


def register(steps) -> None:
    """Add the ``rig`` step to ``hybridhdr calibrate``."""
    p = steps.add_parser(
        "rig", help="stereo rig: blinking-board event images, intrinsics, extrinsics, frame->event mapping",
        formatter_class=HelpFormatter, parents=[COMMON_NO_JSON],
        description="Calibrate an event camera against a frame camera with a blinking checkerboard "
                    "(--events with --frames), or two frame cameras (--left/--right). Writes "
                    "calibration.json (schema in docs/calibrate.md), report.json, PNG plots and, for "
                    "--events, the event image of every static pose.")
    src = p.add_argument_group("input (either --events [--frames], or --left and --right)")
    src.add_argument("--events", type=Path, default=None,
                     help="recording of the blinking board (any readable format); its triggers, when "
                          "present, mark the blink period")
    src.add_argument("--frames", type=Path, default=None,
                     help="frame-camera views: a folder of images (one per static pose, in time order) or "
                          "a recording with frames (default: the frames of --events)")
    src.add_argument("--left", nargs="+", default=None, help="camera-1 images (files, globs or one folder)")
    src.add_argument("--right", nargs="+", default=None, help="camera-2 images (same order as --left)")
    b = p.add_argument_group("board and models")
    b.add_argument("--board", required=True, help="inner corners COLSxROWS, e.g. 9x6")
    b.add_argument("--square-mm", type=positive_float, required=True, help="square side in millimetres")
    b.add_argument("--model", default="plumb_bob", choices=["none", "k1", "fixed_k3", "plumb_bob", "rational"],
                   help="distortion model of the frame (or left) camera")
    b.add_argument("--model-events", default=None, choices=["none", "k1", "fixed_k3", "plumb_bob", "rational"],
                   help="distortion model of the event (or right) camera (default: --model)")
    b.add_argument("--detector-frames", default="sb+subpix", choices=["sb", "sb+subpix", "classic"],
                   help="corner detector for frame images")
    b.add_argument("--detector-events", default="sb", choices=["sb", "sb+subpix", "classic"],
                   help="corner detector for event images (and for --right)")
    b.add_argument("--max-sharpness-px", type=nonneg_float, default=4.0,
                   help="drop SB views whose estimated edge width exceeds this (px); 0 disables")
    b.add_argument("--prune-factor", type=nonneg_float, default=2.0,
                   help="drop views whose RMS error exceeds this times the median and re-calibrate; 0 disables")
    b.add_argument("--min-views", type=positive_int, default=4, help="fewest views accepted per camera")
    b.add_argument("--depth-m", type=positive_float, default=None,
                   help="scene depth (metres) of the frame->event homography (default: infinity)")
    e = p.add_argument_group("event images (--events)")
    e.add_argument("--trigger-channel", type=int, default=None, help="trigger channel marking the blink")
    e.add_argument("--no-triggers", action="store_true", help="ignore triggers; find the period in the event rate")
    e.add_argument("--image-mode", default="count", choices=["count", "binary"], help="event image values")
    e.add_argument("--min-both-pixels", type=int, default=100, help="fewest both-polarity pixels per window")
    e.add_argument("--max-single-ratio", type=float, default=0.15,
                   help="reject a window whose ON-only or OFF-only pixels exceed this fraction of its "
                        "both-polarity pixels")
    e.add_argument("--median-radius", type=int, default=1, help="median filter radius (px)")
    e.add_argument("--min-period-us", type=positive_int, default=10_000, help="shortest blink period searched (µs)")
    e.add_argument("--max-period-us", type=positive_int, default=500_000, help="longest blink period searched (µs)")
    e.add_argument("--min-windows-per-pose", type=positive_int, default=2, help="blink periods a static pose needs")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the files a previous run wrote in a non-empty --out (refused without it)")
    p.set_defaults(func=run)


def _expand(items) -> list[Path]:
    out: list[Path] = []
    for it in items:
        pth = Path(it)
        if pth.is_dir():
            out.extend(sorted(q for q in pth.iterdir() if q.suffix.lower() in IMAGE_EXTENSIONS))
        elif any(ch in str(it) for ch in "*?["):
            out.extend(Path(q) for q in sorted(glob.glob(str(it))))
        else:
            if not pth.exists():
                raise FileNotFoundError(f"image not found: {pth}")
            out.append(pth)
    return out


def _read_images(paths) -> list:
    import cv2
    ims = []
    for pth in paths:
        im = cv2.imread(str(pth), cv2.IMREAD_GRAYSCALE)
        if im is None:
            raise ValueError(f"{pth}: not a readable image")
        ims.append(im)
    return ims


def _frames_for_poses(frames, poses):
    """For each pose, the frame exposed inside it with the highest mean (the board shown 'on')."""
    import numpy as np
    picked = []
    for pose in poses:
        inside = np.flatnonzero((frames.t_start_us >= pose.t0_us) & (frames.t_end_us <= pose.t1_us))
        if inside.size == 0:
            picked.append(None)
            continue
        means = [float(np.mean(frames.images[i])) for i in inside]
        picked.append(int(inside[int(np.argmax(means))]))
    return picked


def _save_png(fig, path: Path) -> None:
    import matplotlib.pyplot as plt
    try:
        with atomic_path(path, ".png") as tmp:
            fig.savefig(tmp, dpi=110)
    finally:
        plt.close(fig)


#: Fewer views than this per camera draw a warning (OpenCV's calibration guide asks for 10-20).
FEW_VIEWS = 10


def simulated_camera(provenance) -> dict | None:
    """The camera a simulated recording states (``provenance["source"]``, written by
    ``hybridhdr simulate``: ``K``, ``width``, ``height``), else None. Its frames and events come
    from that one pinhole camera, so both calibrated cameras should find this K and no baseline."""
    src = provenance.get("source") if isinstance(provenance, dict) else None
    if not isinstance(src, dict) or "K" not in src:
        return None
    try:
        K = [[float(v) for v in row] for row in src["K"]]
        if len(K) != 3 or any(len(r) != 3 for r in K):
            return None
    except (TypeError, ValueError):
        return None
    return {"K": K, "width": src.get("width"), "height": src.get("height"), "scene": src.get("scene")}


def compare_with_truth(truth: dict, cameras: dict, stereo) -> dict:
    """Estimated intrinsics of each camera against the simulated camera's K, and the stereo
    estimate against the true (zero) baseline of one camera."""
    K = truth["K"]
    out = {"source": "recording provenance (simulated single camera)", "K": K, "cameras": {},
           "true_baseline_m": 0.0, "estimated_baseline_m": float(stereo.baseline_m),
           "estimated_rotation_deg": float(stereo.rotation_deg)}
    for n, c in cameras.items():
        k = c.K
        out["cameras"][n] = {"fx_error_pct": 100.0 * (float(k[0, 0]) / K[0][0] - 1.0),
                             "fy_error_pct": 100.0 * (float(k[1, 1]) / K[1][1] - 1.0),
                             "cx_error_px": float(k[0, 2]) - K[0][2], "cy_error_px": float(k[1, 2]) - K[1][2],
                             "views_used": len(c.views)}
    return out


@json_command
def run(args) -> int:
    import cv2
    import numpy as np

    from .event_images import BlinkParams, event_images
    from .rig import (Board, calibrate_rig, plot_corners, plot_parallax, plot_per_view_errors,
                      save_calibration)

    board = Board.parse(args.board, args.square_mm)
    names2 = None  # per-view names of camera 2 where they differ from camera 1's (--left/--right)
    if (args.events is None) == (args.left is None and args.right is None):
        raise ValueError("give either --events (with optional --frames) or --left and --right")
    from .._util.atomic import check_outputs
    out = Path(args.out)
    images_in = [Path(x) for x in [*(args.left or ()), *(args.right or ())]]
    check_outputs({"--out": out}, [args.events, args.frames, *images_in],
                  overwrite=args.overwrite, command="calibrate rig")
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {"command": " ".join(sys.argv), "board": board.to_dict()}
    progress = not args.no_progress
    truth_src = None
    if args.events is not None:
        from ..formats import read as read_any
        rec = read_any(args.events)
        if rec.sensor_size is None:
            raise ValueError(f"{args.events}: the event-camera size is unknown (no geometry in the file)")
        params = BlinkParams(min_both_pixels=args.min_both_pixels, max_single_ratio=args.max_single_ratio,
                             median_radius=args.median_radius, image_mode=args.image_mode,
                             min_period_us=args.min_period_us, max_period_us=args.max_period_us,
                             trigger_channel=args.trigger_channel,
                             min_windows_per_pose=args.min_windows_per_pose)
        trig = None if args.no_triggers else rec.triggers
        if args.frames is None:  # frames and events of one recording: is it a simulated single camera?
            truth_src = simulated_camera(rec.metadata.provenance)
        res = event_images(rec.events, rec.sensor_size, trig, params, progress=progress)
        report["event_images"] = res.summary()
        per = res.period
        print(f"blink period {per.period_us:.1f} µs ({per.frequency_hz:.3f} Hz) from {per.source}; "
              f"{len(res.stats)} windows, {int(res.stats.accepted.sum())} accepted; {len(res.poses)} static poses")
        if not res.poses:
            raise ValueError(f"no static pose found in {args.events}: {len(res.stats)} blink windows, "
                             f"{int(res.stats.accepted.sum())} accepted, need {params.min_windows_per_pose} "
                             f"consecutive per pose")
        evdir = out / "event_images"
        evdir.mkdir(exist_ok=True)
        for i, pose in enumerate(res.poses):
            with atomic_path(evdir / f"pose_{i:03d}.png", ".png") as tmp:
                cv2.imwrite(str(tmp), pose.image)
        kept = {f"pose_{i:03d}.png" for i in range(len(res.poses))}
        for stale in evdir.glob("pose_*.png"):  # a replaced run's extra poses (--overwrite)
            if stale.name not in kept and (stale.is_file() or stale.is_symlink()):
                stale.unlink()
        # frame views
        if args.frames is not None and Path(args.frames).is_dir():
            paths = _expand([args.frames])
            if len(paths) != len(res.poses):
                raise ValueError(f"{args.frames}: found {len(paths)} images but {len(res.poses)} static poses in "
                                 f"the events; give one frame image per pose, in time order")
            frames_imgs = _read_images(paths)
            names = [f"pose{i:03d}" for i in range(len(res.poses))]
            ev_imgs = [p.image for p in res.poses]
        else:
            frames = rec.frames if args.frames is None else read_any(args.frames).frames
            if frames is None or len(frames) == 0:
                raise ValueError(f"no frame-camera images: {args.frames or args.events} holds no frames; "
                                 f"pass --frames DIR (one image per pose) or a recording with frames")
            idx = _frames_for_poses(frames, res.poses)
            keep = [i for i, j in enumerate(idx) if j is not None]
            report["poses_without_frame"] = [i for i, j in enumerate(idx) if j is None]
            frames_imgs = [np.asarray(frames.images[idx[i]]) for i in keep]
            ev_imgs = [res.poses[i].image for i in keep]
            names = [f"pose{i:03d}" for i in keep]
        images1, images2, cam_names = frames_imgs, ev_imgs, ("frame", "event")
    else:
        if args.left is None or args.right is None:
            raise ValueError("--left and --right must be given together")
        lp, rp = _expand(args.left), _expand(args.right)
        if len(lp) != len(rp):
            raise ValueError(f"--left has {len(lp)} images but --right has {len(rp)}; they must pair up")
        images1, images2 = _read_images(lp), _read_images(rp)
        names = [p.stem for p in lp]
        names2 = [p.stem for p in rp]  # the right camera's panels are titled with its own files
        cam_names = ("left", "right")
    rig, det = calibrate_rig(images1, images2, board, names=names, model=args.model, model2=args.model_events,
                             detector1=args.detector_frames, detector2=args.detector_events,
                             depth_m=args.depth_m, prune_factor=args.prune_factor or None,
                             min_views=args.min_views, camera_names=cam_names,
                             max_sharpness_px=args.max_sharpness_px or None, progress=progress)
    rig = type(rig)(rig.camera1, rig.camera2, rig.stereo, rig.board, rig.depth_m, rig.names,
                    {**rig.provenance, "command": " ".join(sys.argv), "hybridhdr_version": __version__})
    save_calibration(rig, out / "calibration.json")
    n1, n2 = rig.names
    found1 = sum(c is not None for c in det["corners1"])
    found2 = sum(c is not None for c in det["corners2"])
    report.update({
        "views": len(names), "board_found": {n1: found1, n2: found2},
        "cameras": {n: {"rms_px": c.rms_px, "K": c.K.tolist(), "dist": c.dist.tolist(), "views_used": len(c.views),
                        "rejected_views": [list(r) for r in c.rejected_views]}
                    for n, c in ((n1, rig.camera1), (n2, rig.camera2))},
        "stereo": {"rms_px": rig.stereo.rms_px, "baseline_m": rig.stereo.baseline_m,
                   "rotation_deg": rig.stereo.rotation_deg, "T_m": rig.stereo.T_m.tolist(),
                   "views_used": len(rig.stereo.views),
                   "rejected_views": [list(r) for r in rig.stereo.rejected_views]},
        "homography_depth_m": rig.depth_m, "parallax": rig.parallax_table(),
        "hybridhdr_version": __version__,
    })
    few = {n: len(c.views) for n, c in ((n1, rig.camera1), (n2, rig.camera2)) if len(c.views) < FEW_VIEWS}
    from .._util.cliargs import BLINKING_BOARD_MAX_POSES
    report["warnings"] = [f"{n}: only {k} views used; intrinsics from fewer than {FEW_VIEWS} views of the board at "
                          f"varied angles are poorly constrained (record more views; a simulated board gives at "
                          f"most {BLINKING_BOARD_MAX_POSES}: simulate builtin:blinking_checkerboard --poses "
                          f"{BLINKING_BOARD_MAX_POSES})"
                          for n, k in few.items()]
    if truth_src is not None:
        report["ground_truth"] = compare_with_truth(truth_src, {n1: rig.camera1, n2: rig.camera2}, rig.stereo)
    write_json_atomic(out / "report.json", report)
    # plots
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    shown = [i for i in range(len(names)) if det["corners1"][i] is not None or det["corners2"][i] is not None][:3]
    if shown:
        fig, axes = plt.subplots(2, len(shown), figsize=(3.6 * len(shown), 5.6), squeeze=False)
        for j, i in enumerate(shown):
            plot_corners(images1[i], det["corners1"][i], board, f"{n1} {names[i]}", ax=axes[0, j])
            plot_corners(images2[i], det["corners2"][i], board, f"{n2} {(names2 or names)[i]}", ax=axes[1, j])
        fig.tight_layout()
        _save_png(fig, out / "corners.png")
    fig, _ = plot_per_view_errors(rig)
    _save_png(fig, out / "per_view_errors.png")
    fig, _ = plot_parallax(rig)
    _save_png(fig, out / "parallax.png")
    # summary
    for n, c in ((n1, rig.camera1), (n2, rig.camera2)):
        print(f"{n}: {c.image_size} fx {c.K[0, 0]:.2f} fy {c.K[1, 1]:.2f} cx {c.K[0, 2]:.2f} cy {c.K[1, 2]:.2f}; "
              f"RMS {c.rms_px:.3f} px over {len(c.views)} views ({len(c.rejected_views)} pruned)")
    st = rig.stereo
    gt = report.get("ground_truth")
    if gt is not None:  # one simulated camera made both: there is no stereo pair, only estimation error
        for n, e in gt["cameras"].items():
            print(f"{n} vs the recording's ground truth (fx {gt['K'][0][0]:.2f} fy {gt['K'][1][1]:.2f} cx "
                  f"{gt['K'][0][2]:.2f} cy {gt['K'][1][2]:.2f}): fx {e['fx_error_pct']:+.2f} %, fy "
                  f"{e['fy_error_pct']:+.2f} %, cx {e['cx_error_px']:+.2f} px, cy {e['cy_error_px']:+.2f} px")
        print(f"stereo: none, one simulated camera records frames and events (true baseline 0); the estimated "
              f"{1000 * st.baseline_m:.2f} mm, {st.rotation_deg:.3f} deg are calibration error (RMS {st.rms_px:.3f} "
              f"px over {len(st.views)} views)")
    else:
        print(f"stereo: baseline {1000 * st.baseline_m:.2f} mm, rotation {st.rotation_deg:.3f} deg, RMS "
              f"{st.rms_px:.3f} px over {len(st.views)} views")
    for w in report["warnings"]:
        print(f"warning: {w}", file=sys.stderr)
    tab = rig.parallax_table()
    dname = "infinity" if rig.depth_m is None else f"{rig.depth_m:g} m"
    print(f"{n1}->{n2} homography at {dname}; residual parallax (max over the image, {n2} px):")
    for z, m in zip(tab["depth_m"], tab["max_px"]):
        print(f"  depth {z:8.3f} m: {m:8.3f} px")
    print(f"wrote {out / 'calibration.json'}, report.json, corners.png, per_view_errors.png, parallax.png")
    args.emit_json({**report, "out": str(out),
                    "written": ["calibration.json", "report.json", "per_view_errors.png", "parallax.png"]
                    + (["corners.png"] if shown else [])})
    return 0
