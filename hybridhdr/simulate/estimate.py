"""How long a simulation will take, predicted before it runs.

A run's time is (number of renders) x (time per render); the time per render is measured on the
run's own first renders, the number of renders predicted by running the adaptive sampler itself
(:mod:`hybridhdr.simulate.sampling`, with its bisections and the run's mandatory times: the
exposure bounds and mid-exposures cut steps and the steps then grow again, which costs renders) on
a few stretches of the scene (its real speeds):

* **switches**: the times the scene declares its radiance jumps (its blinking lights' on/off edges,
  :func:`switch_times_us`). Each owns a guard ``[e - g, e + g]``, ``g`` the longest step the sampler
  can take (1 / min rate) and at most half the way to its neighbours: the step that meets the edge
  is bisected down to the shortest and grows again inside it. Up to ``n_switch_probes`` guards,
  spread over the duration, are rendered whole; each guard of the run then costs their mean excess
  over the quiet density plus the quiet density times its length. A jump is a point in time, so
  probes placed by chance would either all miss it or all meet it (a blink every 50 ms and probes
  at one phase of a 100 ms segment: 3x too many renders); its cost is counted from its declaration.
* **quiet time** (the duration less the guards): cut into as many equal parts as its share of the
  duration asks for (``n_probes`` for a scene without switches); one probe in each, at a fraction of
  its part that differs from probe to probe (a Weyl sequence: no two probes at the same phase of a
  periodic event or of the frame timing), runs for ``per_probe`` renders after its first accepted
  step (the start-up, whose first step is the longest allowed and is bisected down, is left out),
  and its render density (renders per second of scene time, bisections included) times its part's
  length is counted; a probe that finishes its window counts its own renders less the window's two
  forced ends.

Events the scene does not declare and shorter than a probe (an object that flashes past between
probes) are missed. The same rule is used on every scene; ``benchmarks/simulate.py`` tabulates the
prediction against the measured time on each built-in scene. The probes cost about ``n_probes *
(per_probe + 4)`` renders plus about 20 per probed switch (a few % of a long run; on a short run
with few switches, up to as many renders as the run).
"""

from __future__ import annotations

import bisect
import math
import time

__all__ = ["predict_renders", "RunEstimate", "switch_times_us"]


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


def switch_times_us(source) -> list[int]:
    """Times in ``(0, duration)`` at which the scene's radiance jumps: the on/off edges of its blinking
    emitters (objects' emission and emitters), as the scene declares them. Empty for a source
    without a scene or without blinking lights."""
    sc = getattr(source, "scene", None)
    dur = int(source.duration_us)
    if sc is None:
        return []
    blinks = [o.emission.blink for o in getattr(sc, "objects", ()) if getattr(o, "emission", None) is not None
              and o.emission.blink is not None]
    blinks += [e.blink for e in getattr(sc, "emitters", ()) if getattr(e, "blink", None) is not None]
    out: set[int] = set()
    for b in blinks:
        if b.off_scale == 1.0 or b.duty >= 1.0:
            continue  # no change of radiance
        out.update(t for t in b.edges_us(0, dur) if 0 < t < dur)
    return sorted(out)


def _run_probe(source, p, a, length, mand, *, contrast_threshold, log_eps, max_step_fn, budget, skip_start):
    """The sampler on ``[a, a + length]`` (its mandatory times inside) for at most ``budget`` renders
    after its first accepted step (all of them when ``skip_start`` is False). Returns (renders made,
    density per s of scene time, finished)."""
    import bisect

    from .sampling import TimeSampler
    win = _Window(source, a, length)
    inside = [t - a for t in mand[bisect.bisect_right(mand, a):bisect.bisect_left(mand, a + win.duration_us)]]
    ts = TimeSampler(win, p, contrast_threshold=contrast_threshold, log_eps=log_eps, max_step_fn=max_step_fn,
                     mandatory_times_us=inside)
    first = None if skip_start else (0, 1)
    t_last = 0
    finished = True
    for i, (t, _r) in enumerate(ts):
        if i == 1 and first is None:  # past the start-up (the first step's bisections)
            first = (t, win.renders)
        t_last = t
        if first is not None and win.renders - first[1] >= budget:
            finished = False
            break
    if finished or first is None or t_last <= first[0]:
        # the whole window rendered: its own count less its two ends, which the window forces (a
        # continuous run renders there only by chance; its renders near the ends are counted)
        return win.renders, max(0, win.renders - 2) / (win.duration_us / 1e6), True
    return win.renders, (win.renders - first[1]) / ((t_last - first[0]) / 1e6), False


