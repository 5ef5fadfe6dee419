"""Real-data scoring without ground truth: frames held out of the input become the references.

Two tasks (``hybridhdr evaluate holdout``, ``benchmarks/accuracy.py``'s real suites):

- **leave-one-frame-out** (``leave_one_out``): frame k is removed from the input and the method
  reconstructs at its exposure centre τ_k from everything else (events and the other frames);
- **next-frame prediction** (``next_frame``, causal methods only): the input is cut before frame k
  (frames 0..k−1 and the events with t < τ_k − 1 µs) and the method reconstructs at
  τ_k − 1 µs; the cut makes the prediction causal by construction, whatever the method's mode.

The reference is frame k itself in frame-linear units (the camera profile's ``CRF⁻¹(code)``, 1.0
= the clip level; colour frames: luminance codes), scored only on its **well-exposed** pixels,
codes 20-235 of 8 bits scaled to the bit depth (:func:`well_exposed_range`): elsewhere the frame
is no measurement of the scene. Scoring follows ``docs/evaluate.md``'s policy (unaltered, then
reconstruction and reference both divided by the references' maximum over the held-out frames,
the reconstruction not clipped: symmetric, ``metrics.DEFAULT_CLIP``; data range 1), per held-out
frame (:func:`score_frame`,
luminance for colour output): on the well-exposed pixels MSE, PSNR and SSIM (the Gaussian SSIM map of :func:`hybridhdr.evaluate.metrics.ssim_map`,
averaged over the well-exposed pixels outside the map's border). Means over the held-out frames
(PSNR: the mean of the per-frame PSNRs).

Baselines beside every method, both frames-only: **hold previous** (``frames_zoh``: frame k−1)
and **linear interpolation** (``frames_linear`` between k−1 and k+1, in intensity). In the
next-frame task hold-previous is the causal baseline; linear interpolation needs frame k+1, so
it is shown as a non-causal reference (the same number as in the leave-one-out task).

Contrast thresholds (``thresholds="auto"``; the command line's ``--thresholds`` words, one
vocabulary with ``reconstruct``: ``auto`` estimated, ``input`` what the recording declares,
``params`` the method's own, or a per-pixel map): a real recording rarely states its sensor's
thresholds, and a method's threshold only means something in its own log model (the AKF's
``log(I + 1e-3)``, CF's ``log(I + 1)``). Each event method's pooled ON and OFF thresholds are then
estimated **without frame k** (on the leave-one-out input, the recording with frame k withheld:
in next-frame prediction the filter still sees only the data before τ_k, and its two threshold
numbers are a camera constant calibrated once, never from the scored frame), in that method's
log model (its ``intensity_offset``), by
:func:`hybridhdr.calibrate.thresholds.estimate_thresholds` (least squares of the frames' log
changes on the event counts, ``docs/calibrate.md``); the same procedure for every method, no
ground truth, no per-scene setting. Where the input has too little information (fewer than two
frames inside the events' span), the method keeps its own thresholds; what was used is recorded
per held-out frame. Methods without a frame model (high-pass) keep their own.

Held-out frames (default): the frames whose neighbours k−1 and k+1 exist among the frames with
mid-exposure inside the events' span (up to the last event) and whose τ_k is after the first
event; frames after the last event are dropped from the input (no events around them).
"""

from __future__ import annotations

import dataclasses
import os
import time

import numpy as np

from ..calibrate.resolve import (THRESHOLD_KEYS, THRESHOLD_WORDS, recording_declares_thresholds,
                                 resolve_thresholds)
from ..camera import load_profile, profile_for_frames
from ..camera.encoding import well_exposed_range
from ..errors import InputMismatchError
from ..events import slice_time
from ..reconstruct import reconstruct
from ..reconstruct.methods import make_params, method_spec, methods_with, resolve_method
from ..camera.encoding import frames_to_codes
from .metrics import DEFAULT_CLIP, ssim_map

__all__ = ["TASKS", "HoldoutSpec", "BASELINES", "default_held_frames", "holdout_input", "holdout_reconstructions",
           "input_thresholds", "THRESHOLD_SOURCES", "score_frame", "evaluate_holdout", "format_holdout"]

TASKS = ("leave_one_out", "next_frame")


