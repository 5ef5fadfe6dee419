"""``hybridhdr simulate``: render a scene (TOML file or built-in) to a hybrid recording."""

from __future__ import annotations

import contextlib
import json
import os
import sys
from pathlib import Path

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


@contextlib.contextmanager
def _signals_exit():
    """SIGTERM and SIGHUP raise SystemExit(128 + signal), SIGINT KeyboardInterrupt, while the block
    runs (main thread only), so ``finally``/``except BaseException`` clean-ups run instead of the
    process just ending. A Mitsuba render turns an exception raised inside it into its own error:
    a received signal decides what leaves the block."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    got = []

    def _exit(signum, frame):
        got.append(signum)
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise SystemExit(128 + signum)

    sigs = [getattr(signal, n) for n in ("SIGTERM", "SIGHUP", "SIGINT") if hasattr(signal, n)]
    old = {sg: signal.signal(sg, _exit) for sg in sigs}
    try:
        yield
    except BaseException:
        if got:
            if got[0] == signal.SIGINT:
                raise KeyboardInterrupt from None
            raise SystemExit(128 + got[0]) from None
        raise
    finally:
        for sg, h in old.items():
            signal.signal(sg, h)


class _MinuteAdvice:
    """With the fallback renderer (``scalar_rgb``, about 50x slower than ``llvm_ad_mono``), once the
    run has rendered for ``after_s`` seconds, print the measured render rate and the duration (at
    this size) and the size (for the whole duration) that would finish in about a minute, when the
    run itself would take much longer. Wraps ``source.render`` (the sampler's only call into the
    renderer); the estimate is the measured scene time per wall second, and a render's cost taken
    as proportional to its pixel count (the number of renders depends on the scene's motion and
    brightness changes, not on its size)."""

    def __init__(self, source, scene, t_start, *, after_s: float = 10.0, target_s: float = 60.0):
        self.source, self.scene, self.t_start = source, scene, t_start
        self.after_s, self.target_s = after_s, target_s
        self.t_max = 0
        self.done = False

    def install(self):
        render = self.source.render

        def wrapped(t_us):
            out = render(t_us)
            self.t_max = max(self.t_max, int(t_us))
            if not self.done:
                self.check()
            return out
        self.source.render = wrapped

    def check(self):
        import time
        wall = time.perf_counter() - self.t_start
        if wall < self.after_s or self.t_max <= 0:
            return
        self.done = True
        est = wall * self.scene.duration_us / self.t_max  # the whole run at the measured pace
        if est < 2 * self.target_s:
            return
        w, h = self.scene.camera.width, self.scene.camera.height
        k = (self.target_s / est) ** 0.5
        w2, h2 = max(16, int(w * k) // 2 * 2), max(16, int(h * k) // 2 * 2)
        dur = self.target_s * self.t_max / wall / 1e6
        n = self.source.renders
        print(f"\nnote: the renderer is scalar_rgb (the fallback when no usable LLVM is found): {n} renders of "
              f"{w}x{h} in {wall:.0f} s ({n / wall:.2g} renders/s, {self.t_max / 1e6:.3g} s of scene time); this "
              f"run will take about {est / 60:.0f} min. About a minute: --duration-s {dur:.2g} at this size, or --width {w2} "
              f"--height {h2} for the whole {self.scene.duration_us / 1e6:g} s", file=sys.stderr)


_SENSOR_FLAGS = {"pos_thres": "contrast_threshold_on", "neg_thres": "contrast_threshold_off",
                 "sigma_thres": "threshold_mismatch_sigma", "cutoff_hz": "photoreceptor_cutoff_hz",
                 "leak_rate_hz": "leak_rate_hz", "shot_noise_rate_hz": "shot_noise_rate_hz",
                 "refractory_period_us": "refractory_period_us"}


def sensor_params(args):
    """The --preset's EventSensorParams with the v2e-named flags applied (checked before rendering)."""
    import dataclasses

    from .sensor import sensor_preset
    over = {field: getattr(args, flag) for flag, field in _SENSOR_FLAGS.items() if getattr(args, flag, None) is not None}
    if getattr(args, "refractory_period_s", None) is not None:  # v2e's --refractory_period, in seconds
        s = float(args.refractory_period_s)
        if s > 1e3:
            raise ValueError(f"--refractory_period is in seconds (v2e's unit): expected at most 1000, got {s:g}")
        over["refractory_period_us"] = int(round(s * 1e6))
    profile = getattr(args, "sensor", None)
    preset = getattr(args, "preset", None) or ("ideal" if profile else "clean")
    base = sensor_preset(preset)
    if profile:
        from .sensor import sensor_from_profile
        base = sensor_from_profile(profile, base)
    if over.get("photoreceptor_cutoff_hz") == 0:
        over["photoreceptor_cutoff_hz"] = None
    for name in ("contrast_threshold_on", "contrast_threshold_off"):
        if name in over and over[name] < base.min_threshold:
            base = dataclasses.replace(base, min_threshold=min(base.min_threshold, over[name]))
    return dataclasses.replace(base, **over) if over else base


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
        summary = run_dataset(args, _human(args, err_default=True))
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

    import time

    import numpy as np

    from .camera import FrameCameraParams
    from .pipeline import simulate_to_file
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


