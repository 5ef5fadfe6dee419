"""Event-sensor model: log-intensity threshold crossings from rendered radiance.

The model works on ``L = ln(I + log_eps)`` of the linear radiance ``I`` (ESIM), linearly
interpolated in time between two renders per pixel. Every crossing of ``ref + C_on`` or
``ref - C_off`` emits one event at its analytic time ``t = t_k + (L_cross - L_k) Δt /
(L_{k+1} - L_k)``, rounded to the nearest µs, and moves the reference to the crossing (ESIM), so a
large change gives several events in one interval. Optional tiers, each off unless asked for:

* **threshold mismatch**: ``C_on``/``C_off`` drawn once per pixel from ``N(C, σ)`` and clamped at
  ``min_threshold`` = 0.01 (v2e's fixed pattern; σ = 0.03 default, 0.02 clean, 0.05 noisy);
* **refractory period**: after an event the pixel is blind for ``refractory_period_us``; its
  reference follows the input during that time and the pixel is re-referenced to the input at
  the end of the period, so changes during the period are lost (IEBCS's behaviour, chosen
  because it is what the pixel's reset switch does: the differencing amplifier is held in reset,
  its capacitor tracking the photoreceptor, until the switch opens; ESIM instead drops the event
  but advances the reference, v2e keeps the reference so the residual fires later);
* **shot noise**: a Poisson process of ``shot_noise_rate_hz`` events per pixel per second (ON and
  OFF equally likely), with exponential inter-arrival times in continuous time, i.e. uniform
  sub-frame timestamps, not v2e's one Bernoulli draw per frame stamped at the frame end
  (``SensorsINI/v2e#74``). Noise events are independent of the pixel state: they neither move
  the reference nor respect the refractory period;
* **leak**: the reference drifts down by ``leak_rate_hz * C_on`` log units per second, so a static
  pixel with the nominal threshold emits ON events at ``leak_rate_hz`` (v2e's leak model; a pixel
  with a lower mismatched threshold leaks more often). The initial leak phase is uniform per
  pixel (seeded), so static pixels do not fire in lockstep. Leak events are ordinary crossings,
  so their timestamps are sub-frame too;
* **photoreceptor low-pass**: a first-order low-pass on ``L`` with ``τ = 1/(2π f3dB)`` and
  ``f3dB = photoreceptor_cutoff_hz * I / photoreceptor_white_radiance``, so the bandwidth grows
  with intensity (v2e: 300 Hz at white, 30 Hz in its noisy preset). Intensity is in radiance
  units, not v2e's 8-bit ``(I+20)/275`` (wrong for HDR input, ``SensorsINI/v2e#65``). The filter
  is solved exactly for the linear ramp between two renders; the sampler keeps steps <= τ/3.

References
----------
H. Rebecq, D. Gehrig, D. Scaramuzza, "ESIM: an Open Event Camera Simulator", CoRL 2018.
Y. Hu, S.-C. Liu, T. Delbruck, "v2e: From Video Frames to Realistic DVS Events", CVPRW 2021,
doi:10.1109/CVPRW53098.2021.00144.
D. Joubert et al., "Event Camera Simulator Improvements via Characterized Parameters" (IEBCS),
Front. Neurosci. 15:702765, 2021, doi:10.3389/fnins.2021.702765.
Defaults and facts: ``docs/simulate-sensor.md`` ("Event sensor").
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .._util.checks import check_shape
from ..events import EVENT_DTYPE, SensorSize

__all__ = ["EventSensorParams", "EventSensor", "PRESETS", "sensor_preset", "generate_events", "BUILTIN_PROFILES",
           "sensor_from_profile", "load_profile_spec", "SENSOR_TIERS", "restrict_to_tiers"]

#: Longest step (µs) handled in one kernel call; longer steps are cut into equal pieces on the
#: same linear interpolation, which bounds the counting-sort histogram (8 bytes per µs).
MAX_STEP_BINS = 1 << 20
#: Most threshold crossings one call of the crossing kernel may have to walk: a compiled kernel
#: cannot take Ctrl-C or SIGTERM, so a step with more is split in time, and the signals act
#: between the pieces (a fraction of a second apart).
MAX_CROSSINGS_PER_CALL = 1 << 24


@dataclass(frozen=True, kw_only=True)
class EventSensorParams:
    """Parameters of the event-sensor model; every noise tier is off (0) unless set.

    Parameters
    ----------
    contrast_threshold_on, contrast_threshold_off : float
        Nominal ON/OFF thresholds in natural-log units (v2e default 0.2; ESIM configs 0.5-0.6;
        AKF's ``ct`` 0.1; simulator.md Tier 0).
    threshold_mismatch_sigma : float
        σ of the fixed per-pixel N(C, σ) threshold pattern, log units (v2e: 0.03; clean 0.02;
        noisy 0.05). 0 = off.
    min_threshold : float
        Clamp of mismatched thresholds (v2e and ESIM: 0.01).
    refractory_period_us : int
        Blind time after each event in µs (v2e 500, IEBCS 100, ESIM 0). 0 = off. Behaviour: the
        reference follows the input and is re-set at the end of the period (IEBCS).
    shot_noise_rate_hz : float
        Shot-noise events per pixel per second, ON + OFF (v2e noisy preset: 5 Hz). 0 = off.
    leak_rate_hz : float
        Leak ON events per pixel per second at the nominal threshold (v2e: 0.01 Hz; noisy
        0.1 Hz). 0 = off.
    photoreceptor_cutoff_hz : float or None
        Photoreceptor corner frequency at ``photoreceptor_white_radiance`` (v2e: 300 Hz at white,
        noisy 30 Hz). None or 0 = infinite bandwidth (off).
    photoreceptor_white_radiance : float
        Radiance at which the corner frequency equals ``photoreceptor_cutoff_hz``.
    log_eps : float
        ε of ``L = ln(I + ε)`` in radiance units (ESIM: 1e-3 on [0, 1] images).
    """

    contrast_threshold_on: float = 0.2
    contrast_threshold_off: float = 0.2
    threshold_mismatch_sigma: float = 0.0
    min_threshold: float = 0.01
    refractory_period_us: int = 0
    shot_noise_rate_hz: float = 0.0
    leak_rate_hz: float = 0.0
    photoreceptor_cutoff_hz: float | None = None
    photoreceptor_white_radiance: float = 1.0
    log_eps: float = 1e-3

    def __post_init__(self):
        def num(name, lo, lo_open, allow_none=False):
            v = getattr(self, name)
            if v is None and allow_none:
                return
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise TypeError(f"EventSensorParams.{name} must be a number, got {type(v).__name__} {v!r}")
            v = float(v)
            if not math.isfinite(v) or (v <= lo if lo_open else v < lo):
                rel = ">" if lo_open else ">="
                raise ValueError(f"EventSensorParams.{name} must be finite and {rel} {lo}, got {v}")

        num("contrast_threshold_on", 0.0, True)
        num("contrast_threshold_off", 0.0, True)
        num("threshold_mismatch_sigma", 0.0, False)
        num("min_threshold", 0.0, True)
        num("shot_noise_rate_hz", 0.0, False)
        num("leak_rate_hz", 0.0, False)
        num("photoreceptor_cutoff_hz", 0.0, False, allow_none=True)
        num("photoreceptor_white_radiance", 0.0, True)
        num("log_eps", 0.0, True)
        r = self.refractory_period_us
        if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or r < 0:
            raise ValueError(f"EventSensorParams.refractory_period_us must be an int >= 0 (µs), got {r!r}")
        from ..formats.sensor_profile import PARAM_RANGES, check_param_range
        for name in PARAM_RANGES:  # physics: values outside make the crossing kernel run without end
            v = getattr(self, name)
            if not (name == "photoreceptor_cutoff_hz" and not v):
                check_param_range(name, v, "EventSensorParams")
        for name in ("contrast_threshold_on", "contrast_threshold_off"):
            if getattr(self, name) < self.min_threshold:
                raise ValueError(f"EventSensorParams.{name} = {getattr(self, name)} is below "
                                 f"min_threshold = {self.min_threshold}")

    @property
    def lowpass_on(self) -> bool:
        return bool(self.photoreceptor_cutoff_hz)

    @property
    def contrast_threshold(self) -> float:
        """The smaller nominal threshold (used by the adaptive sampler)."""
        return min(self.contrast_threshold_on, self.contrast_threshold_off)

    def min_time_constant_s(self, max_radiance: float) -> float:
        """Smallest photoreceptor τ = 1/(2π f3dB) at ``max_radiance`` (inf when the low-pass is off)."""
        if not self.lowpass_on:
            return math.inf
        f = self.photoreceptor_cutoff_hz * (max_radiance + self.log_eps) / self.photoreceptor_white_radiance
        return 1.0 / (2.0 * math.pi * f) if f > 0 else math.inf

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_profile(cls, profile, base="ideal", **overrides) -> "EventSensorParams":
        """From a sensor profile (object, JSON path or ``builtin:NAME``): :func:`sensor_from_profile`."""
        return sensor_from_profile(profile, base, **overrides)

    @classmethod
    def from_dict(cls, d: dict) -> "EventSensorParams":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown EventSensorParams field(s) {unknown}; expected some of {sorted(names)}")
        return cls(**d)

    def replace(self, **changes) -> "EventSensorParams":
        return dataclasses.replace(self, **changes)


#: Named presets (values from v2e's ``--dvs_params`` presets and defaults, simulator.md Tiers 0-4).
PRESETS: dict[str, EventSensorParams] = {
    # Tier 0 only: exact crossings, C = 0.2 (v2e default threshold)
    "ideal": EventSensorParams(),
    # v2e "clean": σ_C = 0.02, no noise, infinite bandwidth; v2e's default refractory 0.5 ms
    "clean": EventSensorParams(threshold_mismatch_sigma=0.02, refractory_period_us=500),
    # v2e "noisy": σ_C = 0.05, 30 Hz photoreceptor at white, leak 0.1 Hz, shot noise 5 Hz
    "noisy": EventSensorParams(threshold_mismatch_sigma=0.05, refractory_period_us=500,
                               shot_noise_rate_hz=5.0, leak_rate_hz=0.1, photoreceptor_cutoff_hz=30.0),
}


#: The optional tiers of the model (simulator.md; tier 0, exact crossings at the nominal
#: thresholds, is always on) and the fields that switch each one on.
SENSOR_TIERS: dict[int, tuple[str, ...]] = {
    1: ("threshold_mismatch_sigma",),                # per-pixel threshold mismatch
    2: ("refractory_period_us",),                    # refractory period
    3: ("shot_noise_rate_hz", "leak_rate_hz"),       # shot and leak noise
    4: ("photoreceptor_cutoff_hz",),                 # photoreceptor bandwidth
}


def restrict_to_tiers(params, tiers) -> dict:
    """``params`` (an :class:`EventSensorParams` or a dict of its fields) with every optional tier
    not in ``tiers`` switched off (its fields 0 / None), as a dict: a scene models no more of the
    sensor than it needs."""
    d = params.to_dict() if isinstance(params, EventSensorParams) else dict(params)
    bad = sorted(set(tiers) - set(SENSOR_TIERS))
    if bad:
        raise ValueError(f"sensor tiers: expected some of {sorted(SENSOR_TIERS)}, found {bad}")
    for tier, fields in SENSOR_TIERS.items():
        if tier not in tiers:
            for f in fields:
                if f in d:
                    d[f] = None if f == "photoreceptor_cutoff_hz" else type(d[f])(0) if d[f] is not None else 0
    return d


#: Built-in sensor profiles (``builtin:NAME``), package data in ``simulate/profiles/``; each was
#: estimated by ``hybridhdr calibrate sensor`` (docs/simulate-sensor.md, "Sensor profiles").
BUILTIN_PROFILES = {"davis240c": "davis240c_ecd.json"}


def load_profile_spec(spec):
    """A :class:`~hybridhdr.formats.sensor_profile.SensorProfile` from a profile object, a JSON path
    or ``builtin:NAME`` (:data:`BUILTIN_PROFILES`)."""
    from ..formats.sensor_profile import SensorProfile, load_sensor_profile
    if isinstance(spec, SensorProfile):
        return spec.validate()
    if isinstance(spec, str) and spec.startswith("builtin:"):
        key = spec[len("builtin:"):]
        if key not in BUILTIN_PROFILES:
            raise ValueError(f"unknown built-in sensor profile {spec!r}; expected one of "
                             f"{['builtin:' + k for k in sorted(BUILTIN_PROFILES)]}")
        from pathlib import Path
        return load_sensor_profile(Path(__file__).with_name("profiles") / BUILTIN_PROFILES[key])
    return load_sensor_profile(spec)


def sensor_from_profile(profile, base: "EventSensorParams | str" = "ideal", **overrides) -> EventSensorParams:
    """EventSensorParams from a sensor profile (object, JSON path or ``builtin:NAME``).

    The profile's ``simulator_params`` (what its recording identified) replace ``base``'s values
    (a preset name or EventSensorParams; default ``ideal``: every tier the recording could not
    tell stays off); ``overrides`` (EventSensorParams fields) replace both. ``min_threshold`` is
    lowered to the smallest threshold when a profile's threshold lies below it.
    """
    prof = load_profile_spec(profile)
    b = sensor_preset(base) if isinstance(base, str) else base
    if not isinstance(b, EventSensorParams):
        raise TypeError(f"base must be a preset name or EventSensorParams, got {type(base).__name__}")
    vals = {**prof.simulator_params, **overrides}
    if vals.get("photoreceptor_cutoff_hz") == 0:
        vals["photoreceptor_cutoff_hz"] = None
    lo = min([v for k, v in vals.items() if k.startswith("contrast_threshold_")] + [b.min_threshold])
    if "min_threshold" not in vals and lo < b.min_threshold:
        vals["min_threshold"] = lo
    try:
        return dataclasses.replace(b, **vals)
    except (TypeError, ValueError) as e:
        raise ValueError(f"sensor profile {prof.name or profile!s}: {e}") from None


def _is_profile_spec(name) -> bool:
    from pathlib import Path

    from ..formats.sensor_profile import SensorProfile
    return (isinstance(name, (Path, SensorProfile))
            or (isinstance(name, str) and (name.startswith("builtin:") or name.lower().endswith(".json"))))


def sensor_preset(name) -> EventSensorParams:
    """The preset ``name`` ("ideal", "clean" or "noisy"), or a sensor profile (a ``.json`` path,
    ``builtin:NAME`` or a ``SensorProfile``) over the ``ideal`` preset (:func:`sensor_from_profile`)."""
    if isinstance(name, EventSensorParams):
        return name
    if _is_profile_spec(name):
        return sensor_from_profile(name)
    try:
        return PRESETS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown event-sensor preset {name!r}; expected one of {sorted(PRESETS)}, a sensor "
                         f"profile .json or one of {['builtin:' + k for k in sorted(BUILTIN_PROFILES)]}") from None


def _check_radiance(radiance, shape, what="radiance") -> np.ndarray:
    r = np.asarray(radiance)
    check_shape(r, "H W", what, sizes=dict(zip("HW", shape)))
    if r.dtype.kind not in "fiu":
        raise TypeError(f"{what} must be a real array, got dtype {r.dtype}")
    r = r.astype(np.float64, copy=False).ravel()
    if not np.all(np.isfinite(r)) or (r.size and r.min() < 0):
        raise ValueError(f"{what} must be finite and >= 0 (linear radiance)")
    return r


def _as_time(t_us, name="t_us") -> int:
    if isinstance(t_us, bool) or not isinstance(t_us, (int, np.integer)):
        if isinstance(t_us, (float, np.floating)) and float(t_us).is_integer():
            return int(t_us)
        raise TypeError(f"{name} must be an integer number of µs, got {t_us!r}")
    return int(t_us)


class EventSensor:
    """Streaming event sensor: feed radiance samples in time order, get the events between them.

    Parameters
    ----------
    sensor_size : SensorSize or (height, width)
    params : EventSensorParams or preset name
    seed : int or None
        Seeds the threshold pattern, the leak phase and the shot noise (``None``: fresh entropy).

    Examples
    --------
    >>> import numpy as np
    >>> s = EventSensor((1, 1), "ideal", seed=0)
    >>> s.start(0, np.full((1, 1), 1.0))
    >>> ev = s.step(1000, np.full((1, 1), 3.0))   # ln(I + 1e-3) rises by 1.098: 5 ON events at C = 0.2
    >>> ev["t"].tolist(), ev["p"].tolist()
    ([182, 364, 546, 729, 911], [1, 1, 1, 1, 1])
    """

    def __init__(self, sensor_size, params: EventSensorParams | str = "clean", seed: int | None = 0):
        self.sensor_size = SensorSize.from_any(sensor_size)
        if self.sensor_size is None:
            raise ValueError("EventSensor needs a sensor_size (height, width)")
        if not isinstance(params, (EventSensorParams, str)) and not _is_profile_spec(params):
            raise TypeError(f"params must be EventSensorParams, a preset name or a sensor profile, got "
                            f"{type(params).__name__}")
        self.params = params if isinstance(params, EventSensorParams) else sensor_preset(params)
        if not isinstance(self.params, EventSensorParams):
            raise TypeError(f"params must be EventSensorParams, a preset name or a sensor profile, got "
                            f"{type(params).__name__}")
        self.seed = seed
        self._rng = np.random.default_rng(seed)
        p = self.params
        n = self.sensor_size.n_pixels
        if p.threshold_mismatch_sigma > 0:
            self.c_on = np.maximum(self._rng.normal(p.contrast_threshold_on, p.threshold_mismatch_sigma, n),
                                   p.min_threshold)
            self.c_off = np.maximum(self._rng.normal(p.contrast_threshold_off, p.threshold_mismatch_sigma, n),
                                    p.min_threshold)
        else:
            self.c_on = np.full(n, float(p.contrast_threshold_on))
            self.c_off = np.full(n, float(p.contrast_threshold_off))
        self._leak_per_us = p.leak_rate_hz * p.contrast_threshold_on * 1e-6
        self._t = None
        self.n_events = 0
        self.n_noise_events = 0

    # -- state ---------------------------------------------------------------------------------
    @property
    def t_us(self) -> int | None:
        """Time of the last sample (None before :meth:`start`)."""
        return self._t

    def _log(self, r: np.ndarray) -> np.ndarray:
        return np.log(r + self.params.log_eps)

    def start(self, t_us: int, radiance) -> None:
        """Set the initial sample: the reference of every pixel is its log intensity at ``t_us``."""
        t = _as_time(t_us)
        r = _check_radiance(radiance, self.sensor_size.shape)
        lg = self._log(r)
        self._t = t
        self._rad = r.copy()
        self._x = lg                      # unfiltered log intensity of the last sample
        self._lp = lg.copy()              # filtered log intensity (== _x without the low-pass)
        self._ref = lg.copy()
        if self._leak_per_us > 0:
            # uniform leak phase: the reference starts between 0 and C_on below the input
            self._ref -= self._rng.random(r.size) * self.c_on
        self._blind = np.full(r.size, -1.0)
        self.n_events = 0
        self.n_noise_events = 0

    def step(self, t_us: int, radiance) -> np.ndarray:
        """Advance to ``t_us`` with the sample ``radiance``; return the events in ``(t_prev, t_us]``.

        Returns
        -------
        ndarray of shape (N,), dtype EVENT_DTYPE
            Sorted by ``t`` (stable: ties by pixel index, then noise events).
        """
        if self._t is None:
            raise RuntimeError("EventSensor.step called before start()")
        t1 = _as_time(t_us)
        if t1 <= self._t:
            raise ValueError(f"EventSensor.step: t_us must increase; got {t1} µs after {self._t} µs")
        r = _check_radiance(radiance, self.sensor_size.shape)
        x1 = self._log(r)
        p = self.params
        t0 = self._t
        dt = t1 - t0
        if p.lowpass_on:
            from . import _kernels as K
            lp1 = np.empty_like(x1)
            K.lowpass_step(self._lp, self._x, x1, self._rad, r, dt * 1e-6,
                           2.0 * math.pi * p.photoreceptor_cutoff_hz / p.photoreceptor_white_radiance, lp1)
        else:
            lp1 = x1
        if not np.all(np.isfinite(lp1)):
            raise ValueError(f"the sensor's log intensity at {t1} µs is not finite (photoreceptor cut-off "
                             f"{p.photoreceptor_cutoff_hz} Hz, white radiance {p.photoreceptor_white_radiance}); "
                             f"check the sensor parameters")
        bound = self._crossing_bound(self._lp, lp1, dt)
        pieces = max(-(-dt // MAX_STEP_BINS), min(dt, int(-(-bound // MAX_CROSSINGS_PER_CALL))))
        if pieces <= 1:
            ev = self._crossings(t0, t1, self._lp, lp1)
        else:
            bounds = [t0 + (dt * j) // pieces for j in range(pieces + 1)]
            out = []
            la = self._lp
            for j in range(pieces):
                w = (bounds[j + 1] - t0) / dt
                lb = lp1 if j == pieces - 1 else self._lp + (lp1 - self._lp) * w
                out.append(self._crossings(bounds[j], bounds[j + 1], la, lb))
                la = lb
            ev = np.concatenate(out)
        self._t, self._rad, self._x, self._lp = t1, r, x1, lp1
        self.n_events += len(ev)
        return ev

    def _crossing_bound(self, la: np.ndarray, lb: np.ndarray, dt: int) -> float:
        """An upper bound on the events of a step, checked against the run's event budget
        (``max_events``, lifted by ``--allow-huge``) before the kernel walks them: per pixel, the
        log change over its smallest threshold plus one (the reference lies within a threshold of
        the input), plus the leak and (5 sigma above) the shot-noise events."""
        from .._util.limits import LIMITS, LimitExceeded, huge_allowed
        p = self.params
        n = la.size
        c = np.minimum(self.c_on, self.c_off)
        cross = float(np.sum(np.abs(lb - la) / c)) + n
        leak = p.leak_rate_hz * dt * 1e-6 * n
        mu = p.shot_noise_rate_hz * dt * 1e-6 * n
        bound = cross + leak + mu + 5.0 * math.sqrt(mu)
        if not math.isfinite(bound) or (self.n_events + bound > LIMITS["max_events"] and not huge_allowed()):
            raise LimitExceeded(None, f"the simulated sensor would emit up to {bound:,.0f} events in the step to "
                                      f"{self._t + dt} µs (after {self.n_events:,}), above the budget of "
                                      f"{LIMITS['max_events']:,} events a run may emit (thresholds "
                                      f"{p.contrast_threshold_on:g}/{p.contrast_threshold_off:g}, leak "
                                      f"{p.leak_rate_hz:g} Hz, noise {p.shot_noise_rate_hz:g} Hz); check the sensor "
                                      f"parameters or, if the data really is that large, pass --allow-huge")
        return bound

    def _noise(self, dt: int):
        rate = self.params.shot_noise_rate_hz
        n = self.sensor_size.n_pixels
        if rate <= 0:
            z = np.zeros(0, np.int64)
            return z, z, np.zeros(0, np.int8)
        m = int(self._rng.poisson(rate * n * dt * 1e-6))
        # Poisson process: given the count, arrival times are iid uniform over the step
        tt = self._rng.random(m) * dt
        k = np.clip(np.floor(tt + 0.5).astype(np.int64), 1, dt)
        pix = self._rng.integers(0, n, m).astype(np.int64)
        pol = np.where(self._rng.random(m) < 0.5, 1, -1).astype(np.int8)
        return k, pix, pol

    def _crossings(self, t0: int, t1: int, la: np.ndarray, lb: np.ndarray) -> np.ndarray:
        from . import _kernels as K
        dt = t1 - t0
        nk, npix, npol = self._noise(dt)
        hist = np.zeros(dt, np.int64)
        pos = np.empty(dt, np.int64)
        args = (la, lb, self._ref, self._blind, self.c_on, self.c_off, self._leak_per_us, float(dt),
                float(self.params.refractory_period_us), self.sensor_size.width, nk, npix, npol)
        dummy_i8 = np.zeros(0, np.int64)
        K.crossings(*args, False, hist, pos, np.int64(t0), dummy_i8, np.zeros(0, np.uint16),
                    np.zeros(0, np.uint16), np.zeros(0, np.int8))
        total = K.exclusive_cumsum(hist, pos)
        ev = np.zeros(total, EVENT_DTYPE)  # zeroed: the padding bytes are deterministic too
        K.crossings(*args, True, hist, pos, np.int64(t0), ev["t"], ev["x"], ev["y"], ev["p"])
        self.n_noise_events += len(nk)
        return ev


def generate_events(radiance, times_us, params: EventSensorParams | str = "ideal", seed: int | None = 0) -> np.ndarray:
    """Events of a whole radiance sequence (convenience wrapper around :class:`EventSensor`).

    Parameters
    ----------
    radiance : ndarray of shape (K, H, W)
        Linear radiance samples.
    times_us : array_like of int, shape (K,)
        Strictly increasing sample times in µs.
    """
    radiance = np.asarray(radiance)
    times = np.asarray(times_us)
    if radiance.ndim != 3 or times.shape != (radiance.shape[0],):
        raise ValueError(f"radiance must be (K, H, W) with K = len(times_us); got {radiance.shape} "
                         f"and {times.shape}")
    s = EventSensor(SensorSize(*radiance.shape[1:]), params, seed)
    s.start(int(times[0]), radiance[0])
    out = [s.step(int(t), im) for t, im in zip(times[1:], radiance[1:])]
    return np.concatenate(out) if out else np.zeros(0, EVENT_DTYPE)
