"""``reconstruct`` / ``reconstruct_iter``: HDR video from a hybrid recording, by method name."""

from __future__ import annotations

import dataclasses
import itertools
import os
from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np

from .._util import phases as PH
from .._util.checks import check_shape
from .._util.limits import check_fps_outputs, check_sensor_size
from ..calibrate.resolve import recording_declares_thresholds, resolve_thresholds
from ..camera import CameraProfile, profile_for_frames
from ..camera.profile import load_profile
from ..events import EVENT_DTYPE, SensorSize, events_fields
from ..model import Frames, Recording, source_metadata
from . import _engine as E
from .augment import AugmentedMeasurements, deblur_min_events
from .colour import colour_source, rgb_to_luminance
from .edi import EDIEngine, exposure_log_corrections
from .event_arrays import EventArrays, StreamingEventArrays
from .measurement import FrameMeasurements
from .methods import (METHOD_ALIASES, METHODS, MODES, MethodSpec, make_augment_params, make_params, method_spec,
                      resolve_method)
from .request import ReconstructRequest, host_workers
from .smoother import output_times, two_sided_iter

__all__ = ["Video", "METHODS", "METHOD_ALIASES", "MODES", "MethodSpec", "reconstruct", "reconstruct_iter",
           "resolve_method", "method_spec", "make_params", "make_augment_params", "source_profile",
           "engine_for", "ReconstructRequest", "recording_facts"]


@dataclass(frozen=True, eq=False)
class Video:
    """A reconstructed video.

    Attributes
    ----------
    frames : ndarray of shape (K, H, W) or (K, H, W, 3), float32
        Linear intensity in the camera profile's scaled-irradiance units (brightest frame code =
        1); for ``highpass`` the relative intensity exp(L̂) (1 = unchanged). Linear RGB
        (demosaicked) for a colour event camera (:mod:`~hybridhdr.reconstruct.colour`);
        :meth:`luminance` gives (K, H, W) in either case.
    t_us : ndarray of shape (K,), int64
        Timestamp of each frame in µs (the state at t includes events with timestamps < t).
    method : str
    params : dict
        The resolved parameters.
    info : dict
        Mode, number of events used, start time, profile name.
    """

    frames: np.ndarray
    t_us: np.ndarray
    method: str = ""
    params: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        fr = np.asarray(self.frames, dtype=np.float32)
        k = check_shape(fr, "K H W | K H W 3", "Video.frames")["K"]
        t = np.asarray(self.t_us, dtype=np.int64)
        check_shape(t, "K", "Video.t_us", sizes={"K": k})
        object.__setattr__(self, "frames", fr)
        object.__setattr__(self, "t_us", t)

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.frames.shape[1:3])

    @property
    def is_colour(self) -> bool:
        """True for linear RGB frames (K, H, W, 3) (a colour event camera, ``info["cfa"]``)."""
        return self.frames.ndim == 4

    def luminance(self) -> np.ndarray:
        """(K, H, W) float32: the frames themselves, or Rec. 709 luminance of RGB frames."""
        if not self.is_colour:
            return self.frames
        return rgb_to_luminance(self.frames)


# -- sources ------------------------------------------------------------------------------------

def _open_source(source, n_workers: int = 1):
    """(sensor_size, frames, chunk iterator factory, closer, declared event count or None, the
    opened source: the Recording or the reader, whose metadata, time range and stored threshold
    map are read once) for a Recording, reader or path."""
    if isinstance(source, Recording):
        ev = source.events
        ss = source.sensor_size

        def chunks(n):
            return _RecordChunks(ev, n, n_workers)
        return ss, source.frames, chunks, (lambda: None), _declared_event_count(source), source
    reader = source
    close = (lambda: None)
    if isinstance(source, (str, os.PathLike)):
        from ..formats import open_reader
        reader = open_reader(source)
        close = reader.close
    if not hasattr(reader, "iter_chunks"):
        raise TypeError(f"source must be a Recording, a reader (with iter_chunks), a RecordingFile or a path, "
                        f"got {type(source).__name__}")
    ss = SensorSize.from_any(getattr(reader, "sensor_size", None))
    frames = reader.read_frames() if hasattr(reader, "read_frames") else None
    if frames is not None and len(frames):
        # the filters hold the frames as float64 log intensities (8 bytes a pixel, plus work copies):
        # a 1 MB container of 1 GiB of compressed zero frames used to take the AKF to 7.2 GB
        from .._util.limits import check_memory
        check_memory(int(frames.images.size) * 8, getattr(reader, "path", None),
                     "the frames as the filter holds them (8 bytes a pixel)")

    if hasattr(reader, "iter_event_columns"):  # the container: columns straight from HDF5
        # (read ahead in a thread by the consumer: the driver's prefetcher or StreamingEventArrays)
        def chunks(n):
            return reader.iter_event_columns(n)
    else:
        def chunks(n):
            for c in reader.iter_chunks(n):
                ev = c.events if hasattr(c, "events") else c
                if len(ev):
                    yield events_fields(ev)
    return ss, frames, chunks, close, _declared_event_count(reader), reader


