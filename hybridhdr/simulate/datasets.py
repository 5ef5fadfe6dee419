"""Simulated datasets from a benchmark's dataset table: a :class:`SimulatedData` (a Recording with
its nominal threshold, description and camera profile) for :mod:`hybridhdr.evaluate.datasets`.

Kinds (keys besides ``kind``/``name``):

``sim_procedural``
    The analytic :class:`hybridhdr.simulate.procedural.ProceduralScene` (bright disc over a textured
    background) rendered through the simulator pipeline (no Mitsuba: cheap), so the sensor
    models, the frame camera and the **adaptive time sampling** apply. Scene keys:
    ``bright_ratio``, ``speed_px_per_s`` (or ``motion.speed_px_per_s``), ``disc_radius_px``.
``builtin``
    A built-in Mitsuba scene: ``scene`` (one of ``hybridhdr.simulate.builtin.BUILTIN_SCENES``),
    ``spp``.
``ahdr``
    :func:`hybridhdr.simulate.ahdr.build_ahdr` on ``image`` (a path, or ``"procedural:RATIO"``:
    a still of the procedural scene at twice the sensor size) with ``motion`` (a table).

Common keys: ``width``, ``height``, ``duration_us``, ``hdr_rate_hz`` (extra ground truth at
that rate besides the frames' mid-exposures), ``sensor`` (preset name "ideal"/"clean"/"noisy"
or a table of ``EventSensorParams`` fields), ``camera`` (table of ``FrameCameraParams``; default
20 Hz, 5 ms, 8-bit gamma), ``sampling`` (table of ``SamplingParams``, e.g. ``mode = "fixed"``,
``fixed_rate_hz``), ``exposure_scale`` (multiplies the camera's electrons per radiance·s),
``contrast_threshold`` (sets the sensor's ON and OFF thresholds), and dotted overrides
``sensor.X``, ``camera.X``, ``sampling.X`` (as the stability sweeps produce).

The HDR references of every kind are returned in the reconstruction's **frame-linear units**
(1.0 = the frame camera's clip level at the frame's exposure; :mod:`hybridhdr.simulate.units`),
each converted with the exposure of its nearest frame.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..camera import CameraProfile, profile_from_inverse_crf
from ..events import SensorSize
from ..model import HDRReferences, Recording
from . import builtin
from .ahdr import MotionParams, build_ahdr
from .camera import FrameCameraParams, crf_inverse_table
from .source import AnalyticSceneSource
from .pipeline import simulate
from .procedural import ProceduralScene
from .render import MitsubaSource
from .sampling import SamplingParams
from .sensor import EventSensorParams, sensor_preset
from .units import reference_to_frame_units

__all__ = ["SimulatedData", "simulated_dataset", "camera_profile", "profile_from_provenance", "to_frame_units",
           "ProceduralSource"]

_COMMON = {"width", "height", "duration_us", "hdr_rate_hz", "sensor", "camera", "sampling", "exposure_scale",
           "contrast_threshold", "seed_offset"}
_KIND_KEYS = {"sim_procedural": {"bright_ratio", "speed_px_per_s", "disc_radius_px"},
              "builtin": {"scene", "spp"}, "ahdr": {"image", "motion"}}


@dataclass
class SimulatedData:
    """A simulated dataset: the recording (HDR references in frame-linear units), the sensor's
    nominal contrast threshold (log units, None if unknown), its length in µs, a description (the
    resolved spec and the simulator's statistics) and the camera profile of its frames (None: the
    built-in profile of the frames' encoding)."""

    recording: Recording
    contrast_threshold: float | None
    duration_us: int
    description: dict
    profile: CameraProfile | None = None


class ProceduralSource(AnalyticSceneSource):
    """:class:`hybridhdr.simulate.procedural.ProceduralScene` as a ``RadianceSource`` (simulate/source.py)."""

    def max_image_speed_px_per_s(self, t0_us: int, t1_us: int) -> float:
        # the disc moves at speed_px_per_s; the background grating drifts by at most
        # 0.7 rad/s · 23 px / 2π ≈ 2.6 px/s
        return float(self.scene.speed_px_per_s) + 2.6

    def describe(self) -> dict:
        s = self.scene
        return {"source": "hybridhdr.simulate.procedural.ProceduralScene", "bright_ratio": s.bright_ratio,
                "speed_px_per_s": s.speed_px_per_s, "disc_radius_px": s.disc_radius_px,
                "background": s.background}


def _split(spec: dict) -> tuple[dict, dict]:
    """Flat keys and dotted overrides (``sensor.X`` ...) -> (flat, {"sensor": {...}, ...})."""
    flat, dotted = {}, {"sensor": {}, "camera": {}, "sampling": {}, "motion": {}}
    for k, v in spec.items():
        if "." in k:
            head, tail = k.split(".", 1)
            if head not in dotted:
                raise ValueError(f"dataset key {k!r}: the prefix must be sensor., camera., sampling. or motion.")
            dotted[head][tail] = v
        else:
            flat[k] = v
    return flat, dotted


def _params(cls, base, over: dict, what: str):
    names = {f.name for f in dataclasses.fields(cls)}
    bad = sorted(set(over) - names)
    if bad:
        raise ValueError(f"unknown {what} parameter(s) {bad}; expected some of {sorted(names)}")
    over = {k: tuple(v) if isinstance(v, list) else v for k, v in over.items()}
    return dataclasses.replace(base, **over) if over else base


def camera_profile(camera):
    """A reconstruction :class:`CameraProfile` for a simulated camera whose codes are clipped.

    The inverse CRF is the simulator's own table (:func:`hybridhdr.simulate.camera.crf_inverse_table`,
    flat beyond the clip); the weighting is eqs. 4-5 of that table
    (:func:`hybridhdr.camera.profile.weighting_from_inverse_crf`) with the clip codes
    themselves set to 0 (a clipped code only bounds the intensity). ``None`` when the camera does
    not clip (the built-in profile of the frames' encoding then applies).
    """
    if camera is None or getattr(camera, "code_clip", None) is None:
        return None
    lo, hi = camera.code_clip
    return profile_from_inverse_crf(crf_inverse_table(camera), clip_codes=(lo, hi),
                                    name=f"simulated {camera.crf} camera, codes clipped to [{lo}, {hi}]",
                                    source="hybridhdr.simulate.datasets")


def profile_from_provenance(prov):
    """:func:`camera_profile` of the camera recorded in a simulated recording's provenance."""
    cam = prov.get("camera") if isinstance(prov, dict) else None
    if not isinstance(cam, dict) or cam.get("code_clip") is None:
        return None
    names = {f.name for f in dataclasses.fields(FrameCameraParams)}
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in cam.items() if k in names}
    try:
        return camera_profile(FrameCameraParams(**kw))
    except (TypeError, ValueError):
        return None


