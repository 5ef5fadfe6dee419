"""Stability sweeps: stress axes mapped onto dataset-generator parameters.

Each :class:`StressAxis` names one stress, the parameter it drives, where that parameter lives
(``"dataset"``: a key of the dataset spec; ``"method"``: a method setting such as
``threshold_factor`` = the method's contrast threshold / the sensor's), its values in order of
increasing stress, and how the stress grows with the value (``stress="increasing"`` or
``"decreasing"``: e.g. a lower exposure scale or frame rate is more stress).

For the ``procedural`` dataset kind the parameters are those of
:mod:`hybridhdr.evaluate.datasets`; for the simulator kinds (``ahdr``, ``builtin``) the same
axes map onto ``EventSensorParams`` / ``FrameCameraParams`` / motion keys
(:data:`SIMULATOR_KEYS`).

:func:`stability_bench` builds a bench dict (one dataset per axis, its grid = the axis values,
one stability chart per axis and metric: ``metric`` (log SSIM) and the perceptual ColorVideoVDP
JOD, the bench's default perceptual score), which :func:`hybridhdr.evaluate.bench.parse_bench`
accepts; the bundled ``benches/stability.toml`` is the same sweep written out.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

__all__ = ["StressAxis", "STRESS_AXES", "SIMULATOR_KEYS", "stability_bench", "DEFAULT_METHODS"]


@dataclass(frozen=True)
class StressAxis:
    """One stress axis of the stability sweep."""

    name: str
    parameter: str
    target: str  # "dataset" or "method"
    values: tuple
    stress: str  # "increasing" or "decreasing"
    description: str
    unit: str = ""


STRESS_AXES: dict[str, StressAxis] = {a.name: a for a in (
    StressAxis("noise_rate", "noise_rate_hz", "dataset", (0.0, 1.0, 3.0, 10.0, 30.0, 100.0), "increasing",
               "uniform shot-noise events per pixel", "Hz per pixel"),
    StressAxis("threshold_mismatch", "threshold_mismatch_sigma", "dataset", (0.0, 0.05, 0.1, 0.2, 0.35, 0.5),
               "increasing", "relative σ of per-pixel contrast thresholds", "relative"),
    StressAxis("refractory", "refractory_period_us", "dataset", (0, 300, 1000, 3000, 10000, 30000), "increasing",
               "refractory period: events lost after each event", "µs"),
    StressAxis("threshold_under", "threshold_factor", "method", (1.0, 0.8, 0.6, 0.45, 0.3), "decreasing",
               "method's contrast threshold below the sensor's (misestimate)", "× sensor c"),
    StressAxis("threshold_over", "threshold_factor", "method", (1.0, 1.25, 1.6, 2.2, 3.0), "increasing",
               "method's contrast threshold above the sensor's (misestimate)", "× sensor c"),
    StressAxis("under_exposure", "exposure_scale", "dataset", (1.0, 0.5, 0.25, 0.1, 0.05, 0.02), "decreasing",
               "frame camera gain × this (dark frames)", "× nominal"),
    StressAxis("over_exposure", "exposure_scale", "dataset", (1.0, 1.5, 2.0, 3.0, 4.0, 8.0), "increasing",
               "frame camera gain × this (saturated frames)", "× nominal"),
    StressAxis("motion_speed", "speed_px_per_s", "dataset", (50.0, 150.0, 400.0, 1000.0, 2500.0, 6000.0),
               "increasing", "speed of the bright disc", "px/s"),
    StressAxis("frame_rate", "frame_rate_hz", "dataset", (50.0, 25.0, 10.0, 5.0, 4.0), "decreasing",
               "frame rate of the frame camera", "Hz"),
)}

#: Simulator mapping of the dataset-side axes (the simulator's parameter names): key -> dotted path in an
#: ``ahdr``/``builtin`` dataset spec.
SIMULATOR_KEYS = {
    "noise_rate_hz": "sensor.shot_noise_rate_hz",
    "threshold_mismatch_sigma": "sensor.threshold_mismatch_sigma",
    "refractory_period_us": "sensor.refractory_period_us",
    "exposure_scale": "camera.exposure_scale",
    "speed_px_per_s": "motion.speed_px_per_s",
    "frame_rate_hz": "camera.frame_rate_hz",
}

DEFAULT_METHODS = (
    {"name": "akf", "method": "akf"},
    {"name": "cf", "method": "cf"},
    {"name": "highpass", "method": "highpass"},
    {"name": "direct", "method": "direct"},
    {"name": "edi", "method": "edi"},
    {"name": "frames_zoh", "method": "frames_zoh"},
)


def stability_bench(axes=None, *, methods=DEFAULT_METHODS, base: dict | None = None, metric: str = "log_ssim",
                    relative_bound: float = 0.8, seed: int = 0, quick: bool = False, name: str = "stability",
                    perceptual: str | None = "jod", perceptual_relative_bound: float = 0.8) -> dict:
    """A bench dict sweeping each stress axis on its own (all other parameters at ``base``).

    Parameters
    ----------
    axes : iterable of str, optional
        Names from :data:`STRESS_AXES` (default: all).
    methods : sequence of dict
        ``[[methods]]`` entries.
    base : dict, optional
        The unstressed dataset spec (default: a 64x48, 0.4 s procedural HDR scene with
        references at 50 Hz).
    metric, relative_bound : str, float
        Failure when ``metric`` is worse than ``relative_bound`` × the method's unstressed value
        (or NaN/Inf appears).
    quick : bool
        Three values per axis and a 40x32, 0.25 s scene (for tests).
    perceptual, perceptual_relative_bound : str or None, float
        A second panel per axis for this metric (default ``"jod"``, ColorVideoVDP, computed
        for every run unless ``[bench] jod = false``), after all ``metric`` panels; None: none.
    """
    names = list(STRESS_AXES) if axes is None else list(axes)
    unknown = sorted(set(names) - set(STRESS_AXES))
    if unknown:
        raise ValueError(f"unknown stress axis {unknown}; expected some of {sorted(STRESS_AXES)}")
    b = dict(base) if base is not None else {"kind": "procedural", "width": 64, "height": 48, "duration_us": 400_000,
                                               "hdr_rate_hz": 50.0, "disc_radius_px": 8.0}
    if quick and base is None:
        b.update(width=40, height=32, duration_us=250_000, disc_radius_px=6.0)
    datasets, charts = [], []
    for n in names:
        ax = STRESS_AXES[n]
        vals = list(ax.values[:3] if quick else ax.values)
        d = copy.deepcopy(b)
        d["name"] = n
        if n == "frame_rate" and not quick:
            d["duration_us"] = max(int(d.get("duration_us", 0)), 600_000)
        key = ax.parameter
        if ax.target == "dataset":
            key = ax.parameter if b.get("kind") == "procedural" else SIMULATOR_KEYS.get(ax.parameter, ax.parameter)
            d["grid"] = {key: vals}
        else:
            d["method_grid"] = {ax.parameter: vals}
        datasets.append(d)
        charts.append({"dataset": n, "axis": key, "metric": metric, "relative_bound": relative_bound,
                       "stress": ax.stress, "title": f"{n}: {ax.description}"})
    if perceptual and perceptual != metric:
        charts += [{**c, "metric": perceptual, "relative_bound": perceptual_relative_bound,
                    "title": f"{c['title']} ({perceptual.upper()})"} for c in list(charts)]
    return {"bench": {"name": name, "seed": seed, "tolerance_us": 1000, "strips": 4},
            "datasets": datasets, "methods": [dict(m) for m in methods],
            "charts": {"speed_accuracy": False, "stability": charts}}
