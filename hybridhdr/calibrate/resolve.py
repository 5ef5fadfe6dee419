"""Which contrast thresholds a run uses: the one resolver behind ``reconstruct``'s API and command
line and ``evaluate``'s hold-out and over-exposure scoring.

The user's choice is one of four words or a per-pixel map:

``"input"``
    what the recording declares: a per-pixel map stored in it (``/thresholds`` of the
    container), else its event camera's nominal ON/OFF (``CameraInfo.contrast_thresholds``, or a
    simulated recording's sensor in provenance); when the caller's parameters state thresholds
    (``stated``) only a stored map overrides them; when the recording declares nothing the
    method's own parameters stay.
``"params"``
    the method's own parameters (given on the command line or their default).
``"auto"``
    one ON and one OFF threshold estimated from the recording's frames and events
    (:func:`hybridhdr.calibrate.thresholds.pooled_thresholds`) in the method's log model
    ``ln(I + intensity_offset)``.
``"selfcal"``
    the event/frame self-calibration (:func:`hybridhdr.calibrate.selfcal.self_calibration`):
    the time each frame stands for, ON/OFF thresholds and, when ``intensity_offset`` is None
    (the AKF), the log offset I0.
a sensor profile
    the ``.json`` file ``hybridhdr calibrate sensor`` writes (the camera model, also what
    ``simulate --sensor`` reads): its ON/OFF thresholds, its log offset I0 (when
    ``intensity_offset`` is None: the AKF) and the time its frames stand for.
a map
    a threshold map (``c_on``/``c_off`` arrays, e.g. from ``hybridhdr calibrate thresholds``),
    a dict, a ``(c_on, c_off)`` pair or the path of a ``.npz`` map.

:func:`resolve_thresholds` returns a frozen :class:`ResolvedThresholds`: the values (scalars or
per-pixel arrays, and any calibrated log offset and frame time offset), the source that gave
them and the line that reports it. It knows no reconstruction method: the caller applies the
result to its parameters (:meth:`ResolvedThresholds.overrides`) and decides which methods take
thresholds at all.
"""

from __future__ import annotations

import argparse
import math
import os
from dataclasses import dataclass
from pathlib import Path


__all__ = ["THRESHOLD_WORDS", "DEFAULT_THRESHOLDS", "THRESHOLD_KEYS", "THRESHOLDS_HELP", "thresholds_arg",
           "ResolvedThresholds", "resolve_thresholds", "declared_thresholds", "stored_thresholds",
           "threshold_arrays", "thresholds_stated", "recording_declares_thresholds", "is_sensor_profile",
           "SENSOR_PROFILE_HELP", "sensor_profile_arg", "add_sensor_profile_arg", "take_sensor_profile_arg"]

#: The words a thresholds choice takes besides a map (module docstring).
THRESHOLD_WORDS = ("auto", "input", "params", "selfcal")

#: ``--thresholds`` when it is not given (and no threshold is given on the command line), in
#: ``reconstruct``, ``evaluate holdout`` and ``evaluate overexpose`` alike: the one real-data
#: default. "selfcal": a recording that declares no thresholds (nor stores a map) is self-calibrated
#: from its frames and events (measured never to make a hold-out suite worse); one that declares
#: them keeps them ("input").
DEFAULT_THRESHOLDS = "selfcal"

#: Parameter names that state contrast thresholds.
THRESHOLD_KEYS = ("contrast_threshold", "contrast_threshold_on", "contrast_threshold_off")

THRESHOLDS_HELP = ("contrast thresholds: FILE = a per-pixel ON/OFF map (.npz from 'hybridhdr calibrate "
                   "thresholds'); auto = one ON and one OFF threshold estimated from the recording's frames and "
                   "events (least squares of the frames' log changes on the event counts); input = what the "
                   "recording declares (a map stored in it, else its event camera's nominal ON/OFF; the "
                   "method's own parameters when it declares none, and the output says so); params = the "
                   "method's own parameters (--contrast-threshold, --set, --config/--params, else its default); "
                   "selfcal = the event/frame self-calibration of a recording that declares none (the time each "
                   "frame stands for, ON/OFF thresholds and the AKF's log offset, estimated from the recording's "
                   "frames and events; docs/calibrate.md), input for a recording that declares them "
                   f"[default: {DEFAULT_THRESHOLDS}, or params when a threshold is given on the command line]")


