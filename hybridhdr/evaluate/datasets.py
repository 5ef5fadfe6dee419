"""Dataset providers for the benchmark: a spec dict (from the bench TOML) -> a hybrid recording
with HDR references.

``spec = {"kind": ..., **params}``; every kind is deterministic given ``seed``.

``procedural``
    :func:`hybridhdr.simulate.procedural.procedural_recording` (bright disc ``bright_ratio`` × brighter than a
    textured background, ideal events, 8-bit gamma frames, HDR references in frame-linear units:
    the scene intensity times the frames' gain, 1.0 = code 255) plus the sensor and
    camera stresses of the stability sweeps, applied here:

    - ``threshold_mismatch_sigma`` (relative σ of per-pixel thresholds, c_p = c·max(1 + σ·N(0,1), 0.25))
      and ``refractory_period_us``: the scene is first rendered to ideal events at c / ``fine_steps``,
      which :func:`requantise` turns into the sensor's events (per-pixel thresholds, refractory
      losses; timing error ≤ one fine step);
    - ``noise_rate_hz``: uniform shot-noise events, Poisson per pixel at that rate (Hz per
      pixel), random polarity;
    - ``exposure_scale``: the frames are re-rendered with the camera gain times this factor
      (< 1 under-exposed, > 1 over-exposed; 1 puts the background mean at 1/4 of full scale);
    - scene: ``bright_ratio``, ``speed_px_per_s``, ``disc_radius_px``; camera: ``frame_rate_hz``,
      ``exposure_us``; ``width``, ``height``, ``duration_us``, ``contrast_threshold``,
      ``hdr_rate_hz``.
``file``
    ``path`` to any recording :func:`hybridhdr.read` understands, which must hold HDR references,
    or ``holdout_frames`` (frame indices): real data without ground truth, where those frames are
    removed from the input and, linearised by the camera ``profile`` (built-in by default), become
    the references (a frame-prediction test); ``contrast_threshold`` (log units) states the
    sensor's threshold for the methods.
``sim_procedural`` / ``builtin`` / ``ahdr``
    The simulator (:mod:`hybridhdr.simulate`): the procedural scene through the simulator's
    sensor, camera and adaptive sampling; a built-in Mitsuba scene; an AHDR-style recording from
    an image. Keys in :mod:`hybridhdr.simulate.datasets`.

HDR references of the simulated kinds are in the reconstruction's frame-linear units (1.0 = the
frame camera's clip level at the frame's exposure, :mod:`hybridhdr.simulate.units`); a ``file``
dataset's references are whatever the file holds (``holdout_frames``: the camera profile's
frame-linear units).

Simulated datasets can be slow to build (Mitsuba renders): with ``cache_dir`` (bench key
``cache_dir``) each is written once as a hybridhdr container named by a hash of its spec and
seed, and read back afterwards.
"""

from __future__ import annotations

import dataclasses

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._util.atomic import write_text_atomic
from ..camera.profile import load_profile, profile_for_frames
from ..events import EVENT_DTYPE, SensorSize
from ..formats import read
from ..formats.container import read_recording, write_recording
from ..model import Frames, HDRReferences, Recording
from ..simulate.datasets import profile_from_provenance, simulated_dataset
from ..simulate.procedural import ProceduralScene, procedural_recording

__all__ = ["DATASET_KINDS", "Dataset", "load_dataset", "event_log_change", "requantise", "add_noise_events",
           "PROCEDURAL_KEYS"]

DATASET_KINDS = ("procedural", "file", "sim_procedural", "ahdr", "builtin")

PROCEDURAL_KEYS = {
    "width": 64, "height": 48, "duration_us": 300_000, "contrast_threshold": 0.2, "frame_rate_hz": 20.0,
    "exposure_us": 5_000, "step_us": 250, "bright_ratio": 1.0e3, "speed_px_per_s": 150.0, "disc_radius_px": 8.0,
    "hdr_rate_hz": None, "noise_rate_hz": 0.0, "threshold_mismatch_sigma": 0.0, "refractory_period_us": 0,
    "exposure_scale": 1.0, "fine_steps": 4,
}


@dataclass(frozen=True, eq=False)
class Dataset:
    """A loaded benchmark dataset.

    Attributes
    ----------
    recording : Recording
        Events, frames and HDR references (``recording.hdr``, linear).
    contrast_threshold : float or None
        The sensor's nominal threshold (log units) for methods told to use it.
    duration_us : int
        Length of the data in µs (for "time per second of data").
    description : dict
        The resolved spec and generator statistics.
    profile : CameraProfile or None
        Camera profile the methods should read the frames with (None: the built-in profile for
        the frames' encoding); set for simulated cameras with clipped codes (AHDR).
    """

    recording: Recording
    contrast_threshold: float | None
    duration_us: int
    description: dict = field(default_factory=dict)
    profile: object = None


