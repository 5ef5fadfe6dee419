"""``hybridhdr simulate``: render a scene (TOML file or built-in) to a hybrid recording."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from .runner import run_simulation, sensor_params
from .._util.cliargs import COMMON, HelpFormatter, fraction, json_output, nonneg_float, nonneg_int, positive_float, \
    positive_int, image_side


def add_parser(subparsers) -> None:
    """Add the ``simulate`` subcommand (sets ``func=run``)."""
    p = subparsers.add_parser(
        "simulate", help="render scenes to events, LDR frames and HDR ground truth",
        formatter_class=HelpFormatter, parents=[COMMON], allow_abbrev=False,
        description="Render a Mitsuba 3 scene (a TOML scene file or builtin:NAME) with adaptive time "
                    "sampling into events, LDR frames and HDR ground truth, written as a hybridhdr "
                    "recording (HDF5) that 'hybridhdr reconstruct' reads. Scene format: docs/simulate.md.")
    p.add_argument("scene", nargs="?", default=None,
                   help="SCENE.toml or builtin:NAME (see --list); a video file or a folder of images (events from "
                        "footage, docs/simulate.md); or the word dataset followed by SPEC.toml")
    p.add_argument("spec", nargs="?", default=None, metavar="SPEC.toml",
                   help="with 'dataset': the dataset spec (scenes x sensor profiles x seeds; docs/simulate.md)")
    p.add_argument("--list", action="store_true", help="list the built-in scenes and exit")
    p.add_argument("--out", type=Path, default=None, help="output recording (.h5)")
    p.add_argument("--jobs", type=positive_int, default=1, help="dataset: local processes running recordings at once")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="dataset: run the recordings on this Dask scheduler (tcp://HOST:PORT) instead of locally")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --out (and start again over an interrupted run's OUT.resume)")
    p.add_argument("--resume", action="store_true",
                   help="finish an interrupted run from its OUT.resume partial (bit-identical to an uninterrupted "
                        "run with the same options and seed)")
    p.add_argument("--preset", default=None, choices=["ideal", "clean", "noisy"],
                   help="event-sensor preset (noise tiers; docs/simulate.md); default clean, or ideal under --sensor")
    p.add_argument("--fixed-rate-hz", type=positive_float, default=None,
                   help="render at this fixed rate (Hz) instead of adaptive sampling")
    p.add_argument("--min-rate-hz", type=positive_float, default=None, help="adaptive sampling: lowest render rate (Hz)")
    p.add_argument("--max-rate-hz", type=positive_float, default=None, help="adaptive sampling: highest render rate (Hz)")
    p.add_argument("--robust-quantile", type=fraction, default=None,
                   help="adaptive sampling: quantile of the per-pixel log change taken as its maximum "
                        "(default: the sampler's; 0.99 ignores anti-aliasing jumps at high-contrast edges)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sensor and camera noise")
    p.add_argument("--duration-s", type=positive_float, default=None, help="scene length in seconds (default: the scene's)")
    p.add_argument("--spp", type=positive_int, default=None, help="Mitsuba samples per pixel (default: the scene's)")
    p.add_argument("--render-seed", type=int, default=None,
                   help="Mitsuba sampler seed, the same for every render (default: the scene's)")
    p.add_argument("--variant", default=None, choices=["llvm_ad_mono", "scalar_rgb", "llvm_ad_rgb", "cuda_ad_mono"],
                   help="Mitsuba variant (default: cuda_ad_mono on an NVIDIA GPU, else llvm_ad_mono if LLVM works, else "
                        "scalar_rgb)")
    p.add_argument("--allow-huge", action="store_true",
                   help="lift the limits on scene sizes, durations and sample counts (docs/security.md)")
    p.add_argument("--width", type=image_side, default=None, help="image width in pixels (intrinsics scale with it)")
    p.add_argument("--height", type=image_side, default=None, help="image height in pixels")
    f = p.add_argument_group("frame camera")
    f.add_argument("--no-frames", action="store_true", help="events and ground truth only")
    f.add_argument("--fps", "--frame-rate-hz", dest="frame_rate_hz", type=positive_float, default=None,
                   help="frames per second (--frame-rate-hz is the old name); default 20, or the input's rate for a "
                        "video")
    f.add_argument("--exposure-us", type=positive_int, default=None,
                   help="exposure time (µs); default 10000 (a video: at most half its frame period)")
    f.add_argument("--auto-exposure", action="store_true", help="adapt the exposure from frame to frame")
    f.add_argument("--crf", default="gamma", help="camera response: linear, gamma, srgb, akf_s_curve_<K>")
    f.add_argument("--bit-depth", type=int, default=8, choices=[8, 10, 12], help="frame bit depth")
    f.add_argument("--electrons-per-radiance-s", type=positive_float, default=None,
                   help="sensitivity: electrons per second per unit radiance (default: the camera model's)")
    p.add_argument("--gt-fps", "--gt-rate-hz", dest="gt_rate_hz", type=positive_float, default=None,
                   help="also store HDR ground truth at this many per second, besides every frame's mid-exposure "
                        "(--gt-rate-hz is the old name)")
    e = p.add_argument_group("event sensor (v2e names, and v2e's own underscore spellings as aliases: --pos_thres "
                             "... --refractory_period in seconds; each overrides the --preset's and the --sensor "
                             "profile's value)")
    e.add_argument("--sensor", default=None, metavar="PROFILE",
                   help="sensor profile JSON from 'hybridhdr calibrate sensor', or builtin:davis240c; its identified "
                        "parameters replace the --preset's (default with --sensor: ideal, every other tier off)")
    e.add_argument("--pos-thres", "--pos_thres", dest="pos_thres", type=positive_float, default=None,
                   help="ON contrast threshold, log units (v2e 0.2)")
    e.add_argument("--neg-thres", "--neg_thres", dest="neg_thres", type=positive_float, default=None,
                   help="OFF contrast threshold, log units, given positive (v2e 0.2)")
    e.add_argument("--sigma-thres", "--sigma_thres", dest="sigma_thres", type=nonneg_float, default=None,
                   help="sigma of the per-pixel threshold mismatch, log units (v2e 0.03)")
    e.add_argument("--cutoff-hz", "--cutoff_hz", dest="cutoff_hz", type=nonneg_float, default=None,
                   help="photoreceptor corner frequency at white, Hz (v2e 300; 0 = infinite bandwidth)")
    e.add_argument("--leak-rate-hz", "--leak_rate_hz", dest="leak_rate_hz", type=nonneg_float, default=None,
                   help="leak events per pixel per second (v2e 0.01)")
    e.add_argument("--shot-noise-rate-hz", "--shot_noise_rate_hz", dest="shot_noise_rate_hz", type=nonneg_float,
                   default=None, help="shot-noise events per pixel per second, ON + OFF (v2e noisy 5)")
    r = e.add_mutually_exclusive_group()
    r.add_argument("--refractory-period-us", type=nonneg_int, default=None,
                   help="blind time after each event, µs (v2e 500)")
    r.add_argument("--refractory_period", dest="refractory_period_s", type=nonneg_float, default=None,
                   metavar="SECONDS", help="v2e's spelling and unit: blind time after each event in SECONDS "
                                           "(v2e 0.0005); rounded to whole µs")
    b = p.add_argument_group("builtin:blinking_checkerboard (calibration board)")
    b.add_argument("--poses", type=positive_int, default=None,
                   help="static camera views of the board (1-5; 'calibrate rig' needs at least 4 with its default "
                        "--min-views); default 1")
    b.add_argument("--blink-period-us", type=positive_int, default=None, help="blink period, µs; default 100000")
    v = p.add_argument_group("video input (simulate VIDEO: a video file or a folder of images)")
    v.add_argument("--input-fps", type=positive_float, default=None,
                   help="the input's frame rate when it states no times (an image folder without images.txt or "
                        "timestamps.txt, a video without a rate)")
    v.add_argument("--max-input-frames", type=positive_int, default=None, help="use at most this many input frames")
    v.add_argument("--start-frame", type=nonneg_int, default=0, help="skip this many input frames first")
    p.add_argument("--preview", type=Path, default=None,
                   help="only render a PNG strip of a few frames (log radiance) to this file and exit")
    p.add_argument("--preview-frames", type=positive_int, default=4, help="frames in the --preview strip")
    p.add_argument("--allow-outside", type=Path, action="append", default=[], metavar="PATH",
                   help="let the scene file read files under PATH too (repeatable); by default its textures, "
                        "meshes and calibration must lie inside its own folder (docs/security.md)")
    p.set_defaults(func=run)


def load_any_scene(spec: str, *, width=None, height=None, duration_s=None, spp=None, render_seed=None,
                   board_options=None, allow_outside=()):
    """A :class:`Scene` from ``builtin:NAME`` or a TOML path, with the overrides applied;
    ``board_options`` (``poses``, ``period_us``) go to ``builtin:blinking_checkerboard``."""
    from .builtin import builtin_scene
    from .scene import load_scene
    opts = {k: v for k, v in (board_options or {}).items() if v is not None}
    if opts and spec not in ("builtin:blinking_checkerboard", "blinking_checkerboard"):
        raise ValueError(f"--poses/--blink-period-us apply to builtin:blinking_checkerboard, not {spec}")
    if spec.startswith("builtin:"):
        sc = builtin_scene(spec, duration_s=duration_s, **opts)
    else:
        sc = load_scene(spec, allow_outside=allow_outside)
        if duration_s is not None:
            if not duration_s > 0:
                raise ValueError(f"--duration-s: expected > 0, found {duration_s}")
            sc = sc.with_changes(duration_us=int(round(duration_s * 1e6)))
    if (width is None) != (height is None):
        raise ValueError("give both --width and --height, or neither")
    if width is not None and (width < 1 or height < 1):
        raise ValueError(f"--width/--height: expected positive integers, found {width}x{height}")
    return sc.with_changes(width=width, height=height, spp=spp, seed=render_seed)


@json_output
def run(args) -> int:
    from .builtin import BUILTIN_SCENES
    if args.list:
        w = max(len(n) for n in BUILTIN_SCENES)
        for n, d in BUILTIN_SCENES.items():
            print(f"builtin:{n:<{w}}  {d}")
        return 0
    if args.scene is None:
        raise ValueError("give a scene (SCENE.toml or builtin:NAME), a video, 'dataset SPEC.toml', or --list")
    if args.scene == "dataset":
        from .dataset_run import run_dataset
        summary = run_dataset(args, _human(args, err_default=True), check_argv=_check_argv)
        _human(args)(f"wrote {summary['recordings']} recordings ({summary['ran']} run now) to {summary['out']}, "
                     f"{summary['events']} events; manifest {summary['manifest']}")
        if args.json:
            print(json.dumps(summary))
        return 0
    if args.spec is not None:
        raise ValueError(f"unexpected second argument {args.spec!r} (only 'simulate dataset SPEC.toml' takes one)")
    if args.jobs != 1 or args.scheduler:
        raise ValueError("--jobs and --scheduler apply to 'simulate dataset'")
    from .video import is_video_input
    if is_video_input(args.scene):
        from .video import run_video
        return run_video(args, _human(args))
    from .._util.atomic import refuse_existing_output, refuse_overwriting_inputs
    refuse_overwriting_inputs({"--out": args.out, "--preview": args.preview},
                              [] if str(args.scene).startswith("builtin:") else [args.scene])
    human = _human(args)
    scene = load_any_scene(args.scene, width=args.width, height=args.height, duration_s=args.duration_s,
                           spp=args.spp, render_seed=args.render_seed,
                           board_options={"poses": args.poses, "period_us": args.blink_period_us},
                           allow_outside=args.allow_outside)
    sensor = sensor_params(args)
    if args.preview is None and args.out is None:
        raise ValueError("--out REC.h5 is required (or use --list / --preview)")
    from .resume import partial_path, partial_source_info
    variant = args.variant
    partial = None
    if args.preview is None:
        refuse_existing_output(args.out, overwrite=args.overwrite, flag="--out", command="simulate")
        partial = partial_path(args.out)
        if args.resume:
            info = partial_source_info(partial) if partial.exists() else None
            if info is None:
                raise ValueError(f"--resume: no readable partial {partial} (an interrupted 'simulate --out "
                                 f"{args.out}' leaves one)")
            if variant is not None and variant != info.get("variant"):
                raise ValueError(f"--resume: {partial} was rendered with {info.get('variant')}, not --variant {variant}")
            variant = info.get("variant")  # the same renderer as the interrupted run: the same bits
        elif partial.exists():
            if not args.overwrite:
                raise ValueError(f"{partial} exists (an interrupted run's partial): pass --resume to finish it, "
                                 f"or --overwrite to start again")
            partial.unlink()
    os.environ["_HYBRIDHDR_VARIANT_NOTED"] = "1"  # the line below says it (not the renderer's own note)
    from .render import MitsubaSource, variant_reason
    source = MitsubaSource(scene, variant=variant)
    why = variant_reason(source.variant, asked=variant if (args.variant or args.resume) else None)
    if args.resume:
        why = f"{source.variant}, the interrupted run's"
    if args.preview is not None:
        from .render import preview_strip
        preview_strip(source, args.preview, n=args.preview_frames)
        human(f"scene {scene.name}: variant {why}; wrote {args.preview}")
        if args.json:
            print(json.dumps({"preview": str(args.preview), "scene": scene.name, "variant": source.variant}))
        return 0

    import numpy as np

    from .camera import FrameCameraParams
    from .sampling import SamplingParams

    if args.fixed_rate_hz is not None:
        sampling = SamplingParams(mode="fixed", fixed_rate_hz=args.fixed_rate_hz)
    else:
        kw = {}
        if args.min_rate_hz is not None:
            kw["min_rate_hz"] = args.min_rate_hz
        if args.max_rate_hz is not None:
            kw["max_rate_hz"] = args.max_rate_hz
        if args.robust_quantile is not None:
            kw["robust_quantile"] = args.robust_quantile
        sampling = SamplingParams(mode="adaptive", **kw)
    camera = None
    if not args.no_frames:
        ckw = dict(frame_rate_hz=args.frame_rate_hz or 20.0, exposure_us=args.exposure_us or 10_000, crf=args.crf,
                   bit_depth=args.bit_depth, auto_exposure=args.auto_exposure)
        if args.electrons_per_radiance_s is not None:
            ckw["electrons_per_radiance_s"] = args.electrons_per_radiance_s
        camera = FrameCameraParams(**ckw)
    gt = None
    if args.gt_rate_hz is not None:
        if not args.gt_rate_hz > 0:
            raise ValueError(f"--gt-rate-hz: expected > 0, found {args.gt_rate_hz}")
        step = 1e6 / args.gt_rate_hz
        gt = np.unique(np.round(np.arange(0, scene.duration_us + 1, step)).astype(np.int64))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    human(f"scene {scene.name}: {scene.camera.width}x{scene.camera.height}, {scene.duration_us / 1e6:g} s, "
          f"spp {source.spp}, {sampling.mode} sampling; variant {why}", err=True)
    res, summary = run_simulation(source, args.out, partial, resume=args.resume, sensor=sensor, camera=camera,
                                  sampling=sampling, gt_times_us=gt, seed=args.seed,
                                  progress=not args.no_progress, say=lambda s: human(s, err=True),
                                  estimate=not args.quiet)
    summary = {"out": str(args.out), "scene": scene.name, **summary}
    human(f"wrote {args.out}: variant {source.variant}, {summary['renders']} renders "
          f"({summary['renders_reused']} from the partial), {summary['events']} events, {summary['frames']} frames, "
          f"{summary['hdr_references']} HDR references, {summary['wall_s']:.2f} s wall "
          f"({summary['render_s']:.2f} s rendering)")
    if args.json:
        print(json.dumps(summary))
    return 0


def _human(args, err_default: bool = False):
    """``say(line, err=False)``: a human-readable line, on stdout, or on stderr with ``--json`` (stdout then
    holds only the JSON object) or ``err=True``; nothing under ``--quiet``."""
    def say(line, err=err_default):
        if getattr(args, "quiet", False):
            return
        print(line, file=sys.stderr if (err or getattr(args, "json", False)) else sys.stdout, flush=True)
    return say


def _check_argv(argv: list[str]) -> None:
    """Parse a dataset recording's command line with this command's parser (SystemExit on a bad one)."""
    import argparse
    parser = argparse.ArgumentParser(prog="hybridhdr", add_help=False)
    add_parser(parser.add_subparsers(dest="command"))
    parser.parse_args(argv)
