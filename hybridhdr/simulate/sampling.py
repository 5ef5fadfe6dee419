"""Adaptive time sampling of a radiance source and event-fidelity scoring.

Renders are the cost of a simulation, so the sampler renders only as often as the sensor model
needs. After each accepted render at ``t`` the next step ``Δt`` is the smallest of

* the **brightness rule**: ``max_log_change_fraction * C / r``, where ``r`` is the robust maximum
  over pixels of ``|L_t - L_prev| / (t - t_prev)`` (the per-pixel log-brightness rate extrapolated
  from the last two renders; robust = the ``k``-th largest with ``k = ceil((1 - robust_quantile)
  * n_pixels)``, so a handful of pixels cannot stall the simulation); ESIM's rule
  ``Δt = λ / max |∇L·u|`` predicts the same change from the optical flow, and
  ``docs/simulate-sensor.md`` proposes C/4;
* the **motion rule**: ``max_motion_px / v`` with ``v = source.max_image_speed_px_per_s(t, t +
  1/min_rate)`` (a bound over the longest possible step, so it holds for the shorter one);
* ``τ/3`` when the photoreceptor low-pass is on (v2e README), through ``max_step_fn``;
* twice the previous step (growth limit, as in adaptive ODE steppers);

clamped to ``[1/max_rate_hz, 1/min_rate_hz]`` and cut short at the next *mandatory* time
(exposure starts and ends, ground-truth times, the end of the scene), which is therefore
rendered exactly.

**Bisection policy.** The prediction can miss (a light switches on, an object enters). After
rendering the candidate, the realised robust change ``max_k |L_cand - L_t|`` is compared with
``bisect_margin * max_log_change_fraction * C``; if it is larger and the step is longer than
``1/max_rate``, the candidate is kept on a stack (it is not wasted) and the midpoint is rendered
and checked the same way. Accepted samples are emitted in time order and every render is used,
so ``renders == samples``.

In ``fixed`` mode the renders are on the grid ``round(k * 1e6 / fixed_rate_hz)`` µs plus the
mandatory times (for a dense reference).
"""

from __future__ import annotations

import bisect as _bisect
import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from .._util.checks import check_shape
from ..events import SensorSize

__all__ = ["SamplingParams", "TimeSampler", "event_fidelity"]


