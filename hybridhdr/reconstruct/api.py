"""``reconstruct`` / ``reconstruct_iter``: HDR video from a hybrid recording, by method name."""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np

from .._util import phases as PH
from .._util.checks import check_shape
from .._util.limits import check_fps_outputs, check_output_count, check_sensor_size
from ..camera import CameraProfile
from ..camera.profile import load_profile
from ..events import EVENT_DTYPE, SensorSize, events_fields
from ..model import Frames, Recording
from . import _engine as E
from .augment import AugmentedMeasurements, AugmentParams
from .colour import _metadata, colour_source, rgb_to_luminance
from .edi import EDIEngine, EDIParams
from .event_arrays import EventArrays, StreamingEventArrays
from .learned.params import E2VIDParams, FireNetParams
from .measurement import FrameMeasurements
from .params import AKFParams, CFParams, DirectParams, FramesParams, HighPassParams
from .cuda import resolve_device
from .smoother import output_times, two_sided_iter

__all__ = ["Video", "METHODS", "METHOD_ALIASES", "reconstruct", "reconstruct_iter", "resolve_method",
           "make_params", "make_augment_params"]

#: method name -> (Params class, needs frames, uses events, one-line description)
METHODS: dict[str, tuple[type, bool, bool, str]] = {
    "akf": (AKFParams, True, True, "Asynchronous Kalman Filter (Wang et al., ICCV 2021)"),
    "cf": (CFParams, True, True, "complementary filter, fixed or HDR-adaptive gain (Scheerlinck et al., ACCV 2018)"),
    "highpass": (HighPassParams, False, True, "high-pass filter on events only (CF with zero frame input)"),
    "direct": (DirectParams, True, True, "direct integration of events onto the last frame"),
    "frames_zoh": (FramesParams, True, False, "frames only, zero-order hold"),
    "frames_linear": (FramesParams, True, False, "frames only, linear interpolation in intensity"),
    "edi": (EDIParams, True, True, "EDI deblurring: high-rate video from each blurred frame and its events "
                                   "(Pan et al., CVPR 2019)"),
    "e2vid": (E2VIDParams, False, True, "E2VID recurrent UNet on event voxel grids, events only, released "
                                        "weights (Rebecq et al., TPAMI 2019)"),
    "firenet": (FireNetParams, False, True, "FireNet light recurrent network, events only, released weights "
                                            "(Scheerlinck et al., WACV 2020)"),
}
METHOD_ALIASES = {"hpf": "highpass", "frames": "frames_zoh"}
MODES = ("offline", "causal", "forward")


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


def resolve_method(method: str) -> str:
    if not isinstance(method, str):
        raise TypeError(f"method must be a str, got {type(method).__name__}")
    m = METHOD_ALIASES.get(method, method)
    if m not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {sorted(METHODS) + sorted(METHOD_ALIASES)}")
    return m


def make_params(method: str, params=None):
    """Params for ``method`` from None (defaults), a dict, a TOML path or a Params instance."""
    method = resolve_method(method)
    cls = METHODS[method][0]
    if params is None:
        p = cls()
    elif isinstance(params, cls):
        p = params
    elif isinstance(params, dict):
        p = cls.from_dict(params)
    elif isinstance(params, (str, os.PathLike)):
        p = cls.from_toml(params)
    else:
        raise TypeError(f"params for method {method!r} must be {cls.__name__}, a dict, a TOML path or None, "
                        f"got {type(params).__name__}")
    if method == "frames_linear" and p.interpolation != "linear":
        p = p.replace(interpolation="linear")
    if method == "frames_zoh" and p.interpolation != "zoh":
        p = p.replace(interpolation="zoh")
    return p


# -- sources ------------------------------------------------------------------------------------

def _host_workers(device: str, n_workers) -> int:
    """Threads for the host-side work around the filter (column split, output collection): the
    ``n_workers`` asked for on the CPU; on the GPU, where the filter needs no host thread, at
    least the machine's cores (up to 16). Thread counts never change a result's bits."""
    n = int(n_workers)
    return n if device != "cuda" else max(n, min(os.cpu_count() or 1, 16))


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
    tm = PH.ACTIVE
    c0 = PH.now() if tm is not None else 0
    t = np.empty(n, np.int64)
    x = np.empty(n, np.uint16)
    y = np.empty(n, np.uint16)
    p = np.empty(n, np.int8)
    map_ranges(n, n_workers, lambda i0, i1: split_range(ev, i0, i1, t, x, y, p))
    if tm is not None:
        tm.add("read_split", c0, "parallel")  # split over the workers, in the driving thread
    return t, x, y, p


