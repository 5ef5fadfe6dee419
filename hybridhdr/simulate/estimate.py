"""How long a simulation will take, predicted before it runs.

A run's time is (number of renders) x (time per render); the time per render is measured on the
run's own first renders, the number of renders predicted from the sampler's own step rule
(:mod:`hybridhdr.simulate.sampling`) at ``n_probes`` times spread over the duration:

* at each probe time ``t`` the source is rendered at ``t`` and ``t + d`` (``d`` = the motion
  rule's step, at most 1 ms), and the step the adaptive sampler would take there is computed from
  those two renders with the sampler's rules (brightness: ``f * C / r`` with the robust per-pixel
  log rate ``r``; motion: ``max_motion_px / v``; the photoreceptor's ``τ/3``; the rate limits);
  when that step differs from ``d`` by more than 25 %, ``t + step`` is rendered and the step
  computed again (at most 3 times): the sampler settles where the change over a step is ``f * C``,
  and a change over a much shorter step overstates the rate at edges that saturate;
* the duration is split into equal segments around the probes, each covering ``len / step``
  renders, and every mandatory time (the frame camera's exposure bounds and mid-exposures,
  ground-truth times) adds one, because it cuts a step short.

Events that last less than a probe spacing (a light switching on between probes) are missed by
the probes and cost bisections; the same scene-independent rule is used on every scene, and
``benchmarks/simulate.py`` tabulates the prediction against the measured time on each built-in
scene. The probes render 2 to 4 images each (about 1-3 % of a built-in scene's renders).
"""

from __future__ import annotations

import math
import time

import numpy as np

__all__ = ["predict_renders", "RunEstimate"]


def predict_renders(source, sampling, *, contrast_threshold: float, log_eps: float, n_mandatory: int,
                    max_step_fn=None, n_probes: int = 12) -> dict:
    """Predicted number of renders of a run of ``source`` (module notes), and the probe renders' time.

    Returns ``{"renders": float, "probe_renders": int, "probe_s": float, "steps_us": [...]}``."""
    from .sampling import TimeSampler
    p = sampling
    duration = int(source.duration_us)
    if p.mode == "fixed":
        return {"renders": duration * p.fixed_rate_hz / 1e6 + n_mandatory + 1, "probe_renders": 0, "probe_s": 0.0,
                "steps_us": []}
    ts = TimeSampler(source, p, contrast_threshold=contrast_threshold, log_eps=log_eps)
    dt_max = 1e6 / p.min_rate_hz
    dt_min = 1e6 / p.max_rate_hz
    seg = duration / n_probes
    total = 0.0
    steps = []
    t_render = 0.0
    n_r = 0
    for k in range(n_probes):
        t = int(round((k + 0.5) * seg))
        v = float(source.max_image_speed_px_per_s(t, int(t + math.ceil(dt_max))))
        d_motion = p.max_motion_px / v * 1e6 if v > 0 else math.inf
        room = max(1, duration - t)
        d = int(round(min(max(min(d_motion, 1000.0), dt_min), room)))
        t0 = time.perf_counter()
        la = np.log(np.asarray(source.render(t)).astype(np.float64).ravel() + log_eps)
        n_r += 1
        dt = d
        for it in range(3):
            b = np.asarray(source.render(t + d))
            n_r += 1
            lb = np.log(b.astype(np.float64).ravel() + log_eps)
            rate = ts._change(la, lb) / d
            dt = dt_max if rate <= 0 else p.max_log_change_fraction * contrast_threshold / rate
            dt = min(dt, d_motion, dt_max)
            if max_step_fn is not None:
                dt = min(dt, float(max_step_fn(b)))
            dt = max(dt, dt_min)
            # the sampler's steady step is where the change over the step itself is f*C: a change
            # measured over a much shorter step (edges that saturate) overstates the rate, so
            # measure again over the step found until it agrees within 25 %
            if abs(dt / d - 1) <= 0.25 or int(round(min(dt, room))) == d:
                break
            d = int(round(min(dt, room)))
        t_render += time.perf_counter() - t0
        steps.append(round(dt, 1))
        total += seg / dt
    return {"renders": total + n_mandatory + 1, "probe_renders": n_r, "probe_s": t_render, "steps_us": steps}


class RunEstimate:
    """Print the run's predicted total time once ``after`` renders have been timed.

    Wraps ``source.render`` (the sampler's only call into the renderer): the wall time per render
    is measured over renders ``skip+1 .. after`` of the run itself (its pipeline work included:
    the sensor, the frame camera and the writer run between renders), and the prediction is
    ``predicted_renders * that + the time already spent``. ``line`` holds what was printed;
    ``predicted_s`` the prediction (None before)."""

    def __init__(self, source, predicted_renders: float, t_start: float, *, after: int = 40, skip: int = 5,
                 printer=None):
        self.source, self.n_pred, self.t_start = source, float(predicted_renders), t_start
        self.after, self.skip = int(after), int(skip)
        self.calls = 0
        self._t_skip = None
        self.predicted_s = None
        self.per_s = None
        self.line = ""
        self.printer = printer

    def install(self):
        render = self.source.render

        def wrapped(t_us):
            out = render(t_us)
            self.tick()
            return out
        self.source.render = wrapped
        return self

    def tick(self):
        self.calls += 1
        if self.calls == self.skip:
            self._t_skip = time.perf_counter()
        elif self.calls == self.after and self._t_skip is not None:
            now = time.perf_counter()
            per = self.per_s = (now - self._t_skip) / (self.after - self.skip)
            left = max(0.0, self.n_pred - self.calls) * per
            self.predicted_s = (now - self.t_start) + left
            self.line = (f"estimate: about {int(round(self.n_pred)):,} renders at {per * 1e3:.0f} ms each: "
                         f"{_fmt_s(self.predicted_s)} in all ({_fmt_s(left)} left)")
            if self.printer is not None:
                self.printer(self.line)


def _fmt_s(s: float) -> str:
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"