@dataclasses.dataclass(frozen=True)
class HoldoutSpec:
    """One row of the table: a label, the method, its mode, parameters and augmentation."""

    label: str
    method: str
    mode: str = "offline"
    params: object = None
    augment: object = None


#: The frames-only baselines shown beside every method.
BASELINES = (HoldoutSpec("hold_previous", "frames_zoh", "causal"),
             HoldoutSpec("linear_interpolation", "frames_linear", "offline"))


def _trimmed_frames(rec):
    fr = rec.frames
    if fr is None or len(fr) < 2:
        raise InputMismatchError("holdout scoring needs at least 2 frames")
    if len(rec.events) == 0:
        raise InputMismatchError("holdout scoring needs events")
    t1 = int(rec.events["t"][-1])
    keep = np.flatnonzero(fr.t_mid_us <= t1)
    return fr.select(keep)


def default_held_frames(rec) -> list[int]:
    """Indices (into the frames kept, those with mid-exposure up to the last event) of the frames
    held out by default: a neighbour on each side and τ_k after the first event."""
    fr = _trimmed_frames(rec)
    t0 = int(rec.events["t"][0])
    return [k for k in range(1, len(fr) - 1) if fr.t_mid_us[k] > t0]


def holdout_input(rec, k: int, task: str, time_offset_us: int = 0):
    """``(recording, t_us)``: the input without frame k (``leave_one_out``) or cut before it
    (``next_frame``), and the output time (τ_k, or τ_k − 1 µs). ``time_offset_us``: frame k stands
    for τ_k + offset (a calibrated frame time), so the output time and the next-frame cut move by it
    (the input's frames keep their stamps; the method shifts them by the same offset)."""
    fr = _trimmed_frames(rec)
    if not 0 <= k < len(fr):
        raise ValueError(f"held-out frame {k} is not among the {len(fr)} frames inside the events' span")
    tk = int(fr.t_mid_us[k]) + int(time_offset_us)
    if task == "leave_one_out":
        sub = fr.select(np.setdiff1d(np.arange(len(fr)), [k]))
        return dataclasses.replace(rec, frames=sub, hdr=None), tk
    if task == "next_frame":
        if k < 1:
            raise ValueError("next-frame prediction needs a frame before the predicted one")
        t = tk - 1
        sub = fr.select(np.arange(k))
        return dataclasses.replace(rec, events=slice_time(rec.events, None, t), frames=sub, hdr=None,
                                   triggers=slice_time(rec.triggers, None, t), imu=slice_time(rec.imu, None, t)), t
    raise ValueError(f"task must be one of {TASKS}, got {task!r}")


def _luminance(frame):
    """A reconstructed (H, W) frame as is; an (H, W, 3) linear RGB frame as Rec. 709 luminance."""
    x = np.asarray(frame, np.float64)
    if x.ndim == 3:
        from ..reconstruct.colour import rgb_to_luminance
        return np.asarray(rgb_to_luminance(x), np.float64)
    return x


#: Methods whose events are scaled by contrast thresholds (``thresholds="auto"`` calibrates them).
THRESHOLD_METHODS = methods_with(takes_thresholds=True)

#: Values of ``thresholds`` besides a per-pixel map (a ThresholdMap or a path to one): the words of
#: :func:`hybridhdr.calibrate.resolve.resolve_thresholds` (``"params"``: the methods' own;
#: ``"auto"``: estimated on each input; ``"input"``: what the recording declares, else the
#: method's own; ``"selfcal"``: the event/frame self-calibration of each input).
THRESHOLD_SOURCES = THRESHOLD_WORDS


def default_threshold_source(rec) -> str:
    """What the command line's default (``--thresholds``' :data:`DEFAULT_THRESHOLDS`, "selfcal")
    means on ``rec``: ``"selfcal"`` for a recording that declares no contrast thresholds and stores
    no map, else ``"input"`` (the declared ones)."""
    return "input" if recording_declares_thresholds(rec) else "selfcal"


def default_thresholds_for(rec, specs) -> str:
    """The thresholds source a run takes when none is given, the same for the API and the command
    line: ``"params"`` when any spec carries explicit parameters (they win), else
    :func:`default_threshold_source` (``"selfcal"`` or the recording's declared ``"input"``)."""
    return "params" if any(getattr(s, "params", None) is not None for s in specs) else default_threshold_source(rec)


