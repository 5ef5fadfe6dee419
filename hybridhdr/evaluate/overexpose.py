"""HDR recovery on real recordings without an HDR reference: over-expose the frames after the fact.

``hybridhdr evaluate overexpose`` and ``benchmarks/accuracy.py``'s ``real_overexpose`` suite.

**The over-exposed recording** (:func:`overexpose_recording`): every frame's linear intensity
``I = CRF⁻¹(code)`` (the camera profile of the frames, :func:`hybridhdr.camera.profile_for_frames`:
the recording's declared profile, else the built-in one of the frames' encoding) is multiplied by
``gain``, encoded back through the same profile (``code = round(CRF(gain·I))``, the profile's
response inverted piecewise linearly) and clipped to the code range ``[0, max_code]`` (8 bits:
255). Events, triggers, times and metadata are untouched; the provenance notes the gain. The
**references** are the original frames' intensity × ``gain`` (float, unclipped), at the frames'
mid-exposure times τ_k (``Frames.t_mid_us``), in the frames' own layout (colour frames: RGB).

**Input and scored frames** (:func:`evaluate_overexpose`): as :mod:`~hybridhdr.evaluate.realdata`,
only the frames with τ_k up to the last event are kept (the others have no events around them);
every method gets the events and all these over-exposed frames, **frame k included** (its clipped
codes are the measurement the method has to complete), and reconstructs at τ_k. Scored by
default: every kept frame with an earlier kept frame (k ≥ 1, so hold-previous and the causal
class exist) and τ_k at or after the first event.

**Pixel classes** of scored frame k (codes: per pixel, its channel, or all three channels of a
colour frame; "unclipped" = every channel strictly between the profile's clip codes,
``clip_low_code < code < clip_high_code``, i.e. 0 < code < 255 for 8 bits; "well exposed" = every
channel in the well-exposed codes, 20-235 of 8 bits scaled to the bit depth,
:func:`~hybridhdr.camera.encoding.well_exposed_range`):

- ``recoverable_causal``: the over-exposed frame k clips the pixel, the ORIGINAL frame k shows it
  well exposed, and an earlier over-exposed frame j < k (kept frames only) saw it unclipped;
- ``recoverable_offline``: the same with any other over-exposed kept frame j ≠ k;
- ``well_exposed``: the over-exposed frame k shows it unclipped and the original frame k shows
  it well exposed.

**Scores** per method (reconstruction luminance for colour output; the pixel's own channel for
a mosaic frame), unaltered (the paper's practice): ``log r ≈ a·log max(x, 1e-6) + b`` fitted
once per (gain, method) by least squares over all scored frames, on the pixels the over-exposed
frame shows unclipped (:func:`hybridhdr.evaluate.accuracy.log_errors`, the fit of the accuracy
suites), then the RMSE of ``log r − (a·log x + b)`` on each class, pooled over the frames and per
frame (same fit), and on the fit's own pixels (``log_rmse_fit_pixels``, a diagnostic); the
ratio to ``frames_only`` per class (none where the frames-only error is below
:data:`RATIO_FLOOR`: the well-exposed class, where the frame is the reference); and the
fraction of non-positive or non-finite reconstructed pixels (before any floor). Baselines:
``frames_only`` (the clipped frame k itself, ``CRF⁻¹(code)``) and ``hold_previous`` (frame k−1,
causal). Memory: one method's reconstructions at the scored frames at a time.

**Parameters**: each method's own (``thresholds="params"``, the CLI defaults) or, with
``thresholds="auto"``, pooled ON/OFF thresholds estimated in the method's log model on the
over-exposed input **without frame k** (:func:`hybridhdr.evaluate.realdata.input_thresholds`).
``calibrate`` (a callable) is the hook for a self-calibration: called once per scored frame
with the over-exposed input without frame k, it returns overrides (:func:`apply_calibration`)
applied on top; what was used is recorded per frame. Neither ever sees the scored frame.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import os
import time

import numpy as np

from ..camera import load_profile, profile_for_frames
from ..camera.encoding import LUMINANCE_WEIGHTS, well_exposed_range
from ..errors import InputMismatchError, UsageError
from ..model import Frames, HDRReferences, Metadata, Recording
from ..reconstruct import reconstruct
from ..reconstruct.methods import METHODS as RECON_METHODS
from ..reconstruct.methods import make_params, methods_with, resolve_method
from . import realdata as RD
from .accuracy import LOG_FLOOR, log_errors, recoverable_masks

__all__ = ["CLASSES", "BASELINES", "OverexposeSpec", "default_specs", "FRAME_METHODS", "overexpose_recording",
           "pixel_classes", "default_scored_frames", "gain_key", "apply_calibration", "calibrated_on_original",
           "evaluate_overexpose",
           "format_overexpose", "per_frame_rows", "write_per_frame_csv", "plot_method"]

#: The pixel classes (module docstring), in the order of the tables.
CLASSES = ("recoverable_causal", "recoverable_offline", "well_exposed")

#: The frames-only baselines.
BASELINES = ("frames_only", "hold_previous")

#: Reconstruction methods that take frames (the events-only ones have no clipped frame to complete).
FRAME_METHODS = methods_with(needs_frames=True, uses_events=True)


@dataclasses.dataclass(frozen=True)
class OverexposeSpec:
    """One scored method: a label, the reconstruction method, its mode, parameters (Params, dict,
    TOML path or None: the method's defaults) and AKF frame augmentation (None: off)."""

    label: str
    method: str
    mode: str = "offline"
    params: object = None
    augment: object = None


def _label(method: str, mode: str) -> str:
    return method if mode == "offline" else f"{method}_{mode}"


def default_specs(methods=FRAME_METHODS, modes=("offline", "causal"), params: dict | None = None):
    """``(specs, skipped)``: every method in every mode it supports (EDI needs the whole exposure:
    no causal mode), labelled ``method`` (offline) or ``method_mode``. ``params``: per label or
    method name, that method's parameters. ``skipped``: ``{label: why}``."""
    params = params or {}
    specs, skipped = [], {}
    for m in methods:
        m = resolve_method(m)
        if not RECON_METHODS[m].needs_frames:
            raise InputMismatchError(f"method {m!r} takes no frames; overexpose scores methods that complete clipped "
                             f"frames: {', '.join(FRAME_METHODS)}")
        if RECON_METHODS[m].frames_only:
            raise UsageError(f"method {m!r} is a frames-only baseline; frames_only and hold_previous are always "
                             f"scored")
        for mode in modes:
            lab = _label(m, mode)
            if m == "edi" and mode == "causal":
                skipped[lab] = "EDI needs the events of the whole exposure: no causal mode"
                continue
            specs.append(OverexposeSpec(lab, m, mode, params.get(lab, params.get(m))))
    return specs, skipped


# -- the over-exposed recording -----------------------------------------------------------------

def _frames_profile(rec, profile):
    if profile is None:
        from ..reconstruct.api import source_profile
        profile = source_profile(rec)
    return profile_for_frames(load_profile(profile), rec.frames)


def _check_codes(fr: Frames, prof) -> None:
    im = fr.images
    if im.dtype.kind not in "ui":
        raise TypeError(f"overexpose needs integer frame codes (uint8, uint16), got frames of dtype {im.dtype}")
    from ..camera.profile import check_codes_in_profile
    check_codes_in_profile(im, prof)


def _encode(prof, intensity) -> np.ndarray:
    """``round(CRF(I))`` clipped to ``[0, max_code]`` (float64): the profile's response inverted
    piecewise linearly; an intensity at or above the clip code's intensity gives ``max_code``."""
    x = np.asarray(intensity, np.float64)
    top = prof.max_code
    if prof.inverse_crf is None:  # linear: CRF⁻¹(code) = code / max_code
        c = x * top
    else:
        lut = np.asarray(prof.inverse_crf, np.float64)
        vals, first = np.unique(lut, return_index=True)  # strictly increasing knots, lowest code of each
        c = np.interp(x, vals, first.astype(np.float64))
        c = np.where(x >= lut[prof.clip_high_code], float(top), c)
    return np.clip(np.rint(c), 0.0, float(top))


def overexpose_recording(rec, gain: float, *, profile=None) -> tuple[Recording, HDRReferences]:
    """``(recording, references)``: ``rec`` with every frame over-exposed ``gain`` times after the
    fact, and the references (module docstring).

    Parameters
    ----------
    rec : Recording with integer frames (mono (K, H, W) or colour (K, H, W, 3))
    gain : float > 0
        Factor on the frames' linear intensity (> 1 over-exposes).
    profile : CameraProfile, path or None
        The frames' camera profile; None: the recording's declared one, else the built-in one of
        the frames' encoding.

    Returns
    -------
    recording : Recording
        Same events, triggers, HDR references, times and metadata; frames re-encoded (same dtype
        and encoding); ``metadata.provenance["overexposed"]`` records the gain and the profile.
    references : HDRReferences
        Original ``CRF⁻¹(code) × gain`` per frame (unclipped, float32), ``t_us`` = τ_k.
    """
    if isinstance(gain, bool) or not isinstance(gain, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(gain)) or float(gain) <= 0:
        raise ValueError(f"gain must be a finite number > 0, got {gain!r}")
    gain = float(gain)
    fr = rec.frames
    if fr is None or len(fr) == 0:
        raise InputMismatchError("overexpose needs a recording with frames; this one has none")
    prof = _frames_profile(rec, profile)
    _check_codes(fr, prof)
    ref = prof.intensity(fr.images) * gain
    codes = _encode(prof, ref).astype(fr.images.dtype)
    new = Frames(codes, fr.t_start_us, fr.t_end_us, fr.gain, fr.iso, fr.encoding)
    md = rec.metadata if rec.metadata is not None else Metadata()
    prov = dict(md.provenance or {})
    prov["overexposed"] = {"gain": gain, "profile": prof.name, "max_code": int(prof.max_code),
                           "how": "frame codes re-encoded as round(CRF(gain * CRF^-1(code))) clipped to "
                                  "[0, max_code]; events untouched (hybridhdr.evaluate.overexpose)",
                           "clipped_fraction": float(np.mean(codes >= prof.clip_high_code))}
    out = dataclasses.replace(rec, frames=new, metadata=dataclasses.replace(md, provenance=prov))
    return out, HDRReferences(ref, fr.t_mid_us)


# -- classes ------------------------------------------------------------------------------------

def _per_pixel(mask) -> np.ndarray:
    """A per-channel mask (K, H, W, 3) as per pixel (every channel); (K, H, W) as is."""
    m = np.asarray(mask, bool)
    return m.all(axis=-1) if m.ndim == 4 else m


def pixel_classes(over_codes, orig_codes, scored, *, clip_codes, well_exposed) -> dict:
    """The classes of the module docstring, bool (n_scored, H, W) each.

    Parameters
    ----------
    over_codes, orig_codes : (F, H, W) or (F, H, W, 3) integer codes of the over-exposed and the
        original frames (the kept frames, in time order)
    scored : indices into the F frames
    clip_codes : (lo, hi): unclipped means ``lo < code < hi``
    well_exposed : (lo, hi): well exposed means ``lo <= code <= hi`` (inclusive)

    Also returns ``unclipped`` (the over-exposed frame k's unclipped pixels: the fit's pixels).
    """
    lo, hi = (int(v) for v in clip_codes)
    wlo, whi = (int(v) for v in well_exposed)
    oc, gc = np.asarray(over_codes), np.asarray(orig_codes)
    if oc.shape != gc.shape:
        raise ValueError(f"over-exposed codes {oc.shape} and original codes {gc.shape} differ in shape")
    unc = _per_pixel((oc > lo) & (oc < hi))
    good = _per_pixel((gc >= wlo) & (gc <= whi))
    cur = np.asarray(scored, np.int64)
    if cur.size and (cur.min() < 0 or cur.max() >= len(unc)):
        raise ValueError(f"scored frames {cur.tolist()} are not among the {len(unc)} frames")
    m = recoverable_masks(unc, cur)  # offline: clipped at k and unclipped in some frame, so some j != k
    g = good[cur]
    return {"recoverable_causal": m["recoverable_causal"] & g, "recoverable_offline": m["recoverable_offline"] & g,
            "well_exposed": m["well_exposed"] & g, "unclipped": m["well_exposed"]}


# -- the evaluation -----------------------------------------------------------------------------

def _kept(rec):
    """Indices of the frames with τ_k up to the last event (the input's frames)."""
    n = 0 if rec.frames is None else len(rec.frames)
    if n < 2:
        raise InputMismatchError(f"overexpose needs a recording with events and at least 2 frames; this one has {n} frame(s)")
    if len(rec.events) == 0:
        raise InputMismatchError(f"overexpose needs a recording with events and at least 2 frames; this one has {n} frames "
                         f"but no events")
    return np.flatnonzero(rec.frames.t_mid_us <= int(rec.events["t"][-1]))


def default_scored_frames(rec) -> list[int]:
    """Indices (into the kept frames) scored by default: k ≥ 1 with τ_k at or after the first event."""
    kept = _kept(rec)
    t0 = int(rec.events["t"][0])
    mid = rec.frames.t_mid_us[kept]
    return [k for k in range(1, len(kept)) if mid[k] >= t0]


def _luminance(img) -> np.ndarray:
    x = np.asarray(img, np.float64)
    return x @ np.asarray(LUMINANCE_WEIGHTS, np.float64) if x.ndim >= 3 and x.shape[-1] == 3 else x


def _as_reference_layout(img, ref_ndim: int, pattern) -> np.ndarray:
    """A reconstruction (H, W) or (H, W, 3) in the references' layout: luminance for RGB frames,
    the pixel's own channel for mosaic frames (``pattern``), as is for mono."""
    x = np.asarray(img, np.float64)
    if x.ndim == 3 and ref_ndim == 3:  # RGB output, mosaic (K, H, W) frames
        if pattern is None:
            return _luminance(x)
        from ..camera.cfa import channel_index
        ch = channel_index(pattern, x.shape[:2]).astype(np.int64)
        return np.take_along_axis(x, ch[..., None], axis=2)[..., 0]
    return _luminance(x)


def apply_calibration(spec: OverexposeSpec, params, overrides) -> tuple[object, dict, dict]:
    """``(params, reconstruct_kwargs, used)``: a calibration's ``overrides`` applied to ``spec``.

    ``overrides`` (what a ``calibrate`` callable returns; None = nothing): a dict with any of

    - ``"params"``: Params fields for every method that has them (others skip them);
    - ``"method_params"``: ``{label or method name: {field: value}}`` for one method (after ``params``);
    - ``"thresholds"``: a per-pixel threshold map for ``reconstruct(thresholds=...)``;
    - ``"profile"``: a camera profile for the reconstruction (the scoring keeps the frames' own);
    - ``"frame_time_offset_us"``: the time frame k stands for is τ_k + this offset (the method's
      input frames are shifted alike and it reconstructs there; frame methods included);
    - ``"note"``: a string, recorded.

    A dict without any of these keys is taken as ``"params"``.
    """
    keys = ("params", "method_params", "thresholds", "profile", "frame_time_offset_us", "note")
    if overrides is None:
        return params, {}, {}
    if not isinstance(overrides, dict):
        raise TypeError(f"calibrate must return a dict of overrides or None, got {type(overrides).__name__}")
    if not any(k in overrides for k in keys):
        overrides = {"params": overrides}
    bad = set(overrides) - set(keys)
    if bad:
        raise ValueError(f"calibrate returned unknown keys {sorted(bad)}; expected some of {keys}")
    p = make_params(spec.method, params)
    fields = set(p.to_dict())
    applied, skipped = {}, []
    for src in (overrides.get("params") or {}, (overrides.get("method_params") or {}).get(spec.method) or {},
                (overrides.get("method_params") or {}).get(spec.label) or {}):
        for k, v in src.items():
            if k in fields:
                applied[k] = v
            else:
                skipped.append(k)
    if applied:
        p = p.replace(**applied)
    kw = {k: overrides[k] for k in ("thresholds", "profile") if overrides.get(k) is not None}
    if overrides.get("frame_time_offset_us"):
        kw["frame_time_offset_us"] = int(overrides["frame_time_offset_us"])
    used = {"applied": {k: (float(v) if isinstance(v, (int, float, np.number)) and not isinstance(v, bool) else v)
                        for k, v in applied.items()}}
    if skipped:
        used["not_fields_of_method"] = sorted(set(skipped))
    for k in kw:
        used[k] = kw[k] if k == "frame_time_offset_us" else getattr(kw[k], "name", type(kw[k]).__name__)
    if overrides.get("note"):
        used["note"] = str(overrides["note"])[:500]
    return p, kw, used


def _without(rec_in, k):
    """The over-exposed input without its frame(s) k (for the calibration: never a scored frame)."""
    fr = rec_in.frames
    return dataclasses.replace(rec_in, frames=fr.select(np.setdiff1d(np.arange(len(fr)), np.atleast_1d(k))), hdr=None)


def calibrated_on_original(original, *, profile=None):
    """A ``calibrate`` callable for :func:`evaluate_overexpose`: the camera calibrated once on the
    well-exposed frames of ``original`` (the recording before :func:`overexpose_recording`).

    Given the over-exposed input without its held-out frame(s), it self-calibrates
    (:func:`hybridhdr.calibrate.resolve.resolve_thresholds`, ``"selfcal"``) the ORIGINAL recording
    restricted to the frames the input still has (matched by their exposure start), so the
    scored frame is never seen, clipped or not; the log offset I0, in the original frames' linear
    units, is scaled by the input's over-exposure gain (its frames read ``gain`` times brighter,
    as :func:`_profile_at_gain` does for a profile file). This is the "calibrate the camera once,
    on well-exposed footage, then reuse the model" workflow, against which the default
    (self-calibration of the clipped input itself) can be compared.

    Returns ``calibrate(rec_without_frame_k) -> overrides`` (:func:`apply_calibration`): the AKF's
    thresholds and I0 (``method_params["akf"]``: the model is the AKF's ``ln(I + I0)``; other
    methods keep their own parameters and take only the frame offset), ``frame_time_offset_us``
    and a ``note``; a recording the calibration cannot use raises ValueError naming why.
    """
    from ..calibrate.resolve import resolve_thresholds
    ts = np.asarray(original.frames.t_start_us)
    done = {}  # per set of original frames: its calibration (every gain of a run asks for the same sets)

    def calibrate(rec_in):
        have = np.asarray(rec_in.frames.t_start_us)
        keep = np.flatnonzero(np.isin(ts, have))
        if keep.size != have.size:
            raise ValueError(f"the input has {have.size} frames, {have.size - keep.size} of them not in the original "
                             f"recording (matched by exposure start): not an over-exposed copy of it")
        key = tuple(keep.tolist())
        if key not in done:
            sub = dataclasses.replace(original, frames=original.frames.select(keep), hdr=None)
            done[key] = resolve_thresholds(sub, "selfcal", profile=profile)
        got = done[key]
        gain = float((rec_in.metadata.provenance or {}).get("overexposed", {}).get("gain", 1.0))
        ov = got.overrides()
        if "intensity_offset" in ov:
            ov["intensity_offset"] = ov["intensity_offset"] * gain
        return {"method_params": {"akf": ov}, "frame_time_offset_us": int(got.frame_time_offset_us),
                "note": f"calibrated on the original's {keep.size} well-exposed frames; I0 x {gain:g}, the gain"}
    return calibrate


#: What a calibration leaves out of its input (``evaluate_overexpose(calibration_holdout=...)``):
#: the scored frame (one calibration per scored frame) or every scored frame (one calibration).
CALIBRATION_HOLDOUTS = ("frame", "scored")


def _profile_at_gain(path, spec, rec_in):
    """The sensor profile ``path`` resolved for ``spec`` on the over-exposed input ``rec_in``: its
    log offset I0 is in the original frames' linear units, and the input's frames read ``gain``
    times brighter (:func:`overexpose_recording`), so I0 is scaled by the gain; ``ln(I + I0)``
    then differs from the original's by the constant ``ln gain`` and the thresholds hold as they are."""
    from ..calibrate.resolve import resolve_thresholds
    method = resolve_method(spec.method)
    own_i0 = None if method == "akf" else getattr(make_params(method, spec.params), "intensity_offset", 0.0)
    got = resolve_thresholds(None, path, intensity_offset=own_i0)
    gain = float((rec_in.metadata.provenance or {}).get("overexposed", {}).get("gain", 1.0))
    if got.intensity_offset is not None and gain != 1.0:
        got = dataclasses.replace(got, intensity_offset=got.intensity_offset * gain,
                                  note=f"{got.note}; I0 × {gain:g}, the over-exposure gain")
    return got


def _run_spec(spec, rec_in, scored, tk, *, profile, thresholds, calibrate, cal_cache, ref_ndim, pattern,
              tmap=None, holdout="frame"):
    """``(frames (n, H, W) float64, wall_s, used per frame or None)`` of one spec; ``tmap``: the
    per-pixel threshold map every threshold method takes (``thresholds`` a map file)."""
    from ..calibrate.resolve import is_sensor_profile
    loo = thresholds in ("auto", "selfcal") or calibrate is not None
    if not loo:
        # without a map, the method's own parameters (and what the input declares), never
        # reconstruct's default self-calibration: that would read the scored frames
        use_map = tmap is not None and resolve_method(spec.method) in RD.THRESHOLD_METHODS
        kw_map = {"thresholds": tmap if use_map else "input"}
        dt = 0
        if use_map and is_sensor_profile(tmap):
            # a sensor profile states the time each frame stands for: frame k is reconstructed there,
            # as with the self-calibration (and reconstruct shifts every input frame alike)
            kw_map["thresholds"] = got = _profile_at_gain(tmap, spec, rec_in)
            dt = int(got.frame_time_offset_us)
        t0 = time.perf_counter()
        v = reconstruct(rec_in, spec.method, spec.params, times_us=tk + dt, mode=spec.mode, profile=profile,
                        augment=spec.augment, **kw_map)
        wall = time.perf_counter() - t0
        if not np.array_equal(v.t_us, tk + dt):
            raise RuntimeError(f"output times {v.t_us.tolist()} differ from the frames' times {tk.tolist()}")
        return np.stack([_as_reference_layout(f, ref_ndim, pattern) for f in v.frames]), wall, None
    out, used_all, wall = [], [], 0.0
    for i, k in enumerate(scored):
        params, used, kw = spec.params, {}, {}
        key = k if holdout == "frame" else "scored"
        if key not in cal_cache:
            cal_cache[key] = {"rec": _without(rec_in, k if holdout == "frame" else scored), "thr": {}}
        sub = cal_cache[key]
        dt = 0
        if thresholds == "auto":
            params, u = RD.input_thresholds(sub["rec"], spec.method, params, profile, cache=sub["thr"])
            used["thresholds"] = u
        elif thresholds == "selfcal" and not RECON_METHODS[resolve_method(spec.method)].frames_only:
            # the self-calibration of the input without frame k: frame k stands for tau_k + dt,
            # so the method reconstructs there (and every frame of its input is shifted alike)
            params, dt, u = RD.selfcal_params(sub["rec"], spec.method, params, profile, cache=sub["thr"])
            used["thresholds"] = u
        if calibrate is not None:
            if "overrides" not in sub:
                sub["overrides"] = calibrate(sub["rec"])
            params, kw, u = apply_calibration(spec, params, sub["overrides"])
            used["calibration"] = u
            dt += int(kw.get("frame_time_offset_us", 0))
        t0 = time.perf_counter()
        v = reconstruct(rec_in, spec.method, params, times_us=tk[i:i + 1] + dt, mode=spec.mode,
                        profile=kw.get("profile", profile), augment=spec.augment,
                        thresholds=kw.get("thresholds") if kw.get("thresholds") is not None else "input",
                        frame_time_offset_us=dt)
        wall += time.perf_counter() - t0
        if not np.array_equal(v.t_us, tk[i:i + 1] + dt):
            raise RuntimeError(f"output time {v.t_us.tolist()} differs from frame {k}'s {int(tk[i])} µs")
        out.append(_as_reference_layout(v.frames[0], ref_ndim, pattern))
        used_all.append({"frame": int(k), **used})
    return np.stack(out), wall, used_all


def _scores(x, ref, classes, frames_ids, t_us) -> dict:
    """Pooled and per-frame class errors of one reconstruction stack (module docstring)."""
    masks = {"well_exposed": classes["unclipped"], **{f"c_{c}": classes[c] for c in CLASSES}}
    e = log_errors(x, ref, masks)  # the fit's pixels are log_errors' "well_exposed": the unclipped ones
    fit = (e["log_fit_a"], e["log_fit_b"])
    finite_pos = np.isfinite(x) & (x > 0)
    out = {"log_fit": [fit[0], fit[1]],
           "log_rmse": {c: e[f"log_rmse_c_{c}"] for c in CLASSES},
           "n_pixels": {c: e[f"n_c_{c}"] for c in CLASSES},
           "log_rmse_fit_pixels": e["log_rmse_well_exposed"],
           "nonpositive_frac": float(np.mean(~finite_pos)),
           "n_nonfinite": int(np.count_nonzero(~np.isfinite(x))),
           "per_frame": []}
    for i in range(x.shape[0]):  # each frame with the sequence's fit
        ei = log_errors(x[i], ref[i], {"well_exposed": classes["unclipped"][i],
                                       **{c: classes[c][i] for c in CLASSES}}, fit=fit)
        out["per_frame"].append({"frame": int(frames_ids[i]), "t_us": int(t_us[i]),
                                 "nonpositive_frac": float(np.mean(~finite_pos[i])),
                                 **{c: {"n_pixels": ei[f"n_{c}"], "log_rmse": ei[f"log_rmse_{c}"]} for c in CLASSES}})
    return out


#: Below this frames-only log error (ln) no ratio is given: it is rounding only (the frames-only
#: well-exposed error is the re-quantisation of ``round(CRF(gain·I))``, exactly 0 up to float64
#: rounding, ~1e-16, for a linear profile and an integer gain), so a ratio to it means nothing.
RATIO_FLOOR = 1e-6


def gain_key(gain) -> str:
    """The key of a gain in ``evaluate_overexpose(...)["by_gain"]``: ``"4"``, ``"2.5"``."""
    return f"{float(gain):g}"


def _ratio(a, b) -> float:
    return float(a / b) if (math.isfinite(a) and math.isfinite(b) and b > RATIO_FLOOR) else float("nan")


def evaluate_overexpose(rec, gains, specs=None, *, frames=None, profile=None, thresholds: str | None = None,
                        calibrate=None, baselines: bool = True, skipped=None, keep_images: bool = False,
                        log=None, progress=None, calibration_holdout: str = "frame") -> dict:
    """Score ``specs`` and the baselines on ``rec`` over-exposed by each gain (module docstring).

    Parameters
    ----------
    rec : Recording with events and integer frames
    gains : sequence of float > 0
    specs : sequence of OverexposeSpec; default :func:`default_specs` (every frame method,
        offline and causal)
    frames : indices into the kept frames (τ_k up to the last event) to score, each ≥ 1; default
        :func:`default_scored_frames`
    profile : the frames' camera profile (default: the recording's, else built-in)
    thresholds : a per-pixel threshold map (a path to a ``.npz`` from ``calibrate thresholds`` or a
        ``ThresholdMap``, as ``reconstruct(thresholds=...)`` takes: every threshold method uses it),
        ``"params"`` (each method's own; ``"input"`` is the same here: with no parameters
        given, the method takes what the recording declares), ``"auto"`` (estimated without frame k) or
        ``"selfcal"`` (the event/frame self-calibration of the input without frame k,
        :func:`hybridhdr.evaluate.realdata.selfcal_params`: frame k is reconstructed at the time it
        stands for, τ_k + the calibrated offset); None (default): what ``evaluate overexpose`` does
        without ``--thresholds``, :func:`hybridhdr.evaluate.realdata.default_thresholds_for`
        (``"params"`` when a spec carries parameters, else the self-calibration or the recording's
        declared thresholds)
    calibrate : callable ``calibrate(recording_without_frame_k) -> overrides``
        (:func:`apply_calibration`), called once per scored frame and gain; None: no calibration
    calibration_holdout : ``"frame"`` (default) or ``"scored"``
        What the ``"auto"``/``"selfcal"`` thresholds and ``calibrate`` leave out of their input:
        the scored frame (one calibration per scored frame and gain) or every scored frame (one
        calibration per gain, shared by the scored frames: the same never-the-scored-frame rule
        at a fraction of the cost on recordings with many frames)
    skipped : ``{label: why}`` of specs left out (reported)
    keep_images : also return, under ``_images``, per (gain, label) the reconstruction of the figures'
        frame (the scored frame with the most recoverable-causal pixels) and that frame's data
    log : callable(str) for failures; progress : callable() after each (gain, method)

    Returns
    -------
    dict with ``frames`` (scored, indices into the kept frames), ``frame_indices`` (into the
    recording's frames), ``t_us``, ``well_exposed_codes``, ``clip_codes``, ``thresholds``,
    ``gains`` and ``by_gain``: per :func:`gain_key` ``{"counts": {class: n}, "counts_per_frame",
    "clipped_fraction", "methods": {label: {"method", "mode", "role", "status", "log_rmse",
    "ratio_to_frames_only", "n_pixels", "nonpositive_frac", "n_nonfinite", "log_fit",
    "wall_s", "per_frame", "used" (with thresholds="auto", "selfcal" or calibrate)}}}``.
    """
    from ..calibrate.resolve import is_sensor_profile
    if thresholds is None:
        thresholds = RD.default_thresholds_for(rec, specs if specs is not None else default_specs()[0])
    tmap = None
    if not isinstance(thresholds, str):  # a map, as reconstruct's and evaluate holdout's thresholds take
        tmap = thresholds
        if isinstance(thresholds, os.PathLike) and not is_sensor_profile(thresholds):
            # a sensor profile (.json) stays a path: reconstruct reads its camera model as it is
            from ..formats.thresholds import load_thresholds
            tmap = load_thresholds(thresholds)
    elif thresholds not in RD.THRESHOLD_SOURCES:
        raise ValueError(f"thresholds must be one of {RD.THRESHOLD_SOURCES} or a threshold map, got {thresholds!r}")
    if calibration_holdout not in CALIBRATION_HOLDOUTS:
        raise ValueError(f"calibration_holdout must be one of {CALIBRATION_HOLDOUTS}, got {calibration_holdout!r}")
    if calibrate is not None and not callable(calibrate):
        raise TypeError(f"calibrate must be a callable (recording without frame k -> overrides), got "
                        f"{type(calibrate).__name__}")
    gains = [float(g) for g in gains]
    if not gains:
        raise ValueError("give at least one gain")
    for g in gains:
        if not (math.isfinite(g) and g > 1):
            raise ValueError(f"gains must be finite and > 1 (a gain of 1 or less over-exposes nothing: no "
                             f"clipped pixel to recover), got {g!r}")
    if specs is None:
        specs, sk = default_specs()
        skipped = {**sk, **(skipped or {})}
    specs = list(specs)
    labels = [s.label for s in specs] + (list(BASELINES) if baselines else [])
    if len(set(labels)) != len(labels):
        raise ValueError(f"method labels must be unique (and not {BASELINES}), got {labels}")
    kept = _kept(rec)
    scored = default_scored_frames(rec) if frames is None else [int(k) for k in frames]
    if not scored:
        raise ValueError("no frame to score: need a frame after the first event with an earlier frame, both up "
                         "to the last event")
    bad = [k for k in scored if not 1 <= k < len(kept)]
    if bad:
        raise ValueError(f"scored frames {bad} are not among frames 1..{len(kept) - 1} (the frames up to the last "
                         f"event, k >= 1 so that an earlier frame exists)")
    if len(set(scored)) != len(scored) or scored != sorted(scored):
        raise ValueError(f"scored frames must be increasing and distinct, got {scored}")
    mid_all = rec.frames.t_mid_us[kept]
    for k in scored:  # a held-out frame is predicted from the others: none may share its instant
        same = [int(j) for j in np.flatnonzero(mid_all == mid_all[k]) if j != k]
        if same:
            raise ValueError(f"frame {k} has the mid-exposure time {int(mid_all[k])} µs of frame(s) {same[:5]}: a "
                             f"held-out frame cannot be scored at an instant another input frame covers (the "
                             f"recording's frame times are not distinct instants)")
    fr_all = rec.frames.select(kept)
    rec_k = dataclasses.replace(rec, frames=fr_all, hdr=None)
    prof = _frames_profile(rec_k, profile)
    lo, hi = well_exposed_range(prof.max_code)
    clip = (int(prof.clip_low_code), int(prof.clip_high_code))
    md = rec.metadata
    pattern = getattr(md.frame_camera, "cfa", None) or getattr(md.event_camera, "cfa", None)
    t_us = fr_all.t_mid_us[scored]
    res = {"frames": scored, "frame_indices": [int(kept[k]) for k in scored], "t_us": [int(t) for t in t_us],
           "n_frames_kept": int(len(kept)), "n_events": int(len(rec.events)), "well_exposed_codes": [lo, hi],
           "clip_codes": list(clip), "profile": prof.name,
           "thresholds": thresholds if isinstance(thresholds, str) else (f"sensor profile {thresholds}" if is_sensor_profile(thresholds) else f"per-pixel map {thresholds}"),
           "calibrate": None if calibrate is None else getattr(calibrate, "__name__", type(calibrate).__name__),
           "calibration_holdout": calibration_holdout,
           "fit": "log r = a log max(x, %g) + b, least squares once per (gain, method) over the scored frames' "
                  "pixels the over-exposed frame shows unclipped" % LOG_FLOOR,
           "gains": gains, "skipped": dict(skipped or {}), "by_gain": {}}
    images = {}
    for g in gains:
        over, refs = overexpose_recording(rec_k, g, profile=prof)
        # every method reads its input's frames in the units of their median exposure
        # (Frames.exposure_scale): each scored frame's reconstruction goes to that frame's own units,
        # the reference's (all factors 1 when the exposures are equal)
        ref_ex = over.frames.reference_exposure()
        units = np.array([fr_all.units_factor(k, ref_ex) for k in scored])
        ref_ndim = refs.images.ndim
        ref_all = prof.intensity(fr_all.images) * g  # = refs.images in float64 (no float32 rounding)
        ref = np.stack([_luminance(r) for r in ref_all[scored]]) if ref_ndim == 4 else ref_all[scored]
        over_lin = prof.intensity(over.frames.images)
        cls = pixel_classes(over.frames.images, fr_all.images, scored, clip_codes=clip, well_exposed=(lo, hi))
        gres = {"counts": {c: int(cls[c].sum()) for c in CLASSES},
                "counts_per_frame": {c: [int(v) for v in cls[c].sum(axis=(1, 2))] for c in CLASSES},
                "clipped_fraction": float(np.mean(~cls["unclipped"])), "methods": {}}
        fig_i = int(np.argmax(cls["recoverable_causal"].sum(axis=(1, 2))))  # the figures' frame
        base = None

        def record(lab, row, x, wall, used):
            nonlocal base
            sc = _scores(x, ref, cls, scored, t_us)
            row.update(status="ok", log_rmse=sc["log_rmse"], n_pixels=sc["n_pixels"],
                       log_rmse_fit_pixels=sc["log_rmse_fit_pixels"], nonpositive_frac=sc["nonpositive_frac"],
                       n_nonfinite=sc["n_nonfinite"], log_fit=sc["log_fit"], wall_s=wall, per_frame=sc["per_frame"])
            if used is not None:
                row["used"] = used
            if lab == "frames_only":
                base = row
            if keep_images:
                images[(g, lab)] = x[fig_i]

        if baselines:
            for lab, ks in (("frames_only", scored), ("hold_previous", [k - 1 for k in scored])):
                x = over_lin[ks]
                x = np.stack([_luminance(v) for v in x]) if ref_ndim == 4 else x
                gres["methods"][lab] = row = {"method": "frames", "mode": "causal", "role": "baseline"}
                record(lab, row, x, 0.0, None)
        cal_cache = {}
        for s in specs:
            gres["methods"][s.label] = row = {"method": s.method, "mode": s.mode, "role": "method"}
            try:
                x, wall, used = _run_spec(s, over, scored, t_us, profile=profile, thresholds=thresholds,
                                          calibrate=calibrate, cal_cache=cal_cache, holdout=calibration_holdout,
                                          ref_ndim=ref_ndim, pattern=pattern, tmap=tmap)
            except Exception as e:  # reported per method, never hidden
                row["status"] = f"error: {type(e).__name__}: {e}"
                if log is not None:
                    log(f"gain {g:g}, {s.label}: {row['status']}")
            else:
                if np.any(units != 1.0):
                    x = x * units.reshape((-1,) + (1,) * (x.ndim - 1))
                record(s.label, row, x, wall, used)
                x = None  # one method's stack at a time
            if progress is not None:
                progress()
        for lab, row in gres["methods"].items():
            if row.get("status") != "ok":
                continue
            if base is None:
                row["ratio_to_frames_only"] = {c: float("nan") for c in CLASSES}
                continue
            row["ratio_to_frames_only"] = {c: _ratio(row["log_rmse"][c], base["log_rmse"][c]) for c in CLASSES}
            for pf, bf in zip(row["per_frame"], base["per_frame"]):
                for c in CLASSES:
                    pf[c]["ratio_to_frames_only"] = _ratio(pf[c]["log_rmse"], bf[c]["log_rmse"])
        if keep_images:
            images[(g, "_data")] = {"frame_index": fig_i, "reference": ref[fig_i],
                                    "over_codes": over.frames.images[scored[fig_i]],
                                    "orig_codes": fr_all.images[scored[fig_i]],
                                    "classes": {c: cls[c][fig_i] for c in cls}, "max_code": prof.max_code}
        res["by_gain"][gain_key(g)] = gres
    if keep_images:
        res["_images"] = images
    return res


# -- outputs ------------------------------------------------------------------------------------

def _f(v, fmt="{:.3f}"):
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)