class _RecordChunks:
    """``(t, x, y, p)`` chunks of ``n`` in-memory structured events, each split into columns by
    ``n_workers`` threads in the consumer's thread when it asks for it (``prefetch = False``: the
    driver starts no reading thread, which on a many-core machine would be one thread copying
    for all the workers, and a hand-off per chunk)."""

    prefetch = False

    def __init__(self, ev, n: int, n_workers: int):
        self.ev, self.n, self.n_workers = ev, int(n), int(n_workers)

    def __iter__(self):
        ev, n = self.ev, self.n
        for i in range(0, ev.shape[0], n):
            yield _record_columns(ev[i:i + n], self.n_workers)


def _record_columns(ev, n_workers: int = 1):
    """Contiguous ``(t, x, y, p)`` of structured events: ``EVENT_DTYPE`` records copied by
    ``n_workers`` threads, each a contiguous part (:func:`.event_arrays.split_range`), anything
    else through :func:`events_fields`."""
    from .event_arrays import map_ranges, split_range
    n = ev.shape[0]
    if ev.dtype != EVENT_DTYPE or not ev.flags.c_contiguous:
        return events_fields(ev)
    t = np.empty(n, np.int64)
    x = np.empty(n, np.uint16)
    y = np.empty(n, np.uint16)
    p = np.empty(n, np.int8)
    with PH.phase("read_split", "parallel"):  # split over the workers, in the driving thread
        map_ranges(n, n_workers, lambda i0, i1: split_range(ev, i0, i1, t, x, y, p))
    return t, x, y, p


def _declared_event_count(source) -> int | None:
    """The number of events a source says it holds (in-memory recording, container), else None."""
    if isinstance(source, Recording):
        return int(source.events.shape[0])
    n = getattr(source, "n_events", None)
    return int(n) if isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n >= 0 else None


def source_profile(source):
    """The camera profile a source declares (``metadata.provenance["camera_profile"]``, e.g. an
    AKF ``.mat`` file's ``f_Q`` table), or None."""
    prov = getattr(source_metadata(source), "provenance", None)
    d = prov.get("camera_profile") if isinstance(prov, dict) else None
    if not isinstance(d, dict):
        return None
    try:
        return CameraProfile.from_dict(d)
    except (TypeError, ValueError) as e:
        raise ValueError(f"the recording's camera profile (metadata provenance 'camera_profile') is invalid: "
                         f"{e}") from None


def recording_facts(source) -> tuple[bool, int]:
    """(whether the recording declares contrast thresholds or stores a map, its number of frames),
    read without its events: what decides whether reconstruct's default self-calibrates it."""
    _, frames, _, close, _, opened = _open_source(source)
    try:
        return recording_declares_thresholds(opened), 0 if frames is None else len(frames)
    finally:
        close()


def _time_span_us(source, frames) -> tuple[int, int] | None:
    """(first, last) µs of the data a source declares without reading its events, or None."""
    lo = hi = None
    if isinstance(source, Recording) and len(source.events):
        lo, hi = int(source.events["t"][0]), int(source.events["t"][-1])
    else:
        tr = getattr(source, "time_range_us", None)
        try:
            tr = tr() if callable(tr) else tr
        except Exception:  # noqa: BLE001 - a reader that cannot say declares nothing
            tr = None
        if tr is not None:
            lo, hi = int(tr[0]), int(tr[1])
    if frames is not None and len(frames):
        f0, f1 = int(frames.t_mid_us[0]), int(frames.t_mid_us[-1])
        lo = f0 if lo is None else min(lo, f0)
        hi = f1 if hi is None else max(hi, f1)
    return None if lo is None else (lo, hi)


def _sensor_shape(ss, frames: Frames | None) -> tuple[int, int]:
    if ss is not None:
        return ss.shape
    if frames is not None and len(frames):
        return frames.shape
    raise ValueError("cannot tell the sensor size: the source has no sensor_size and no frames")


@dataclass(eq=False)
class _Opened:
    """An opened recording as the drivers use it: its source, the sensor shape, the frames (shifted
    by the frame time offset), the event chunk factory and closer, the parameters with the
    recording's thresholds, a per-pixel threshold map, the camera profile, and the events when
    they are held in memory."""

    source: object
    shape: tuple
    frames: Frames | None
    chunks: Callable
    close: Callable
    n_declared: int | None
    params: object = None
    thr: tuple | None = None
    profile: object = None
    use_aug: bool = False
    events: object = None
    exposure_mean: bool = False  # the AKF reads its frames as exposure means: events held
    t_end_us: int | None = None  # the end of the outputs (:func:`_output_end`)


    def has_frames(self) -> bool:
        return self.frames is not None and len(self.frames) > 0