def thresholds_arg(text):
    """``--thresholds``: one of :data:`THRESHOLD_WORDS`, else the path of a threshold map file."""
    t = str(text).strip()
    if t.lower() in THRESHOLD_WORDS:
        return t.lower()
    if not t:
        raise argparse.ArgumentTypeError(f"expected FILE, {', '.join(THRESHOLD_WORDS)}, got {text!r}")
    return Path(t)


SENSOR_PROFILE_HELP = ("sensor profile (.json from 'hybridhdr calibrate sensor', the file 'simulate --sensor' reads): "
                       "the run uses its ON/OFF thresholds, its log offset I0 (methods that estimate it: the AKF) "
                       "and the time its frames stand for, with no estimation (the same as --thresholds FILE.json)")


def sensor_profile_arg(text):
    """``--sensor-profile``: the path of a sensor profile file (``.json``)."""
    t = str(text).strip()
    if not t.lower().endswith(".json"):
        raise argparse.ArgumentTypeError(f"expected a sensor profile .json (from 'hybridhdr calibrate sensor'), got {text!r}")
    return Path(t)


def add_sensor_profile_arg(parser):
    """Add ``--sensor-profile FILE`` to a command that takes ``--thresholds``."""
    parser.add_argument("--sensor-profile", type=sensor_profile_arg, default=None, metavar="FILE", help=SENSOR_PROFILE_HELP)


def take_sensor_profile_arg(args):
    """Fold ``--sensor-profile FILE`` into ``args.thresholds`` (the one resolver reads it): the
    file is checked now (a clear error before any work), and giving it with ``--thresholds`` is an error."""
    path = getattr(args, "sensor_profile", None)
    if path is None:
        return
    if getattr(args, "thresholds", None) is not None:
        from ..errors import UsageError
        raise UsageError(f"--sensor-profile {path} and --thresholds {args.thresholds} both give the camera model; use one")
    if not Path(path).is_file():
        raise FileNotFoundError(f"--sensor-profile {path} does not exist")
    from ..formats.sensor_profile import load_sensor_profile
    load_sensor_profile(path)  # a malformed profile fails here, naming the field
    args.thresholds = Path(path)


@dataclass(frozen=True, eq=False)
class ResolvedThresholds:
    """The thresholds a run uses and where they come from.

    Attributes
    ----------
    source : str
        ``"map"`` (a map the user gave), ``"stored"`` (the map stored in the recording),
        ``"declared"`` (the recording's nominal ON/OFF), ``"params"`` (the method's own: nothing
        to change), ``"auto"``, ``"selfcal"`` or ``"profile"`` (a sensor profile file).
    c_on, c_off : float or None
        Scalar ON/OFF thresholds (log units) to put into the method's parameters; None: keep
        the parameters'.
    maps : (c_on, c_off) arrays or None
        Per-pixel thresholds (``"map"``, ``"stored"``).
    intensity_offset : float or None
        The log offset I0 self-calibration estimated (only when asked to estimate it).
    frame_time_offset_us : int
        The shift to add to every frame's exposure interval (self-calibration), else 0.
    note : str or None
        The line reporting what was used (``Video.info["thresholds"]``, ``run.json``).
    record : dict or None
        The estimator's full record (``"auto"``, ``"selfcal"``).
    """

    source: str
    c_on: float | None = None
    c_off: float | None = None
    maps: tuple | None = None
    intensity_offset: float | None = None
    frame_time_offset_us: int = 0
    note: str | None = None
    record: dict | None = None

    def overrides(self) -> dict:
        """The parameter fields to replace (``contrast_threshold_on``/``_off``, and
        ``intensity_offset`` when it was calibrated); empty when the parameters stay."""
        out = {}
        if self.c_on is not None:
            out.update(contrast_threshold_on=self.c_on, contrast_threshold_off=self.c_off)
        if self.intensity_offset is not None:
            out["intensity_offset"] = self.intensity_offset
        return out