def _declared_event_count(source) -> int | None:
    """The number of events a source says it holds (in-memory recording, container), else None."""
    if isinstance(source, Recording):
        return int(source.events.shape[0])
    n = getattr(source, "n_events", None)
    return int(n) if isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n >= 0 else None


def _source_profile(source):
    """The camera profile a source declares (``metadata.provenance["camera_profile"]``, e.g. an
    AKF ``.mat`` file's ``f_Q`` table), or None."""
    prov = getattr(_metadata(source), "provenance", None)
    d = prov.get("camera_profile") if isinstance(prov, dict) else None
    if not isinstance(d, dict):
        return None
    try:
        return CameraProfile.from_dict(d)
    except (TypeError, ValueError) as e:
        raise ValueError(f"the recording's camera profile (metadata provenance 'camera_profile') is invalid: "
                         f"{e}") from None


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


def _stored_thresholds(source):
    """The threshold map an opened container source stores (``/thresholds``), or None."""
    fn = getattr(source, "read_thresholds", None)
    return fn() if callable(fn) else None


def _thresholds_unset(params) -> bool:
    """True when ``params`` (None or a dict) gives no contrast threshold: the recording's declared
    ones may then be used. A Params instance or a TOML file counts as set."""
    if params is None:
        return True
    if isinstance(params, dict):
        return not any(k in params for k in ("contrast_threshold", "contrast_threshold_on", "contrast_threshold_off"))
    return False


def _declared_thresholds(source) -> tuple[float, float] | None:
    """The event sensor's nominal (ON, OFF) thresholds a source's metadata states, or None."""
    md = _metadata(source)
    got = getattr(getattr(md, "event_camera", None), "contrast_thresholds", None)
    if got is None:  # recordings simulated before CameraInfo stated them keep the sensor in provenance
        prov = getattr(md, "provenance", None) or {}
        sensor = prov.get("sensor") if prov.get("generator") == "hybridhdr.simulate" else None
        if isinstance(sensor, dict):
            on, off = sensor.get("contrast_threshold_on"), sensor.get("contrast_threshold_off")
            if all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
                   for v in (on, off)):
                got = (float(on), float(off))
    return got


def _threshold_arrays(thresholds):
    """(c_on, c_off) arrays of a threshold map (an object with ``c_on``/``c_off`` arrays, a dict,
    a ``(c_on, c_off)`` pair or a path that :func:`hybridhdr.formats.thresholds.load_thresholds`
    reads), or None."""
    if thresholds is None:
        return None
    if isinstance(thresholds, (str, os.PathLike)):
        from ..formats.thresholds import load_thresholds
        thresholds = load_thresholds(thresholds)
    if hasattr(thresholds, "filled"):  # a ThresholdMap: pixels it could not estimate take its fallbacks
        c_on, c_off = thresholds.filled()
        return np.asarray(c_on), np.asarray(c_off)
    if isinstance(thresholds, dict):
        return np.asarray(thresholds["c_on"]), np.asarray(thresholds["c_off"])
    if hasattr(thresholds, "c_on") and hasattr(thresholds, "c_off"):
        return np.asarray(thresholds.c_on), np.asarray(thresholds.c_off)
    if isinstance(thresholds, (tuple, list)) and len(thresholds) == 2:
        return np.asarray(thresholds[0]), np.asarray(thresholds[1])
    raise TypeError(f"thresholds must be a threshold map (c_on, c_off arrays), a dict, a pair or a path, "
                    f"got {type(thresholds).__name__}")


def _sensor_shape(ss, frames: Frames | None) -> tuple[int, int]:
    if ss is not None:
        return ss.shape
    if frames is not None and len(frames):
        return frames.shape
    raise ValueError("cannot tell the sensor size: the source has no sensor_size and no frames")


