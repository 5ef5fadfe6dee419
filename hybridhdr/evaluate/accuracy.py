"""Accuracy suites: every method side by side on the same data, scored as the paper scores.

Used by ``benchmarks/accuracy.py``; every piece is reusable on its own.

Scoring (:func:`score_run`), per method and suite:

- **unaltered** MSE, SSIM and PU21-SSIM (:mod:`hybridhdr.evaluate.metrics` with
  ``normalise="none"``: reconstruction and reference, both in frame-linear units, are divided by
  the reference maximum over the sequence; the reconstruction is not clipped, so overshoot and
  undershoot cost alike, as in the AKF authors' evaluation);
- the fraction of **non-positive** (or non-finite) reconstructed pixels, before any clipping;
- ``mse_share_worst_0p1pct``: the share of the MSE that the worst 0.1 % of pixels (over all
  frames) make (symmetric scoring lets a few overshooting pixels decide a linear MSE);
- **log-domain errors that separate HDR recovery from tracking**: ``log r ≈ a·log x + b``
  (``x = max(recon, 1e-6)``) fitted by least squares, once per sequence, on the pixels the
  current frame sees unclipped, then the RMSE of ``log r − (a·log x + b)`` on

  - ``well_exposed``: the pixels of the fit (the current frame sees them unclipped);
  - ``recoverable_causal``: the current frame clips them but an earlier frame saw them unclipped;
  - ``recoverable_offline``: the current frame clips them but some frame saw them unclipped;
  - ``all``: the whole image with its own fit over all pixels (reported, but misleading here:
    the fit trades the clipped pixels against the rest).

  "Clipped" means a code at or beyond the clip codes (``code <= lo`` or ``code >= hi``: 0 and the
  maximum code, or the AHDR ``code_clip``). The current frame of a reference is the frame whose
  mid-exposure is nearest to it (the references of the suites are at mid-exposures). Pixels
  whose reference is 0 (black in a rendered scene) have no log and are left out of these RMSEs.
  Every method is scored at the same reference times, those at or after the first event.

Suites: :func:`edge_sweep_suite` (:func:`hybridhdr.simulate.procedural.edge_sweep_recording`),
:func:`hdr_suite` (built-in Mitsuba scenes), :func:`ahdr_suite` (``build_ahdr``, codes outside
[100, 160] clipped), :func:`real_leave_one_out` (a real recording, each frame in turn withheld
and predicted at its exposure centre, scored against it on its well-exposed pixels) and
:func:`real_next_frame` (causal methods predict each frame from the data before it).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from ..reconstruct import AKFParams, reconstruct
from ..reconstruct.methods import method_spec
from ..simulate.procedural import edge_sweep_recording
from . import realdata as RD
from .datasets import event_log_change, load_dataset
from .metrics import normalise_pair, pu_ssim, ssim_map
from .metrics import pu21_encode
from .paper import paper_bench

__all__ = ["METHODS", "MethodSpec", "clip_masks", "recoverable_masks", "fit_log_affine", "log_errors",
           "score_run", "SuiteData", "edge_sweep_suite", "hdr_suite", "hdr_v2_suite", "ahdr_suite", "run_suite",
           "real_leave_one_out", "real_next_frame", "LOG_FLOOR", "event_log_change"]

#: Floor of the reconstruction before the log of the log-domain errors.
LOG_FLOOR = 1e-6


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """One column of the comparison: a label, the method and how it is run."""

    label: str
    method: str
    mode: str = "offline"
    augment: object = None
    preset: str | None = None  # AKFParams classmethod: "paper", "reference_code"


#: The methods compared in every suite (same settings everywhere; the sensor's nominal
#: threshold is passed where the dataset states it).
METHODS = (
    MethodSpec("frames_zoh", "frames_zoh", "causal"),
    MethodSpec("frames_linear", "frames_linear", "offline"),
    MethodSpec("cf", "cf", "causal"),
    MethodSpec("highpass", "highpass", "causal"),
    MethodSpec("direct", "direct", "causal"),
    MethodSpec("edi", "edi", "offline"),
    MethodSpec("akf", "akf", "offline"),
    MethodSpec("akf_causal", "akf", "causal"),
    MethodSpec("akf_aug", "akf", "offline", augment=True),  # frame augmentation (opt-in)
    MethodSpec("akf_forward", "akf", "forward"),  # one forward pass using the next frame
    MethodSpec("akf_paper", "akf", "offline", preset="paper"),
    MethodSpec("akf_refcode", "akf", "offline", preset="reference_code"),
)


def method_params(spec: MethodSpec, contrast_threshold: float | None):
    """The parameters of ``spec``: its preset (if any) with the sensor's nominal threshold."""
    if spec.preset is not None:
        kw = {} if contrast_threshold is None else {"contrast_threshold": float(contrast_threshold)}
        return getattr(AKFParams, spec.preset)(**kw)
    if contrast_threshold is None or method_spec(spec.method).frames_only:
        return None
    return {"contrast_threshold": float(contrast_threshold)}


