"""The event-sensor profile file (``profile.json``): a recording's sensor parameters, as the
simulator defines them, with the uncertainty of each.

``hybridhdr calibrate sensor`` writes it (:func:`hybridhdr.calibrate.sensor_profile.estimate_sensor_profile`);
``hybridhdr simulate --sensor PROFILE`` and :func:`hybridhdr.simulate.sensor.sensor_preset` read
it. The format lives here (formats) because calibrate may not import simulate: both read this
module, neither the other.

Schema (version 1)::

    {"format": "hybridhdr-sensor-profile", "version": 1,
     "name": "davis240c_ecd",
     "sensor": {"model": "DAVIS240C", "width": 240, "height": 180},
     "simulator_params": {"contrast_threshold_on": 0.39, ...},   # only the identified ones
     "estimates": {"contrast_threshold_on": {"value": 0.39, "std": 0.01, "ci95": [0.37, 0.41],
                                              "identifiable": true, "reason": "", "method": "...",
                                              "unit": "ln"}, ...},
     "provenance": {...}}

``simulator_params`` holds the :class:`hybridhdr.simulate.sensor.EventSensorParams` fields the
recording identified (names carry their units: ``refractory_period_us``, ``leak_rate_hz``...);
a field it could not tell is absent there, and the simulator takes it from a base preset.
``estimates`` holds every parameter looked for, identified or not, with its reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from .._util.atomic import write_json_atomic

__all__ = ["SensorProfile", "load_sensor_profile", "SENSOR_PROFILE_FORMAT", "SENSOR_PROFILE_VERSION",
           "SIMULATOR_FIELDS", "SensorProfileError"]

SENSOR_PROFILE_FORMAT = "hybridhdr-sensor-profile"
SENSOR_PROFILE_VERSION = 1
#: The simulator's sensor fields a profile may set (``EventSensorParams``; a test keeps the two equal),
#: with their kind: "pos" (> 0), "nonneg" (>= 0), "int" (int >= 0), "nonneg_or_null".
SIMULATOR_FIELDS = {
    "contrast_threshold_on": "pos", "contrast_threshold_off": "pos", "threshold_mismatch_sigma": "nonneg",
    "min_threshold": "pos", "refractory_period_us": "int", "shot_noise_rate_hz": "nonneg",
    "leak_rate_hz": "nonneg", "photoreceptor_cutoff_hz": "nonneg_or_null",
    "photoreceptor_white_radiance": "pos", "log_eps": "pos",
}
#: Physical range of each field (inclusive; units as the names say). Values outside are no
#: sensor's and make the simulator's crossing kernel run without end: a threshold of 1e-300 with
#: no refractory period (1e300 crossings a pixel), a photoreceptor cut-off of 1e308 Hz (NaN
#: crossing times). Thresholds: 1e-4 log units is a 0.01 % contrast step, two orders below the
#: finest of any event sensor (about 1 %), 10 a factor of 22,000 per event. Rates: a pixel
#: cannot fire faster than once a µs (1 MHz). Photoreceptor bandwidth: at most 10 MHz (real ones
#: are kHz). Refractory period: at most 100 s. Radiance scales: 1e-9 .. 1e12 of the scene's units.
PARAM_RANGES = {
    "contrast_threshold_on": (1e-4, 10.0), "contrast_threshold_off": (1e-4, 10.0),
    "threshold_mismatch_sigma": (0.0, 10.0), "min_threshold": (1e-4, 10.0),
    "refractory_period_us": (0, 100_000_000), "shot_noise_rate_hz": (0.0, 1e6), "leak_rate_hz": (0.0, 1e6),
    "photoreceptor_cutoff_hz": (0.0, 1e7), "photoreceptor_white_radiance": (1e-9, 1e12), "log_eps": (1e-12, 1.0),
}


def check_param_range(name: str, v, where: str, error=ValueError) -> None:
    """``v`` inside :data:`PARAM_RANGES` for ``name`` (None passes: the caller checks it)."""
    if v is None or name not in PARAM_RANGES:
        return
    lo, hi = PARAM_RANGES[name]
    if not lo <= float(v) <= hi:
        raise error(f"{where}: {name} = {v!r} is outside the physical range [{lo:g}, {hi:g}] of an event sensor")


#: Largest profile file read (a profile is a few kB).
MAX_PROFILE_BYTES = 1 << 20


class SensorProfileError(ValueError):
    """A sensor profile that does not follow the schema (says what was expected and found)."""


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check_param(name, v, where):
    kind = SIMULATOR_FIELDS[name]
    if v is None and kind == "nonneg_or_null":
        return
    if kind == "int":
        if not (isinstance(v, int) and not isinstance(v, bool)) or v < 0:
            raise SensorProfileError(f"{where}: simulator_params.{name} must be an integer >= 0 (µs), found {v!r}")
        check_param_range(name, v, f"{where}: simulator_params", SensorProfileError)
        return
    if not _is_num(v) or not math.isfinite(v) or (v <= 0 if kind == "pos" else v < 0):
        rel = "> 0" if kind == "pos" else ">= 0"
        raise SensorProfileError(f"{where}: simulator_params.{name} must be a finite number {rel}, found {v!r}")
    if not (kind == "nonneg_or_null" and v == 0):
        check_param_range(name, v, f"{where}: simulator_params", SensorProfileError)


def _check_estimate(name, e, where):
    if not isinstance(e, dict):
        raise SensorProfileError(f"{where}: estimates.{name} must be an object, found {type(e).__name__}")
    if not isinstance(e.get("identifiable"), bool):
        raise SensorProfileError(f"{where}: estimates.{name}.identifiable must be true or false, "
                                 f"found {e.get('identifiable')!r}")
    for k in ("value", "std"):
        v = e.get(k)
        if v is not None and (not _is_num(v) or not math.isfinite(v)):
            raise SensorProfileError(f"{where}: estimates.{name}.{k} must be a finite number or null, found {v!r}")
    ci = e.get("ci95")
    if ci is not None and (not isinstance(ci, list) or len(ci) != 2 or not all(_is_num(c) for c in ci)
                           or not ci[0] <= ci[1]):
        raise SensorProfileError(f"{where}: estimates.{name}.ci95 must be [lo, hi] with lo <= hi or null, "
                                 f"found {ci!r}")


@dataclass
class SensorProfile:
    """An event-sensor profile (module docstring has the schema).

    Attributes
    ----------
    simulator_params : dict
        Identified ``EventSensorParams`` fields and their values.
    estimates : dict
        Every parameter looked for: value, std, ci95, identifiable, reason, method, unit.
    name, sensor, provenance : str, dict, dict
    """

    simulator_params: dict
    estimates: dict = field(default_factory=dict)
    name: str = ""
    sensor: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)

    def __post_init__(self):
        self.validate()

    def validate(self, where: str = "sensor profile") -> "SensorProfile":
        if not isinstance(self.simulator_params, dict):
            raise SensorProfileError(f"{where}: simulator_params must be an object, found "
                                     f"{type(self.simulator_params).__name__}")
        unknown = sorted(set(self.simulator_params) - set(SIMULATOR_FIELDS))
        if unknown:
            raise SensorProfileError(f"{where}: unknown simulator_params {unknown}; expected some of "
                                     f"{sorted(SIMULATOR_FIELDS)}")
        for k, v in self.simulator_params.items():
            _check_param(k, v, where)
        if not isinstance(self.estimates, dict):
            raise SensorProfileError(f"{where}: estimates must be an object, found {type(self.estimates).__name__}")
        for k, e in self.estimates.items():
            _check_estimate(k, e, where)
        for k in ("sensor", "provenance"):
            if not isinstance(getattr(self, k), dict):
                raise SensorProfileError(f"{where}: {k} must be an object, found {type(getattr(self, k)).__name__}")
        if not isinstance(self.name, str):
            raise SensorProfileError(f"{where}: name must be a string, found {self.name!r}")
        return self

    def to_dict(self) -> dict:
        return {"format": SENSOR_PROFILE_FORMAT, "version": SENSOR_PROFILE_VERSION, "name": self.name,
                "sensor": self.sensor, "simulator_params": self.simulator_params, "estimates": self.estimates,
                "provenance": self.provenance}

    @classmethod
    def from_dict(cls, d, where: str = "sensor profile") -> "SensorProfile":
        if not isinstance(d, dict):
            raise SensorProfileError(f"{where}: expected a JSON object, found {type(d).__name__}")
        if d.get("format") != SENSOR_PROFILE_FORMAT:
            raise SensorProfileError(f"{where}: expected format {SENSOR_PROFILE_FORMAT!r}, found {d.get('format')!r}")
        if d.get("version") != SENSOR_PROFILE_VERSION:
            raise SensorProfileError(f"{where}: expected version {SENSOR_PROFILE_VERSION}, found {d.get('version')!r}")
        if "simulator_params" not in d:
            raise SensorProfileError(f"{where}: missing 'simulator_params'")
        extra = sorted(set(d) - {"format", "version", "name", "sensor", "simulator_params", "estimates",
                                 "provenance"})
        if extra:
            raise SensorProfileError(f"{where}: unknown top-level key(s) {extra}")
        p = cls.__new__(cls)
        p.simulator_params = d["simulator_params"]
        p.estimates = d.get("estimates", {})
        p.name = d.get("name", "")
        p.sensor = d.get("sensor", {})
        p.provenance = d.get("provenance", {})
        return p.validate(where)

    def save(self, path) -> Path:
        """Write the profile as JSON, atomically (``NAME.partial`` renamed when complete)."""
        self.validate()
        return write_json_atomic(Path(path), self.to_dict(), indent=1)


def load_sensor_profile(path) -> SensorProfile:
    """Read and check a sensor profile JSON file (:class:`SensorProfileError` when it is not one).

    Read as every small input is (:func:`hybridhdr._util.limits.read_json_bounded`): a regular
    file (never a FIFO or a device), at most :data:`MAX_PROFILE_BYTES`, nesting bounded."""
    from .._util.limits import read_json_bounded
    from ..errors import FormatError
    path = Path(path)
    try:
        d = read_json_bounded(path, "sensor profile", limit=MAX_PROFILE_BYTES, parse_constant=lambda c: float(c))
    except FormatError as e:
        raise SensorProfileError(str(e)) from None
    except OSError as e:
        raise SensorProfileError(f"sensor profile {path}: cannot read it ({e.strerror or e})") from None
    return SensorProfile.from_dict(d, where=f"sensor profile {path}")
