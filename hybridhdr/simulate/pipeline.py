"""The simulation pipeline: a radiance source to events, frames and HDR ground truth.

:func:`simulate` drives a :class:`~hybridhdr.simulate.source.RadianceSource` through the
:class:`~hybridhdr.simulate.sampling.TimeSampler`; every accepted render goes to the event
sensor (events in ``(t_prev, t]``), to the frame camera (exposure integration) and, at
ground-truth times, into the HDR references. Ground truth is the rendered
linear radiance (float32) at every frame's mid-exposure ``t_start + (t_end - t_start) // 2``
(``Frames.t_mid_us``) and at the requested ``gt_times_us``; these times, and the exposure bounds,
are mandatory render times, so they are exact renders, not interpolations.

:func:`simulate_to_file` streams the same output into a :class:`~hybridhdr.formats.container.RecordingWriter`
(events written after every step, frames and references as they complete; bounded memory;
``NAME.partial`` renamed when complete).

Random streams: ``np.random.SeedSequence(seed).spawn(2)`` seeds the event sensor and the frame
camera, so the same seed gives the same bits.

**Colour** (``cfa="RGGB"``, ``"BGGR"``, ``"GRBG"``, ``"GBRG"``): a Bayer event sensor and a frame
sensor behind the same filter (the DAVIS346 colour). A source may render linear RGB
(H, W, 3); each pixel of both sensors sees only its own channel
(:func:`hybridhdr.camera.cfa.mosaic`), so the sampler, the event sensor and the frame camera
work unchanged on the mosaic; frames are the raw mosaic (K, H, W) and HDR references the
rendered RGB (K, H, W, 3) (the rendered grey for a grey source, whose mosaic is the grey image).
Both cameras' ``metadata.*.cfa`` record the pattern. The Mitsuba sources render luminance
(``llvm_ad_mono``, or ``scalar_rgb`` reduced to Y), so colour scenes come from sources that
return RGB, e.g. :func:`hybridhdr.simulate.procedural.colour_edge_sweep_recording`'s scene.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._version import __version__
from ..camera.cfa import mosaic, parse_cfa
from ..events import EVENT_DTYPE
from ..formats.container import RecordingWriter
from ..model import CameraInfo, Frames, HDRReferences, Metadata, Recording
from .camera import FrameCamera, FrameCameraParams
from .sampling import SamplingParams, TimeSampler, event_fidelity
from .sensor import EventSensor, EventSensorParams, sensor_preset
from .source import RadianceSource

__all__ = ["simulate", "simulate_to_file", "SimulationResult", "event_fidelity"]


@dataclass
class SimulationResult:
    """Output of :func:`simulate` / :func:`simulate_to_file`.

    Attributes
    ----------
    recording : Recording or None
        The recording (None from :func:`simulate_to_file`; read ``path`` instead).
    renders : int
        Number of calls to ``source.render`` made by the simulation.
    stats : dict
        Counts and timings: ``n_events``, ``n_noise_events``, ``n_frames``, ``n_hdr``,
        ``renders``, ``bisections``, ``wall_s``, ``render_s``, ``sensor_s``.
    path : Path or None
        The written file (:func:`simulate_to_file`).
    """

    recording: Recording | None
    renders: int
    stats: dict = field(default_factory=dict)
    path: Path | None = None


def _resolve_sensor(sensor) -> EventSensorParams:
    if isinstance(sensor, EventSensorParams):
        return sensor
    from ..formats.sensor_profile import SensorProfile
    if isinstance(sensor, (str, Path, SensorProfile)):
        return sensor_preset(sensor)
    raise TypeError(f"sensor must be a preset name, a sensor profile (path, builtin:NAME, SensorProfile) or "
                    f"EventSensorParams, got {type(sensor).__name__}")


def _check_source(source):
    missing = [a for a in ("sensor_size", "duration_us", "render", "max_image_speed_px_per_s", "describe")
               if not hasattr(source, a)]
    if missing:
        raise TypeError(f"source must implement the RadianceSource protocol (hybridhdr.simulate.source); "
                        f"{type(source).__name__} lacks {missing}")


class _MosaicSource:
    """A radiance source seen through a Bayer filter: :meth:`render` returns each pixel's own
    channel of the wrapped source's RGB render; :meth:`rgb` the render itself (the most recent
    renders are kept, so ground truth at a sampled time costs no extra render)."""

    def __init__(self, source, pattern: str):
        self._src = source
        self.pattern = pattern
        self.sensor_size = source.sensor_size
        self.duration_us = source.duration_us
        self._recent: dict[int, np.ndarray] = {}

    def __getattr__(self, name):
        return getattr(self._src, name)

    def rgb(self, t_us: int) -> np.ndarray:
        t = int(t_us)
        if t not in self._recent:
            self._recent[t] = np.asarray(self._src.render(t))
            while len(self._recent) > 8:
                self._recent.pop(next(iter(self._recent)))
        return self._recent[t]

    def render(self, t_us: int) -> np.ndarray:
        r = self.rgb(t_us)
        if r.ndim == 3:
            return mosaic(r, self.pattern)
        return r  # a grey scene: every channel is the grey value

    def max_image_speed_px_per_s(self, t0_us: int, t1_us: int) -> float:
        return self._src.max_image_speed_px_per_s(t0_us, t1_us)

    def describe(self) -> dict:
        return dict(self._src.describe(), cfa=self.pattern)


class _MemorySink:
    def __init__(self):
        self.events, self.frames, self.hdr_im, self.hdr_t = [], [], [], []

    def write_events(self, ev):
        if len(ev):
            self.events.append(ev)

    def write_frames(self, f):
        self.frames.append(f)

    def write_hdr(self, h: HDRReferences):
        self.hdr_im.append(h.images)
        self.hdr_t.append(h.t_us)


def planned_mandatory_times(camera, duration_us: int, gt_times_us=None) -> list[int]:
    """About the mandatory render times of a run (used by the run-time estimate): each exposure's
    start, middle and end at the camera's nominal frame rate and exposure (no auto-exposure), and
    the ground-truth times."""
    ts = {int(t) for t in (gt_times_us if gt_times_us is not None else [])}
    if camera is not None:
        n = int(math.floor(duration_us * camera.frame_rate_hz / 1e6)) + 1
        for k in range(n):
            t0 = int(round(k * 1e6 / camera.frame_rate_hz))
            ts.update((t0, t0 + camera.exposure_us // 2, t0 + camera.exposure_us))
    return sorted(t for t in ts if 0 <= t <= duration_us)


def frame_mandatory_count(camera, duration_us: int, gt_times_us=None) -> int:
    """How many :func:`planned_mandatory_times` a run has."""
    return len(planned_mandatory_times(camera, duration_us, gt_times_us))


#: wall-clock statistics: printed and returned, never written into the recording (a recording is a
#: function of its inputs and seed, so a resumed or repeated run writes the same bits)
_TIMING_STATS = ("wall_s", "sensor_s", "render_s")


def _run(source, sink, *, sensor, camera, sampling, gt_times_us, seed, progress, cfa=None, write_hdr=True):
    _check_source(source)
    pattern = parse_cfa(cfa)
    if pattern is not None:
        source = _MosaicSource(source, pattern)
    params = _resolve_sensor(sensor)
    sampling = sampling or SamplingParams()
    if not isinstance(sampling, SamplingParams):
        raise TypeError(f"sampling must be SamplingParams, got {type(sampling).__name__}")
    if camera is not None and not isinstance(camera, FrameCameraParams):
        raise TypeError(f"camera must be FrameCameraParams or None, got {type(camera).__name__}")
    ss = source.sensor_size
    duration = int(source.duration_us)
    gt = sorted({int(t) for t in (gt_times_us if gt_times_us is not None else [])})
    bad = [t for t in gt if not 0 <= t <= duration]
    if bad:
        raise ValueError(f"gt_times_us must lie in [0, {duration}] µs (the source duration); got {bad[:5]}")
    seq = np.random.SeedSequence(seed)
    s_sensor, s_camera = seq.spawn(2)
    ev_sensor = EventSensor(ss, params, seed=s_sensor)
    cam = FrameCamera(camera, ss, seed=s_camera, duration_us=duration) if camera is not None else None
    hdr_times = set(gt)
    mandatory = list(gt)
    if cam is not None:
        for iv in cam.pop_new_intervals():
            mandatory += cam.mandatory_times(iv)
            hdr_times.add(iv[0] + (iv[1] - iv[0]) // 2)
    max_step_fn = None
    if params.lowpass_on:
        def max_step_fn(r):  # τ/3 at the brightest pixel (v2e README)
            tau = params.min_time_constant_s(float(np.max(r)))
            return tau / 3.0 * 1e6
    sampler = TimeSampler(source, sampling, contrast_threshold=params.contrast_threshold, log_eps=params.log_eps,
                          mandatory_times_us=mandatory, max_step_fn=max_step_fn)
    renders0 = int(getattr(source, "renders", 0))
    t_wall = time.perf_counter()
    t_sensor = 0.0
    n_frames = n_hdr = 0
    pbar = None
    if progress:
        from tqdm.auto import tqdm
        pbar = tqdm(total=duration, unit="µs", desc="simulate", unit_scale=True, leave=False)
    last = 0
    first = True
    it = iter(sampler)
    while True:
        try:
            t, r = next(it)
        except StopIteration:
            break
        t0 = time.perf_counter()
        if first:
            ev_sensor.start(t, r)
            first = False
        else:
            sink.write_events(ev_sensor.step(t, r))
        t_sensor += time.perf_counter() - t0
        if cam is not None:
            for f in cam.feed(t, r):
                sink.write_frames(f)
                n_frames += 1
            for iv in cam.pop_new_intervals():
                for tm in cam.mandatory_times(iv):
                    sampler.add_mandatory(tm)
                hdr_times.add(iv[0] + (iv[1] - iv[0]) // 2)
        if write_hdr and t in hdr_times:
            ref = r if pattern is None else source.rgb(t)
            sink.write_hdr(HDRReferences(np.asarray(ref, np.float32)[None], np.array([t], np.int64)))
            n_hdr += 1
        if pbar is not None:
            pbar.update(t - last)
            pbar.set_postfix(renders=sampler.renders, events=ev_sensor.n_events, refresh=False)
        last = t
    if pbar is not None:
        pbar.close()
    wall = time.perf_counter() - t_wall
    renders = int(getattr(source, "renders", renders0 + sampler.renders)) - renders0
    stats = {"renders": renders, "samples": sampler.renders, "bisections": sampler.bisections,
             "n_events": int(ev_sensor.n_events), "n_noise_events": int(ev_sensor.n_noise_events),
             "n_frames": n_frames, "n_hdr": n_hdr, "wall_s": wall, "sensor_s": t_sensor,
             "render_s": sampler.render_s, "duration_us": duration}
    prov = {"generator": "hybridhdr.simulate", "hybridhdr_version": __version__,
            "source": source.describe(), "sensor": params.to_dict(),
            "camera": None if cam is None else {**camera.to_dict(), **cam.crf_metadata()},
            "sampling": sampling.to_dict(), "seed": seed, "seed_entropy": str(seq.entropy),
            "gt_times_us": gt, "renders": renders,
            "stats": {k: v for k, v in stats.items() if k not in _TIMING_STATS}}
    meta = Metadata(event_camera=CameraInfo(ss, model="hybridhdr simulated event sensor", cfa=pattern,
                                            contrast_threshold_on=params.contrast_threshold_on,
                                            contrast_threshold_off=params.contrast_threshold_off),
                    frame_camera=CameraInfo(ss if cam is not None else None,
                                            model="hybridhdr simulated frame camera" if cam is not None else "",
                                            cfa=pattern if cam is not None else None),
                    provenance=prov)
    return renders, stats, meta


def simulate(source: RadianceSource, *, sensor: str | EventSensorParams = "clean",
             camera: FrameCameraParams | None = None, sampling: SamplingParams | None = None,
             gt_times_us=None, seed: int | None = 0, progress: bool = True, cfa: str | None = None) -> SimulationResult:
    """Simulate a hybrid recording from ``source`` in memory.

    Parameters
    ----------
    source : RadianceSource
        Renders linear radiance (H, W) at any µs time in ``[0, source.duration_us]``.
    sensor : {"ideal", "clean", "noisy"} or EventSensorParams
    camera : FrameCameraParams, optional
        Frame camera; None = events (and requested ground truth) only.
    sampling : SamplingParams, optional
        Adaptive by default.
    gt_times_us : iterable of int, optional
        Extra ground-truth times (µs) besides every frame's mid-exposure.
    seed : int or None
    progress : bool
        tqdm bar on stderr.
    cfa : {"RGGB", "BGGR", "GRBG", "GBRG"} or None
        A Bayer colour camera (module notes): events and raw mosaic frames of each pixel's own
        channel of an RGB source, RGB references. None: monochrome (unchanged).

    Returns
    -------
    SimulationResult
        ``recording`` has the events, frames (one per planned exposure that fits in the duration),
        HDR references (float32 radiance) and metadata whose provenance records the source's
        ``describe()``, all parameters, the seed, the number of renders and the hybridhdr version.
    """
    sink = _MemorySink()
    renders, stats, meta = _run(source, sink, sensor=sensor, camera=camera, sampling=sampling,
                                gt_times_us=gt_times_us, seed=seed, progress=progress, cfa=cfa)
    events = np.concatenate(sink.events) if sink.events else np.zeros(0, EVENT_DTYPE)
    frames = None
    if sink.frames:
        fr = sink.frames
        frames = Frames(np.concatenate([f.images for f in fr]), np.concatenate([f.t_start_us for f in fr]),
                        np.concatenate([f.t_end_us for f in fr]), np.concatenate([f.gain for f in fr]),
                        np.concatenate([f.iso for f in fr]), fr[0].encoding)
    hdr = HDRReferences(np.concatenate(sink.hdr_im), np.concatenate(sink.hdr_t)) if sink.hdr_im else None
    rec = Recording(events, source.sensor_size, frames, hdr=hdr, metadata=meta)
    return SimulationResult(rec, renders, stats)


def simulate_to_file(source: RadianceSource, path, *, sensor: str | EventSensorParams = "clean",
                     camera: FrameCameraParams | None = None, sampling: SamplingParams | None = None,
                     gt_times_us=None, seed: int | None = 0, progress: bool = True,
                     compression: str | None = "gzip", cfa: str | None = None,
                     write_hdr: bool = True) -> SimulationResult:
    """Like :func:`simulate`, streaming into the hybridhdr container at ``path`` (HDF5).

    Events are handed to the writer after every step (it buffers at most ``buffer_events``),
    frames and references as they complete; the file is written as ``path + '.partial'`` and
    renamed when complete, or removed on error. The provenance (renders, stats) is written at
    the end. Returns a :class:`SimulationResult` with ``recording=None`` and ``path`` set.
    """

    class _Writer(RecordingWriter):
        final_metadata = None

        def _finish(self):
            if self.final_metadata is not None:
                import json
                md = self.final_metadata.to_dict()
                md["event_camera"]["height"], md["event_camera"]["width"] = self.sensor_size.shape
                self._f.attrs["metadata_json"] = json.dumps(md)
            super()._finish()

    _check_source(source)
    path = Path(path)
    # a writer that fails while creating its file leaves no .partial (EventFileWriter aborts), and
    # one that finds another run's partial there leaves that alone
    w = _Writer(path, sensor_size=source.sensor_size, compression=compression)
    try:
        renders, stats, meta = _run(source, w, sensor=sensor, camera=camera, sampling=sampling,
                                    gt_times_us=gt_times_us, seed=seed, progress=progress, cfa=cfa,
                                    write_hdr=write_hdr)
        w.final_metadata = meta
        w.close()
    except BaseException:
        w.abort()
        raise
    return SimulationResult(None, renders, stats, path)