def to_frame_units(rec, camera=None):
    """``rec`` with its HDR references converted from radiance to frame-linear units
    (:func:`hybridhdr.simulate.units.reference_to_frame_units`; the camera from the provenance
    when not given). Returns ``(recording, info)``; unchanged (info None) without references."""
    if rec.hdr is None or len(rec.hdr) == 0 or rec.frames is None or len(rec.frames) == 0:
        return rec, None
    cam = camera if camera is not None else rec.metadata.provenance
    im, info = reference_to_frame_units(rec.hdr.images, rec.hdr.t_us, cam, rec.frames)
    return dataclasses.replace(rec, hdr=HDRReferences(im, rec.hdr.t_us)), info


def _units_desc(info) -> dict:
    if info is None:
        return {}
    sc = info["scale"]
    return {"gt_units": "frame_linear", "gt_scale_min": float(min(sc)), "gt_scale_max": float(max(sc)),
            "gt_exposure_varies": info["exposure_varies"], "gt_v_clip": info["v_clip"]}


def _provenance_threshold(prov) -> float | None:
    """The sensor's nominal threshold from a recording's provenance (any nesting), if stated."""
    if isinstance(prov, dict):
        on, off = prov.get("contrast_threshold_on"), prov.get("contrast_threshold_off")
        if isinstance(on, (int, float)) and isinstance(off, (int, float)):
            return 0.5 * (float(on) + float(off))
        if isinstance(prov.get("contrast_threshold"), (int, float)):
            return float(prov["contrast_threshold"])
        for v in prov.values():
            c = _provenance_threshold(v)
            if c is not None:
                return c
    return None