def _x(r) -> str:
    return f" ({r:.2f}x)" if isinstance(r, float) and math.isfinite(r) else "        "


def format_overexpose(res: dict, title: str = "") -> str:
    """The tables of :func:`evaluate_overexpose` as text, one per gain."""
    lines = []
    for g in res["gains"]:
        gr = res["by_gain"][gain_key(g)]
        n = gr["counts"]
        lines.append(f"{title}gain {g:g}: frames {res['frames']} (recording frames {res['frame_indices']}); "
                     f"pixels recoverable causal {n['recoverable_causal']}, offline {n['recoverable_offline']}, "
                     f"well-exposed {n['well_exposed']}; over-exposed frames clip {gr['clipped_fraction']:.1%}")
        lines.append(f"  log RMSE after a*log x + b (x frames_only); thresholds: {res['thresholds']}"
                     + (f"; calibrate: {res['calibrate']}" if res.get("calibrate") else ""))
        lines.append(f"  {'method':<16} {'rec. causal':>15} {'rec. offline':>15} {'well-exposed':>15} "
                     f"{'non-pos':>8} {'wall s':>7}")
        for lab, row in gr["methods"].items():
            if row["status"] != "ok":
                lines.append(f"  {lab:<16} {row['status'][:200]}")
                continue
            cells = [_f(row["log_rmse"][c]) + _x(row["ratio_to_frames_only"][c]) for c in CLASSES]
            lines.append(f"  {lab:<16} " + " ".join(f"{c:>15}" for c in cells)
                         + f" {row['nonpositive_frac']:>8.1e} {row['wall_s']:>7.2f}")
        for lab, why in res.get("skipped", {}).items():
            lines.append(f"  {lab:<16} skipped: {why}")
        lines.append("")
    return "\n".join(lines).rstrip()