def make_augment_params(augment) -> AugmentParams:
    """AugmentParams from None/True (defaults), False (off), a dict, a TOML path or an instance."""
    if augment is None:
        return AugmentParams()  # off: the default measurement carries frames forward with events
    if augment is True:
        return AugmentParams(enabled=True)
    if augment is False:
        return AugmentParams.off()
    if isinstance(augment, AugmentParams):
        return augment
    if isinstance(augment, dict):
        return AugmentParams.from_dict({"enabled": True, **augment})
    if isinstance(augment, (str, os.PathLike)):
        from .._util.toml import load_toml
        d = load_toml(augment)
        d = d["augment"] if isinstance(d.get("augment"), dict) else d
        return AugmentParams.from_dict({"enabled": True, **{k: v for k, v in d.items() if not isinstance(v, dict)}})
    raise TypeError(f"augment must be AugmentParams, a dict, a TOML path, a bool or None, "
                    f"got {type(augment).__name__}")


def _exposure_mean(params, frames) -> bool:
    """The AKF reads its frames as exposure means (``AKFParams.exposure_mean``) and some frame
    stamps an exposure: the events inside the exposures are then needed."""
    return (bool(getattr(params, "exposure_mean", False)) and frames is not None and len(frames) > 0
            and bool(np.any(frames.t_end_us > frames.t_start_us)))


def _build_engine(method, params, shape, frames, mode, profile, n_workers, measurements, events=None,
                  augment: AugmentParams | None = None, device: str = "cpu"):
    needs_frames = METHODS[method][1]
    prof = load_profile(profile)
    if method in ("e2vid", "firenet"):  # learned, events only (reconstruct.learned; needs PyTorch)
        from .learned.engine import LearnedEngine
        return LearnedEngine(shape, params, method), prof
    if method == "edi":
        if frames is None or len(frames) == 0:
            raise ValueError("method 'edi' needs frames, but the recording has none")
        if mode == "causal":
            raise ValueError("method 'edi' needs the events of the whole exposure, so it cannot run in causal mode")
        return EDIEngine(shape, frames, events, prof, params), prof
    if method == "akf" and measurements is None and augment is not None and augment.enabled and mode != "causal":
        if frames is None or len(frames) == 0:
            raise ValueError("method 'akf' needs frames, but the recording has none "
                             "(use method='highpass' for events only)")
        measurements = AugmentedMeasurements(frames, events, shape, prof, akf_params=params, params=augment)
    if needs_frames and measurements is None:
        if frames is None or len(frames) == 0:
            raise ValueError(f"method {method!r} needs frames, but the recording has none "
                             f"(use method='highpass' for events only)")
        if method == "akf":
            corr = None
            if _exposure_mean(params, frames) and events is not None:  # frames as exposure means (EDI)
                from .edi import exposure_log_corrections
                from .augment import deblur_min_events
                n_min = deblur_min_events(min(params.c_on, params.c_off), params.exposure_min_events)
                corr = exposure_log_corrections(frames, events, params.c_on, params.c_off, min_events=n_min)
            measurements = FrameMeasurements(
                frames, shape, prof, intensity_offset=params.intensity_offset,
                bias_correction=params.bias_correction,
                interpolate_covariance=(mode != "causal" and params.covariance_interpolation == "linear"),
                precision_scale=params.frame_precision_scale, saturation=params.saturation,
                min_weighting=params.min_weighting,
                event_step=-1.0 if params.event_interpolation else 0.0,  # -1: L^A follows each jump
                log_corrections=corr)
        else:
            off = getattr(params, "intensity_offset", 1.0)
            measurements = FrameMeasurements(frames, shape, prof, intensity_offset=off, bias_correction=False,
                                             interpolate_covariance=False)
    if device == "cuda" and method in ("akf", "cf", "direct", "highpass"):  # reconstruct.cuda (numba.cuda)
        from .cuda import CudaAKFEngine, CudaCFEngine
        if method == "akf":
            return CudaAKFEngine(shape, measurements, params), prof
        return CudaCFEngine(shape, measurements, params, method), prof
    if method == "akf":
        return E.AKFEngine(shape, measurements, params, n_workers), prof
    if method in ("cf", "direct", "highpass"):
        return E.CFEngine(shape, measurements, params, method, n_workers), prof
    if mode == "causal" and method == "frames_linear":
        raise ValueError("method 'frames_linear' needs the next frame, so it cannot run in causal mode")
    return E.FramesEngine(shape, measurements, params), prof


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
    kw = dict(times_us=times_us, fps=fps, mode=mode, profile=profile, t_start_us=t_start_us, t_end_us=t_end_us,
              n_workers=n_workers, chunk_events=chunk_events, measurements=measurements, progress=progress,
              info=info, augment=augment, thresholds=thresholds, frame_time_offset_us=frame_time_offset_us,
              device=device)
    cs = colour_source(source, cfa, demosaic)
    if cs is None:  # monochrome: the driver below, unchanged
        yield from _reconstruct_iter_mono(source, method, params, **kw)
    else:  # every method on the Bayer mosaic, outputs demosaicked (reconstruct.colour)
        yield from cs.demosaic_outputs(_reconstruct_iter_mono(cs.source, method, params, **kw), info)