def _check_keys(spec: dict, allowed, kind):
    unknown = sorted(set(spec) - set(allowed) - {"kind", "name"})
    if unknown:
        raise ValueError(f"unknown {kind!r} dataset key(s) {unknown}; expected some of {sorted(allowed)}")


def requantise(events: np.ndarray, sensor_size, c_fine: float, c_on_map, c_off_map,
               refractory_period_us: int = 0) -> np.ndarray:
    """Turn ideal events at threshold ``c_fine`` into a sensor's events (see ``_kernels``).

    Parameters
    ----------
    events : ndarray (N,), EVENT_DTYPE
        Ideal events, each a log step of ``p·c_fine`` (log units), sorted by ``t`` (µs).
    sensor_size : SensorSize or (height, width)
    c_on_map, c_off_map : ndarray (H, W), float
        Per-pixel ON / OFF thresholds (log units), each >= ``c_fine``.
    refractory_period_us : int
        Refractory period in µs (0: none).
    """
    from ._kernels import requantise_events
    ss = SensorSize.from_any(sensor_size)
    h, w = ss.shape
    if events.dtype != EVENT_DTYPE:
        raise TypeError(f"events must have dtype EVENT_DTYPE, got {events.dtype}")
    c_on = np.ascontiguousarray(c_on_map, dtype=np.float64).ravel()
    c_off = np.ascontiguousarray(c_off_map, dtype=np.float64).ravel()
    for name, c in (("c_on_map", c_on), ("c_off_map", c_off)):
        if c.shape != (h * w,):
            raise ValueError(f"{name} must have shape {(h, w)}, got {np.shape(c_on_map)}")
        if not np.all(c >= c_fine * (1 - 1e-12)):
            raise ValueError(f"{name} must be >= c_fine = {c_fine} everywhere, found min {c.min()}")
    if refractory_period_us < 0:
        raise ValueError(f"refractory_period_us must be >= 0, got {refractory_period_us}")
    t = np.ascontiguousarray(events["t"])
    x = np.ascontiguousarray(events["x"])
    y = np.ascontiguousarray(events["y"])
    p = np.ascontiguousarray(events["p"])
    cap = int(t.size * math.ceil(c_fine / min(c_on.min(), c_off.min()) + 1)) + 1
    ot, ox, oy, op = (np.empty(cap, np.int64), np.empty(cap, np.uint16), np.empty(cap, np.uint16),
                      np.empty(cap, np.int8))
    n, overflow = requantise_events(t, x, y, p, w, float(c_fine), c_on, c_off, int(refractory_period_us),
                                    ot, ox, oy, op)
    if overflow:  # cannot happen with the bound above; kept as a guard
        raise RuntimeError(f"requantise: output capacity {cap} exceeded")
    out = np.empty(n, EVENT_DTYPE)
    out["t"], out["x"], out["y"], out["p"] = ot[:n], ox[:n], oy[:n], op[:n]
    return out


def add_noise_events(events: np.ndarray, sensor_size, rate_hz: float, t0_us: int, t1_us: int,
                     rng: np.random.Generator) -> np.ndarray:
    """Merge uniform shot-noise events: Poisson(``rate_hz``·duration) per pixel over ``[t0, t1)`` µs."""
    if rate_hz < 0:
        raise ValueError(f"noise_rate_hz must be >= 0 (Hz per pixel), got {rate_hz}")
    if rate_hz == 0 or t1_us <= t0_us:
        return events
    h, w = SensorSize.from_any(sensor_size).shape
    counts = rng.poisson(rate_hz * (t1_us - t0_us) * 1e-6, size=h * w)
    n = int(counts.sum())
    pix = np.repeat(np.arange(h * w), counts)
    noise = np.empty(n, EVENT_DTYPE)
    noise["t"] = rng.integers(t0_us, t1_us, size=n)
    noise["x"] = pix % w
    noise["y"] = pix // w
    noise["p"] = np.where(rng.random(n) < 0.5, 1, -1)
    allev = np.concatenate([events, noise])
    return allev[np.argsort(allev["t"], kind="stable")]