def _self_calibration(req: ReconstructRequest, source, opened, frames, params, info: dict | None):
    """``(params, frame_time_offset_us)`` after the default self-calibration, the command line's
    default (:data:`hybridhdr.calibrate.resolve.DEFAULT_THRESHOLDS`): for a method with a frame
    model and thresholds, when the caller gives no thresholds (no map, parameters that state none,
    no frame time offset, ``thresholds`` None) and the recording declares none (nor stores a map),
    the event/frame self-calibration of the recording
    (:func:`hybridhdr.calibrate.resolve.resolve_thresholds`, ``"selfcal"``): the AKF takes the
    calibrated log offset and thresholds, CF and direct integration the thresholds in their own
    log model, all the time each frame stands for. ``thresholds="selfcal"`` calibrates whatever
    the recording declares (an error when it cannot tell); ``"input"``/``"params"`` never. A
    recording that cannot tell keeps ``params`` (said in ``info["self_calibration"]``)."""
    rd, method = req.reading, req.run.method
    choice = rd.choice
    if choice not in ("default", "selfcal"):
        return params, 0
    spec = METHODS[method]
    if not (spec.takes_thresholds and spec.needs_frames):
        if choice == "selfcal":
            raise ValueError(f"thresholds='selfcal' applies to the methods with frames and thresholds, not {method!r}")
        return params, 0
    if choice == "default" and (rd.thresholds_stated or rd.frame_time_offset_us
                                or recording_declares_thresholds(opened) or frames is None or len(frames) < 3):
        return params, 0
    rec = source if isinstance(source, Recording) else None
    if rec is None:
        from ..formats import read
        path = source if isinstance(source, (str, os.PathLike)) else getattr(source, "path", None)
        if path is None:
            if choice == "selfcal":
                raise ValueError("thresholds='selfcal' needs a Recording or a path (the calibration reads it whole)")
            return params, 0
        rec = read(path)
    own_i0 = None if method == "akf" else float(params.intensity_offset)
    try:
        # a grid edge is logged by the resolver and kept in the record's "warnings"
        got = resolve_thresholds(rec, "selfcal", intensity_offset=own_i0, profile=rd.profile)
    except ValueError as e:
        if choice == "selfcal":
            raise ValueError(f"thresholds='selfcal': the recording cannot tell ({e})") from None
        if info is not None:
            info["self_calibration"] = f"skipped: {e}"
        return params, 0
    if info is not None:
        info["thresholds"] = got.note
        info["self_calibration"] = got.record
    return params.replace(**got.overrides()), int(got.frame_time_offset_us)


def _recording_thresholds(req: ReconstructRequest, opened, info: dict | None):
    """(params, per-pixel (c_on, c_off) or None): the caller's map, else what the recording
    declares (:func:`hybridhdr.calibrate.resolve.resolve_thresholds`, ``"input"``) for a method
    that takes thresholds; reported in ``info["thresholds"]``."""
    p = req.run.params
    given = req.reading.thresholds
    if given is not None and given.source == "profile":
        # the camera model of a sensor profile file, exactly its values (no estimation)
        if not METHODS[req.run.method].takes_thresholds:
            return p, None
        ov = {k: v for k, v in given.overrides().items() if hasattr(p, k)}
        if info is not None:
            info["thresholds"] = given.note
            info["camera_model"] = {"source": "profile", "c_on": given.c_on, "c_off": given.c_off,
                                    "intensity_offset": ov.get("intensity_offset"),
                                    "frame_time_offset_us": given.frame_time_offset_us, **(given.record or {})}
        return p.replace(**{k: v for k, v in given.overrides().items() if hasattr(p, k)}), None
    if given is not None:
        return p, given.maps
    if not METHODS[req.run.method].takes_thresholds:
        return p, None
    got = resolve_thresholds(opened, "input", stated=req.reading.thresholds_stated)
    if info is not None and got.note is not None:
        info["thresholds"] = got.note
    return (p.replace(**got.overrides()) if got.overrides() else p), got.maps


def _output_end(req: ReconstructRequest, source, opened, frames) -> int | None:
    """The exclusive end of the outputs: the caller's ``t_end_us``; with ``fps`` and none given,
    one past the last event for a method that reads events (the command line's ``--until
    events``; None, up to the last event or frame, for a source that cannot tell where its
    events end), else one past the last frame (the frames-only methods, ``--until frames``)."""
    out = req.output
    if out.t_end_us is not None or out.fps is None or out.times_us is not None:
        return out.t_end_us
    last = None
    if METHODS[req.run.method].uses_events:
        if isinstance(opened, Recording):
            last = int(opened.events["t"][-1]) if len(opened.events) else None
        elif isinstance(source, (str, os.PathLike)) and not str(source).startswith("builtin:"):
            from ..formats.span import recording_span
            ev = recording_span(source).events
            last = None if ev is None else int(ev[1])
        else:
            tr = getattr(opened, "time_range_us", None)
            try:
                tr = tr() if callable(tr) else tr
            except Exception:  # noqa: BLE001 - a reader that cannot say declares nothing
                tr = None
            last = None if tr is None else int(tr[1])
        if last is None:  # a source that cannot say where its events end: up to the last event or frame
            return None
    elif frames is not None and len(frames):
        last = int(frames.t_mid_us[-1])
    return None if last is None else last + 1


def _check_fps(req: ReconstructRequest, opened, frames) -> None:
    """Bound the number of ``fps`` outputs over the span the source declares, before any work."""
    out = req.output
    if out.fps is not None and out.times_us is None:
        span = _time_span_us(opened, frames)
        if span is not None:
            lo = span[0] if out.t_start_us is None else max(span[0], int(out.t_start_us))
            hi = span[1] + 1 if out.t_end_us is None else int(out.t_end_us)
            check_fps_outputs(lo, max(hi, lo), out.fps)