@dataclass(frozen=True, kw_only=True)
class SamplingParams:
    """How render times are chosen.

    Parameters
    ----------
    mode : {"adaptive", "fixed"}
    fixed_rate_hz : float
        Render rate of the fixed mode.
    min_rate_hz : float
        Floor of the adaptive rate (ESIM's default minimum rate: 30 Hz; configs 5-50 Hz).
    max_rate_hz : float
        Ceiling of the adaptive rate (the shortest step, also the bisection limit).
    max_log_change_fraction : float
        Allowed predicted per-pixel log change per step, as a fraction of the contrast threshold
        (simulator.md proposal: 1/4; ESIM's λ = 0.5 of a threshold of 1 per step).
    max_motion_px : float
        Allowed image motion per step in pixels (default 0.5 px; vid2e uses ≤ 1 px).
    robust_quantile : float
        Quantile of the per-pixel change used as the "maximum" (1.0 = the true maximum).
    bisect : bool
        Re-render in between when a step exceeded the bound by ``bisect_margin``.
    bisect_margin : float
        Factor over the bound that triggers bisection (> 1).
    """

    mode: str = "adaptive"
    fixed_rate_hz: float = 1000.0
    min_rate_hz: float = 30.0
    max_rate_hz: float = 20000.0
    max_log_change_fraction: float = 0.25
    max_motion_px: float = 0.5
    robust_quantile: float = 0.99
    bisect: bool = True
    bisect_margin: float = 2.0

    def __post_init__(self):
        if self.mode not in ("adaptive", "fixed"):
            raise ValueError(f"SamplingParams.mode must be 'adaptive' or 'fixed', got {self.mode!r}")
        for name in ("fixed_rate_hz", "min_rate_hz", "max_rate_hz", "max_log_change_fraction",
                     "max_motion_px", "bisect_margin"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise ValueError(f"SamplingParams.{name} must be a positive finite number, got {v!r}")
        if self.min_rate_hz > self.max_rate_hz:
            raise ValueError(f"SamplingParams.min_rate_hz ({self.min_rate_hz}) must be <= max_rate_hz "
                             f"({self.max_rate_hz})")
        if self.max_rate_hz > 1e6 or self.fixed_rate_hz > 1e6:
            raise ValueError("render rates above 1 MHz are below the 1 µs time base")
        if not 0.5 <= self.robust_quantile <= 1.0:
            raise ValueError(f"SamplingParams.robust_quantile must be in [0.5, 1], got {self.robust_quantile}")
        if self.bisect_margin < 1.0:
            raise ValueError(f"SamplingParams.bisect_margin must be >= 1, got {self.bisect_margin}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def replace(self, **changes) -> "SamplingParams":
        return dataclasses.replace(self, **changes)


def _robust_k(n: int, q: float) -> int:
    return max(1, int(math.ceil((1.0 - q) * n)))


class TimeSampler:
    """Iterate ``(t_us, radiance)`` over ``[0, source.duration_us]`` with adaptive or fixed steps.

    Parameters
    ----------
    source : RadianceSource
    params : SamplingParams
    contrast_threshold : float
        Nominal threshold C (log units) of the brightness rule.
    log_eps : float
        ε of ``L = ln(I + ε)``.
    mandatory_times_us : iterable of int
        Times that must be rendered exactly (0 and the duration are always added).
    max_step_fn : callable, optional
        ``f(radiance) -> µs``: an extra bound on the next step (the photoreceptor's τ/3).

    Attributes
    ----------
    renders, bisections : int
    """

    def __init__(self, source, params: SamplingParams | None = None, *, contrast_threshold: float = 0.2,
                 log_eps: float = 1e-3, mandatory_times_us=(), max_step_fn: Callable | None = None):
        self.source = source
        self.params = params or SamplingParams()
        self.c = float(contrast_threshold)
        self.eps = float(log_eps)
        self.duration = int(source.duration_us)
        if self.duration <= 0:
            raise ValueError(f"source.duration_us must be > 0, got {self.duration}")
        self._mand: list[int] = []
        for t in list(mandatory_times_us) + [0, self.duration]:
            self.add_mandatory(t)
        self.max_step_fn = max_step_fn
        self.renders = 0
        self.bisections = 0
        self.render_s = 0.0
        self._last_t = None
        self._n_pix = source.sensor_size.n_pixels
        self._k = _robust_k(self._n_pix, self.params.robust_quantile)

    def add_mandatory(self, t_us) -> None:
        """Require a render at ``t_us`` (must lie after the last emitted sample; beyond the
        duration it is ignored)."""
        t = int(t_us)
        if t < 0:
            raise ValueError(f"mandatory time {t} µs is negative")
        if t > self.duration:
            return
        if getattr(self, "_last_t", None) is not None and t <= self._last_t:
            if t == self._last_t:
                return
            raise ValueError(f"mandatory time {t} µs lies before the last sample {self._last_t} µs")
        i = _bisect.bisect_left(self._mand, t)
        if i == len(self._mand) or self._mand[i] != t:
            self._mand.insert(i, t)

    def _next_mandatory(self, t: int) -> int:
        i = _bisect.bisect_right(self._mand, t)
        return self._mand[i] if i < len(self._mand) else self.duration

    def _render(self, t: int):
        t_start = time.perf_counter()
        r = np.asarray(self.source.render(int(t)))
        self.render_s += time.perf_counter() - t_start
        check_shape(r, "H W", f"source.render({t})", sizes=dict(zip("HW", self.source.sensor_size.shape)))
        self.renders += 1
        lg = np.log(r.astype(np.float64, copy=False).ravel() + self.eps)
        return t, r, lg

    def _change(self, la, lb) -> float:
        d = np.abs(lb - la)
        if self._k == 1:
            return float(d.max())
        # the k-th largest of d >= 0 is the k-th largest of its non-zero part, or 0 when fewer than
        # k pixels changed. Selecting among the non-zeros only also avoids np.partition's slow path
        # on the many equal zeros of a mostly static scene (14 ms instead of 0.1 ms at 346x260)
        nz = d[d > 0]
        if nz.size < self._k:
            return 0.0
        return float(np.partition(nz, nz.size - self._k)[nz.size - self._k])

    def _adaptive_dt(self, t, lg, prev) -> int:
        p = self.params
        dt_max = 1e6 / p.min_rate_hz
        dt_min = 1e6 / p.max_rate_hz
        dt = dt_max
        if prev is not None:
            tp, lp = prev
            rate = self._change(lp, lg) / (t - tp)
            if rate > 0:
                dt = min(dt, p.max_log_change_fraction * self.c / rate)
            dt = min(dt, 2.0 * (t - tp))
        v = float(self.source.max_image_speed_px_per_s(int(t), int(t + math.ceil(dt_max))))
        if v > 0:
            dt = min(dt, p.max_motion_px / v * 1e6)
        return max(1, int(round(max(dt, dt_min))))

    def __iter__(self) -> Iterator[tuple[int, np.ndarray]]:
        p = self.params
        t, r, lg = self._render(0)
        self._last_t = 0
        yield 0, r
        extra = self.max_step_fn(r) if self.max_step_fn is not None else math.inf
        prev = None
        pending: list = []  # rendered candidates after t, latest first (stack top = earliest)
        bound = p.bisect_margin * p.max_log_change_fraction * self.c
        dt_min = max(1, int(round(1e6 / p.max_rate_hz)))
        while t < self.duration:
            m = self._next_mandatory(t)
            if pending and pending[-1][0] <= m:
                cand = pending.pop()
            else:
                if p.mode == "fixed":
                    k = math.floor(t * p.fixed_rate_hz / 1e6) + 1
                    tn = int(round(k * 1e6 / p.fixed_rate_hz))
                    while tn <= t:
                        k += 1
                        tn = int(round(k * 1e6 / p.fixed_rate_hz))
                else:
                    dt = self._adaptive_dt(t, lg, prev)
                    if math.isfinite(extra):
                        dt = max(1, min(dt, int(extra)))
                    tn = t + dt
                cand = self._render(min(tn, m))
            if p.mode == "adaptive" and p.bisect:
                while cand[0] - t > dt_min and self._change(lg, cand[2]) > bound:
                    pending.append(cand)
                    self.bisections += 1
                    cand = self._render((t + cand[0]) // 2)
            prev = (t, lg)
            t, r, lg = cand
            self._last_t = t
            yield t, r
            if self.max_step_fn is not None:
                extra = self.max_step_fn(r)


def event_fidelity(events_a: np.ndarray, events_b: np.ndarray, sensor_size) -> dict:
    """Compare an event stream ``a`` with a reference ``b`` pixel by pixel.

    Definitions (per pixel *and* polarity ``q``, with event counts ``n_a(q)``, ``n_b(q)``):

    * ``count_error = Σ_q |n_a(q) - n_b(q)| / Σ_q n_b(q)`` (0 = identical counts everywhere; an
      empty reference gives 0 if ``a`` is empty too, else inf);
    * ``timestamp_rmse_us``: every event of ``a`` is paired with the nearest-in-time event of ``b``
      at the same pixel and polarity; the RMS of those time differences in µs (NaN when no
      event of ``a`` has a partner). Nearest-neighbour pairing keeps one missing event from
      shifting every later pair of a busy pixel;
    * ``timestamp_median_us``, ``timestamp_p99_us``: the median and 99th percentile of the
      absolute paired differences (the RMS is dominated by the few pixels whose reference level
      diverged: one crossing missed near a brightness extremum shifts all their later events);
    * ``matched``: events of ``a`` with a partner; ``n_a``, ``n_b``: the totals.

    Parameters
    ----------
    events_a, events_b : ndarray of dtype EVENT_DTYPE
    sensor_size : SensorSize or (height, width)
    """
    ss = SensorSize.from_any(sensor_size)
    w = ss.width
    nq = ss.n_pixels * 2

    def group(ev):
        return (ev["y"].astype(np.int64) * w + ev["x"].astype(np.int64)) * 2 + (ev["p"] > 0)

    ga, gb = group(events_a), group(events_b)
    na = np.bincount(ga, minlength=nq)
    nb = np.bincount(gb, minlength=nq)
    tot_b = int(nb.sum())
    diff = int(np.abs(na - nb).sum())
    count_error = diff / tot_b if tot_b else (0.0 if diff == 0 else math.inf)
    rmse = p99 = med = math.nan
    matched = 0
    if len(events_a) and len(events_b):
        ta = events_a["t"].astype(np.int64)
        tb = events_b["t"].astype(np.int64)
        t0 = min(int(ta.min()), int(tb.min()))
        span = max(int(ta.max()), int(tb.max())) - t0 + 1
        big = 2 * span + 1  # keys of different groups are > span apart
        ka = ga * big + (ta - t0)
        kb = np.sort(gb * big + (tb - t0))
        i = np.searchsorted(kb, ka)
        lo = np.clip(i - 1, 0, len(kb) - 1)
        hi = np.clip(i, 0, len(kb) - 1)
        d = np.minimum(np.abs(ka - kb[lo]), np.abs(ka - kb[hi]))
        ok = d <= span  # partner in the same group
        matched = int(ok.sum())
        if matched:
            dm = d[ok].astype(np.float64)
            rmse = float(np.sqrt(np.mean(dm ** 2)))
            p99 = float(np.percentile(dm, 99))
            med = float(np.median(dm))
    return {"count_error": float(count_error), "timestamp_rmse_us": rmse, "timestamp_median_us": med, "timestamp_p99_us": p99,
            "matched": matched, "n_a": int(len(events_a)), "n_b": tot_b}
