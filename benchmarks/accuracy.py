"""Accuracy of every reconstruction method side by side, scored as the paper scores.

Usage: ``python benchmarks/accuracy.py [--quick]``. Prints a table per suite, then ONE JSON object
on the last line.

Suites (same method settings everywhere; the sensor's nominal threshold is passed where the data
states one, nothing is tuned per scene), all in frame-linear units (1.0 = the frame camera's clip
level at the frame's exposure), references at the frames' mid-exposures:

- ``edge_sweep``: :func:`hybridhdr.simulate.procedural.edge_sweep_recording` (64x48, a bright textured
  object 3-12x the clip level sweeping across a textured background, ideal events c = 0.1,
  20 Hz gamma-2.2 8-bit frames clipping the whole object); seed 0 (``--quick``) or 0, 1, 2;
- ``hdr_v2``: HDR set v2 (``hybridhdr.evaluate.paper.hdr_v2_datasets``): the hand-held Mitsuba
  scenes window_scenery, lamp_shade, sunlit_facade (bright textured panes 10^2-10^4x the shadows
  that the camera sweeps over, frames clipping them, the realistic sensor profile
  ``hybridhdr.simulate.builtin.REALISTIC_SENSOR``) at the quick (173x130) or full (346x260) size;
  the acceptance targets are measured on it;
- ``hdr``: the ``HDR-stress`` set, the former HDR scenes (dark_room_window, night_drive_sign,
  fast_object_bright_background: hard 10^4 edges the events cannot follow) at the quick (48x36)
  or full (128x96) size, with the ``event_log_change`` diagnostic beside it;
- ``ahdr``: ``build_ahdr`` stills (3:1, 10:1) with codes outside [100, 160] clipped;
- ``real``: ``ecd_slider_depth`` leave-one-frame-out (each frame with neighbours inside the events'
  span withheld and predicted at its exposure centre, scored on its well-exposed codes 20-235);
  the recording states no thresholds, so every event method's pooled ON/OFF thresholds are
  estimated without frame k in the method's own log model (``evaluate.realdata.input_thresholds``);
- ``real_next``: ``ecd_slider_depth`` next-frame prediction for the causal methods (the same frames,
  each predicted at tau_k - 1 us from the frames and events before it; ``frames_zoh`` is
  hold-previous, ``frames_linear`` the non-causal interpolation shown for reference).
  ``--quick`` scores only the methods the checks read (``QUICK_REAL_METHODS``; the
  ``real_overexpose`` suites AKF and CF on ``ecd_slider_depth``, the AKF on ``davis346_street``,
  with the baselines); the full run scores every method.

Numbers per method and suite (:mod:`hybridhdr.evaluate.accuracy`): unaltered MSE, SSIM and
PU21-SSIM, the fraction of non-positive pixels, events/s, and log-domain RMSEs after
``a·log x + b`` fitted on the pixels the current frame sees unclipped: on those pixels
(well-exposed), on pixels the current frame clips but an earlier frame saw (recoverable, causal)
or any frame saw (recoverable, offline); the whole-image log-RMSE after its own fit is reported
but misleading (the fit trades clipped pixels against the rest).

- ``real_overexpose``: two real sensors with their frames over-exposed after the fact
  (:mod:`hybridhdr.evaluate.overexpose`: linear intensity x gain, re-encoded, clipped; events
  untouched), every frame method in offline and causal mode with its CLI-default parameters,
  scored at the frames' times against the original frames x gain: log RMSE (after
  ``a·log x + b`` on the unclipped pixels) on the pixels the over-exposed frame clips but the
  original shows well exposed and an earlier (recoverable causal) or any other (recoverable
  offline) frame saw, and on the well-exposed pixels; ratios to the clipped frame itself
  (``frames_only``), pixel counts, non-positive fraction. ``ecd_slider_depth`` (DAVIS240C, no
  exposures stamped): gains 2, 4 and 8 (``--quick``: 4), every frame inside the events, each calibrated without
  itself. ``davis346_street`` (DAVIS346, AEDAT4, 500 µs exposures stamped): gain 4 (``--quick``)
  or 2, 4, 8, on 6 (``--quick``) or 12 scored frames evenly spread over the 58 inside the events,
  with one calibration per gain that leaves every scored frame out (``calibration_holdout=
  "scored"``: one per scored frame would cost 12 calibrations of 59 frames). Beside the defaults
  (self-calibrated on the clipped input), the AKF rows ``once_akf``/``once_akf_causal`` use the
  camera calibrated once on the recording's original, well-exposed frames without the scored
  one(s), its I0 x the gain (:func:`hybridhdr.evaluate.overexpose.calibrated_on_original`: the
  "calibrate once, reuse the profile" workflow). Each recording is skipped, with the reason, when
  its sample data is absent.

Diagnostics, not targets: ``hdr_no_refractory`` (the same HDR renders with the event sensor's
0.5 ms refractory period off) and ``event_log_change`` (per HDR dataset, how much of a > 2 ln-unit
brightening the events report: the refractory period re-references the pixel, so the change
during it is lost, and where every frame clips no method can recover it).

Simulated datasets are cached in ``benchmarks/_data/accuracy/`` (keyed by their parameters). The
first (cold) run renders the Mitsuba scenes (about a minute with the scalar fallback); warm
``--quick`` runs take well under a minute. Mitsuba is rendered in a child process first: when
its JIT variant aborts (LLVM < 19 on some machines) the renders are retried with
``HYBRIDHDR_MITSUBA_VARIANT=scalar_rgb``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED_DATA  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DATA = Path(__file__).resolve().parent / "_data" / "accuracy"
ECD = SHARED_DATA / "ecd_slider_depth"
STREET = SHARED_DATA / "aedat4" / "davis346_street.aedat4"

COLS = (("mse", "MSE", "{:.3e}"), ("ssim", "SSIM", "{:.3f}"), ("pu_ssim", "PU-SSIM", "{:.3f}"),
        ("nonpositive_frac", "non-pos", "{:.1e}"), ("events_per_s", "Mev/s", None),
        ("log_rmse_well_exposed", "log well", "{:.3f}"), ("log_rmse_recoverable_causal", "log rec.causal", "{:.3f}"),
        ("log_rmse_recoverable_offline", "log rec.offline", "{:.3f}"), ("log_rmse_all", "log all*", "{:.3f}"))


def _log(*a):
    print(*a, file=sys.stderr, flush=True)


def _fmt(v, f):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if f is None:
        return f"{v / 1e6:.3g}"
    return f.format(v)


def _render_cache(quick: bool) -> dict:
    """Build (or find) the cached HDR datasets in a child process; retry with the scalar variant."""
    code = ("import sys; sys.path.insert(0, %r); from hybridhdr.evaluate.accuracy import hdr_suite; "
            "hdr_suite(%r, cache_dir=%r); hdr_suite(%r, cache_dir=%r, refractory_period_us=0); "
            "from hybridhdr.evaluate.accuracy import hdr_v2_suite; hdr_v2_suite(%r, cache_dir=%r)"
            % (str(Path(__file__).resolve().parents[1]), quick, str(DATA), quick, str(DATA), quick, str(DATA)))
    t0 = time.perf_counter()
    before = set(DATA.glob("*.h5"))
    info = {"variant_env": os.environ.get("HYBRIDHDR_MITSUBA_VARIANT")}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if r.returncode != 0 and not os.environ.get("HYBRIDHDR_MITSUBA_VARIANT"):
        tail = (r.stderr or "").strip().splitlines()[-1:] or [""]
        _log(f"  Mitsuba render failed with the default variant (exit {r.returncode}: {tail[0][:120]}); "
             f"retrying with HYBRIDHDR_MITSUBA_VARIANT=scalar_rgb")
        os.environ["HYBRIDHDR_MITSUBA_VARIANT"] = "scalar_rgb"
        info["variant_env"] = "scalar_rgb (fallback after a crash)"
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"rendering the HDR set failed (exit {r.returncode}): "
                           + " | ".join((r.stderr or "").strip().splitlines()[-3:]))
    info["cold"] = bool(set(DATA.glob("*.h5")) - before)
    info["render_s"] = time.perf_counter() - t0
    return info


def _table(suite, rows, methods):
    head = ["method"] + [c[1] for c in COLS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in methods:
        r = rows.get(m)
        if r is None:
            continue
        lines.append("| " + " | ".join([m] + [_fmt(r.get(k), f) for k, _, f in COLS]) + " |")
    return "\n".join(lines)


def _mean_rows(rows):
    """Mean per method over a suite's datasets (ok rows); errors kept as status."""
    by = {}
    for r in rows:
        by.setdefault(r["method"], []).append(r)
    out = {}
    for m, rs in by.items():
        ok = [r for r in rs if r.get("status") == "ok"]
        d = {"n_datasets": len(ok), "status": "ok" if len(ok) == len(rs) else
             "; ".join(sorted({r['status'] for r in rs if r.get('status') != 'ok'}))}
        keys = {k for r in ok for k, v in r.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        for k in sorted(keys):
            vals = [float(r[k]) for r in ok if isinstance(r.get(k), (int, float)) and math.isfinite(float(r[k]))]
            d[k] = float(np.mean(vals)) if vals else float("nan")
        out[m] = d
    return out


def _targets(s) -> dict:
    """The lead's acceptance checks, as measured (never tuned for)."""
    t = {}

    def g(suite, m, k):
        return s.get(suite, {}).get(m, {}).get(k, float("nan"))
    f = g("edge_sweep", "frames_zoh", "log_rmse_recoverable_causal")
    a = g("edge_sweep", "akf_causal", "log_rmse_recoverable_causal")
    t["edge_akf_causal_rec_causal_le_0.1x_frames"] = {"akf_causal": a, "frames_zoh": f, "ratio": a / f,
                                                      "pass": bool(a <= 0.1 * f)}
    # HDR set v2 (the stress set, ``hdr``, is a diagnostic: see _diagnostics)
    am, cm, fm = g("hdr_v2", "akf", "mse"), g("hdr_v2", "cf", "mse"), g("hdr_v2", "frames_zoh", "mse")
    asim, csim, fsim = g("hdr_v2", "akf", "ssim"), g("hdr_v2", "cf", "ssim"), g("hdr_v2", "frames_zoh", "ssim")
    t["hdr_v2_akf_mse_48pct_below_cf"] = {"akf": am, "cf": cm, "reduction_pct": 100 * (cm - am) / cm,
                                          "pass": bool(am <= 0.52 * cm)}
    t["hdr_v2_akf_ssim_11pct_above_cf"] = {"akf": asim, "cf": csim, "improvement_pct": 100 * (asim - csim) / csim,
                                           "pass": bool(asim >= 1.11 * csim)}
    t["hdr_v2_akf_mse_30pct_below_frames_and_ssim_higher"] = {
        "akf_mse": am, "frames_mse": fm, "reduction_pct": 100 * (fm - am) / fm, "akf_ssim": asim, "frames_ssim": fsim,
        "pass": bool(am <= 0.70 * fm and asim > fsim)}
    ah = s.get("ahdr", {})
    ok = {m: d for m, d in ah.items() if math.isfinite(d.get("mse", float("nan")))}
    if ok and "akf" in ok:
        # the default AKF against every method that is not an AKF variant; the overall best is shown too
        others = {m: d for m, d in ok.items() if not m.startswith("akf")}
        bo_mse = min(others, key=lambda m: others[m]["mse"])
        bo_ssim = max(others, key=lambda m: others[m]["ssim"])
        t["ahdr_akf_best"] = {"akf_mse": ok["akf"]["mse"], "best_other_mse": f"{bo_mse} {others[bo_mse]['mse']:.4g}",
                              "akf_ssim": ok["akf"]["ssim"],
                              "best_other_ssim": f"{bo_ssim} {others[bo_ssim]['ssim']:.4g}",
                              "best_overall_mse": min(ok, key=lambda m: ok[m]["mse"]),
                              "best_overall_ssim": max(ok, key=lambda m: ok[m]["ssim"]),
                              "pass": bool(ok["akf"]["mse"] < others[bo_mse]["mse"]
                                           and ok["akf"]["ssim"] > others[bo_ssim]["ssim"])}
    rm = {m: g("real", m, "mse") for m in ("akf_causal", "frames_zoh", "cf", "akf", "frames_linear")}
    t["real_akf_causal_beats_hold_and_cf"] = {**{k: rm[k] for k in ("akf_causal", "frames_zoh", "cf")},
                                              "pass": bool(rm["akf_causal"] < rm["frames_zoh"]
                                                           and rm["akf_causal"] < rm["cf"])}
    t["real_akf_offline_beats_linear"] = {"akf": rm["akf"], "frames_linear": rm["frames_linear"],
                                          "pass": bool(rm["akf"] < rm["frames_linear"])}
    nm = {m: g("real_next", m, "mse") for m in ("akf_causal", "frames_zoh", "cf")}
    t["real_next_akf_causal_beats_hold_and_cf"] = {**nm, "pass": bool(nm["akf_causal"] < nm["frames_zoh"]
                                                                      and nm["akf_causal"] < nm["cf"])}
    # a filter worth using on real data: the causal AKF's next-frame MSE at least 20 % below causal CF's, and below hold-previous's
    t["real_next_akf_causal_20pc_below_cf"] = {"akf_causal_over_cf": nm["akf_causal"] / nm["cf"],
                                               "pass": bool(nm["akf_causal"] <= 0.8 * nm["cf"]
                                                            and nm["akf_causal"] < nm["frames_zoh"])}
    # frame augmentation never hurts: akf_aug against akf on every target suite (MSE and SSIM)
    aug = {}
    for su in ("edge_sweep", "hdr_v2", "ahdr", "real"):
        pm, am_, ps, as_ = g(su, "akf", "mse"), g(su, "akf_aug", "mse"), g(su, "akf", "ssim"), g(su, "akf_aug", "ssim")
        if all(math.isfinite(v) for v in (pm, am_, ps, as_)):
            aug[su] = {"mse_ratio": am_ / pm, "ssim_ratio": as_ / ps}
    t["akf_aug_not_worse_than_akf"] = {**{f"{su}_{k}": round(v, 4) for su, d in aug.items() for k, v in d.items()},
                                       "pass": bool(aug) and all(d["mse_ratio"] <= 1.0 and d["ssim_ratio"] >= 1.0
                                                                 for d in aug.values())}
    bad = {f"{su}/{m}": (d.get("nonpositive_frac"), d.get("n_nonfinite")) for su, dd in s.items()
           for m, d in dd.items() if (d.get("nonpositive_frac") or 0) > 0 or (d.get("n_nonfinite") or 0) > 0}
    t["no_nonpositive_or_nan"] = {"offenders": bad, "pass": not bad}
    return t


def _diagnostics(s) -> dict:
    """What the HDR set can show: the same scenes with the sensor's refractory period off."""
    d = {}
    for suite in ("hdr_v2", "hdr", "hdr_no_refractory"):
        g = s.get(suite, {})
        if not all(m in g for m in ("akf", "cf", "frames_zoh")):
            continue
        a, c, f = g["akf"], g["cf"], g["frames_zoh"]
        d[f"{suite}_akf_vs_cf_and_frames"] = {
            "akf_mse": a["mse"], "cf_mse": c["mse"], "frames_mse": f["mse"],
            "mse_below_cf_pct": 100 * (c["mse"] - a["mse"]) / c["mse"],
            "mse_below_frames_pct": 100 * (f["mse"] - a["mse"]) / f["mse"],
            "ssim_above_cf_pct": 100 * (a["ssim"] - c["ssim"]) / c["ssim"],
            "ssim_above_frames_pct": 100 * (a["ssim"] - f["ssim"]) / f["ssim"]}
    return d


def _event_log_change(data) -> dict:
    """``hybridhdr.evaluate.accuracy.event_log_change`` per dataset of a suite (those with a result)."""
    from hybridhdr.evaluate.accuracy import event_log_change
    out = {}
    for d in data:
        v = event_log_change(d.recording, d.contrast_threshold)
        if v is not None:
            out[d.name] = v
    return out


#: Label prefix of the real_overexpose rows whose camera model is calibrated once on the
#: recording's original (well-exposed) frames without the scored one (OE.calibrated_on_original).
ONCE = "once_"
#: The AKF rows of the real_overexpose checks that every row must pass (well exposed, non-positive).
AKF_ROWS = ("akf", "akf_causal", ONCE + "akf", ONCE + "akf_causal")

#: Gains of the real_overexpose suite.
OVEREXPOSE_GAINS = (2.0, 4.0, 8.0)


#: Scored frames of davis346_street in the real_overexpose suite: (quick, full), evenly spread.
STREET_FRAMES = (6, 12)


def _street_frames(rec, n: int) -> list[int]:
    """``n`` of the default scored frames of ``rec``, evenly spread (the first and the last included)."""
    from hybridhdr.evaluate import overexpose as OE
    sc = OE.default_scored_frames(rec)
    return sorted({sc[int(i)] for i in np.linspace(0, len(sc) - 1, min(n, len(sc))).round()})


#: --quick: the methods of the real-data suites the checks read (the full run scores every method).
QUICK_REAL_METHODS = ("frames_zoh", "frames_linear", "cf", "akf", "akf_causal", "akf_aug")
QUICK_OVEREXPOSE_METHODS = ("akf", "cf")
#: --quick on davis346_street: the AKF only (its checks; each method's log model costs a calibration of 59 frames).
QUICK_STREET_METHODS = ("akf",)


def _real_overexpose(rec, name: str = "ecd_slider_depth", gains=OVEREXPOSE_GAINS, frames=None,
                     calibration_holdout: str = "frame", methods=None) -> dict:
    """The ``real_overexpose`` suite on one recording: per gain and method the three class errors,
    the ratios to frames_only, the class counts and the non-positive fraction (plus the text table)."""
    from hybridhdr.evaluate import overexpose as OE
    from hybridhdr.evaluate.realdata import default_threshold_source
    # every frame method, offline and causal, CLI defaults (self-calibrated where the recording declares
    # no thresholds)
    specs, skipped = OE.default_specs() if methods is None else OE.default_specs(methods)
    r = OE.evaluate_overexpose(rec, gains, specs, frames=frames, thresholds=default_threshold_source(rec),
                               calibration_holdout=calibration_holdout, skipped=skipped)
    # the camera calibrated once on the recording's well-exposed (original) frames, never the
    # scored one, its I0 x the gain (OE.calibrated_on_original): the AKF, causal and two-sided
    once = OE.evaluate_overexpose(
        rec, gains, [OE.OverexposeSpec(ONCE + "akf", "akf", "offline"), OE.OverexposeSpec(ONCE + "akf_causal", "akf", "causal")],
        frames=frames, thresholds="params", calibrate=OE.calibrated_on_original(rec),
        calibration_holdout=calibration_holdout)  # its baselines are the defaults' (the same frames): their ratios
    for g in r["gains"]:
        r["by_gain"][OE.gain_key(g)]["methods"].update(
            {lab: row for lab, row in once["by_gain"][OE.gain_key(g)]["methods"].items() if lab.startswith(ONCE)})
    out = {"recording": name, "frames": r["frames"], "t_us": r["t_us"], "thresholds": r["thresholds"],
           "calibration_holdout": calibration_holdout, "fit": r["fit"],
           "skipped_methods": r["skipped"], "table": OE.format_overexpose(r, f"{name}, "), "gains": {}}
    for g in r["gains"]:
        gr = r["by_gain"][OE.gain_key(g)]
        d = {"counts": gr["counts"], "clipped_fraction": gr["clipped_fraction"], "methods": {}}
        for lab, row in gr["methods"].items():
            if row.get("status") != "ok":
                d["methods"][lab] = {"status": row.get("status")}
                continue
            d["methods"][lab] = {**{f"log_rmse_{c}": row["log_rmse"][c] for c in OE.CLASSES},
                                 **{f"ratio_{c}": row["ratio_to_frames_only"][c] for c in OE.CLASSES},
                                 **{f"n_{c}": row["n_pixels"][c] for c in OE.CLASSES},
                                 "nonpositive_frac": row["nonpositive_frac"], "n_nonfinite": row["n_nonfinite"],
                                 "wall_s": row["wall_s"], "status": "ok"}
        out["gains"][OE.gain_key(g)] = d
    return out


def _sim_to_real(v2_data, real) -> dict:
    """The sim-to-real figure (does the simulator predict the real sensor's recovery?): the real_overexpose protocol (gain 4, CLI defaults) on each
    HDR set v2 recording (simulated with the measured DAVIS240C profile) beside the real
    ecd_slider_depth figure; the ratio of the two recoverable ratios (1 = the simulator predicts the
    real sensor's recovery; no pass mark)."""
    from hybridhdr.evaluate import overexpose as OE
    from hybridhdr.evaluate.realdata import default_threshold_source
    specs = [OE.OverexposeSpec("akf", "akf", "offline"), OE.OverexposeSpec("akf_causal", "akf", "causal")]
    sims = {}
    for d in v2_data:
        rec = d.recording
        try:
            r = OE.evaluate_overexpose(rec, [4.0], specs, thresholds=default_threshold_source(rec),
                                       profile=d.profile)
            m = r["by_gain"]["4"]["methods"]
            sims[d.name] = {"akf_causal_ratio_recoverable_causal": m["akf_causal"]["ratio_to_frames_only"]["recoverable_causal"],
                            "akf_ratio_recoverable_offline": m["akf"]["ratio_to_frames_only"]["recoverable_offline"],
                            "n_recoverable_causal": r["by_gain"]["4"]["counts"]["recoverable_causal"]}
        except Exception as e:  # reported; the figure is for watching
            sims[d.name] = {"error": f"{type(e).__name__}: {e}"[:300]}
    ok = [v for v in sims.values() if "error" not in v]
    out = {"sim": sims}
    rm = (real or {}).get("gains", {}).get("4", {}).get("methods", {})
    if ok and rm:
        sc = float(np.nanmean([v["akf_causal_ratio_recoverable_causal"] for v in ok]))
        so = float(np.nanmean([v["akf_ratio_recoverable_offline"] for v in ok]))
        rc, ro = rm["akf_causal"]["ratio_recoverable_causal"], rm["akf"]["ratio_recoverable_offline"]
        out.update({"sim_mean_ratio_causal": sc, "real_ratio_causal": rc, "sim_over_real_causal": sc / rc,
                    "sim_mean_ratio_offline": so, "real_ratio_offline": ro, "sim_over_real_offline": so / ro})
    return out


def _overexpose_targets(ro) -> dict:
    """The ecd_slider_depth real_overexpose checks at gain 4 (measured, not tuned for)."""
    m = ro.get("gains", {}).get("4", {}).get("methods", {})
    if not m:
        return {}

    def g(lab, k):
        return m.get(lab, {}).get(k, float("nan"))
    t = {"akf_causal_rec_causal_le_0.6x_frames": {"ratio": g("akf_causal", "ratio_recoverable_causal"),
                                                  "pass": bool(g("akf_causal", "ratio_recoverable_causal") <= 0.6)},
         "akf_causal_rec_causal_le_0.65x_frames": {"ratio": g("akf_causal", "ratio_recoverable_causal"),
                                                   "pass": bool(g("akf_causal", "ratio_recoverable_causal") <= 0.65)},
         # the camera calibrated once on the well-exposed frames (never the scored one), I0 x gain
         "calibrated_once_akf_causal_rec_causal_le_0.65x_frames": {
             "ratio": g(ONCE + "akf_causal", "ratio_recoverable_causal"),
             "pass": bool(g(ONCE + "akf_causal", "ratio_recoverable_causal") <= 0.65)},
         "calibrated_once_two_sided_le_causal_rec_causal": {
             "akf": g(ONCE + "akf", "log_rmse_recoverable_causal"),
             "akf_causal": g(ONCE + "akf_causal", "log_rmse_recoverable_causal"),
             "pass": bool(g(ONCE + "akf", "log_rmse_recoverable_causal")
                          <= g(ONCE + "akf_causal", "log_rmse_recoverable_causal"))},
         "two_sided_le_causal_rec_causal": {"akf": g("akf", "log_rmse_recoverable_causal"),
                                            "akf_causal": g("akf_causal", "log_rmse_recoverable_causal"),
                                            "pass": bool(g("akf", "log_rmse_recoverable_causal")
                                                         <= g("akf_causal", "log_rmse_recoverable_causal"))},
         "akf_rec_offline_le_0.55x_frames": {"ratio": g("akf", "ratio_recoverable_offline"),
                                             "pass": bool(g("akf", "ratio_recoverable_offline") <= 0.55)},
         "akf_well_exposed_le_0.08": {**{k: g(k, "log_rmse_well_exposed") for k in AKF_ROWS},
                                      "pass": bool(max(g(k, "log_rmse_well_exposed") for k in AKF_ROWS) <= 0.08)},
         "akf_no_nonpositive": {**{k: g(k, "nonpositive_frac") for k in AKF_ROWS},
                                "pass": all(g(k, "nonpositive_frac") == 0 for k in AKF_ROWS)}}
    return t


#: The default before frames were read as exposure means and the camera model was unified: the
#: causal and two-sided AKF's recoverable-causal log RMSE on davis346_street x4, the quick frames
#: (1, 12, 24, 35, 47, 58), self-calibrated once without them (measured on main f7f0db6 with this
#: suite's protocol). A reference for the ">= 10 % better" check, not a result of this run.
STREET_BEFORE = {"akf_causal": 0.113, "akf": 0.112}


def _street_targets(rs) -> dict:
    """The davis346_street checks at gain 4 (measured, not tuned for)."""
    m = rs.get("gains", {}).get("4", {}).get("methods", {})
    if not m:
        return {}

    def g(lab, k):
        return m.get(lab, {}).get(k, float("nan"))
    c = g("akf_causal", "log_rmse_recoverable_causal")
    o = g("akf", "log_rmse_recoverable_causal")
    c1 = g(ONCE + "akf_causal", "log_rmse_recoverable_causal")
    o1 = g(ONCE + "akf", "log_rmse_recoverable_causal")
    t = {"akf_causal_rec_causal_10pct_below_before": {
            "log_rmse": c, "before": STREET_BEFORE["akf_causal"], "ratio": c / STREET_BEFORE["akf_causal"],
            "pass": bool(c <= 0.9 * STREET_BEFORE["akf_causal"]) and rs.get("frames") == [1, 12, 24, 35, 47, 58]},
         "calibrated_once_akf_causal_rec_causal_10pct_below_before": {
            "log_rmse": c1, "before": STREET_BEFORE["akf_causal"], "ratio": c1 / STREET_BEFORE["akf_causal"],
            "pass": bool(c1 <= 0.9 * STREET_BEFORE["akf_causal"]) and rs.get("frames") == [1, 12, 24, 35, 47, 58]},
         "calibrated_once_two_sided_le_causal_rec_causal": {"akf": o1, "akf_causal": c1, "pass": bool(o1 <= c1)},
         "two_sided_le_causal_rec_causal": {"akf": o, "akf_causal": c, "pass": bool(o <= c)},
         "akf_well_exposed_le_0.08": {**{k: g(k, "log_rmse_well_exposed") for k in AKF_ROWS},
                                      "pass": bool(max(g(k, "log_rmse_well_exposed") for k in AKF_ROWS) <= 0.08)},
         "akf_no_nonpositive": {**{k: g(k, "nonpositive_frac") for k in AKF_ROWS},
                                "pass": all(g(k, "nonpositive_frac") == 0 for k in AKF_ROWS)}}
    return t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="quick sizes, one edge-sweep seed (< 60 s when cached)")
    args = ap.parse_args()
    t_start = time.perf_counter()
    from hybridhdr.evaluate import accuracy as A

    DATA.mkdir(parents=True, exist_ok=True)
    res = {"benchmark": "accuracy", "quick": bool(args.quick),
           "scoring": "unaltered (normalise=none), references in frame-linear units; log errors after a·log x+b "
                      "fitted per sequence on the current frame's unclipped pixels",
           "loadavg": list(os.getloadavg())}
    methods = [m.label for m in A.METHODS]
    _log("rendering / loading the HDR set ...")
    try:
        res["render"] = _render_cache(args.quick)
    except Exception as e:  # reported; the other suites still run
        res["render"] = {"error": str(e)}
    suites = {}
    t = time.perf_counter()
    suites["edge_sweep"] = A.edge_sweep_suite(seeds=(0,) if args.quick else (0, 1, 2))
    if "error" not in res["render"]:
        suites["hdr_v2"] = A.hdr_v2_suite(args.quick, cache_dir=DATA)
        suites["hdr"] = A.hdr_suite(args.quick, cache_dir=DATA)
        suites["hdr_no_refractory"] = A.hdr_suite(args.quick, cache_dir=DATA, refractory_period_us=0)
    suites["ahdr"] = A.ahdr_suite(args.quick, cache_dir=DATA)
    res["data_s"] = time.perf_counter() - t
    res["datasets"] = {d.name: {k: v for k, v in d.description.items()
                                if k in ("events", "saturated_fraction", "object_clipped_frac", "gt_units",
                                         "gt_exposure_varies", "gt_scale_min", "renders", "simulate_wall_s",
                                         "sensor", "width", "height", "spp")} | {"clip_codes": list(d.clip_codes)}
                       for ds in suites.values() for d in ds}
    res["event_log_change"] = {name: _event_log_change(suites[name]) for name in ("hdr_v2", "hdr", "hdr_no_refractory")
                               if name in suites}
    all_rows = {}
    for name, data in suites.items():
        _log(f"suite {name}: {len(data)} dataset(s)")
        t = time.perf_counter()
        all_rows[name] = A.run_suite(data)
        res[f"{name}_s"] = time.perf_counter() - t
    if ECD.exists():
        import hybridhdr
        t = time.perf_counter()
        rec = hybridhdr.read(ECD)
        from hybridhdr.evaluate.realdata import default_threshold_source
        thr = default_threshold_source(rec)  # the CLI defaults: self-calibration (ecd declares no thresholds)
        real_methods = A.METHODS if not args.quick else tuple(m for m in A.METHODS if m.label in QUICK_REAL_METHODS)
        all_rows["real"] = A.real_leave_one_out(rec, methods=real_methods, thresholds=thr)
        res["real_s"] = time.perf_counter() - t
        res["real_held_out_frames"] = all_rows["real"][0].get("held_out")
        t = time.perf_counter()
        all_rows["real_next"] = A.real_next_frame(rec, methods=real_methods, thresholds=thr)
        res["real_next_s"] = time.perf_counter() - t
        t = time.perf_counter()
        # --quick: the gain the targets are set at (the full run adds 2 and 8)
        res["real_overexpose"] = _real_overexpose(rec, gains=(4.0,) if args.quick else OVEREXPOSE_GAINS,
                                                  methods=QUICK_OVEREXPOSE_METHODS if args.quick else None)
        res["real_overexpose_s"] = time.perf_counter() - t
    else:
        res["real_error"] = f"{ECD} not found"
        res["real_overexpose"] = {"skipped": f"{ECD} not found (the ../shared sample data is absent)"}
    if STREET.exists():
        import hybridhdr
        t = time.perf_counter()
        srec = hybridhdr.read(STREET)
        res["real_overexpose_street"] = _real_overexpose(
            srec, "davis346_street", gains=(4.0,) if args.quick else OVEREXPOSE_GAINS,
            frames=_street_frames(srec, STREET_FRAMES[0] if args.quick else STREET_FRAMES[1]),
            calibration_holdout="scored", methods=QUICK_STREET_METHODS if args.quick else None)
        res["real_overexpose_street_s"] = time.perf_counter() - t
    else:
        res["real_overexpose_street"] = {"skipped": f"{STREET} not found (the ../shared sample data is absent)"}
    if "hdr_v2" in suites:
        t = time.perf_counter()
        res["sim_to_real"] = _sim_to_real(suites["hdr_v2"], res.get("real_overexpose"))
        res["sim_to_real_s"] = time.perf_counter() - t
        _log("sim-to-real (overexpose x4 on HDR set v2 vs ecd_slider_depth): "
             + json.dumps({k: v for k, v in res["sim_to_real"].items() if k != "sim"}, default=float))
    summary = {name: _mean_rows(rows) for name, rows in all_rows.items()}
    res["per_dataset"] = {name: [{k: v for k, v in r.items() if k in ("dataset", "method", "status", "mse", "ssim",
                                                                      "log_rmse_recoverable_causal",
                                                                      "nonpositive_frac", "mse_share_worst_0p1pct")}
                                 for r in rows] for name, rows in all_rows.items()}
    res["summary"] = summary
    res["targets"] = _targets(summary)
    res["diagnostics"] = _diagnostics(summary)
    res["runtime_s"] = time.perf_counter() - t_start
    for name in summary:
        print(f"\n## {name}" + {"edge_sweep": " (edge sweep, ideal events c=0.1, object 3-12x clip)",
                                 "hdr_v2": " (HDR set v2: hand-held Mitsuba scenes, realistic sensor, mean of 3)",
                                 "hdr": " (HDR-stress: the former Mitsuba HDR scenes, hard edges; mean of 3)",
                                 "hdr_no_refractory": " (diagnostic, not a target: the same HDR renders with the event "
                                                      "sensor's 0.5 ms refractory period off)", "ahdr": " (AHDR, codes [100,160], mean of 2)",
                                 "real": f" (ecd_slider_depth leave-one-frame-out, frames {res.get('real_held_out_frames')}"
                                         f", well-exposed pixels only)",
                                 "real_next": f" (ecd_slider_depth next-frame prediction, causal methods: frames "
                                              f"{res.get('real_held_out_frames')} predicted from the data before them "
                                              f"at tau_k - 1 us; frames_linear is the non-causal interpolation of "
                                              f"k-1, k+1)"}.get(name, ""))
        print(_table(name, summary[name], methods))
        if name in ("hdr_v2", "hdr", "hdr_no_refractory", "ahdr"):
            for dname in sorted({r["dataset"] for r in all_rows[name]}):
                rr = {r["method"]: r for r in all_rows[name] if r["dataset"] == dname and r.get("status") == "ok"}
                dd = res["datasets"][dname]
                rn = f", {dd['renders']} renders" if "renders" in dd else ""
                print(f"  {dname} (clipped {dd['saturated_fraction']:.0%}{rn}): MSE / SSIM " + ", ".join(
                    f"{m} {rr[m]['mse']:.3e} / {rr[m]['ssim']:.3f}" for m in ("frames_zoh", "cf", "akf", "akf_causal")
                    if m in rr) + (f"; akf MSE share of its worst 0.1 % px {rr['akf']['mse_share_worst_0p1pct']:.0%}"
                                   if "mse_share_worst_0p1pct" in rr.get("akf", {}) else ""))
        errs = {m: d["status"] for m, d in summary[name].items() if d.get("status") != "ok"}
        for m, e in errs.items():
            print(f"  {m}: {e[:300]}")
    ro = res.get("real_overexpose", {})
    print(f"\n## real_overexpose (ecd_slider_depth, frames over-exposed x{', x'.join(ro.get('gains', {}) or ['?'])} after the fact; log RMSE after "
          "a·log x + b on the unclipped pixels, (x frames_only))")
    print(ro.pop("table", None) or f"  skipped: {ro.get('skipped')}")
    res["real_overexpose_targets"] = _overexpose_targets(ro)
    print("  checks at gain 4 (measured, not tuned for): " + "; ".join(
        f"{'PASS' if v['pass'] else 'FAIL'} {k} (" + ", ".join(f"{a}={b:.3g}" for a, b in v.items() if a != "pass")
        + ")" for k, v in res["real_overexpose_targets"].items()))
    rs = res.get("real_overexpose_street", {})
    print(f"\n## real_overexpose, davis346_street (frames {rs.get('frames')} over-exposed after the fact; one "
          f"calibration per gain without the scored frames; (x frames_only))")
    print(rs.pop("table", None) or f"  skipped: {rs.get('skipped')}")
    res["real_overexpose_street_targets"] = _street_targets(rs)
    print("  checks at gain 4 (measured, not tuned for): " + "; ".join(
        f"{'PASS' if v['pass'] else 'FAIL'} {k} (" + ", ".join(f"{a}={b:.3g}" for a, b in v.items() if a != "pass")
        + ")" for k, v in res["real_overexpose_street_targets"].items()))
    print("\n* whole-image log-RMSE after its own a·log x + b fit: reported, but misleading (the fit trades the "
          "clipped pixels against the rest). Unaltered MSE/SSIM/PU21-SSIM: both divided by the reference maximum, "
          "reconstruction not clipped (symmetric, as the AKF authors' anal_hdr_results.m). Mev/s of frames-only "
          "methods is not an event rate that matters.")
    print("\ntargets (measured, not tuned for):")
    for k, v in res["targets"].items():
        print(f"  {'PASS' if v['pass'] else 'FAIL'} {k}: " + ", ".join(
            f"{a}={b:.4g}" if isinstance(b, float) else f"{a}={b}" for a, b in v.items() if a != "pass"))
    print("\ndiagnostics (not targets):")
    for k, v in res["diagnostics"].items():
        print(f"  {k}: " + ", ".join(f"{a}={b:.4g}" if isinstance(b, float) else f"{a}={b}" for a, b in v.items()))
    for name, per in res.get("event_log_change", {}).items():
        for dname, v in per.items():
            print(f"  {name} {dname}: on {v['pixels']} pixels brightening > 2 ln units (mean {v['true_ln_rise']:.2f}) "
                  f"the events report {v['events_ln_rise']:.2f} ({100 * v['fraction_reported']:.0f} %)")
    cold = res.get("render", {}).get("cold")
    print(f"\nruntime {res['runtime_s']:.1f} s" + (" (cold: the HDR set was rendered this run; warm reruns are "
                                                      "faster)" if cold else " (HDR set from the cache)"))
    print(json.dumps(res, default=lambda o: o if not isinstance(o, np.generic) else o.item()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