def _open(req: ReconstructRequest, source, info: dict | None) -> _Opened:
    """Open the source: frames shifted by the frame time offset, the thresholds resolved once,
    the shape checked, the camera profile chosen, the events held in memory when frame
    augmentation or EDI looks ahead in time."""
    ss, frames, chunks, close, n_declared, opened = _open_source(source, req.run.host_workers)
    try:
        dt = req.reading.frame_time_offset_us
        if dt and frames is not None and len(frames):
            # the time each frame stands for, as calibrated (hybridhdr.calibrate.selfcal): every
            # exposure interval shifted, events untouched
            frames = frames.shifted(dt)
            if info is not None:
                info["frame_time_offset_us"] = dt
        op = _Opened(opened, (), frames, chunks, close, n_declared)
        op.params, op.thr = _recording_thresholds(req, opened, info)
        given = req.reading.thresholds
        if (given is not None and given.source == "profile" and given.frame_time_offset_us
                and METHODS[req.run.method].takes_thresholds and frames is not None and len(frames)):
            # the time each frame stands for, as the sensor profile states it
            op.frames = frames = frames.shifted(given.frame_time_offset_us)
            if info is not None:
                info["frame_time_offset_us"] = given.frame_time_offset_us
        op.params, cal_dt = _self_calibration(req, source, opened, frames, op.params, info)
        if cal_dt and frames is not None and len(frames):  # the time each frame stands for, calibrated
            op.frames = frames = frames.shifted(cal_dt)
            if info is not None:
                info["frame_time_offset_us"] = cal_dt
        op.t_end_us = _output_end(req, source, opened, frames)
        op.shape = _sensor_shape(ss, frames)
        check_sensor_size(*op.shape, what="sensor (per-pixel filter state)")
        if info is not None and frames is not None:
            info["frame_encoding"] = str(frames.encoding)  # the previews' display map (display_gamma)
        _check_fps(req, opened, frames)
        op.use_aug = req.run.augmented and op.has_frames()
        op.profile = req.reading.profile if req.reading.profile is not None else source_profile(opened)
        op.exposure_mean = (req.run.method == "akf" and req.run.measurements is None and not op.use_aug
                            and _exposure_mean(op.params, frames))
        noise = _measures_frame_noise(req, op.params, frames)
        in_memory = isinstance(opened, Recording)
        if op.use_aug or req.run.method == "edi" or op.exposure_mean or (noise and not in_memory):
            # EDI, frame augmentation and frames read as exposure means look ahead in time (the
            # events inside an exposure), and the frame-noise measurement reads every frame
            # interval's events: hold the events in memory (13 B/event)
            if n_declared is None:
                op.events = EventArrays.from_chunks(chunks(req.run.chunk_events), op.shape)
            else:  # read in the background: the filter starts on the first chunks
                op.events = StreamingEventArrays(chunks(req.run.chunk_events), op.shape, n_declared)
            op.chunks = op.events.chunks
        if noise:
            op.params = _frame_noise(op, opened if in_memory else None, info)
        return op
    except BaseException:
        close()
        raise


def _measures_frame_noise(req: ReconstructRequest, params, frames) -> bool:
    """The AKF with its own frame measurements measures σ²_im and σ²_proc on the input's frames
    (``AKFParams.noise_from_frames``; needs three frames)."""
    return (req.run.method == "akf" and req.run.measurements is None
            and bool(getattr(params, "noise_from_frames", False)) and frames is not None and len(frames) >= 3)


def _frame_noise(op: _Opened, rec: Recording | None, info: dict | None):
    """``op.params`` with the frame noise σ²_im and the process noise σ²_proc measured on the
    input (:func:`hybridhdr.calibrate.frame_noise.estimate_frame_noise`, on the frames as the
    filter reads them and the camera profile it uses) in place of the fields left at their
    defaults (``frame_precision_scale`` None, ``process_noise_per_s`` the class default: a value
    the caller states wins); unchanged where the frames do not identify them. The record, with
    the fields it replaced (``"applied"``), goes to ``info["frame_noise"]``."""
    from ..calibrate.frame_noise import estimate_frame_noise
    from .params import AKFParams
    p = op.params
    if rec is not None:
        t, x, y = rec.events["t"], rec.events["x"], rec.events["y"]
    else:
        ev = op.events
        n = len(ev)  # a background reader: wait for every event
        t, x, y = ev.t[:n], ev.x[:n], ev.y[:n]
    prof = load_profile(op.profile)
    if p.min_weighting is not None:  # the weighting floor the filter's measurements use
        prof = dataclasses.replace(prof, min_weighting=float(p.min_weighting))
    got = estimate_frame_noise(op.frames, t, x, y, prof, p.intensity_offset)
    applied = []
    prec, q, rate = p.frame_precision_scale, p.process_noise_per_s, p.fusion_carried_rate_per_s
    if got["identifiable"]:
        if p.frame_precision_scale is None:
            prec = got["frame_precision_scale"]
            applied.append("frame_precision_scale")
        if p.process_noise_per_s == AKFParams.process_noise_per_s:
            q = got["process_noise_per_s"]
            applied.append("process_noise_per_s")
            if p.fusion_carried_rate_per_s is None:  # the fusion keeps its rate (AKFParams)
                rate = p.process_noise_per_s
                applied.append("fusion_carried_rate_per_s")
    if info is not None:
        info["frame_noise"] = {**got, "applied": sorted(applied)}
    if not applied:
        return p
    return p.replace(frame_precision_scale=prec, process_noise_per_s=q, fusion_carried_rate_per_s=rate)


def _exposure_mean(params, frames) -> bool:
    """The AKF reads its frames as exposure means (``AKFParams.exposure_mean``) and some frame
    stamps an exposure: the events inside the exposures are then needed."""
    return (bool(getattr(params, "exposure_mean", False)) and frames is not None and len(frames) > 0
            and bool(np.any(frames.t_end_us > frames.t_start_us)))