def stored_thresholds(source):
    """The threshold map an opened container source stores (``/thresholds``), or None."""
    fn = getattr(source, "read_thresholds", None)
    return fn() if callable(fn) else None


def declared_thresholds(source) -> tuple[float, float] | None:
    """The event sensor's nominal (ON, OFF) thresholds a source's metadata states, or None."""
    from ..model import source_metadata  # here: building the command line's parser imports no numpy
    md = source_metadata(source)
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


def recording_declares_thresholds(source) -> bool:
    """True when a recording (in memory or opened) declares thresholds: nominal ON/OFF in its
    metadata, or a stored map (an opened container's ``/thresholds``). The default choice (:data:`DEFAULT_THRESHOLDS`) then means ``"input"``."""
    return declared_thresholds(source) is not None or stored_thresholds(source) is not None


def thresholds_stated(params) -> bool:
    """True when ``params`` state contrast thresholds: a dict naming one of :data:`THRESHOLD_KEYS`,
    or a Params instance or TOML path (they count as stated); None states none."""
    if params is None:
        return False
    if isinstance(params, dict):
        return any(k in params for k in THRESHOLD_KEYS)
    return True


def threshold_arrays(thresholds):
    """(c_on, c_off) arrays of a threshold map (an object with ``c_on``/``c_off`` arrays, a dict,
    a ``(c_on, c_off)`` pair or a path that :func:`hybridhdr.formats.thresholds.load_thresholds`
    reads), or None."""
    import numpy as np  # here: building the command line's parser imports no numpy
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


def _from_recording(source, stated: bool, maps: bool) -> ResolvedThresholds:
    """``"input"``: the stored map (when ``maps``), else the declared ON/OFF (unless ``stated``)."""
    if maps:
        stored = stored_thresholds(source)
        if stored is not None:
            return ResolvedThresholds("stored", maps=threshold_arrays(stored),
                                      note="per-pixel map stored in the recording")
    if not stated:
        got = declared_thresholds(source)
        if got is not None:
            return ResolvedThresholds("declared", c_on=got[0], c_off=got[1],
                                      note=f"declared by the recording: ON {got[0]:g}, OFF {got[1]:g} (log units)")
    return ResolvedThresholds("params")


def _pooled(recording, profile, intensity_offset) -> ResolvedThresholds:
    from .thresholds import pooled_thresholds
    on, off, record = pooled_thresholds(recording, profile=profile, intensity_offset=intensity_offset)
    note = (f"estimated from the recording: ON {on:.4g}, OFF {off:.4g} (log units; pooled over "
            f"{record['pixel_intervals']} pixel-intervals of {record['intervals']} frame intervals)")
    return ResolvedThresholds("auto", c_on=on, c_off=off, note=note, record=record)