def selfcal_params(rec_input, method: str, params, profile=None, *, cache: dict | None = None):
    """``(params, time_offset_us, used)``: ``params`` of ``method`` with the self-calibration of
    ``rec_input`` (:func:`hybridhdr.calibrate.resolve.resolve_thresholds`, ``"selfcal"``): the AKF
    takes the calibrated log offset I0 and thresholds, CF and direct integration thresholds
    re-fitted in their own log model; every frame-using method takes the frame time offset. Inputs
    without the information keep ``params`` and no offset (recorded in ``used``)."""
    m = resolve_method(method)
    p = make_params(m, params)
    cache = {} if cache is None else cache
    if m in THRESHOLD_METHODS and not hasattr(p, "intensity_offset"):  # high-pass: no frames
        return params, 0, None
    own_i0 = None if m == "akf" or not hasattr(p, "intensity_offset") else float(p.intensity_offset)
    if own_i0 not in cache:
        try:
            cache[own_i0] = resolve_thresholds(rec_input, "selfcal", intensity_offset=own_i0, profile=profile)
        except ValueError as e:
            cache[own_i0] = str(e)[:200]
    got = cache[own_i0]
    if isinstance(got, str):
        return params, 0, {"source": "params", "why": got}
    used = {"source": "selfcal", **{k: v for k, v in got.record.items() if k != "calibration"}}
    if m in THRESHOLD_METHODS:
        p = p.replace(**got.overrides())
    return p, got.frame_time_offset_us, used


def input_thresholds(rec_input, method: str, params, profile=None, *, cache: dict | None = None):
    """``(params, used)``: ``params`` of ``method`` with pooled ON/OFF thresholds estimated on
    ``rec_input`` in the method's own log model (module docstring; :func:`hybridhdr.calibrate.
    resolve.resolve_thresholds`, ``"auto"``), and a record of what was used. Methods without
    thresholds, and inputs without the information, keep ``params``. ``cache`` (a dict kept for
    one ``rec_input``) holds the estimate per log model, so methods sharing an intensity offset
    estimate it once."""
    m = resolve_method(method)
    if m not in THRESHOLD_METHODS:
        return params, None
    p = make_params(m, params)
    if not hasattr(p, "intensity_offset"):  # no frame model (high-pass): nothing to calibrate against
        return params, None
    i0 = float(p.intensity_offset)
    cache = {} if cache is None else cache
    if i0 not in cache:
        try:
            cache[i0] = resolve_thresholds(rec_input, "auto", intensity_offset=i0, profile=profile)
        except ValueError as e:  # too little information in this input: the method's own thresholds
            cache[i0] = str(e)[:200]
    got = cache[i0]
    if isinstance(got, str):
        return p, {"source": "params", "c_on": float(p.c_on), "c_off": float(p.c_off), "why": got}
    return (p.replace(**got.overrides()),
            {"source": "auto", "c_on": got.c_on, "c_off": got.c_off, "intensity_offset": i0,
             "intervals": got.record["intervals"]})


#: What a calibration (``"auto"``, ``"selfcal"``) leaves out of its input: the held-out frame (one
#: calibration per held-out frame) or every held-out frame (one calibration for all of them).
CALIBRATION_HOLDOUTS = ("frame", "scored")


