"""How long a simulation will take, predicted before it runs.

A run's time is (number of renders) x (time per render); the time per render is measured on the
run's own first renders, the number of renders predicted by running the adaptive sampler itself
(:mod:`hybridhdr.simulate.sampling`, with its bisections) for a few renders at ``n_probes``
times spread over the duration:

* the duration is cut into ``n_probes`` equal segments; from a point of each (0.382 of the way in,
  so that no two probes meet a periodic event, a blink or the frame timing, at the same phase), the
  sampler runs on that stretch of the scene (its real speeds, with the run's mandatory times: the
  exposure bounds and mid-exposures cut steps and the steps then grow again, which costs renders)
  for ``per_probe`` renders after its first accepted
  step (the start-up, whose first step is the longest allowed and is bisected down, is left out),
  and its render density there (renders per second of scene time, bisections included) is
  measured; a segment the sampler finishes within the budget counts its own renders;
* each segment contributes density x length.

Events shorter than a probe (a light switching between probes) are missed and cost renders the
estimate does not count. The same scene-independent rule is used on every scene;
``benchmarks/simulate.py`` tabulates the prediction against the measured time on each built-in
scene. The probes cost about ``n_probes * (per_probe + 4)`` renders (a few % of a long run; about
as many renders as a scene the sampler crosses in large steps has).
"""

from __future__ import annotations

import time

__all__ = ["predict_renders", "RunEstimate"]


class _Window:
    """``[t0, t0 + duration]`` of a source, re-based to 0 (the scene's real speeds), its renders counted."""

    def __init__(self, src, t0_us: int, duration_us: int):
        self.src, self.t0 = src, int(t0_us)
        self.sensor_size = src.sensor_size
        self.duration_us = max(1, int(duration_us))
        self.renders = 0

    def render(self, t_us):
        self.renders += 1
        return self.src.render(self.t0 + int(t_us))

    def max_image_speed_px_per_s(self, t0_us, t1_us):
        return self.src.max_image_speed_px_per_s(self.t0 + int(t0_us), self.t0 + int(t1_us))

    def describe(self):
        return self.src.describe()


def predict_renders(source, sampling, *, contrast_threshold: float, log_eps: float, n_mandatory: int,
                    max_step_fn=None, n_probes: int = 10, per_probe: int = 8, mandatory_us=None,
                    phase: float = 0.381966) -> dict:
    """Predicted number of renders of a run of ``source`` (module notes), and the probes' cost.

    Returns ``{"renders": float, "probe_renders": int, "probe_s": float, "density_per_s": [...]}``."""
    from .sampling import TimeSampler
    p = sampling
    duration = int(source.duration_us)
    if p.mode == "fixed":
        return {"renders": duration * p.fixed_rate_hz / 1e6 + n_mandatory + 1, "probe_renders": 0, "probe_s": 0.0,
                "density_per_s": []}
    import bisect
    seg = duration / n_probes
    total = 0.0
    dens = []
    n_r = 0
    mand = sorted(int(t) for t in (mandatory_us or ()))
    t_start = time.perf_counter()
    for k in range(n_probes):
        # each probe starts at an irrational fraction of its segment, so that no probe lands on the
        # same phase of a periodic scene event (a blink every 50 ms) or of the frame timing
        a = int(round((k + phase) * seg))
        win = _Window(source, a, max(1, min(int(round(seg)), duration - a)))
        inside = [t - a for t in mand[bisect.bisect_right(mand, a):bisect.bisect_left(mand, a + win.duration_us)]]
        ts = TimeSampler(win, p, contrast_threshold=contrast_threshold, log_eps=log_eps, max_step_fn=max_step_fn,
                         mandatory_times_us=inside)
        first = None
        t_last, r_last = 0, 0
        finished = True
        for i, (t, _r) in enumerate(ts):
            if i == 1:  # past the start-up (the first step's bisections)
                first = (t, win.renders)
            t_last, r_last = t, win.renders
            if first is not None and r_last - first[1] >= per_probe:
                finished = False
                break
        n_r += win.renders
        if finished or first is None or t_last <= first[0]:
            d = win.renders / (win.duration_us / 1e6)  # the whole segment rendered: its own count
        else:
            d = (r_last - first[1]) / ((t_last - first[0]) / 1e6)
        dens.append(round(d, 1))
        total += d * seg / 1e6
    # with the mandatory times inside the probes, their cost is in the densities already
    return {"renders": total + (0 if mand else n_mandatory) + 1, "probe_renders": n_r, "probe_s": time.perf_counter() - t_start,
            "density_per_s": dens}


class RunEstimate:
    """Print the run's predicted total time once ``after`` renders have been timed.

    Wraps ``source.render`` (the sampler's only call into the renderer): the wall time per render
    is measured over renders ``skip+1 .. after`` of the run itself (its pipeline work included:
    the sensor, the frame camera and the writer run between renders), as the mean of those
    intervals without the longest 10 % (one-time costs: the sensor's and the camera's kernels are
    compiled on their first call, seconds that a render count would multiply), and the prediction
    is ``predicted_renders * that + the time already spent``. ``line`` holds what was printed;
    ``predicted_s`` the prediction (None before)."""

    def __init__(self, source, predicted_renders: float, t_start: float, *, after: int = 40, skip: int = 5,
                 printer=None):
        self.source, self.n_pred, self.t_start = source, float(predicted_renders), t_start
        self.after, self.skip = int(after), int(skip)
        self.calls = 0
        self._t_skip = None
        self._ticks: list[float] = []
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
        if self.skip <= self.calls <= self.after:
            self._ticks.append(time.perf_counter())
        if self.calls == self.skip:
            self._t_skip = self._ticks[-1]
        elif self.calls == self.after and self._t_skip is not None:
            now = self._ticks[-1]
            iv = sorted(b - a for a, b in zip(self._ticks, self._ticks[1:]))
            keep = iv[:max(1, len(iv) - max(1, len(iv) // 10))]
            per = self.per_s = sum(keep) / len(keep)
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
