"""The core of a ``hybridhdr simulate`` run, shared by its scene, video and dataset paths: the
event-sensor options (v2e names), signals, the resumable run with its time estimate."""

from __future__ import annotations

import sys

from .._util import procs as _procs

__all__ = ["sensor_params", "run_simulation", "signals_exit"]


def signals_exit():
    """SIGTERM and SIGHUP raise SystemExit(128 + signal), SIGINT KeyboardInterrupt, while the block
    runs (:func:`hybridhdr._util.procs.signals_exit`): a Mitsuba render turns an exception raised
    inside it into its own error, and a received signal decides what leaves the block."""
    return _procs.signals_exit(sigint=True)


class _MinuteAdvice:
    """With the fallback renderer (``scalar_rgb``, about 50x slower than ``llvm_ad_mono``), once the
    run has rendered for ``after_s`` seconds, print the measured render rate and the duration (at
    this size) and the size (for the whole duration) that would finish in about a minute, when the
    run itself would take much longer. Wraps ``source.render`` (the sampler's only call into the
    renderer); the estimate is the measured scene time per wall second, and a render's cost taken
    as proportional to its pixel count (the number of renders depends on the scene's motion and
    brightness changes, not on its size)."""

    def __init__(self, source, scene, t_start, *, after_s: float = 10.0, target_s: float = 60.0, estimate=None):
        self.source, self.scene, self.t_start = source, scene, t_start
        self.estimate = estimate  # the run's RunEstimate: its prediction, once made, is the one quoted
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
        if self.estimate is not None and self.estimate.predicted_s is None:
            return  # wait for the run's own estimate (one figure, not two)
        self.done = True
        est = (self.estimate.predicted_s if self.estimate is not None
               else wall * self.scene.duration_us / self.t_max)  # else the whole run at the measured pace
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


def run_simulation(source, out, partial, *, resume: bool, sensor, camera, sampling, gt_times_us, seed: int,
                   progress: bool, say, estimate: bool = True, write_hdr: bool = True):
    """One resumable simulation of ``source`` into ``out`` (the command's core, also run by
    ``simulate dataset`` and ``simulate VIDEO``): its renders kept in ``partial``
    (:mod:`hybridhdr.simulate.resume`) until the output is complete, the partial kept on an
    interrupt (Ctrl-C, SIGTERM, SIGHUP) or an error, the run's time predicted after its first
    renders (:mod:`hybridhdr.simulate.estimate`). Returns (SimulationResult, summary dict)."""
    import time

    from .estimate import RunEstimate, predict_renders
    from .pipeline import planned_mandatory_times, simulate_to_file
    from .resume import RenderCache
    t0 = time.perf_counter()
    cache = RenderCache(source, partial, resume=resume)
    est = None
    try:
        # one render before the output file exists: a renderer that aborts the process (an LLVM that
        # cannot compile the kernels) leaves nothing behind
        with signals_exit():
            cache.render(0)
            cache.calls = cache.reused = 0  # the warm-up render is asked for again at t = 0
            if estimate and cache.rendered:  # a resumed run replays its renders: no prediction
                mand = planned_mandatory_times(camera, source.duration_us, gt_times_us)
                pred = predict_renders(source, sampling, contrast_threshold=sensor.contrast_threshold,
                                       log_eps=sensor.log_eps, n_mandatory=len(mand), mandatory_us=mand,
                                       max_step_fn=_tau_step(sensor))
                est = RunEstimate(cache, pred["renders"], t0, printer=say).install()
            if getattr(source, "variant", "") == "scalar_rgb" and not resume:
                _MinuteAdvice(cache, source.scene, t0, estimate=est).install()
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
               "estimate_s": None if est is None or est.predicted_s is None else round(est.predicted_s, 2),
               "estimate_renders": None if est is None else round(est.n_pred),
               "estimate_ms_per_render": None if est is None or est.per_s is None else round(est.per_s * 1e3, 2)}
    return res, summary


def _tau_step(sensor):
    """The sampler's τ/3 bound of the photoreceptor low-pass (µs), or None."""
    import numpy as np
    if not sensor.lowpass_on:
        return None
    return lambda r: sensor.min_time_constant_s(float(np.max(r))) / 3.0 * 1e6