def _measurements(req: ReconstructRequest, op: _Opened, params, frames, events, prof):
    """The frame measurements of a filter: the caller's, the augmented frame (paper §4.1), or the
    zero-order hold of eqs. 6-9 (None for a method without frames)."""
    run = req.run
    method, measurements = run.method, run.measurements
    if method == "akf" and measurements is None and op.use_aug:
        if frames is None or len(frames) == 0:
            raise ValueError("method 'akf' needs frames, but the recording has none "
                             "(use method='highpass' for events only)")
        return AugmentedMeasurements(frames, events, op.shape, prof, akf_params=params, params=run.augment)
    if not METHODS[method].needs_frames or measurements is not None:
        return measurements
    if frames is None or len(frames) == 0:
        raise ValueError(f"method {method!r} needs frames, but the recording has none "
                         f"(use method='highpass' for events only)")
    if method == "akf":
        corr = None
        if events is not None and _exposure_mean(params, frames):  # frames as exposure means (EDI)
            n_min = deblur_min_events(min(params.c_on, params.c_off), params.exposure_min_events)
            corr = exposure_log_corrections(frames, events, params.c_on, params.c_off, min_events=n_min)
        return FrameMeasurements(
            frames, op.shape, prof, intensity_offset=params.intensity_offset,
            bias_correction=params.bias_correction,
            interpolate_covariance=(run.mode != "causal" and params.covariance_interpolation == "linear"),
            precision_scale=params.frame_precision_scale, saturation=params.saturation,
            min_weighting=params.min_weighting,
            event_step=-1.0 if params.event_interpolation else 0.0,  # -1: L^A follows each jump
            log_corrections=corr)
    off = getattr(params, "intensity_offset", 1.0)
    return FrameMeasurements(frames, op.shape, prof, intensity_offset=off, bias_correction=False,
                             interpolate_covariance=False)


def _build_engine(req: ReconstructRequest, op: _Opened, params, frames, events, n_workers: int):
    """(engine, profile) of the request's method on ``frames`` and ``events`` with ``params``."""
    method, mode, shape = req.run.method, req.run.mode, op.shape
    prof = load_profile(op.profile)
    if method in ("e2vid", "firenet"):  # learned, events only (reconstruct.learned; needs PyTorch)
        from .learned.engine import LearnedEngine
        return LearnedEngine(shape, params, method), prof
    if method == "edi":
        if frames is None or len(frames) == 0:
            raise ValueError("method 'edi' needs frames, but the recording has none")
        if mode == "causal":
            raise ValueError("method 'edi' needs the events of the whole exposure, so it cannot run in causal mode")
        return EDIEngine(shape, frames, events, prof, params), prof
    measurements = _measurements(req, op, params, frames, events, prof)
    if req.run.device.is_cuda and METHODS[method].cuda_engine:  # reconstruct.cuda (numba.cuda)
        from .cuda import CudaAKFEngine, CudaCFEngine
        if method == "akf":
            return CudaAKFEngine(shape, measurements, params), prof
        return CudaCFEngine(shape, measurements, params, method), prof
    if method == "akf":  # the row-band or the pixel-parallel engine, by the worker count (same bits)
        from ._pixel_engine import cpu_akf_engine
        return cpu_akf_engine(shape, measurements, params, n_workers), prof
    if method in ("cf", "direct", "highpass"):
        return E.CFEngine(shape, measurements, params, method, n_workers), prof
    if mode == "causal" and method == "frames_linear":
        raise ValueError("method 'frames_linear' needs the next frame, so it cannot run in causal mode")
    return E.FramesEngine(shape, measurements, params), prof


def engine_for(req: ReconstructRequest, shape, frames, events=None):
    """The engine of ``req``'s method, parameters, mode, profile, workers and device on ``frames``
    and ``events`` (an :class:`~.event_arrays.EventArrays`, for the methods that look ahead),
    without frame augmentation: one pass of a filter, as the two-sided smoother and the GPU
    benchmarks build them."""
    op = _Opened(None, tuple(shape), frames, None, None, None, profile=req.reading.profile)
    return _build_engine(req, op, req.run.params, frames, events, req.run.n_workers)[0]


def _hold_all_events(req: ReconstructRequest, op: _Opened):
    """Every event in memory (the two-sided filter reads them in both directions)."""
    if isinstance(op.source, Recording):  # in memory: columns split in n_workers threads
        with PH.phase("read_all", "parallel"):
            return EventArrays.from_structured(op.source.events, op.shape, n_workers=req.run.host_workers)
    with PH.phase("read_all", "serial"):
        return EventArrays.from_chunks(op.chunks(req.run.chunk_events), op.shape)


def _uses_two_sided(req: ReconstructRequest, op: _Opened) -> bool:
    """The AKF offline with frames and its own measurements: the two-sided filter."""
    run = req.run
    return run.method == "akf" and run.mode == "offline" and run.measurements is None and op.has_frames()