def _reconstruct_iter_mono(source, method: str = "akf", params=None, *, times_us=None, fps: float | None = None,
                           mode: str = "offline", profile=None, t_start_us: int | None = None,
                           t_end_us: int | None = None, n_workers: int = 1, chunk_events: int = 1 << 20,
                           measurements=None, progress: Callable[[int], None] | None = None,
                           info: dict | None = None, augment=None,
                           thresholds=None, frame_time_offset_us: int = 0,
                           device: str = "cpu") -> Iterator[tuple[int, np.ndarray]]:
    method = resolve_method(method)
    device, device_line = resolve_device(device, method)  # "cuda" or "cpu", and the line saying which
    if info is not None:
        info["device"] = device_line
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if isinstance(n_workers, bool) or not isinstance(n_workers, (int, np.integer)) or n_workers < 1:
        raise ValueError(f"n_workers must be an int >= 1, got {n_workers!r}")
    if isinstance(chunk_events, bool) or not isinstance(chunk_events, (int, np.integer)) or chunk_events < 1:
        raise ValueError(f"chunk_events must be an int >= 1, got {chunk_events!r}")
    for name, v in (("t_start_us", t_start_us), ("t_end_us", t_end_us)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer))):
            raise TypeError(f"{name} must be an int (µs) or None, got {type(v).__name__}")
    p = make_params(method, params)
    aug = make_augment_params(augment)
    thr = _threshold_arrays(thresholds)
    if times_us is not None:
        check_output_count(int(np.size(times_us)))  # before any work (docs/security.md)
    if isinstance(frame_time_offset_us, bool) or not isinstance(frame_time_offset_us, (int, np.integer)):
        raise TypeError(f"frame_time_offset_us must be an int (µs), got {type(frame_time_offset_us).__name__}")
    # on the GPU the filter leaves the host's cores idle: its host side (splitting in-memory records
    # into columns) uses them all, with the same bits as one thread
    # learned methods: their own (PyTorch) device parameter
    on_gpu = device == "cuda" or str(getattr(p, "device", "cpu")).startswith(("cuda", "auto"))
    host_workers = _host_workers("cuda" if on_gpu else "cpu", n_workers)
    ss, frames, chunk_factory, close, n_declared, opened = _open_source(source, host_workers)
    events = None
    try:
        if frame_time_offset_us and frames is not None and len(frames):
            # the time each frame stands for, as calibrated (hybridhdr.calibrate.selfcal): every
            # exposure interval shifted, events untouched
            dt = int(frame_time_offset_us)
            frames = dataclasses.replace(frames, t_start_us=frames.t_start_us + dt, t_end_us=frames.t_end_us + dt)
            if info is not None:
                info["frame_time_offset_us"] = dt
        if thr is None and thresholds is None and method in ("akf", "cf", "direct", "highpass"):
            stored = _stored_thresholds(opened)  # a map calibrated into the container is used
            if stored is not None:
                thr = _threshold_arrays(stored)
                if info is not None:
                    info["thresholds"] = "per-pixel map stored in the recording"
        if thr is None and thresholds is None and _thresholds_unset(params) and hasattr(p, "contrast_threshold_on"):
            declared = _declared_thresholds(opened)  # the sensor's nominal ON/OFF the recording states
            if declared is not None:
                p = p.replace(contrast_threshold_on=declared[0], contrast_threshold_off=declared[1])
                if info is not None:
                    info["thresholds"] = (f"declared by the recording: ON {declared[0]:g}, OFF {declared[1]:g} "
                                          f"(log units)")
        shape = _sensor_shape(ss, frames)
        check_sensor_size(*shape, what="sensor (per-pixel filter state)")
        if info is not None and frames is not None:
            info["frame_encoding"] = str(frames.encoding)  # the previews' display map (display_gamma)
        if fps is not None and times_us is None:
            span = _time_span_us(opened, frames)
            if span is not None:
                lo = span[0] if t_start_us is None else max(span[0], int(t_start_us))
                hi = span[1] + 1 if t_end_us is None else int(t_end_us)
                check_fps_outputs(lo, max(hi, lo), fps)
        use_aug = (method == "akf" and mode != "causal" and measurements is None and aug.enabled
                   and frames is not None and len(frames) > 0)
        exp_mean = method == "akf" and measurements is None and not use_aug and _exposure_mean(p, frames)
        if use_aug or method == "edi" or exp_mean:
            # EDI, frame augmentation and frames read as exposure means look ahead in time (the
            # events inside an exposure): hold the events in memory (13 B/event)
            if n_declared is None:
                events = EventArrays.from_chunks(chunk_factory(int(chunk_events)), shape)
            else:  # read in the background: the filter starts on the first chunks
                events = StreamingEventArrays(chunk_factory(int(chunk_events)), shape, n_declared)
            chunk_factory = events.chunks
        if profile is None:
            profile = _source_profile(opened)
        two_sided = (method == "akf" and mode == "offline" and measurements is None
                     and frames is not None and len(frames) > 0)
        if two_sided:
            if events is None:
                tm = PH.ACTIVE
                c0 = PH.now() if tm is not None else 0
                if isinstance(opened, Recording):  # in memory: columns split in n_workers threads
                    events = EventArrays.from_structured(opened.events, shape,
                                                         n_workers=host_workers)
                    if tm is not None:
                        tm.add("read_all", c0, "parallel")
                else:
                    events = EventArrays.from_chunks(chunk_factory(int(chunk_events)), shape)
                    if tm is not None:
                        tm.add("read_all", c0, "serial")
            prof = load_profile(profile)
            if info is not None:
                info.update(method=method, mode=mode, profile=prof.name, params=p.to_dict(),
                            augment=aug.to_dict() if use_aug else {"enabled": False})
            t_last = max(int(events.t[-1]) if len(events) else int(frames.t_mid_us[-1]), int(frames.t_mid_us[-1]))
            times = output_times(frames.t_mid_us, t_last, times_us=times_us, fps=fps, t_start_us=t_start_us,
                                 t_end_us=t_end_us)

            engines = []

            def make_engine(fr, ev, backward, n_workers=n_workers):  # a pass's share of the workers
                tm = PH.ACTIVE
                c0 = PH.now() if tm is not None else 0
                pp = p.replace(contrast_threshold_on=p.c_off, contrast_threshold_off=p.c_on) if backward else p
                e = _build_engine(method, pp, shape, fr, "forward", prof, n_workers, None, events=ev,
                                  augment=aug if use_aug else None, device=device)[0]
                if thr is not None:
                    e.set_thresholds(*((thr[1], thr[0]) if backward else thr))
                engines.append(e)
                if tm is not None:
                    tm.add("build", c0, "serial")
                return e
            if device == "cuda":  # the same two-filter smoother on the GPU (reconstruct.cuda)
                from .cuda import cuda_two_sided_iter
                make_engine.needs_events = use_aug or exp_mean
                yield from cuda_two_sided_iter(events, frames, make_engine, times, offset=p.intensity_offset,
                                               progress=progress, info=info, carried_variance=p.carried_variance())
            else:
                yield from two_sided_iter(events, frames, make_engine, times, offset=p.intensity_offset,
                                          chunk_events=int(chunk_events), progress=progress, info=info,
                                          carried_variance=p.carried_variance(), n_workers=int(n_workers))
            if info is not None:
                info["n_events_used"] = len(events)  # each event by each pass
                stats = [getattr(e.m, "stats", None) for e in engines]
                if use_aug and len(stats) == 2 and all(s is not None for s in stats):
                    info["augmentation"] = dict(stats[1].to_dict(), backward=stats[0].to_dict())
            return
        tm = PH.ACTIVE
        c0 = PH.now() if tm is not None else 0
        engine, prof = _build_engine(method, p, shape, frames, mode, profile, n_workers, measurements,
                                     events=events, augment=aug if use_aug else None, device=device)
        if tm is not None:
            tm.add("build", c0, "serial")
        if thr is not None:
            if not hasattr(engine, "set_thresholds"):
                raise ValueError(f"method {method!r} does not take a per-pixel threshold map")
            engine.set_thresholds(*thr)
        try:
            if times_us is None and fps is None:
                if METHODS[method][1] or (frames is not None and len(frames)):
                    m = getattr(engine, "m", None)
                    ft = (frames.t_mid_us if m is None else getattr(m, "frame_times_us", m.times_us))
                    times_us = np.unique(ft)
                    if t_start_us is not None:
                        times_us = times_us[times_us >= t_start_us]
                else:
                    fps = 30.0
            clock = E.OutputClock(times_us=times_us, fps=fps)
            start = t_start_us
            chunks = chunk_factory(int(chunk_events)) if engine.uses_events else iter(())
            if not METHODS[method][1] and start is None:  # events only: start at the first event
                chunks = iter(chunks)
                first = next(chunks, None)
                if first is None:
                    raise ValueError(f"method {method!r} needs events, but the source has none")
                start = int(first[0][0])
                if clock.times is not None and clock.times.size:  # e.g. frame times before the first event
                    start = min(start, int(clock.times[0]))
                import itertools
                chunks = itertools.chain([first], chunks)
            if info is not None:
                info.update(method=method, mode=mode, profile=prof.name, params=p.to_dict())
                if method == "akf":
                    info["augment"] = aug.to_dict() if use_aug else {"enabled": False}
            yield from E.drive(engine, chunks, clock, t_start_us=start, t_end_us=t_end_us, progress=progress)
            engine.close()  # no measurement is still being computed ahead when the stats are read
            if info is not None:
                info["n_events_used"] = engine.n_events
                info["n_clamped"] = int(getattr(engine, "n_clamped", 0))
                info["n_output_pixels"] = int(getattr(engine, "n_output_pixels", 0))
                stats = getattr(getattr(engine, "m", None), "stats", None)
                if stats is not None:
                    info["augmentation"] = stats.to_dict()
                if method == "edi":
                    info["edi_thresholds"] = {int(k): v for k, v in sorted(engine.thresholds.items())}
        finally:
            engine.close()
    finally:
        if events is not None:
            events.close()
        close()


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
        take the scalar.
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
    info: dict = {}
    ts, imgs = [], []
    for t, img in reconstruct_iter(source, method, params, times_us=times_us, fps=fps, mode=mode,
                                   profile=profile, t_start_us=t_start_us, t_end_us=t_end_us,
                                   n_workers=n_workers, chunk_events=chunk_events, measurements=measurements,
                                   progress=progress, info=info, augment=augment, thresholds=thresholds,
                                   cfa=cfa, demosaic=demosaic, frame_time_offset_us=frame_time_offset_us,
                                   device=device):
        ts.append(t)
        imgs.append(img)
    method = resolve_method(method)
    shape = imgs[0].shape if imgs else (0, 0)
    tm = PH.ACTIVE
    c0 = PH.now() if tm is not None else 0
    if imgs and all(im.shape == imgs[0].shape and im.dtype == np.float32 for im in imgs):
        # one array of all outputs, each worker copying its rows of every image
        from .event_arrays import map_ranges
        frames = np.empty((len(imgs),) + imgs[0].shape, np.float32)

        def rows(r0, r1):
            for k, im in enumerate(imgs):
                frames[k, r0:r1] = im[r0:r1]
        map_ranges(shape[0], _host_workers("cuda" if str(info.get("device", "")).startswith("device: cuda") else "cpu",
                                           n_workers), rows, min_part=8)
    else:
        frames = np.stack(imgs) if imgs else np.zeros((0,) + tuple(shape), np.float32)
    if tm is not None:
        tm.add("collect", c0, "parallel")
    return Video(frames, np.asarray(ts, np.int64), method, info.pop("params", {}), info)