# -- masks and the log-domain fit ---------------------------------------------------------------

def clip_masks(codes, lo: int, hi: int) -> np.ndarray:
    """Unclipped pixels of frame codes: ``lo < code < hi`` (bool, same shape)."""
    c = np.asarray(codes)
    return (c > lo) & (c < hi)


def recoverable_masks(unclipped_frames, current) -> dict:
    """Masks per reference from the frames' unclipped masks.

    Parameters
    ----------
    unclipped_frames : bool ndarray (F, H, W)
        Per frame, the pixels it sees unclipped (:func:`clip_masks`).
    current : int array (K,)
        Index of each reference's current frame.

    Returns
    -------
    dict of bool (K, H, W): ``well_exposed`` (the current frame sees it unclipped),
    ``recoverable_causal`` (the current frame clips it, an earlier frame saw it unclipped),
    ``recoverable_offline`` (the current frame clips it, some frame saw it unclipped).
    """
    u = np.asarray(unclipped_frames, dtype=bool)
    cur = np.asarray(current, dtype=np.int64)
    seen_before = np.zeros_like(u)
    if len(u) > 1:
        seen_before[1:] = np.logical_or.accumulate(u, axis=0)[:-1]
    seen_any = u.any(axis=0)
    well = u[cur]
    clipped = ~well
    return {"well_exposed": well, "recoverable_causal": clipped & seen_before[cur],
            "recoverable_offline": clipped & seen_any[None]}