def _procedural(spec: dict, seed: int) -> Dataset:
    _check_keys(spec, PROCEDURAL_KEYS, "procedural")
    s = dict(PROCEDURAL_KEYS)
    s.update({k: v for k, v in spec.items() if k not in ("kind", "name")})
    ss = SensorSize(int(s["height"]), int(s["width"]))
    c = float(s["contrast_threshold"])
    sigma, refr = float(s["threshold_mismatch_sigma"]), int(s["refractory_period_us"])
    fine = int(s["fine_steps"])
    if sigma < 0 or fine < 1:
        raise ValueError(f"threshold_mismatch_sigma must be >= 0 and fine_steps >= 1, got {sigma}, {fine}")
    if not float(s["exposure_scale"]) > 0:
        raise ValueError(f"exposure_scale must be > 0, got {s['exposure_scale']}")
    scene = ProceduralScene(ss, bright_ratio=float(s["bright_ratio"]), disc_radius_px=float(s["disc_radius_px"]),
                            speed_px_per_s=float(s["speed_px_per_s"]))
    rng = np.random.default_rng([int(seed), 7])
    sensor = sigma > 0 or refr > 0
    c_gen = c / fine if sensor else c
    rec, scene = procedural_recording(ss, int(s["duration_us"]), contrast_threshold=c_gen,
                                      frame_rate_hz=float(s["frame_rate_hz"]), exposure_us=int(s["exposure_us"]),
                                      step_us=int(s["step_us"]), seed=seed, scene=scene,
                                      hdr_rate_hz=s["hdr_rate_hz"])
    ev = rec.events
    stats = {"ideal_events": int(len(ev))}
    if sensor:
        lo = max(0.25, 1.0 / fine)  # thresholds stay >= c_fine
        c_on = c * np.maximum(1 + sigma * rng.standard_normal(ss.shape), lo)
        c_off = c * np.maximum(1 + sigma * rng.standard_normal(ss.shape), lo)
        ev = requantise(ev, ss, c_gen, c_on, c_off, refr)
        stats["sensor_events"] = int(len(ev))
    ev = add_noise_events(ev, ss, float(s["noise_rate_hz"]), 0, int(s["duration_us"]), rng)
    frames = rec.frames
    k = float(s["exposure_scale"])
    if k != 1.0:
        gain = rec.metadata.provenance["frame_gain"] * k
        imgs = np.empty_like(frames.images)
        for i, (a, b) in enumerate(zip(frames.t_start_us, frames.t_end_us)):
            lin = np.mean([scene.intensity(t) for t in np.linspace(a, b, 6)], axis=0) * gain
            imgs[i] = np.round(255.0 * np.clip(lin, 0, 1) ** (1 / 2.2)).astype(np.uint8)
        frames = Frames(imgs, frames.t_start_us, frames.t_end_us, encoding="gamma")
    stats["events"] = int(len(ev))
    stats["saturated_fraction"] = float(np.mean(frames.images == 255))
    stats["black_fraction"] = float(np.mean(frames.images == 0))
    # references in frame-linear units: the frames encode clip(I·gain, 0, 1) (1.0 = code 255)
    unit = float(rec.metadata.provenance["frame_gain"]) * k
    hdr = HDRReferences(rec.hdr.images * np.float32(unit), rec.hdr.t_us)
    stats.update(gt_units="frame_linear", gt_scale=unit)
    rec2 = Recording(ev, ss, frames, rec.triggers, hdr, rec.metadata)
    return Dataset(rec2, c, int(s["duration_us"]), {"kind": "procedural", "seed": seed, **s, **stats})


def _file(spec: dict, seed: int) -> Dataset:
    _check_keys(spec, {"path", "format", "contrast_threshold", "holdout_frames", "profile"}, "file")
    if "path" not in spec:
        raise ValueError("a 'file' dataset needs 'path'")
    rec = read(spec["path"], spec.get("format"))
    hold = spec.get("holdout_frames")
    if hold is not None:
        # real data without HDR ground truth: frames left out of the input become the references,
        # linearised by the camera profile (eq. 3's CRF⁻¹; the built-in profile by default)
        fr = rec.frames
        if fr is None or len(fr) == 0:
            raise ValueError(f"{spec['path']}: holdout_frames needs frames, but the recording has none")
        idx = np.unique(np.asarray(hold, dtype=np.int64))
        if idx.size == 0 or idx.min() < 0 or idx.max() >= len(fr):
            raise ValueError(f"holdout_frames must be indices in [0, {len(fr) - 1}], got {list(hold)}")
        keep = np.setdiff1d(np.arange(len(fr)), idx)
        if keep.size == 0:
            raise ValueError("holdout_frames leaves no input frame")
        prof = profile_for_frames(load_profile(spec.get("profile")), fr)
        ref = prof.intensity(np.asarray(fr.images[idx]))
        sub = fr.select(keep)
        # in the units the methods read the input in (its median exposure: Frames.exposure_scale)
        f = np.array([fr.units_factor(k, sub.reference_exposure()) for k in idx])
        if np.any(f != 1.0):
            ref = ref / f.reshape((-1,) + (1,) * (ref.ndim - 1))
        ref = ref.astype(np.float32)
        rec = dataclasses.replace(rec, frames=sub, hdr=HDRReferences(ref, fr.t_mid_us[idx]))
    if rec.hdr is None or len(rec.hdr) == 0:
        raise ValueError(f"{spec['path']}: a benchmark dataset needs HDR references (or holdout_frames), "
                         f"but the recording has none")
    t = [int(rec.hdr.t_us.min()), int(rec.hdr.t_us.max())]
    if len(rec.events):
        t += [int(rec.events["t"][0]), int(rec.events["t"][-1])]
    dur = max(t) - min(t)
    c = spec.get("contrast_threshold")
    return Dataset(rec, None if c is None else float(c), max(dur, 1),
                   {"kind": "file", "path": str(spec["path"]), "events": int(len(rec.events)),
                    "holdout_frames": None if hold is None else [int(i) for i in np.atleast_1d(hold)]})