def holdout_reconstructions(rec, specs, *, task: str, held, profile=None, log=None, thresholds: str = "params",
                            calibration_holdout: str = "frame") -> dict:
    """Reconstruct every spec at every held-out frame.

    ``thresholds``: ``"params"`` (each spec's own), ``"auto"`` (estimated on each input in the
    method's log model, :func:`input_thresholds`), ``"input"`` (what the recording declares, else
    the spec's own) or a per-pixel threshold map (a ThresholdMap or a path to a ``.npz``).
    ``calibration_holdout``: ``"frame"`` (the calibration of frame k's input leaves frame k out)
    or ``"scored"`` (one calibration leaves every held-out frame out, shared by them: the same
    never-the-scored-frame rule at the cost of one calibration).

    Returns ``{label: {"frames": [(H, W) float64 or None per held-out frame], "wall_s": float,
    "error": str or None, "thresholds": [what was used per held-out frame]}}``; the first failure
    of a spec stops that spec (reported, not hidden).
    """
    from ..calibrate.resolve import is_sensor_profile, resolve_thresholds
    tmap = None
    if not isinstance(thresholds, str):
        tmap = thresholds
        if isinstance(thresholds, os.PathLike) and not is_sensor_profile(thresholds):
            # a sensor profile (.json) stays a path: reconstruct reads its camera model as it is
            from ..formats.thresholds import load_thresholds
            tmap = load_thresholds(thresholds)
    elif thresholds not in THRESHOLD_SOURCES:
        raise ValueError(f"thresholds must be one of {THRESHOLD_SOURCES} or a threshold map, got {thresholds!r}")
    if calibration_holdout not in CALIBRATION_HOLDOUTS:
        raise ValueError(f"calibration_holdout must be one of {CALIBRATION_HOLDOUTS}, got {calibration_holdout!r}")
    out = {s.label: {"frames": [], "wall_s": 0.0, "error": None, "thresholds": []} for s in specs}
    frames_k = _trimmed_frames(rec)  # the held-out frames' exposures (the references' units)
    shared_rec, shared_cal = None, {}
    if calibration_holdout == "scored":
        shared_rec = dataclasses.replace(rec, frames=frames_k.select(np.setdiff1d(np.arange(len(frames_k)), held)),
                                         hdr=None)
    for k in held:
        loo_k, calib_k = None, {}  # the recording without frame k, and its threshold estimates, once per k
        if shared_rec is not None:
            loo_k, calib_k = shared_rec, shared_cal  # without every held-out frame, once for all
        for s in specs:
            st = out[s.label]
            if st["error"] is not None:
                continue
            tk = "leave_one_out" if (task == "next_frame" and s.method == "frames_linear") else task
            try:
                r_k, t = holdout_input(rec, k, tk)
                params = s.params
                kw = {}
                if tmap is not None and resolve_method(s.method) in THRESHOLD_METHODS and is_sensor_profile(tmap):
                    # a sensor profile: reconstruct takes its camera model as it is and shifts the input
                    # frames by its frame offset; frame k stands for tau_k + that offset, predicted there
                    kw["thresholds"] = tmap
                    got = resolve_thresholds(None, tmap, intensity_offset=0.0)
                    st["thresholds"].append({"source": "profile", "file": str(tmap), "note": got.note})
                    if got.frame_time_offset_us and not method_spec(s.method).frames_only:
                        r_k, t = holdout_input(rec, k, tk, time_offset_us=got.frame_time_offset_us)
                elif tmap is not None and resolve_method(s.method) in THRESHOLD_METHODS:
                    kw["thresholds"] = tmap
                    st["thresholds"].append({"source": "map", "file": str(thresholds) if isinstance(
                        thresholds, os.PathLike) else "given"})
                elif thresholds == "input" and resolve_method(s.method) in THRESHOLD_METHODS:
                    # the recording's declared thresholds: the API applies them when the params state none
                    if params is not None:
                        params = {k: v for k, v in make_params(resolve_method(s.method), params).to_dict().items()
                                  if k not in THRESHOLD_KEYS}
                    kw["_record_input"] = True
                dt = 0
                if thresholds == "selfcal" and not method_spec(s.method).frames_only:
                    # the calibration of the recording without frame k (never the scored frame);
                    # frame k stands for tau_k + dt, so it is predicted there (next-frame: the
                    # input is cut just before that time)
                    if loo_k is None:
                        loo_k = r_k if tk == "leave_one_out" else holdout_input(rec, k, "leave_one_out")[0]
                    params, dt, used = selfcal_params(loo_k, s.method, params, profile, cache=calib_k)
                    st["thresholds"].append(used)
                    if dt:
                        r_k, t = holdout_input(rec, k, tk, time_offset_us=dt)
                if thresholds == "auto":
                    # next-frame: the filter sees only the data before tau_k; its two threshold
                    # numbers, a camera constant, come from the recording without frame k
                    if loo_k is None:
                        loo_k = r_k if tk == "leave_one_out" else holdout_input(rec, k, "leave_one_out")[0]
                    params, used = input_thresholds(loo_k, s.method, params, profile, cache=calib_k)
                    st["thresholds"].append(used)
                t0 = time.perf_counter()
                record_input = kw.pop("_record_input", False)
                kw.setdefault("thresholds", "input")  # resolved here: declared, else the method's own
                v = reconstruct(r_k, s.method, params, times_us=np.array([t], np.int64), mode=s.mode,
                                profile=profile, augment=s.augment, frame_time_offset_us=dt, **kw)
                if record_input:
                    st["thresholds"].append({"source": "input", "used": v.info.get(
                        "thresholds", "the method's own (the recording declares none)")})
                st["wall_s"] += time.perf_counter() - t0
                # the reconstruction is in the units of its input's median exposure (Frames.exposure_scale):
                # in frame k's own, the reference's (a factor of 1 when the exposures are equal)
                f_k = frames_k.units_factor(k, r_k.frames.reference_exposure() if r_k.frames is not None else None)
                st["frames"].append(_luminance(v.frames[0]) * f_k if f_k != 1.0 else _luminance(v.frames[0]))
            except Exception as e:  # reported per spec
                st["error"] = f"error: {type(e).__name__}: {e}"
                if log is not None:
                    log(f"{s.label} on frame {k}: {st['error']}")
    return out