def fit_log_affine(recon, reference, mask, floor: float = LOG_FLOOR) -> tuple[float, float]:
    """Least-squares ``(a, b)`` of ``log r ≈ a·log max(x, floor) + b`` over ``mask``.

    Non-finite pixels and non-positive references are left out; a constant ``log x`` gives
    ``a = 1`` with the offset only; no usable pixel gives ``(1, 0)``.
    """
    x = np.asarray(recon, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    m = np.asarray(mask, dtype=bool) & np.isfinite(x) & np.isfinite(r) & (r > 0)
    if not m.any():
        return 1.0, 0.0
    lx = np.log(np.maximum(x[m], floor))
    lr = np.log(r[m])
    mx, mr = float(lx.mean()), float(lr.mean())
    vx = float(np.mean((lx - mx) ** 2))
    if vx <= 1e-24:
        return 1.0, mr - mx
    a = float(np.mean((lx - mx) * (lr - mr)) / vx)
    return a, mr - a * mx


def log_errors(recon, reference, masks: dict, floor: float = LOG_FLOOR, fit=None) -> dict:
    """The log-domain errors of the module docstring.

    ``masks`` must hold ``well_exposed`` (the fit's pixels) and may hold any other named masks;
    pixels with a reference <= 0 are left out; returns ``log_fit_a``, ``log_fit_b``, ``log_rmse_<name>`` and ``n_<name>`` for each mask
    (NaN for an empty mask), plus ``log_rmse_all`` (own fit over all pixels). ``fit``: a given
    ``(a, b)`` instead of the fit on ``well_exposed`` (e.g. one frame scored with its sequence's fit).
    """
    x = np.asarray(recon, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    a, b = fit_log_affine(x, r, masks["well_exposed"], floor) if fit is None else (float(fit[0]), float(fit[1]))
    with np.errstate(invalid="ignore", divide="ignore"):
        lr = np.log(np.where(r > 0, r, np.nan))
        lx = np.log(np.maximum(np.where(np.isfinite(x), x, np.nan), floor))
    res = lr - (a * lx + b)
    out = {"log_fit_a": a, "log_fit_b": b}
    for name, m in masks.items():
        m = np.asarray(m, dtype=bool)
        e = res[m]
        out[f"n_{name}"] = int(m.sum())
        out[f"log_rmse_{name}"] = _rms(e)
    a2, b2 = fit_log_affine(x, r, np.ones(x.shape, bool), floor)
    e = lr - (a2 * lx + b2)
    out["log_rmse_all"] = _rms(e)
    return out


def _rms(e) -> float:
    """RMS of the finite entries (NaN when none: e.g. references of 0, whose log is undefined)."""
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")


def score_run(recon, reference, masks: dict, *, valid=None, peak_luminance_cd_m2: float = 4000.0) -> dict:
    """All numbers of one method on one sequence (module docstring).

    Parameters
    ----------
    recon, reference : (K, H, W) in frame-linear units, matched in time
    masks : dict of bool (K, H, W), with ``well_exposed`` (see :func:`recoverable_masks`)
    valid : bool (K, H, W), optional
        Pixels to score MSE/SSIM/PU21-SSIM on (the real suite: the held-out frame's well-exposed
        pixels); default all (SSIM: the map's mean without its border, as :func:`metrics.ssim`).
    """
    x = np.asarray(recon, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    out = {"n_frames": int(x.shape[0]),
           "nonpositive_frac": float(np.mean(~(np.isfinite(x) & (x > 0)))),
           "n_nonfinite": int(np.count_nonzero(~np.isfinite(x)))}
    t01, r01, info = normalise_pair(np.where(np.isfinite(x), x, 0.0), r, "none")
    out["reference_max"] = info["reference_max"]
    smap, bw = ssim_map(t01, r01, 1.0)
    pmap, _ = ssim_map(*(_pu(v * peak_luminance_cd_m2) for v in (t01, r01)), 256.0)
    if valid is None:
        out["mse"] = float(np.mean((t01 - r01) ** 2))
        # how fragile the MSE is: the share of it from the worst 0.1 % of pixels (over frames)
        se = np.sort(((t01 - r01) ** 2).ravel())[::-1]
        tot = float(se.sum())
        out["mse_share_worst_0p1pct"] = float(se[:max(1, se.size // 1000)].sum() / tot) if tot > 0 else 0.0
        out["ssim"] = float(np.mean(smap[:, bw:-bw, bw:-bw]))
        out["pu_ssim"] = float(pu_ssim(t01 * peak_luminance_cd_m2, r01 * peak_luminance_cd_m2))
    else:
        v = np.asarray(valid, dtype=bool)
        inner = np.zeros_like(v)
        inner[:, bw:-bw, bw:-bw] = True
        out["mse"] = float(np.mean((t01 - r01)[v] ** 2)) if v.any() else float("nan")
        vi = v & inner
        out["ssim"] = float(np.mean(smap[vi])) if vi.any() else float("nan")
        out["pu_ssim"] = float(np.mean(pmap[vi])) if vi.any() else float("nan")
        out["n_valid"] = int(v.sum())
    out.update(log_errors(x, r, masks))
    return out


def _pu(lum):
    return pu21_encode(lum)


# -- suites -------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True, eq=False)
class SuiteData:
    """One dataset of a suite: the recording (references in frame-linear units), the threshold
    the methods get, the camera profile, and the frames' clip codes."""

    name: str
    recording: object
    contrast_threshold: float | None
    profile: object
    clip_codes: tuple
    description: dict = dataclasses.field(default_factory=dict)


def _clip_codes(rec) -> tuple:
    prov = rec.metadata.provenance if rec.metadata is not None else {}
    cam = prov.get("camera") if isinstance(prov, dict) else None
    top = int(np.iinfo(rec.frames.images.dtype).max) if rec.frames.images.dtype.kind == "u" else 1
    if isinstance(cam, dict) and cam.get("code_clip") is not None:
        lo, hi = cam["code_clip"]
        return int(lo), int(hi)
    if isinstance(cam, dict) and cam.get("bit_depth"):
        top = (1 << int(cam["bit_depth"])) - 1
    return 0, top


def edge_sweep_suite(seeds=(0,), **kw) -> list[SuiteData]:
    """The edge sweep (:func:`hybridhdr.simulate.procedural.edge_sweep_recording`) for each seed."""
    out = []
    for s in seeds:
        rec, scene = edge_sweep_recording(int(s), **kw)
        f = rec.frames
        obj = np.stack([scene.object_mask(t) for t in f.t_mid_us])
        frac = float(np.mean(f.images[obj] == 255)) if obj.any() else float("nan")
        out.append(SuiteData(f"edge_sweep_s{s}", rec, rec.metadata.provenance["contrast_threshold"], None, (0, 255),
                             {"events": int(len(rec.events)), "object_clipped_frac": frac,
                              "saturated_fraction": float(np.mean(f.images == 255))}))
    return out


def _sim_suite(specs, cache_dir, seed=0) -> list[SuiteData]:
    out = []
    for spec in specs:
        d = load_dataset(spec, seed=seed, cache_dir=cache_dir)
        rec = d.recording
        lo, hi = _clip_codes(rec)
        desc = dict(d.description)
        desc["saturated_fraction"] = float(np.mean(~clip_masks(rec.frames.images, lo, hi)))
        out.append(SuiteData(spec["name"], rec, d.contrast_threshold, d.profile, (lo, hi), desc))
    return out


def hdr_specs(quick: bool = True, refractory_period_us: int | None = None) -> list[dict]:
    """The HDR set: the paper reproduction's built-in Mitsuba scenes, references at the frames'
    mid-exposures only (:func:`hybridhdr.evaluate.paper.paper_bench`).

    ``refractory_period_us`` (a diagnostic): the same scenes and renders with the event sensor's
    refractory period set to this value (names get ``|refractory=N``). The preset's 0.5 ms
    period loses the change a pixel sees while it is blind, so a sharp edge of ~10 log units
    sweeping across a pixel in a few ms reports only a fraction of it: the bright parts' level is
    then in no input, and no method can recover it."""
    ds = [dict(d) for d in paper_bench(quick)["datasets"] if d["name"].startswith("HDR-stress:")]
    for d in ds:
        d.pop("hdr_rate_hz", None)
        if refractory_period_us is not None:
            d["sensor.refractory_period_us"] = int(refractory_period_us)
            d["name"] = f"{d['name']}|refractory={int(refractory_period_us)}"
    return ds


def hdr_v2_specs(quick: bool = True) -> list[dict]:
    """HDR set v2 (:func:`hybridhdr.evaluate.paper.hdr_v2_datasets`): hand-held scenes with bright
    textured panes the camera sweeps over, the frames clipping them, a realistic sensor."""
    return [dict(d) for d in paper_bench(quick)["datasets"] if d["name"].startswith("HDR:")]


def ahdr_specs(quick: bool = True) -> list[dict]:
    """The AHDR set: ``build_ahdr`` of the paper reproduction (codes outside [100, 160] clipped)."""
    ds = [dict(d) for d in paper_bench(quick)["datasets"] if d["name"].startswith("AHDR:")]
    for d in ds:
        d.pop("hdr_rate_hz", None)
    return ds


def hdr_suite(quick: bool = True, cache_dir=None, seed: int = 0, refractory_period_us: int | None = None
              ) -> list[SuiteData]:
    return _sim_suite(hdr_specs(quick, refractory_period_us), cache_dir, seed)


def hdr_v2_suite(quick: bool = True, cache_dir=None, seed: int = 0) -> list[SuiteData]:
    return _sim_suite(hdr_v2_specs(quick), cache_dir, seed)


def ahdr_suite(quick: bool = True, cache_dir=None, seed: int = 0) -> list[SuiteData]:
    return _sim_suite(ahdr_specs(quick), cache_dir, seed)


def _current_frames(frames, t_us) -> np.ndarray:
    mid = np.asarray(frames.t_mid_us, dtype=np.int64)
    t = np.asarray(t_us, dtype=np.int64)
    j = np.clip(np.searchsorted(mid, t), 0, len(mid) - 1)
    jm = np.clip(j - 1, 0, len(mid) - 1)
    return np.where(np.abs(mid[jm] - t) <= np.abs(mid[j] - t), jm, j)


def _reconstruct(rec, spec: MethodSpec, c, profile, times):
    t0 = time.perf_counter()
    v = reconstruct(rec, spec.method, method_params(spec, c), times_us=times, mode=spec.mode, profile=profile,
                    augment=spec.augment, thresholds="input")  # the dataset's stated threshold, else the method's own
    return v, time.perf_counter() - t0


def run_suite(data: list[SuiteData], methods=METHODS, log=None) -> list[dict]:
    """Run every method on every dataset; one row per (dataset, method)."""
    rows = []
    for d in data:
        rec = d.recording
        lo, hi = d.clip_codes
        unc = clip_masks(rec.frames.images, lo, hi)
        # the same reference times for every method: those at or after the first event (an
        # events-only filter cannot start before it)
        keep = rec.hdr.t_us >= (int(rec.events["t"][0]) if len(rec.events) else 0)
        times = rec.hdr.t_us[keep]
        cur = _current_frames(rec.frames, times)
        masks = recoverable_masks(unc, cur)
        ref = rec.hdr.images if rec.hdr.images.ndim == 3 else rec.hdr.images.mean(axis=3)
        ref = ref[keep]
        for m in methods:
            row = {"dataset": d.name, "method": m.label, "events": int(len(rec.events))}
            try:
                v, wall = _reconstruct(rec, m, d.contrast_threshold, d.profile, times)
                if not np.array_equal(v.t_us, times):
                    raise RuntimeError(f"output times {v.t_us[:3]}... differ from the requested {times[:3]}...")
                row.update(score_run(v.frames, ref, masks))
                row["wall_s"] = wall
                row["events_per_s"] = len(rec.events) / wall if wall > 0 else float("nan")
                row["status"] = "ok"
            except Exception as e:  # reported, never hidden
                row["status"] = f"error: {type(e).__name__}: {e}"
            rows.append(row)
            if log is not None:
                log(row)
    return rows


# -- real data: leave one frame out -------------------------------------------------------------

#: Well-exposed codes of the held-out frame (8-bit).
REAL_WELL_EXPOSED = (20, 235)

#: Leave-one-out methods: the frames-only baselines are hold-previous (frames_zoh, causal) and
#: linear interpolation of k-1 and k+1 (frames_linear, offline).
REAL_BASELINES = {"frames_zoh": "hold previous frame", "frames_linear": "linear interpolation of k-1, k+1"}


def real_leave_one_out(rec, held=None, methods=METHODS, profile=None, contrast_threshold=None,
                       well_exposed=None, log=None, thresholds: str = "auto") -> list[dict]:
    """Leave-one-frame-out on a real recording.

    For each held-out frame k (default: every frame with a frame before and after it inside the
    events' time span), frame k is removed from the input and every method reconstructs at k's
    exposure centre; the reference is frame k linearised by the camera profile (frame-linear
    units), scored on its well-exposed pixels (codes ``well_exposed``, inclusive; default
    :data:`REAL_WELL_EXPOSED` scaled to the bit depth). Per method one
    row, pooled over the held-out frames (MSE, SSIM, PU21-SSIM and the log-domain error on the
    well-exposed pixels; the recoverable sets need ground truth where the frame clips, which real
    data lacks). Inputs and held-out frames: :mod:`hybridhdr.evaluate.realdata`.

    Only the frames inside the events' span are kept (the recording's other frames have no events
    around them).

    ``thresholds="auto"`` (default; a real recording does not state its thresholds): every event
    method's pooled ON/OFF thresholds are estimated on its input, in its own log model
    (:func:`hybridhdr.evaluate.realdata.input_thresholds`); ``"params"``: the methods' own (with
    ``contrast_threshold`` if given).
    """
    return _real_holdout(rec, "leave_one_out", "real_loo", held, methods, profile, contrast_threshold,
                         well_exposed, log, thresholds)


def real_next_frame(rec, held=None, methods=METHODS, profile=None, contrast_threshold=None,
                    well_exposed=None, log=None, thresholds: str = "auto") -> list[dict]:
    """Next-frame prediction on a real recording, for the causal methods of ``methods``.

    For each predicted frame k (default as :func:`real_leave_one_out`) the input is cut before it
    (frames 0..k-1, events before tau_k - 1 us) and every causal method (``mode == "causal"``)
    reconstructs at tau_k - 1 us; scored as :func:`real_leave_one_out`. ``frames_linear`` (needs
    frame k+1) is kept as the non-causal reference: it interpolates k-1 and k+1 as in the
    leave-one-out task. Other non-causal methods are left out. ``thresholds``: as
    :func:`real_leave_one_out` (estimated without frame k; the filter itself sees only the data before it).
    """
    causal = [m for m in methods if m.mode == "causal" or m.method == "frames_linear"]
    return _real_holdout(rec, "next_frame", "real_next", held, causal, profile, contrast_threshold,
                         well_exposed, log, thresholds)


def _real_holdout(rec, task, name, held, methods, profile, contrast_threshold, well_exposed, log,
                  thresholds="auto") -> list[dict]:
    held = RD.default_held_frames(rec) if held is None else [int(k) for k in held]
    ref, valid, _ = RD.reference_frames(rec, held, profile, well_exposed)
    specs = [RD.HoldoutSpec(m.label, m.method, m.mode, method_params(m, contrast_threshold), m.augment)
             for m in methods]
    recs = RD.holdout_reconstructions(rec, specs, task=task, held=held, profile=profile, thresholds=thresholds)
    rows = []
    for m in methods:
        st = recs[m.label]
        row = {"dataset": name, "method": m.label, "held_out": [int(k) for k in held],
               "events": int(len(rec.events))}
        if st["error"] is not None or not st["frames"]:
            row["status"] = st["error"] or "error: no held-out frame"
        else:
            x = np.stack(st["frames"])
            row.update(score_run(x, ref, {"well_exposed": valid}, valid=valid))
            row["wall_s"] = st["wall_s"]
            used = [u for u in st["thresholds"] if u is not None]
            if used:
                row["thresholds"] = used
            # each held-out frame re-reads the event stream (all of it, or up to the cut)
            if task == "next_frame":
                cuts = [RD.holdout_input(rec, k, "next_frame")[1] for k in held]
                n_read = int(np.searchsorted(rec.events["t"], cuts).sum())
            else:
                n_read = len(held) * len(rec.events)
            row["events_per_s"] = n_read / st["wall_s"] if st["wall_s"] > 0 else float("nan")
            row["status"] = "ok"
        rows.append(row)
        if log is not None:
            log(row)
    return rows


def summarise(rows) -> dict:
    """Mean of each number per (suite prefix, method) over ok rows: ``{dataset_group: {method: {...}}}``."""
    groups: dict = {}
    for r in rows:
        if r.get("status") != "ok":
            continue
        groups.setdefault(r["suite"], {}).setdefault(r["method"], []).append(r)
    out = {}
    for s, by in groups.items():
        out[s] = {}
        for m, rs in by.items():
            keys = [k for k, v in rs[0].items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
            d = {}
            for k in keys:
                vals = [float(r[k]) for r in rs if isinstance(r.get(k), (int, float)) and math.isfinite(float(r[k]))]
                d[k] = float(np.mean(vals)) if vals else float("nan")
            d["n_datasets"] = len(rs)
            out[s][m] = d
    return out