def _censored_codes(p, prof, frames) -> tuple | None:
    """``(clip_low_code, clip_high_code)`` when the AKF reads clipped codes as censored bounds
    (``saturation="bound"``): such a code does not measure its pixel, and the two-sided fusion's
    carried variance runs from the pixel's last unclipped frame (:class:`.smoother._CarriedVariance`)."""
    if getattr(p, "saturation", "value") != "bound" or frames is None or len(frames) == 0:
        return None
    prof = profile_for_frames(prof, frames)  # the profile the frame measurements read the codes with
    return int(prof.clip_low_code), int(prof.clip_high_code)


def _two_sided(req: ReconstructRequest, op: _Opened, info: dict | None):
    """The two-sided AKF (:mod:`.smoother`, or :func:`.cuda.cuda_two_sided_iter` on the GPU)."""
    run, out, p, frames = req.run, req.output, op.params, op.frames
    if op.events is None:
        op.events = _hold_all_events(req, op)
    events = op.events
    op.profile = prof = load_profile(op.profile)
    if info is not None:
        info.update(method=run.method, mode=run.mode, profile=prof.name, params=p.to_dict(),
                    augment=run.augment.to_dict() if op.use_aug else {"enabled": False})
    t_last = max(int(events.t[-1]) if len(events) else int(frames.t_mid_us[-1]), int(frames.t_mid_us[-1]))
    times = output_times(frames.t_mid_us, t_last, times_us=out.times_us, fps=out.fps, t_start_us=out.t_start_us,
                         t_end_us=op.t_end_us)
    engines = []

    def make_engine(fr, ev, backward, n_workers=run.n_workers):  # a pass's share of the workers
        with PH.phase("build"):
            pp = p.replace(contrast_threshold_on=p.c_off, contrast_threshold_off=p.c_on) if backward else p
            e = _build_engine(req, op, pp, fr, ev, n_workers)[0]
            if op.thr is not None:
                e.set_thresholds(*((op.thr[1], op.thr[0]) if backward else op.thr))
            engines.append(e)
        return e
    if run.device.is_cuda:  # the same two-filter smoother on the GPU (reconstruct.cuda)
        from .cuda import cuda_two_sided_iter
        make_engine.needs_events = op.use_aug or op.exposure_mean
        yield from cuda_two_sided_iter(events, frames, make_engine, times, offset=p.intensity_offset,
                                       progress=run.progress, info=info, carried_variance=p.carried_variance(),
                                       censored_codes=_censored_codes(p, prof, frames))
    else:
        yield from two_sided_iter(events, frames, make_engine, times, offset=p.intensity_offset,
                                  chunk_events=run.chunk_events, progress=run.progress, info=info,
                                  carried_variance=p.carried_variance(), n_workers=run.n_workers,
                                  censored_codes=_censored_codes(p, prof, frames))
    if info is not None:
        info["n_events_used"] = len(events)  # each event by each pass
        stats = [getattr(e.m, "stats", None) for e in engines]
        if op.use_aug and len(stats) == 2 and all(s is not None for s in stats):
            info["augmentation"] = dict(stats[1].to_dict(), backward=stats[0].to_dict())


def _clock_and_chunks(req: ReconstructRequest, op: _Opened, engine):
    """(output clock, start µs, event chunks) of a one-pass run: the requested times, else the
    frame times (an events-only method without frames: 30 fps from its first event)."""
    out, spec, frames = req.output, METHODS[req.run.method], op.frames
    times_us, fps = out.times_us, out.fps
    if times_us is None and fps is None:
        if spec.needs_frames or op.has_frames():
            m = getattr(engine, "m", None)
            ft = (frames.t_mid_us if m is None else getattr(m, "frame_times_us", m.times_us))
            times_us = np.unique(ft)
            if out.t_start_us is not None:
                times_us = times_us[times_us >= out.t_start_us]
        else:
            fps = 30.0
    clock = E.OutputClock(times_us=times_us, fps=fps)
    start = out.t_start_us
    chunks = op.chunks(req.run.chunk_events) if engine.uses_events else iter(())
    if not spec.needs_frames and start is None:  # events only: start at the first event
        chunks = iter(chunks)
        first = next(chunks, None)
        if first is None:
            raise ValueError(f"method {req.run.method!r} needs events, but the source has none")
        start = int(first[0][0])
        if clock.times is not None and clock.times.size:  # e.g. frame times before the first event
            start = min(start, int(clock.times[0]))
        chunks = itertools.chain([first], chunks)
    return clock, start, chunks


def _one_pass_stats(engine, req: ReconstructRequest, info: dict) -> None:
    """What a one-pass run reports in ``info`` after its last output."""
    info["n_events_used"] = engine.n_events
    info["n_clamped"] = int(getattr(engine, "n_clamped", 0))
    info["n_output_pixels"] = int(getattr(engine, "n_output_pixels", 0))
    stats = getattr(getattr(engine, "m", None), "stats", None)
    if stats is not None:
        info["augmentation"] = stats.to_dict()
    if req.run.method == "edi":
        info["edi_thresholds"] = {int(k): v for k, v in sorted(engine.thresholds.items())}