def reference_frames(rec, held, profile=None, well_exposed=None):
    """``(references (n, H, W) float64 frame-linear, valid (n, H, W) bool, (lo, hi))`` of the
    held-out frames: the profile's ``CRF⁻¹(code)`` and the well-exposed codes."""
    fr = _trimmed_frames(rec)
    if profile is None:
        from ..reconstruct.api import source_profile
        profile = source_profile(rec)
    prof = profile_for_frames(load_profile(profile), fr)
    lo, hi = well_exposed_range(prof.max_code) if well_exposed is None else tuple(int(v) for v in well_exposed)
    sel = fr.select(np.asarray(held, np.int64))
    codes = np.asarray(frames_to_codes(sel, sel.shape))
    ref = prof.intensity(codes).astype(np.float64)
    valid = (codes >= lo) & (codes <= hi)
    return ref, valid, (lo, hi)


def score_frame(recon, reference, valid) -> dict:
    """MSE, PSNR (dB) and SSIM of one reconstruction on the ``valid`` pixels (module docstring)."""
    x = np.asarray(recon, np.float64)
    r = np.asarray(reference, np.float64)
    v = np.asarray(valid, bool)
    n_nonfinite = int(np.count_nonzero(~np.isfinite(x)))
    x = np.where(np.isfinite(x), x, 0.0)
    if DEFAULT_CLIP == "reference_max":
        x = np.clip(x, 0.0, 1.0)
    out = {"n_valid": int(v.sum()), "n_nonfinite": n_nonfinite}
    if not v.any():
        return {**out, "mse": float("nan"), "psnr_db": float("nan"), "ssim": float("nan")}
    mse = float(np.mean((x - r)[v] ** 2))
    smap, bw = ssim_map(x, r, 1.0)
    inner = np.zeros_like(v)
    inner[bw:-bw, bw:-bw] = True
    vi = v & inner
    out.update(mse=mse, psnr_db=float(10 * np.log10(1.0 / mse)) if mse > 0 else float("inf"),
               ssim=float(np.mean(smap[vi])) if vi.any() else float("nan"))
    return out


def _is_causal(spec: HoldoutSpec) -> bool:
    return spec.mode == "causal"