def simulated_dataset(spec: dict, seed: int) -> SimulatedData:
    """The dataset a ``sim_procedural``, ``builtin`` or ``ahdr`` table describes (keys: the module
    docstring), simulated with ``seed``."""
    kind = spec["kind"]
    if kind not in _KIND_KEYS:
        raise ValueError(f"unknown simulated dataset kind {kind!r}")
    flat, dotted = _split({k: v for k, v in spec.items() if k not in ("kind", "name")})
    bad = sorted(set(flat) - _COMMON - _KIND_KEYS[kind])
    if bad:
        raise ValueError(f"unknown {kind!r} dataset key(s) {bad}; expected some of "
                         f"{sorted(_COMMON | _KIND_KEYS[kind])} or sensor.X / camera.X / sampling.X")
    w, h = int(flat.get("width", 64)), int(flat.get("height", 48))
    dur = int(flat.get("duration_us", 300_000))
    sens = flat.get("sensor", "clean")
    sensor = sensor_preset(sens) if isinstance(sens, str) else _params(EventSensorParams, EventSensorParams(),
                                                                          dict(sens), "sensor")
    s_over = dict(dotted["sensor"])
    if "contrast_threshold" in flat:
        c = float(flat["contrast_threshold"])
        s_over.setdefault("contrast_threshold_on", c)
        s_over.setdefault("contrast_threshold_off", c)
    sensor = _params(EventSensorParams, sensor, s_over, "sensor")
    k = dotted["camera"].pop("exposure_scale", None)
    k = float(flat.get("exposure_scale", 1.0 if k is None else k))
    if not k > 0:
        raise ValueError(f"exposure_scale must be > 0, got {k}")
    cam_base = FrameCameraParams(frame_rate_hz=20.0, exposure_us=5_000, crf="gamma")
    camera = _params(FrameCameraParams, cam_base, {**dict(flat.get("camera", {})), **dotted["camera"]}, "camera")
    if k != 1.0:
        camera = dataclasses.replace(camera, electrons_per_radiance_s=camera.electrons_per_radiance_s * k)
    sampling = _params(SamplingParams, SamplingParams(), {**dict(flat.get("sampling", {})), **dotted["sampling"]},
                       "sampling")
    gt = None
    if flat.get("hdr_rate_hz"):
        gt = np.unique(np.round(np.arange(0, dur + 1, 1e6 / float(flat["hdr_rate_hz"]))).astype(np.int64))
    if kind == "sim_procedural":
        speed = dotted["motion"].get("speed_px_per_s", flat.get("speed_px_per_s", 150.0))
        scene = ProceduralScene(SensorSize(h, w), bright_ratio=float(flat.get("bright_ratio", 1e3)),
                                disc_radius_px=float(flat.get("disc_radius_px", 8.0)), speed_px_per_s=float(speed))
        source = ProceduralSource(scene, dur)
    elif kind == "builtin":
        if "scene" not in flat:
            raise ValueError("a 'builtin' dataset needs 'scene' (a built-in scene name)")
        sc = builtin.builtin_scene(str(flat["scene"]), width=w, height=h, duration_s=dur / 1e6,
                           spp=flat.get("spp"))
        source = MitsubaSource(sc)
    else:
        if "image" not in flat:
            raise ValueError("an 'ahdr' dataset needs 'image' (an image path or 'procedural:RATIO')")
        image = flat["image"]
        if isinstance(image, str) and image.startswith("procedural"):
            # a still of the procedural scene, twice the sensor size, disc RATIO x the background
            ratio = float(image.split(":", 1)[1]) if ":" in image else 10.0
            image = ProceduralScene(SensorSize(2 * h, 2 * w), bright_ratio=ratio,
                                    disc_radius_px=float(min(h, w)) / 3).intensity(0).astype(np.float32)
        mot = flat.get("motion")
        mot = MotionParams(**{**dict(mot), **dotted["motion"]}) if (mot or dotted["motion"]) else None
        akw = {}
        if flat.get("sampling") or dotted["sampling"]:
            akw["sampling"] = sampling
        if isinstance(sens, dict) or s_over:
            akw["sensor"] = sensor
        if "frame_rate_hz" in dotted["camera"]:
            akw["frame_rate_hz"] = float(dotted["camera"]["frame_rate_hz"])
        rec = build_ahdr(image, sensor_size=SensorSize(h, w), duration_us=dur, motion=mot, gt_times_us=gt,
                         seed=int(seed) + int(flat.get("seed_offset", 0)), **akw)
        c = flat.get("contrast_threshold")
        if c is None:
            c = _provenance_threshold(rec.metadata.provenance)
        rec, uinfo = to_frame_units(rec)
        return SimulatedData(rec, None if c is None else float(c), dur,
                       {"kind": kind, "seed": seed, **{k2: v for k2, v in spec.items() if k2 != "kind"},
                        "events": int(len(rec.events)), **_units_desc(uinfo)},
                       profile_from_provenance(rec.metadata.provenance))
    res = simulate(source, sensor=sensor, camera=camera, sampling=sampling, gt_times_us=gt,
                   seed=int(seed) + int(flat.get("seed_offset", 0)), progress=False)
    rec, uinfo = to_frame_units(res.recording, camera)
    c_nominal = 0.5 * (sensor.contrast_threshold_on + sensor.contrast_threshold_off)
    frames = rec.frames
    desc = {"kind": kind, "seed": seed, **{k2: v for k2, v in spec.items() if k2 != "kind"},
            "events": int(len(rec.events)), "renders": int(res.renders),
            "simulate_wall_s": float(res.stats.get("wall_s", float("nan"))), **_units_desc(uinfo)}
    if frames is not None and len(frames):
        top = np.iinfo(frames.images.dtype).max if frames.images.dtype.kind == "u" else 1.0
        desc["saturated_fraction"] = float(np.mean(frames.images >= top))
    return SimulatedData(rec, float(c_nominal), dur, desc, camera_profile(camera))