def predict_renders(source, sampling, *, contrast_threshold: float, log_eps: float, n_mandatory: int,
                    max_step_fn=None, n_probes: int = 10, per_probe: int = 8, mandatory_us=None,
                    phase: float = 0.381966, n_switch_probes: int = 4, switches_us=None) -> dict:
    """Predicted number of renders of a run of ``source`` (module notes), and the probes' cost.

    ``switches_us``: the times the radiance jumps (default: :func:`switch_times_us`). Returns
    ``{"renders": float, "probe_renders": int, "probe_s": float, "density_per_s": [...],
    "switch_renders": [...]}``."""
    p = sampling
    duration = int(source.duration_us)
    if p.mode == "fixed":
        return {"renders": duration * p.fixed_rate_hz / 1e6 + n_mandatory + 1, "probe_renders": 0, "probe_s": 0.0,
                "density_per_s": [], "switch_renders": []}
    mand = sorted(int(t) for t in (mandatory_us or ()))
    kw = dict(contrast_threshold=contrast_threshold, log_eps=log_eps, max_step_fn=max_step_fn)
    t_start = time.perf_counter()
    sw = sorted(set(int(t) for t in (switch_times_us(source) if switches_us is None else switches_us)
                    if 0 < int(t) < duration))
    # each switch owns a guard [e - g, e + g]: the longest step the sampler can take (1 / min rate),
    # at most half the way to its neighbours, so that the step arriving at the switch and the steps
    # growing again after it are inside
    reach = int(math.ceil(1e6 / p.min_rate_hz))
    guards = []
    for i, e in enumerate(sw):
        lo = e if i == 0 else (e - sw[i - 1]) // 2
        hi = duration - e if i == len(sw) - 1 else (sw[i + 1] - e) // 2
        g = max(1, min(reach, lo, hi))
        guards.append((e - g, e + g))
    # quiet time: the duration less the guards, as stretches
    quiet = []
    cur = 0
    for a, b in guards:
        if a > cur:
            quiet.append((cur, a))
        cur = max(cur, b)
    if cur < duration:
        quiet.append((cur, duration))
    q_len = sum(b - a for a, b in quiet)
    n_r = 0
    dens = []
    quiet_total = 0.0
    if q_len > 0:
        # as many probes as the quiet time's share of the duration asks for (at least one)
        n_q = max(1, min(n_probes, round(n_probes * q_len / duration)))
        seg = q_len / n_q
        starts = [0]
        for a, b in quiet:
            starts.append(starts[-1] + (b - a))
        for k in range(n_q):
            # stratified: one probe in each n-th of the quiet time, at a different fraction of each
            # (a Weyl sequence: no two probes at the same phase of a periodic event or of the frames)
            u = (k + ((phase + k * 0.618034) % 1.0)) * seg
            j = max(0, min(len(quiet) - 1, bisect.bisect_right(starts, u) - 1))
            s0, s1 = quiet[j]
            length = max(1, min(int(round(seg)), s1 - s0))
            # the window lies inside its quiet stretch (a window cut short by a switch would be
            # mostly its forced ends)
            a = max(s0, min(int(round(s0 + (u - starts[j]))), s1 - length))
            n, d, _fin = _run_probe(source, p, a, length, mand, budget=per_probe, skip_start=True, **kw)
            n_r += n
            dens.append(round(d, 1))
            quiet_total += d * seg / 1e6
    d_quiet = quiet_total / (q_len / 1e6) if q_len > 0 else 0.0
    # the switches: a few, spread over the duration, rendered whole (the step that meets the switch
    # is bisected down to the shortest, then grows again); each other switch costs their mean excess
    # over the quiet density
    sw_counts = []
    excess = []
    if sw:
        m = min(len(sw), n_switch_probes)
        pick = sorted(set(int((j + 0.5) * len(sw) / m) for j in range(m)))
        for i in pick:
            a, b = guards[i]
            n, _d, _fin = _run_probe(source, p, a, b - a, mand, budget=64 * per_probe, skip_start=False, **kw)
            n_r += n
            c = max(0, n - 2)  # less the forced ends, as above
            sw_counts.append(c)
            excess.append(c - d_quiet * (b - a) / 1e6)
    ex = sum(excess) / len(excess) if excess else 0.0
    switch_total = sum(max(0.0, ex + d_quiet * (b - a) / 1e6) for a, b in guards)
    total = quiet_total + switch_total
    # with the mandatory times inside the probes, their cost is in the densities already
    return {"renders": total + (0 if mand else n_mandatory) + 1, "probe_renders": n_r,
            "probe_s": time.perf_counter() - t_start, "density_per_s": dens, "switch_renders": sw_counts}


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