def evaluate_holdout(rec, methods, *, tasks=TASKS, held=None, profile=None, well_exposed=None, baselines=True,
                     log=None, thresholds: str | None = None, calibration_holdout: str = "frame") -> dict:
    """Score ``methods`` (HoldoutSpec list) and the baselines on held-out frames.

    Parameters
    ----------
    rec : Recording
    methods : sequence of HoldoutSpec
    tasks : subset of :data:`TASKS`; ``next_frame`` runs the causal specs only (others are listed
        as skipped) and the baselines.
    held : frame indices (into the frames up to the last event), default :func:`default_held_frames`
    thresholds : ``"params"`` (each method's own), ``"auto"`` (estimated on each input in the
        method's own log model; module docstring), ``"input"`` (what the recording declares),
        ``"selfcal"``, or a per-pixel threshold map (:func:`holdout_reconstructions`); None (default):
        :func:`default_thresholds_for`, what ``evaluate holdout`` does without ``--thresholds``
    calibration_holdout : ``"frame"`` or ``"scored"`` (:func:`holdout_reconstructions`)

    Returns
    -------
    dict: ``held`` (frame indices), ``t_us`` (their mid-exposures), ``well_exposed_codes``,
    ``n_events``, ``thresholds`` (the source used), and per task ``{"methods": {label: {"method", "mode", "role", "status",
    "per_frame": [{"frame", "t_us", "mse", "psnr_db", "ssim", "n_valid"}], "mean": {...}}}}``.
    """
    if thresholds is None:
        thresholds = default_thresholds_for(rec, methods)
    fr = _trimmed_frames(rec)
    held = default_held_frames(rec) if held is None else [int(k) for k in held]
    if not held:
        raise InputMismatchError("no frame to hold out: need frames with a neighbour on each side inside the events' span")
    ref, valid, (lo, hi) = reference_frames(rec, held, profile, well_exposed)
    specs = list(methods) + (list(BASELINES) if baselines else [])
    labels = [s.label for s in specs]
    if len(set(labels)) != len(labels):
        raise ValueError(f"method labels must be unique, got {labels}")
    rmax = float(np.nanmax(ref)) if np.isfinite(ref).any() else 1.0
    rmax = rmax if rmax > 0 else 1.0
    res = {"held": held, "t_us": [int(fr.t_mid_us[k]) for k in held], "well_exposed_codes": [lo, hi],
           "reference_max": rmax, "n_events": int(len(rec.events)), "n_frames_in_span": int(len(fr)),
           "thresholds": thresholds if isinstance(thresholds, str) else f"per-pixel map or profile {thresholds}"}
    for task in tasks:
        if task not in TASKS:
            raise ValueError(f"task must be one of {TASKS}, got {task!r}")
        run = [s for s in specs if task == "leave_one_out" or _is_causal(s) or s in BASELINES]
        recs = holdout_reconstructions(rec, run, task=task, held=held, profile=profile, log=log,
                                       thresholds=thresholds, calibration_holdout=calibration_holdout)
        rows = {}
        for s in specs:
            role = "baseline" if s in BASELINES else "method"
            if task == "next_frame" and s.method == "frames_linear":
                role = "baseline (non-causal: uses frame k+1)"
            row = {"method": s.method, "mode": s.mode, "role": role}
            if s not in run:
                row["status"] = f"skipped: next-frame prediction is for causal methods (mode {s.mode})"
                rows[s.label] = row
                continue
            st = recs[s.label]
            if st["error"] is not None:
                row["status"] = st["error"]
                rows[s.label] = row
                continue
            pf = []
            for i, k in enumerate(held):
                sc = score_frame(st["frames"][i] / rmax, ref[i] / rmax, valid[i])
                pf.append({"frame": int(k), "t_us": res["t_us"][i], **sc})
            row["per_frame"] = pf
            row["mean"] = {key: float(np.mean([p[key] for p in pf])) for key in ("mse", "psnr_db", "ssim")}
            row["wall_s"] = st["wall_s"]
            if any(u is not None for u in st["thresholds"]):
                row["thresholds"] = st["thresholds"]
            row["status"] = "ok"
            rows[s.label] = row
        res[task] = {"methods": rows}
    return res


def format_holdout(res: dict, title: str = "") -> str:
    """The tables of :func:`evaluate_holdout` as text (one per task)."""
    lines = []
    lo, hi = res["well_exposed_codes"]
    for task in TASKS:
        if task not in res:
            continue
        head = {"leave_one_out": "leave-one-frame-out (frame k withheld, reconstructed at its exposure centre)",
                "next_frame": "next-frame prediction (data before tau_k only, reconstructed at tau_k - 1 us)"}[task]
        lines.append(f"{title}{head}; frames {res['held']}; well-exposed codes {lo}-{hi}; both divided by the "
                     f"references' max {res['reference_max']:.4g}")
        lines.append(f"  {'':<24} {'MSE':>10} {'PSNR dB':>8} {'SSIM':>7}  role")
        for label, row in res[task]["methods"].items():
            if row["status"] != "ok":
                lines.append(f"  {label:<24} {row['status']}")
                continue
            m = row["mean"]
            lines.append(f"  {label:<24} {m['mse']:>10.3e} {m['psnr_db']:>8.2f} {m['ssim']:>7.4f}  {row['role']}")
        lines.append("")
    return "\n".join(lines).rstrip()