def per_frame_rows(res: dict) -> list[dict]:
    """One row per (gain, method, frame, class): n_pixels, log_rmse, ratio_to_frames_only."""
    rows = []
    for g in res["gains"]:
        for lab, row in res["by_gain"][gain_key(g)]["methods"].items():
            if row.get("status") != "ok":
                continue
            for pf in row["per_frame"]:
                for c in CLASSES:
                    rows.append({"gain": g, "method": lab, "frame": pf["frame"], "t_us": pf["t_us"], "class": c,
                                 "n_pixels": pf[c]["n_pixels"], "log_rmse": pf[c]["log_rmse"],
                                 "ratio_to_frames_only": pf[c].get("ratio_to_frames_only", float("nan")),
                                 "nonpositive_frac": pf["nonpositive_frac"]})
    return rows


def write_per_frame_csv(res: dict, path) -> None:
    """The per-frame rows as CSV (written atomically)."""
    from .._util.atomic import write_text_atomic
    rows = per_frame_rows(res)
    cols = ["gain", "method", "frame", "t_us", "class", "n_pixels", "log_rmse", "ratio_to_frames_only",
            "nonpositive_frac"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in r.items()})
    write_text_atomic(path, buf.getvalue())


def plot_method(res: dict, gain: float, label: str, path) -> None:
    """A PNG of one method at one gain, for the scored frame with the most recoverable-causal
    pixels (ties: the earliest): the original frame, the over-exposed frame, the reconstruction
    (``exp(a log x + b)``, the fit of the scores, on the reference's log scale) and the log error
    ``log r − (a log x + b)`` (diverging, ±1 ln) on the classes' pixels (others grey), the
    recoverable classes outlined and every class's count and error listed. Needs ``keep_images``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    from .._util.atomic import atomic_path
    data = res["_images"][(gain, "_data")]
    x = res["_images"][(gain, label)]
    row = res["by_gain"][gain_key(gain)]["methods"][label]
    cls = data["classes"]
    i = data["frame_index"]
    a, b = row["log_fit"]
    ref = data["reference"]
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(np.where(ref > 0, ref, np.nan))
        lx = a * np.log(np.maximum(np.where(np.isfinite(x), x, np.nan), LOG_FLOOR)) + b
    err = lr - lx
    fin = lr[np.isfinite(lr)]
    vmin, vmax = (float(np.percentile(fin, 1)), float(fin.max())) if fin.size else (-5.0, 0.0)
    m = data["max_code"]

    def grey(codes):
        c = np.asarray(codes, np.float64)
        return _luminance(c) if c.ndim == 3 else c

    fig, axs = plt.subplots(1, 4, figsize=(16, 4.2), constrained_layout=True)
    k = res["frames"][i]
    pf = row["per_frame"][i]
    axs[0].imshow(grey(data["orig_codes"]), cmap="gray", vmin=0, vmax=m)
    axs[0].set_title(f"original frame {k} (codes)")
    axs[1].imshow(grey(data["over_codes"]), cmap="gray", vmin=0, vmax=m)
    axs[1].set_title(f"over-exposed x{gain:g} (codes)")
    im2 = axs[2].imshow(lx, cmap="gray", vmin=vmin, vmax=vmax)
    axs[2].set_title(f"{label}: a ln x + b (a={a:.2f}, b={b:.2f})")
    fig.colorbar(im2, ax=axs[2], shrink=0.8, label="ln intensity (reference scale)")
    scored_px = cls["recoverable_offline"] | cls["well_exposed"]  # the causal class is inside the offline one
    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="0.8")  # pixels of no class: light grey
    im3 = axs[3].imshow(np.where(scored_px, err, np.nan), cmap=cmap, vmin=-1.0, vmax=1.0)
    fig.colorbar(im3, ax=axs[3], shrink=0.8, label="ln r - (a ln x + b)")
    colours = {"recoverable_causal": "lime", "recoverable_offline": "orange", "well_exposed": "magenta"}
    handles = []
    for c, col in colours.items():
        mk = cls[c]
        if c == "recoverable_offline":
            mk = mk & ~cls["recoverable_causal"]  # outline only what the causal class lacks
        if mk.any() and c != "well_exposed":
            axs[3].contour(mk.astype(float), levels=[0.5], colors=col, linewidths=0.7)
        handles.append(Line2D([0], [0], color=col, lw=1.5 if c != "well_exposed" else 0,
                              label=f"{c}: {pf[c]['n_pixels']} px, {_f(pf[c]['log_rmse'])} ln"
                                    + (" (not outlined)" if c == "well_exposed" else "")))
    axs[3].set_title(f"log error, frame {k} (grey: no class)")
    axs[3].legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.04), fontsize=7, frameon=False)
    for ax in axs:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"{label}, gain {gain:g}: recoverable causal {_f(row['log_rmse']['recoverable_causal'])}, "
                 f"offline {_f(row['log_rmse']['recoverable_offline'])}, well-exposed "
                 f"{_f(row['log_rmse']['well_exposed'])} ln (all scored frames); non-positive "
                 f"{row['nonpositive_frac']:.1e}")
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
