"""Held-out frames on two real sensors: the AKF against hold-previous and CF, CLI defaults.

Usage: ``python benchmarks/real_holdout.py [--quick]``. Prints one table per recording and task,
then ONE JSON object on the last line.

``hybridhdr evaluate holdout``'s protocol (:func:`hybridhdr.evaluate.realdata.evaluate_holdout`):
frame k is withheld and reconstructed at its exposure centre from everything else
(``leave_one_out``), or predicted from the data before it (``next_frame``, causal methods);
scored on its well-exposed codes (MSE, PSNR, SSIM, frame-linear units divided by the references'
maximum). Methods: the two-sided and causal AKF and CF with the command line's default thresholds
(:func:`~hybridhdr.evaluate.realdata.default_threshold_source`: the self-calibration for these
recordings, which declare none), and the baselines hold-previous and linear interpolation.

- ``ecd_slider_depth`` (DAVIS240C, 240x180, frames without exposures): every frame with a
  neighbour on each side inside the events (frames 1-3), each calibrated without itself;
- ``davis346_street`` (DAVIS346, 346x260, AEDAT4, 500 µs exposures): 6 (``--quick``) or 12 of its
  57 held-out frames, evenly spread, with one calibration that leaves every held-out frame out
  (``calibration_holdout="scored"``: one per frame would cost 12 calibrations of 59 frames).

Beside them (full run only; ``--quick`` leaves them out to stay under a minute on 2 cores), the
same AKF with the frames' noise and drift measured on its input
(``AKFParams(noise_from_frames=True)``, labels ``akf_noise`` and ``akf_causal_noise``; off by
default, ``docs/reconstruct.md``, "Frame noise measured on the recording"), with the ratio to
the default AKF in the same mode.

Checks (measured, not tuned for): on each recording and task the AKF's mean MSE is below
hold-previous's and below CF's in the same mode. Each recording is skipped, with the reason,
when its sample data is absent.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED_DATA  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

RECORDINGS = {"ecd_slider_depth": SHARED_DATA / "ecd_slider_depth",
              "davis346_street": SHARED_DATA / "aedat4" / "davis346_street.aedat4"}
#: held-out frames of davis346_street: (quick, full), evenly spread over its default held-out frames
STREET_HELD = (6, 12)


def _log(*a):
    print(*a, file=sys.stderr, flush=True)


def _checks(res) -> dict:
    out = {}
    for task in ("leave_one_out", "next_frame"):
        m = res.get(task, {}).get("methods", {})

        def mse(lab):
            r = m.get(lab, {})
            return r["mean"]["mse"] if r.get("status") == "ok" else float("nan")
        pairs = [("akf", "cf"), ("akf_noise", "cf")] if task == "leave_one_out" else []
        pairs += [("akf_causal", "cf_causal"), ("akf_causal_noise", "cf_causal")]
        for akf, cf in pairs:
            if akf not in m:
                continue  # not run (--quick)
            a, c, h = mse(akf), mse(cf), mse("hold_previous")
            out[f"{task}_{akf}_below_hold_previous"] = {"akf": a, "hold_previous": h, "ratio": a / h,
                                                         "pass": bool(a < h)}
            out[f"{task}_{akf}_below_{cf}"] = {"akf": a, "cf": c, "ratio": a / c, "pass": bool(a < c)}
    return out


def _noise_ratios(res) -> dict:
    """MSE of the AKF with the measured frame noise over the default AKF's, per task and mode."""
    out = {}
    for task in ("leave_one_out", "next_frame"):
        m = res.get(task, {}).get("methods", {})
        for lab in ("akf", "akf_causal"):
            a, b = m.get(f"{lab}_noise", {}), m.get(lab, {})
            if a.get("status") == "ok" and b.get("status") == "ok":
                out[f"{task}_{lab}"] = a["mean"]["mse"] / b["mean"]["mse"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help=f"{STREET_HELD[0]} held-out frames of davis346_street, no measured-frame-noise AKF "
                                                         f"(else {STREET_HELD[1]})")
    args = ap.parse_args()
    import hybridhdr
    from hybridhdr.evaluate import realdata as RD
    t_start = time.perf_counter()
    specs = [RD.HoldoutSpec("akf", "akf", "offline"), RD.HoldoutSpec("akf_causal", "akf", "causal")]
    if not args.quick:
        specs += [RD.HoldoutSpec("akf_noise", "akf", "offline", params={"noise_from_frames": True}),
                  RD.HoldoutSpec("akf_causal_noise", "akf", "causal", params={"noise_from_frames": True})]
    specs += [RD.HoldoutSpec("cf", "cf", "offline"), RD.HoldoutSpec("cf_causal", "cf", "causal")]
    res = {"benchmark": "real_holdout", "quick": bool(args.quick), "recordings": {}}
    for name, path in RECORDINGS.items():
        if not path.exists():
            res["recordings"][name] = {"skipped": f"{path} not found (the ../shared sample data is absent)"}
            print(f"\n## {name}: skipped ({path} not found)")
            continue
        _log(f"{name} ...")
        t = time.perf_counter()
        rec = hybridhdr.read(path)
        held, hold = None, "frame"
        if name == "davis346_street":
            d = RD.default_held_frames(rec)
            n = STREET_HELD[0] if args.quick else STREET_HELD[1]
            held = sorted({d[int(i)] for i in np.linspace(0, len(d) - 1, min(n, len(d))).round()})
            hold = "scored"
        thr = RD.default_threshold_source(rec)
        r = RD.evaluate_holdout(rec, specs, held=held, thresholds=thr, calibration_holdout=hold, log=_log)
        wall = time.perf_counter() - t
        print(f"\n## {name} (thresholds {thr}, calibration without {'each held-out frame' if hold == 'frame' else 'every held-out frame'}; {wall:.0f} s)")
        print(RD.format_holdout(r, f"{name}, "))
        checks = _checks(r)
        print("  checks: " + "; ".join(f"{'PASS' if v['pass'] else 'FAIL'} {k} (ratio {v['ratio']:.3f})"
                                       for k, v in checks.items()))
        noise = _noise_ratios(r)
        if noise:
            print("  measured frame noise / default AKF, MSE: " + "; ".join(f"{k} {v:.3f}" for k, v in noise.items()))
        res["recordings"][name] = {
            "noise_from_frames_over_default": noise,
            "held": r["held"], "thresholds": thr, "calibration_holdout": hold, "wall_s": wall, "checks": checks,
            **{task: {lab: ({"mse": row["mean"]["mse"], "psnr_db": row["mean"]["psnr_db"], "ssim": row["mean"]["ssim"]}
                            if row.get("status") == "ok" else {"status": row.get("status")})
                      for lab, row in r[task]["methods"].items()} for task in RD.TASKS if task in r},
            "calibration_used": {lab: (row.get("thresholds") or [None])[0] for lab, row in
                                 r["leave_one_out"]["methods"].items() if row.get("status") == "ok"}}
    res["runtime_s"] = time.perf_counter() - t_start
    print(f"\nruntime {res['runtime_s']:.1f} s")
    print(json.dumps(res, default=lambda o: o.item() if isinstance(o, np.generic) else str(o)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