def _one_pass(req: ReconstructRequest, op: _Opened, info: dict | None):
    """One filter forward over the recording (:func:`._engine.drive`)."""
    run = req.run
    with PH.phase("build"):
        engine, prof = _build_engine(req, op, op.params, op.frames, op.events, run.n_workers)
    if op.thr is not None:
        if not hasattr(engine, "set_thresholds"):
            raise ValueError(f"method {run.method!r} does not take a per-pixel threshold map")
        engine.set_thresholds(*op.thr)
    try:
        clock, start, chunks = _clock_and_chunks(req, op, engine)
        if info is not None:
            info.update(method=run.method, mode=run.mode, profile=prof.name, params=op.params.to_dict())
            if run.method == "akf":
                info["augment"] = run.augment.to_dict() if op.use_aug else {"enabled": False}
        yield from E.drive(engine, chunks, clock, t_start_us=start, t_end_us=op.t_end_us,
                           progress=run.progress)
        engine.close()  # no measurement is still being computed ahead when the stats are read
        if info is not None:
            _one_pass_stats(engine, req, info)
    finally:
        engine.close()


def _drive(req: ReconstructRequest, source, info: dict | None):
    """The monochrome driver: open, then the two-sided or the one-pass filter."""
    if info is not None:
        info["device"] = req.run.device.line
    op = _open(req, source, info)
    try:
        yield from (_two_sided if _uses_two_sided(req, op) else _one_pass)(req, op, info)
    finally:
        if op.events is not None:
            op.events.close()
        op.close()


def _iter_request(req: ReconstructRequest, source, info: dict | None):
    """The outputs of a request: every method on the Bayer mosaic of a colour source, its
    outputs demosaicked (:mod:`.colour`), else the monochrome driver."""
    cs = colour_source(source, req.reading.cfa, req.reading.demosaic)
    if cs is None:
        yield from _drive(req, source, info)
    else:
        yield from cs.demosaic_outputs(_drive(req, cs.source, info), info)


def reconstruct_iter(source, method: str = "akf", params=None, *, times_us=None, fps: float | None = None,
                     mode: str = "offline", profile=None, t_start_us: int | None = None,
                     t_end_us: int | None = None, n_workers: int = 1, chunk_events: int = 1 << 20,
                     measurements=None, progress: Callable[[int], None] | None = None,
                     info: dict | None = None, augment=None, thresholds=None, cfa=None,
                     demosaic: str = "log_cubic", frame_time_offset_us: int = 0,
                     device: str = "cpu") -> Iterator[tuple[int, np.ndarray]]:
    """Stream ``(t_us, image)`` pairs with memory bounded by ``chunk_events`` (plus the frames).

    Parameters are those of :func:`reconstruct`; ``source`` may also be a reader from
    :func:`hybridhdr.open_reader`, a :class:`hybridhdr.formats.container.RecordingFile` or a path, whose
    events are read chunk by chunk. ``info``, if given, is filled with run statistics. Images
    are (H, W), or (H, W, 3) linear RGB for a colour event camera (``cfa``).
    """
    req = ReconstructRequest.build(method, params, times_us=times_us, fps=fps, mode=mode, profile=profile,
                                   t_start_us=t_start_us, t_end_us=t_end_us, n_workers=n_workers,
                                   chunk_events=chunk_events, measurements=measurements, progress=progress,
                                   augment=augment, thresholds=thresholds, cfa=cfa, demosaic=demosaic,
                                   frame_time_offset_us=frame_time_offset_us, device=device)
    yield from _iter_request(req, source, info)