def _simulated(spec: dict, seed: int) -> Dataset:
    d = simulated_dataset(spec, seed)
    return Dataset(d.recording, d.contrast_threshold, d.duration_us, d.description, d.profile)


def _cached(spec: dict, seed: int, cache_dir) -> Dataset:
    # "gt_units": references in frame-linear units (older caches held radiance: a new key)
    key = json.dumps({"spec": {k: v for k, v in spec.items() if k != "name"}, "seed": seed,
                      "gt_units": "frame_linear"}, sort_keys=True, default=str)
    digest = hashlib.sha1(key.encode()).hexdigest()[:16]
    d = Path(cache_dir)
    d.mkdir(parents=True, exist_ok=True)
    path = d / f"{spec['kind']}_{digest}.h5"
    meta = path.with_suffix(".json")
    if path.is_file() and meta.is_file():
        info = json.loads(meta.read_text())
        rec = read_recording(path)
        return Dataset(rec, info["contrast_threshold"], info["duration_us"], info["description"],
                       profile_from_provenance(rec.metadata.provenance))
    data = _simulated(spec, seed)
    write_recording(data.recording, path)  # atomic (.partial + rename)
    write_text_atomic(meta, json.dumps({"contrast_threshold": data.contrast_threshold,
                                        "duration_us": data.duration_us, "description": data.description},
                                       default=str))
    return data


def load_dataset(spec: dict, *, seed: int = 0, cache_dir=None) -> Dataset:
    """Build the dataset described by ``spec`` (see the module docstring); same seed → same bits.

    ``cache_dir`` caches simulated kinds on disk (procedural and file kinds are cheap and never
    cached).
    """
    if not isinstance(spec, dict):
        raise TypeError(f"a dataset spec must be a dict, got {type(spec).__name__}")
    kind = spec.get("kind")
    if kind not in DATASET_KINDS:
        raise ValueError(f"dataset kind must be one of {DATASET_KINDS}, got {kind!r}")
    if kind == "procedural":
        return _procedural(spec, seed)
    if kind == "file":
        return _file(spec, seed)
    if cache_dir is not None:
        return _cached(spec, seed, cache_dir)
    return _simulated(spec, seed)


def event_log_change(recording, contrast_threshold, min_rise: float = 2.0) -> dict | None:
    """How much of a large brightening the events report (a diagnostic of a dataset, not of a
    method): on the pixels whose reference rises by more than ``min_rise`` ln units between the
    first reference at or after the first event and the last one (references floored at 1e-6),
    the mean true ln change and the mean net change the events carry (ON minus OFF events times
    ``contrast_threshold``). A refractory period that re-references the pixel loses the rest; no
    method can recover it where every frame clips. None without events, threshold or such pixels."""
    rec, c = recording, contrast_threshold
    ev = rec.events
    if not len(ev) or c is None or rec.hdr is None or not len(rec.hdr):
        return None
    h, w = rec.sensor_size.shape
    ref = rec.hdr.images if rec.hdr.images.ndim == 3 else rec.hdr.images.mean(axis=3)
    k0 = int(np.searchsorted(rec.hdr.t_us, int(ev["t"][0])))
    lr = np.log(np.maximum(ref[[min(k0, len(ref) - 1), -1]].astype(np.float64), 1e-6))
    rise = (lr[1] - lr[0]).ravel()
    net = np.bincount(ev["y"].astype(np.int64) * w + ev["x"], weights=np.where(ev["p"] > 0, 1.0, -1.0),
                      minlength=h * w)
    big = rise > float(min_rise)
    if not big.any():
        return None
    return {"pixels": int(big.sum()), "true_ln_rise": float(rise[big].mean()),
            "events_ln_rise": float(c * net[big].mean()),
            "fraction_reported": float(c * net[big].mean() / rise[big].mean())}