def _selfcal(recording, profile, intensity_offset) -> ResolvedThresholds:
    import logging
    import warnings

    from .camera_model import GridEdgeWarning
    from .selfcal import self_calibration
    # a grid edge is said (logged, in the note and in the record's "warnings"), never silent; it does
    # not stop a run: the estimate at the edge is still the best this recording allows
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", GridEdgeWarning)
        cal = self_calibration(recording, profile=profile, intensity_offset=intensity_offset)
    edge = [str(w.message) for w in caught if issubclass(w.category, GridEdgeWarning)]
    for w in caught:
        if not issubclass(w.category, GridEdgeWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    for msg in edge:
        logging.getLogger(__name__).warning("%s", msg)
    if edge and isinstance(cal, dict):
        cal = {**cal, "warnings": edge}
    i0 = cal["intensity_offset"] if intensity_offset is None else intensity_offset
    note = (f"self-calibrated from the recording: frames stand for their stamp {cal['time_offset_us']:+d} µs, ON "
            f"{cal['c_on']:.4g}, OFF {cal['c_off']:.4g} (log units) in ln(I + {i0:.3g}); "
            f"events explain {100 * cal['r2']:.0f} % of the frames' log changes (uncalibrated "
            f"{100 * cal['r2_nominal']:.0f} %)" + "".join(f"; warning: {m}" for m in edge))
    return ResolvedThresholds("selfcal", c_on=cal["c_on"], c_off=cal["c_off"],
                              intensity_offset=cal["intensity_offset"] if intensity_offset is None else None,
                              frame_time_offset_us=int(cal["time_offset_us"]), note=note, record=cal)


def _from_sensor_profile(path, intensity_offset) -> ResolvedThresholds:
    """A sensor profile file (``calibrate sensor``): its thresholds, I0 and frame time offset."""
    from ..formats.sensor_profile import load_sensor_profile
    prof = load_sensor_profile(path)
    est = prof.estimates
    sp = prof.simulator_params
    if "contrast_threshold_on" not in sp or "contrast_threshold_off" not in sp:
        raise ValueError(f"sensor profile {path}: its recording did not identify the ON/OFF thresholds "
                         f"({est.get('contrast_threshold_on', {}).get('reason', 'no estimate')})")
    on, off = float(sp["contrast_threshold_on"]), float(sp["contrast_threshold_off"])
    i0 = (est.get("intensity_offset") or {}).get("value")
    dt = (est.get("time_offset_us") or {}).get("value")
    note = f"sensor profile {Path(path).name}: ON {on:.4g}, OFF {off:.4g} (log units)"
    own = None
    if i0 is not None:
        if intensity_offset is None:
            own = float(i0)
            note += f" in ln(I + {own:.3g})"
        elif not math.isclose(float(intensity_offset), float(i0), rel_tol=1e-9):
            note += (f", estimated in ln(I + {float(i0):.3g}); the method's own log model ln(I + "
                     f"{float(intensity_offset):.3g}) differs, so they are approximate there")
    if dt is not None:
        note += f"; frames stand for their stamp {int(dt):+d} µs"
    return ResolvedThresholds("profile", c_on=on, c_off=off, intensity_offset=own,
                              frame_time_offset_us=int(dt) if dt is not None else 0, note=note,
                              record={"sensor_profile": str(path), "name": prof.name,
                                      "estimates": {k: est[k] for k in ("contrast_threshold_on", "contrast_threshold_off",
                                                                         "intensity_offset", "time_offset_us")
                                                    if k in est}})


def is_sensor_profile(choice) -> bool:
    """True for the path of a sensor profile file (``.json``) as a thresholds choice."""
    return isinstance(choice, (str, os.PathLike)) and str(choice).lower().endswith(".json") \
        and str(choice) not in THRESHOLD_WORDS


def resolve_thresholds(recording, choice="input", *, stated: bool = False, maps: bool = True,
                       intensity_offset: float | None = None, profile=None) -> ResolvedThresholds:
    """The thresholds ``choice`` gives on ``recording`` (module docstring).

    Parameters
    ----------
    recording : Recording or opened reader
        ``"input"`` reads only its metadata and stored map; ``"auto"`` and ``"selfcal"`` need a
        :class:`~hybridhdr.model.Recording` (frames and events in memory).
    choice : {"input", "params", "auto", "selfcal"} or a map
        A map: a threshold map, dict, ``(c_on, c_off)`` pair or ``.npz`` path (any other str
        is a path).
    stated : bool
        The caller's parameters state thresholds (:func:`thresholds_stated`): ``"input"`` then
        keeps them unless the recording stores a map.
    maps : bool
        The method takes per-pixel maps (``"input"`` looks for a stored one only then).
    intensity_offset : float or None
        I0 of the method's log model ``ln(I + I0)`` for ``"auto"`` and ``"selfcal"``; for
        ``"selfcal"`` None estimates it too (the AKF).
    profile : CameraProfile, path or None
        The frame camera's profile for ``"auto"`` and ``"selfcal"``.

    Raises
    ------
    ValueError
        A recording that cannot tell (``"auto"``, ``"selfcal"``: the
        estimator's reason).
    """
    if is_sensor_profile(choice):
        return _from_sensor_profile(choice, intensity_offset)
    if not isinstance(choice, str) or choice not in THRESHOLD_WORDS:  # a str that is no word is a path
        return ResolvedThresholds("map", maps=threshold_arrays(choice))
    if choice == "params":
        return ResolvedThresholds("params")
    if choice == "input":
        return _from_recording(recording, stated, maps)
    if choice == "auto":
        return _pooled(recording, profile, intensity_offset)
    return _selfcal(recording, profile, intensity_offset)