def reconstruct(source, method: str = "akf", params=None, *, times_us=None, fps: float | None = None,
                mode: str = "offline", profile=None, t_start_us: int | None = None, t_end_us: int | None = None,
                n_workers: int = 1, chunk_events: int = 1 << 20, measurements=None,
                progress: Callable[[int], None] | None = None, augment=None, thresholds=None, cfa=None,
                demosaic: str = "log_cubic", frame_time_offset_us: int = 0,
                device: str = "cpu") -> Video:
    """Reconstruct linear-intensity video from events and frames.

    Parameters
    ----------
    source : Recording, reader, RecordingFile or path
        The hybrid recording (events sorted by ``t`` in µs; frames with exposure intervals).
    method : {"akf", "cf", "highpass", "direct", "frames_zoh", "frames_linear", "edi", "e2vid", "firenet"}
        Aliases: "hpf" = "highpass", "frames" = "frames_zoh".
    params : Params, dict, TOML path or None
        The method's parameters (:class:`AKFParams`, :class:`CFParams`, ...); None for defaults.
        Contrast thresholds, when neither ``params`` (None or a dict without them) nor
        ``thresholds`` give them: a per-pixel map stored in the recording, else the ON/OFF
        thresholds its metadata declares (``CameraInfo.contrast_threshold_on``/``_off``, e.g.
        a simulated recording's sensor), else the parameters' default; which one was used is in
        ``Video.info["thresholds"]`` (and ``run.json``).
    times_us : array_like of int (K,), optional
        Output times in µs, strictly increasing, not before the first frame used.
    fps : float, optional
        Output rate in Hz instead of ``times_us``; outputs at ``t0 + round(k 1e6 / fps)`` µs from
        the start up to the last event or frame. Default (neither): the frame times τ_k.
    mode : {"offline", "causal", "forward"}
        "offline" (default): for the AKF, the two-sided filter of
        :mod:`~hybridhdr.reconstruct.smoother` (a forward and a backward pass over the whole
        recording, fused per pixel by their covariances; events held in memory), for the other
        methods the same as "forward". "forward": one forward pass that may use the next frame
        (eq. 7's interpolation of R towards frame k+1, frame augmentation). "causal": only the
        past.
    profile : CameraProfile, path or None
        Camera profile (eqs. 3-6); None takes the one the recording declares
        (``metadata.provenance["camera_profile"]``, e.g. an AKF ``.mat`` file's ``f_Q``), else the
        built-in 8-bit profile of the frames' encoding.
    t_start_us, t_end_us : int, optional
        Half-open window of output times; the filter starts from the last frame at or before
        ``t_start_us``.
    n_workers : int
        Threads for the row-band parallel kernels (bit-identical to 1).
    chunk_events : int
        Events per chunk when streaming from a file.
    measurements : measurement provider, optional
        Replaces the zero-order-hold frame measurements (hook for frame augmentation, see
        :mod:`hybridhdr.reconstruct.measurement`).
    progress : callable, optional
        Called with the number of events consumed after each batch.
    thresholds : threshold map, dict, (c_on, c_off) pair, path or None
        Per-pixel ON and OFF contrast thresholds (log units, arrays of the sensor's shape; e.g.
        from ``hybridhdr calibrate thresholds``) used by the AKF, CF, direct and high-pass
        filters instead of the parameters' scalars; entries that are not finite and positive
        take the scalar. Also a sensor profile (``.json``), one of ``"input"``, ``"params"``,
        ``"selfcal"``, or a :class:`~hybridhdr.calibrate.resolve.ResolvedThresholds` already
        resolved by the caller (used as it is).
    augment : AugmentParams, dict, TOML path, bool or None
        Frame augmentation of the AKF in offline mode (paper §4.1, eqs. 10-13:
        :class:`~hybridhdr.reconstruct.augment.AugmentedMeasurements`): None or True for the
        defaults (on), False for zero-order-hold frames; its ``deblur``, ``interpolate`` and
        ``calibrate`` switches turn off each piece. Ignored in causal mode (the augmentation
        needs the next frame) and by other methods. Calibration fallbacks are reported in
        ``Video.info["augmentation"]``. With augmentation (and for ``method="edi"``) the events
        are held in memory.
    cfa : str or None
        Colour filter array of a colour event camera (``"RGGB"``, ``"BGGR"``, ``"GRBG"``,
        ``"GBRG"``): every method runs on the Bayer mosaic (RGB frames contribute each pixel's
        own channel) and the outputs are demosaicked to linear RGB
        (:mod:`~hybridhdr.reconstruct.colour`). None (default): the recording's
        ``metadata.event_camera.cfa``; ``"none"``: monochrome regardless. The pattern set here
        applies to the frames too (grey frames are then its raw mosaic).
    demosaic : {"log_cubic", "log_bilinear", "bilinear", "edge_aware"}
        Demosaicking of colour outputs (:func:`hybridhdr.camera.cfa.demosaic`; default geometric
        interpolation, the scale-invariant one, measured best in ``benchmarks/colour.py``); reported in
        ``Video.info["cfa"]``.
    frame_time_offset_us : int
        Shift added to every frame's exposure interval (µs; events untouched): the time a frame
        stands for when the recording's stamps mean something else, e.g. the offset
        ``hybridhdr.calibrate.selfcal`` estimates from the recording. Output times are not
        shifted. Recorded in ``Video.info["frame_time_offset_us"]``.
    device : {"cpu", "cuda", "auto"}
        Where the AKF and the CF family (``cf``, ``direct``, ``highpass``) run:
        :mod:`~hybridhdr.reconstruct.cuda` on an NVIDIA GPU through Numba's CUDA target (the same
        equations; L̂ and P agree with the CPU path to 1e-9 relative), or the CPU (default).
        "auto": the GPU when ``numba.cuda`` sees one, else the CPU. ``Video.info["device"]`` is
        the one line saying which ran. ``n_workers`` applies to the CPU only.

    Returns
    -------
    Video

    Notes
    -----
    Outputs are computed in closed form from the filter state without changing it, so they do
    not depend on the output rate, and the timestamp origin does not matter. The filter starts
    at the first frame (events before it are skipped) and uses the last one.
    """
    req = ReconstructRequest.build(method, params, times_us=times_us, fps=fps, mode=mode, profile=profile,
                                   t_start_us=t_start_us, t_end_us=t_end_us, n_workers=n_workers,
                                   chunk_events=chunk_events, measurements=measurements, progress=progress,
                                   augment=augment, thresholds=thresholds, cfa=cfa, demosaic=demosaic,
                                   frame_time_offset_us=frame_time_offset_us, device=device)
    info: dict = {}
    ts, imgs = [], []
    for t, img in _iter_request(req, source, info):
        ts.append(t)
        imgs.append(img)
    shape = imgs[0].shape if imgs else (0, 0)
    with PH.phase("collect", "parallel"):
        if imgs and all(im.shape == imgs[0].shape and im.dtype == np.float32 for im in imgs):
            # one array of all outputs, each worker copying its rows of every image
            from .event_arrays import map_ranges
            frames = np.empty((len(imgs),) + imgs[0].shape, np.float32)

            def rows(r0, r1):
                for k, im in enumerate(imgs):
                    frames[k, r0:r1] = im[r0:r1]
            map_ranges(shape[0], host_workers(req.run.device.is_cuda, n_workers), rows, min_part=8)
        else:
            frames = np.stack(imgs) if imgs else np.zeros((0,) + tuple(shape), np.float32)
    return Video(frames, np.asarray(ts, np.int64), req.run.method, info.pop("params", {}), info)