def run_simulation(source, out, partial, *, resume: bool, sensor, camera, sampling, gt_times_us, seed: int,
                   progress: bool, say, estimate: bool = True, write_hdr: bool = True):
    """One resumable simulation of ``source`` into ``out`` (the command's core, also run by
    ``simulate dataset`` and ``simulate VIDEO``): its renders kept in ``partial``
    (:mod:`hybridhdr.simulate.resume`) until the output is complete, the partial kept on an
    interrupt (Ctrl-C, SIGTERM, SIGHUP) or an error, the run's time predicted after its first
    renders (:mod:`hybridhdr.simulate.estimate`). Returns (SimulationResult, summary dict)."""
    import time

    from .estimate import RunEstimate, predict_renders
    from .pipeline import frame_mandatory_count, simulate_to_file
    from .resume import RenderCache
    t0 = time.perf_counter()
    cache = RenderCache(source, partial, resume=resume)
    est = None
    try:
        # one render before the output file exists: a renderer that aborts the process (an LLVM that
        # cannot compile the kernels) leaves nothing behind
        with _signals_exit():
            cache.render(0)
            cache.calls = cache.reused = 0  # the warm-up render is asked for again at t = 0
            if estimate and cache.rendered:  # a resumed run replays its renders: no prediction
                pred = predict_renders(source, sampling, contrast_threshold=sensor.contrast_threshold,
                                       log_eps=sensor.log_eps, n_mandatory=frame_mandatory_count(
                                           camera, source.duration_us, gt_times_us),
                                       max_step_fn=_tau_step(sensor))
                est = RunEstimate(cache, pred["renders"], t0, printer=say).install()
            if getattr(source, "variant", "") == "scalar_rgb" and not resume:
                _MinuteAdvice(cache, source.scene, t0).install()
            res = simulate_to_file(cache, out, sensor=sensor, camera=camera, sampling=sampling,
                                   gt_times_us=gt_times_us, seed=seed, progress=progress, write_hdr=write_hdr)
    except BaseException as e:
        cache.close(keep=True)
        n = cache._n
        if isinstance(e, (KeyboardInterrupt, SystemExit)):
            say(f"interrupted: {n} renders kept in {partial}; run the same command with --resume to finish "
                f"(the output will be bit-identical to an uninterrupted run)")
        else:
            say(f"{n} renders kept in {partial} (--resume finishes the run)")
        raise
    cache.close(keep=False)
    wall = time.perf_counter() - t0
    st = res.stats
    summary = {"variant": getattr(source, "variant", None), "renders": res.renders, "renders_reused": cache.reused if resume else 0,
               "events": int(st.get("n_events", 0)), "frames": int(st.get("n_frames", 0)),
               "hdr_references": int(st.get("n_hdr", 0)), "wall_s": round(wall, 3),
               "render_s": round(float(getattr(source, "render_time_s", st.get("render_s", 0.0))), 3),
               "estimate_s": None if est is None or est.predicted_s is None else round(est.predicted_s, 2)}
    return res, summary


def _tau_step(sensor):
    """The sampler's τ/3 bound of the photoreceptor low-pass (µs), or None."""
    import numpy as np
    if not sensor.lowpass_on:
        return None
    return lambda r: sensor.min_time_constant_s(float(np.max(r))) / 3.0 * 1e6
