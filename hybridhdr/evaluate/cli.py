"""``hybridhdr evaluate``: metrics of a reconstruction, benchmarks, the paper table, real-data holdout scoring."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from .._util.cliargs import (HelpFormatter, add_format_arg, json_command, json_output, nonneg_int, positive_float,
                             worker_count)
from ..calibrate.resolve import THRESHOLDS_HELP, add_sensor_profile_arg, take_sensor_profile_arg, thresholds_arg


def add_parser(sub) -> None:
    fmt = HelpFormatter  # common options (--debug, --no-progress, --json, -q/-v): hybridhdr._util.cliargs.finalise
    p = sub.add_parser("evaluate", help="metrics and benchmarks", formatter_class=fmt,
                       description="Score reconstructions (MSE, SSIM, PU21, HDR-VDP Q), run benchmarks, "
                                   "reproduce the paper's Table 1. See docs/evaluate.md.")
    esub = p.add_subparsers(dest="evaluate_command", metavar="STEP")

    m = esub.add_parser("metrics", formatter_class=fmt, help="score a reconstruction folder against a recording's "
                                                              "HDR references",
                        description="Score RECON_DIR (frame_*.exr + timestamps.txt as written by 'hybridhdr "
                                    "reconstruct') against the HDR references of REC, matched by timestamp.")
    m.add_argument("recon_dir", type=Path, help="folder with timestamps.txt and EXR frames")
    m.add_argument("--reference", type=Path, required=True, help="recording holding HDR references (any readable "
                                                                 "format)")
    m.add_argument("--tolerance-us", type=nonneg_int, default=1000, help="largest |t_recon - t_ref| accepted, in µs")
    m.add_argument("--normalise", choices=["none", "scale", "affine", "scale_linear", "affine_linear"],
                   default=None, help="normalisation before scoring (default: none, the unaltered reconstruction "
                                      "as the paper scores; scale/affine fit a gain (and exponent) first)")
    m.add_argument("--peak-luminance-cd-m2", type=positive_float, default=4000.0,
                   help="luminance of the reference maximum for PU21 and HDR-VDP, in cd/m²")
    m.add_argument("--hdrvdp-dir", type=Path, default=None,
                   help="HDR-VDP 3 folder (holding hdrvdp3.m); default $HYBRIDHDR_HDRVDP_DIR; Q is n/a without it")
    m.add_argument("--engine", choices=["auto", "octave", "matlab"], default="auto", help="HDR-VDP engine")
    m.add_argument("--protocol", choices=["default", "akf2021"], default="default",
                   help="default: this page's scoring (docs/evaluate.md); akf2021: the AKF authors' evaluation of "
                        "their HDR/AHDR .mat sequences (unaltered reconstruction vs the reference's channel mean / "
                        "255, reference-0 pixels masked; MSE, PSNR, SSIM, HDR-VDP 3 Q in luminance mode at a "
                        "21-inch 640x480 display from 1 m)")
    m.add_argument("--metric", default="jod,q", metavar="LIST",
                   help="perceptual metrics, comma-separated: jod (ColorVideoVDP, on at most 8 evenly spaced "
                        "frames), q (HDR-VDP 3 when installed), or none")
    m.add_argument("--display", default=None, metavar="NAME",
                   help="ColorVideoVDP display model (default standard_hdr_linear: 30-inch 4K HDR, 1500 cd/m², "
                        "0.7472 m)")
    m.add_argument("--csv", type=Path, default=None, metavar="FILE",
                   help="write the per-frame scores to FILE (one row per matched frame: file, times, every "
                        "metric); --json includes them under 'frames' (non-finite values as null)")
    m.set_defaults(func=run_metrics)

    b = esub.add_parser("bench", formatter_class=fmt, help="run a TOML bench file",
                        description="Run methods x datasets x parameter grids from BENCH (a TOML file, or a "
                                    "bundled name: demo, speed_accuracy, stability, tiny); write results.csv, "
                                    "report.md/.html, strips and charts to --out. Each finished task is kept in "
                                    "OUT/runs/ as it finishes (--resume continues an interrupted run). Sizes (tasks, "
                                    "runs): docs/evaluate.md.")
    b.add_argument("bench", help="bench TOML file or bundled bench name")
    b.add_argument("--out", type=Path, required=True, help="output folder")
    b.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786); default: local "
                                                     "processes")
    b.add_argument("--workers", type=worker_count, default=None, help="local worker processes (0 = in this process; "
                                                             "default min(2, CPUs))")
    b.add_argument("--hdrvdp-dir", type=Path, default=None,
                   help="HDR-VDP 3 folder for Q (default $HYBRIDHDR_HDRVDP_DIR; never read from the bench file)")
    b.add_argument("--resume", action="store_true",
                   help="reuse the tasks an interrupted run of the same bench finished (OUT/runs/, written as "
                        "each task finishes) and run only the others; without it they are run again")
    b.add_argument("--overwrite", action="store_true",
                   help="run into a non-empty --out, replacing what a bench run writes there (refused without it "
                        "or --resume)")
    b.add_argument("--allow-outside", type=Path, action="append", default=[], metavar="PATH",
                   help="let the bench file read (and cache) under PATH too (repeatable); by default the files it "
                        "names must lie inside its own folder, its cache there or in --out (docs/security.md)")
    b.add_argument("--allow-huge", action="store_true",
                   help="lift the limits on the number of runs and dataset sizes/durations (docs/security.md)")
    b.set_defaults(func=run_bench_cmd)

    q = esub.add_parser("paper", formatter_class=fmt, help="Table 1 of the paper on simulated HDR and AHDR sets",
                        description="Build an HDR set and an AHDR set (simulator when available), run every "
                                    "method, print a table shaped like the paper's Table 1.")
    q.add_argument("--out", type=Path, required=True, help="output folder")
    q.add_argument("--quick", action="store_true", help="small scenes (48x36, 0.3 s, fixed 500 Hz sampling)")
    q.add_argument("--workers", type=worker_count, default=None, help="local worker processes")
    q.add_argument("--scheduler", default=None, help="Dask scheduler address")
    q.add_argument("--hdrvdp-dir", type=Path, default=None, help="HDR-VDP 3 folder for Q")
    q.add_argument("--normalise", choices=["none", "scale", "affine", "scale_linear", "affine_linear"],
                   default="none", help="scoring: none = the unaltered reconstruction (as the paper); a fit by name")
    q.add_argument("--weights-e2vid", type=Path, default=None, metavar="PATH",
                   help="E2VID checkpoint (E2VID_lightweight.pth.tar); the E2VID column is omitted without it")
    q.add_argument("--weights-firenet", type=Path, default=None, metavar="PATH",
                   help="FireNet checkpoint (firenet_1000.pth.tar); the FireNet column is omitted without it")
    q.add_argument("--no-jod", action="store_true", help="skip ColorVideoVDP (JOD) scoring")
    q.set_defaults(func=run_paper_cmd)
    h = esub.add_parser("holdout", formatter_class=fmt,
                        help="real data without ground truth: leave-one-frame-out and next-frame prediction",
                        description="Score methods on a real recording against its own frames: each held-out "
                                    "frame k is withheld and reconstructed at its exposure centre "
                                    "(leave-one-out), and causal methods also predict it from the data before "
                                    "it at tau_k - 1 us (next-frame). Scored on the frame's well-exposed "
                                    "pixels (codes 20-235 of 8 bits, scaled to the bit depth) in frame-linear "
                                    "units (camera profile), beside the hold-previous and linear-interpolation "
                                    "baselines. See docs/evaluate.md.")
    h.add_argument("recording", type=Path, metavar="RECORDING", help="recording with events and frames")
    h.add_argument("--method", default="akf",
                   help="method(s), comma-separated: akf, cf, highpass, direct, edi, frames_zoh, frames_linear")
    h.add_argument("--mode", default="offline", choices=["offline", "causal", "forward"],
                   help="reconstruction mode of the method(s); next-frame prediction needs causal")
    h.add_argument("--task", default="auto", choices=["auto", "leave-one-out", "next-frame", "both"],
                   help="auto: leave-one-out, plus next-frame prediction when --mode causal")
    h.add_argument("--frames", default=None, metavar="K,K,...",
                   help="held-out frame indices (default: every frame with a neighbour on each side inside the "
                        "events' span)")
    h.add_argument("--params", type=Path, default=None, help="method parameters (TOML)")
    h.add_argument("--contrast-threshold", type=float, default=None, help="contrast threshold c (log units)")
    h.add_argument("--thresholds", type=thresholds_arg, default=None, metavar="FILE|auto|input|params|selfcal",
                   help=THRESHOLDS_HELP + "; here auto and selfcal are estimated without the held-out frame (the "
                        "recording without it; selfcal's frame k is predicted at the time it stands for)")
    add_sensor_profile_arg(h)
    h.add_argument("--augmentation", action="store_true", help="AKF frame augmentation (offline)")
    h.add_argument("--profile", type=Path, default=None, help="camera profile JSON (default: the recording's, "
                                                              "else built-in)")
    h.add_argument("--well-exposed", default=None, metavar="LO,HI",
                   help="well-exposed codes, inclusive (default 20,235 scaled to the bit depth)")
    add_format_arg(h)
    h.set_defaults(func=run_holdout_cmd)
    o = esub.add_parser("overexpose", formatter_class=fmt,
                        help="real data without an HDR reference: over-expose the frames, score HDR recovery",
                        description="Over-expose REC's frames GAIN times after the fact (linear intensity x GAIN, "
                                    "re-encoded through the camera profile, clipped; events untouched) and score "
                                    "every method at the frames' times against the original frames x GAIN on "
                                    "three pixel classes: recoverable causal (frame k clips it, the original "
                                    "shows it well exposed, an earlier over-exposed frame saw it), recoverable "
                                    "offline (any other frame saw it) and well-exposed; log RMSE after "
                                    "a*log x + b fitted on the unclipped pixels, beside frames-only and "
                                    "hold-previous. Writes results.json, table.txt, per_frame.csv and "
                                    "figures/METHOD_gainG.png to --out. See docs/evaluate.md.")
    o.add_argument("recording", type=Path, metavar="RECORDING", help="recording with events and integer frames")
    o.add_argument("--gain", type=_gain_list, default=[4.0], metavar="G[,G...]",
                   help="over-exposure factor(s) on the frames' linear intensity, each > 1, comma-separated (default 4)")
    o.add_argument("--method", default="akf,cf,direct,edi",
                   help="method(s) that take frames, comma-separated: akf, cf, direct, edi")
    o.add_argument("--mode", default="offline,causal", metavar="MODE[,MODE]",
                   help="reconstruction mode(s), comma-separated: offline (the AKF's two-sided filter), causal, "
                        "forward; each method runs in each mode it supports")
    o.add_argument("--frames", default=None, metavar="K,K,...",
                   help="scored frame indices among the frames up to the last event (default: every frame k >= 1 "
                        "at or after the first event)")
    o.add_argument("--params", action="append", default=[], metavar="METHOD=FILE",
                   help="parameters (TOML) of one method, by method name or label (akf_causal); repeatable")
    o.add_argument("--contrast-threshold", type=positive_float, default=None,
                   help="contrast threshold c (log units) for every event method")
    o.add_argument("--thresholds", type=thresholds_arg, default=None, metavar="FILE|auto|input|params|selfcal",
                   help=THRESHOLDS_HELP + "; here auto and selfcal are estimated on the over-exposed input "
                        "without the scored frame")
    add_sensor_profile_arg(o)
    o.add_argument("--calibrate-on-original", action="store_true",
                   help="calibrate the camera once on the ORIGINAL, well-exposed frames (each scored frame left "
                        "out; the log offset I0 x the gain) instead of self-calibrating the clipped input: the "
                        "AKF's thresholds and I0, every method's frame offset (see docs/evaluate.md)")
    o.add_argument("--profile", type=Path, default=None, help="camera profile JSON of the frames (default: the "
                                                              "recording's, else built-in)")
    add_format_arg(o)
    o.add_argument("--out", type=Path, required=True, help="output folder")
    o.add_argument("--overwrite", action="store_true",
                   help="replace the files a previous overexpose run wrote in --out (keeps everything else)")
    o.add_argument("--no-figures", action="store_true", help="skip the figures (PNG per method and gain)")
    o.set_defaults(func=run_overexpose_cmd)
    p.set_defaults(func=lambda args: (p.print_help(), 0)[1])


def _gain_list(text: str) -> list:
    """``--gain 4`` or ``4,8``: finite factors > 1 (a usage error otherwise: a gain of 1 or less
    over-exposes nothing, so there is no clipped pixel to recover)."""
    import argparse
    import math
    out = []
    for v in str(text).split(","):
        try:
            g = float(v)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected numbers > 1 separated by commas, got {text!r}") from None
        if not (math.isfinite(g) and g > 1):
            raise argparse.ArgumentTypeError(f"expected numbers > 1 separated by commas (a gain of 1 or less "
                                             f"over-exposes nothing), got {text!r}")
        out.append(g)
    if len(set(out)) != len(out):
        raise argparse.ArgumentTypeError(f"each gain once, got {text!r}")
    return out


def _perceptual(metric: str) -> set:
    want = {x.strip() for x in str(metric).split(",") if x.strip()}
    bad = want - {"jod", "q", "none"}
    if bad:
        raise ValueError(f"--metric: unknown metric(s) {sorted(bad)}; expected jod, q or none")
    return want - {"none"}


def score_reconstruction(recon_dir, reference, *, tolerance_us: int = 1000, normalise: str | None = None,
                         peak_luminance_cd_m2: float = 4000.0, hdrvdp_dir=None, engine: str = "auto",
                         protocol: str = "default", metric: str = "jod,q", display: str | None = None,
                         per_frame: bool = False) -> dict:
    """Score an EXR reconstruction folder against a recording's HDR references (see the CLI help).

    With ``per_frame`` the result also holds ``frames``: per matched frame its ``file``, ``t_us``,
    ``reference_index``, ``reference_t_us`` and scores (:func:`~.metrics.score_video`)."""
    import numpy as np

    from ..formats import read
    from ..formats.images import read_exr
    from .metrics import HDRVDPNotFound, default_normalise, find_hdrvdp, match_frames, score_akf2021, score_video
    if protocol not in ("default", "akf2021"):
        raise ValueError(f"protocol must be 'default' or 'akf2021', got {protocol!r}")
    if protocol == "akf2021" and normalise not in (None, "none"):
        raise ValueError("--protocol akf2021 scores the unaltered reconstruction: drop --normalise")
    want = _perceptual(metric)
    d = Path(recon_dir)
    tsf = d / "timestamps.txt"
    if not tsf.is_file():
        raise FileNotFoundError(f"{d}: expected timestamps.txt written by 'hybridhdr reconstruct', not found")
    from ..formats.images import read_timestamps
    t, names = read_timestamps(tsf)
    method = None
    if (d / "run.json").is_file():
        try:
            method = json.loads((d / "run.json").read_text()).get("method")
        except (ValueError, OSError):
            method = None
    mode = normalise or default_normalise(method or "")
    rec = read(reference)
    if rec.hdr is None or len(rec.hdr) == 0:
        raise ValueError(f"{reference}: the reference recording has no HDR references")
    vi, ri = match_frames(t, rec.hdr.t_us, int(tolerance_us))
    if len(vi) == 0:
        raise ValueError(f"no reconstructed frame within {tolerance_us} µs of any of the {len(rec.hdr)} references "
                         f"(recon {t.min() if len(t) else '-'}..{t.max() if len(t) else '-'} µs, references "
                         f"{rec.hdr.t_us.min()}..{rec.hdr.t_us.max()} µs)")
    frames = np.stack([read_exr(d / names[i]) for i in vi])
    ref_stored = rec.hdr.images[ri]
    ref = ref_stored if ref_stored.ndim == 3 else ref_stored.mean(axis=3)
    if frames.shape[1:] != ref.shape[1:]:
        raise ValueError(f"reconstruction frames are {frames.shape[2]}x{frames.shape[1]} but references are "
                         f"{ref.shape[2]}x{ref.shape[1]}")
    hv, q_note = None, None
    if "q" in want:
        try:
            find_hdrvdp(hdrvdp_dir)
            hv = {"hdrvdp_dir": hdrvdp_dir, "engine": engine}
        except HDRVDPNotFound as e:
            q_note = str(e)
    else:
        q_note = "not requested (--metric)"
    if protocol == "akf2021":
        res = score_akf2021(frames, ref_stored, hdrvdp=hv, per_frame=per_frame)
    else:
        jod = {"display": display} if "jod" in want else None
        res = score_video(frames, ref, normalise=mode, peak_luminance_cd_m2=peak_luminance_cd_m2, hdrvdp=hv,
                          jod=jod, per_frame=per_frame)
    if per_frame:
        res["frames"] = [{"file": names[int(vi[k])], "t_us": int(t[vi[k]]), "reference_index": int(ri[k]),
                          "reference_t_us": int(rec.hdr.t_us[ri[k]]), **f} for k, f in enumerate(res["frames"])]
    res.update(method=method, matched=int(len(vi)), references=int(len(rec.hdr)), tolerance_us=int(tolerance_us))
    if q_note:
        res["q"] = None
        res["q_note"] = q_note
    return res


def _json_safe(v):
    """``v`` with NaN/±inf floats as None (strict JSON), recursively."""
    import math
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    return v


def write_frames_csv(frames: list[dict], path) -> Path:
    """Per-frame scores as CSV (csv module, one header of the union of keys in first-seen order)."""
    import csv

    from .._util.atomic import atomic_path
    path = Path(path)
    cols = list(dict.fromkeys(k for f in frames for k in f))
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:  # unique temp name
        w = csv.DictWriter(fh, fieldnames=cols, restval="")
        w.writeheader()
        for f in frames:
            w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in f.items()})
    return path


@json_output
def run_metrics(args) -> int:
    if args.csv is not None and not Path(args.csv).parent.is_dir():
        raise FileNotFoundError(f"--csv {args.csv}: the folder {Path(args.csv).parent} does not exist")
    per_frame = bool(args.json or args.csv is not None)
    res = score_reconstruction(args.recon_dir, args.reference, tolerance_us=args.tolerance_us,
                               normalise=args.normalise, peak_luminance_cd_m2=args.peak_luminance_cd_m2,
                               hdrvdp_dir=args.hdrvdp_dir, engine=args.engine, protocol=args.protocol,
                               metric=args.metric, display=args.display, per_frame=per_frame)
    if args.csv is not None:
        write_frames_csv(res["frames"], args.csv)
    if args.json:
        print(json.dumps(_json_safe(res), allow_nan=False))
        return 0
    if res.get("protocol") == "akf2021":
        print(f"{res['matched']} of {res['references']} references matched within {res['tolerance_us']} µs; "
              f"protocol akf2021 (the AKF authors' evaluation): the unaltered reconstruction against the "
              f"reference's channel mean / 255 (frame units), {res['n_masked']} reference-0 (unregistered) pixels "
              f"masked, {res['n_valid']} scored")
        for k, label in (("mse", "MSE (frame units)"), ("psnr_db", "PSNR (dB, peak 1)"),
                         ("ssim", "SSIM (σ=1.5, range 1, masked)"), ("n_nonfinite", "NaN/Inf pixels")):
            print(f"  {label:<32} {res[k]:.6g}" if isinstance(res[k], float) else f"  {label:<32} {res[k]}")
    else:
        _print_default(res)
    if res.get("q") is None:
        print(f"  {'HDR-VDP Q':<32} n/a ({res.get('q_note')})")
    else:
        print(f"  {'HDR-VDP Q':<32} {res['q']:.4g} (version {res['q_version']}, {res['q_task']}, "
              f"{res['q_color_encoding']}, {res['q_pixels_per_degree']:.3g} ppd, "
              f"{res['q_luminance_scale_cd_m2']:g} cd/m²)")
    if args.csv is not None:
        print(f"wrote {len(res['frames'])} per-frame rows to {args.csv}")
    return 0


def _print_default(res) -> None:
    how = "unaltered" if res["normalise"] == "none" else f"gain {res['gain']:.4g} fitted"
    print(f"{res['matched']} of {res['references']} references matched within {res['tolerance_us']} µs; "
          f"normalise={res['normalise']} ({how}); data range 1 after dividing by the reference max "
          f"{res['reference_max']:.4g}")
    for k, label in (("mse", "MSE"), ("psnr_db", "PSNR (dB)"), ("ssim", "SSIM (Gaussian σ=1.5, range 1)"),
                     ("global_ssim", "global SSIM (EAF, one window)"), ("pu_psnr_db", "PU21-PSNR (dB)"),
                     ("pu_ssim", "PU21-SSIM"), ("n_nonfinite", "NaN/Inf pixels")):
        print(f"  {label:<32} {res[k]:.6g}" if isinstance(res[k], float) else f"  {label:<32} {res[k]}")
    if "jod" in res:
        import math
        if math.isfinite(res["jod"]):
            print(f"  {'ColorVideoVDP JOD':<32} {res['jod']:.4g} ({res['jod_frames']} frames; "
                  f"{res['jod_display_line']})")
        else:
            print(f"  {'ColorVideoVDP JOD':<32} {res.get('jod_note') or 'n/a'}")


def _written(w: dict) -> dict:
    """The files a bench/paper run wrote, by name (paths as strings)."""
    out = {}
    for k, v in w.items():
        if isinstance(v, Path):
            out[k] = str(v)
        elif k == "strips":
            out[k] = [str(p) for p in v]
    return out


@json_command
def run_bench_cmd(args) -> int:
    from .bench import claim_bench_out, load_bench, remove_stale_outputs, run_bench, write_results
    import dataclasses
    from .report import akf_vs_cf, summary_table
    bench = load_bench(args.bench, allow_outside=args.allow_outside, out_dir=args.out)  # checked before --out is made
    lock = claim_bench_out(args.out, overwrite=args.overwrite, resume=args.resume)  # held until this returns
    try:
        return _run_bench_locked(args, bench, run_bench, write_results, remove_stale_outputs, dataclasses,
                                 akf_vs_cf, summary_table)
    finally:
        os.close(lock)


def _run_bench_locked(args, bench, run_bench, write_results, remove_stale_outputs, dataclasses, akf_vs_cf,
                      summary_table) -> int:
    hv = args.hdrvdp_dir if args.hdrvdp_dir is not None else os.environ.get("HYBRIDHDR_HDRVDP_DIR")
    if hv:
        bench = dataclasses.replace(bench, hdrvdp_dir=str(hv))
    rows = run_bench(bench, workers=args.workers, scheduler=args.scheduler, progress=not args.no_progress,
                     out_dir=args.out, resume=args.resume)
    w = write_results(rows, args.out, bench)
    remove_stale_outputs(args.out, w)  # an earlier run's strips and charts are not this report's
    print(w["report_md"].read_text(encoding="utf-8").split("## Numerical failures")[0].rstrip())
    print(f"\nwrote {w['csv']}, {w['report_md']}, {w['report_html']}"
          + "".join(f", {w[k]}" for k in ("speed_accuracy", "sampling", "stability") if k in w))
    bad = sum(1 for r in rows if r.get("status") != "ok")
    if bad:
        print(f"{bad} of {len(rows)} runs failed; see the report", file=sys.stderr)

    args.emit_json({"bench": bench.name, "runs": len(rows), "failed": bad, "summary": summary_table(rows),
                    "akf_vs_cf": akf_vs_cf(rows), "stability_failures": w.get("failures", []),
                    "errors": [{"dataset": r.get("dataset"), "method": r.get("method_label"),
                                "status": r.get("status")} for r in rows if r.get("status") != "ok"],
                    "written": _written(w)})
    if rows and bad == len(rows):  # nothing was measured: a failure, not a result (docs/security.md)
        print(f"{getattr(args, '_prog', 'hybridhdr evaluate bench')}: error: every run failed ({bad} of {len(rows)}); "
              f"the reasons are in {w['report_md']}", file=sys.stderr)
        return 1
    return 0


@json_command
def run_paper_cmd(args) -> int:
    from .paper import run_paper
    details: dict = {}
    text = run_paper(args.out, quick=args.quick, workers=args.workers, scheduler=args.scheduler,
                     hdrvdp_dir=args.hdrvdp_dir, normalise=args.normalise, progress=not args.no_progress,
                     weights={"e2vid": args.weights_e2vid, "firenet": args.weights_firenet}, jod=not args.no_jod,
                     details=details)
    print(text)
    args.emit_json({**details, "written": _written(details.pop("written_paths", {}))})
    return 0


def _holdout_params(method: str, params_path, contrast_threshold):
    from ..reconstruct.api import make_params, resolve_method
    m = resolve_method(method)
    if params_path is None and contrast_threshold is None:
        return None
    p = make_params(m, None if params_path is None else str(params_path))
    if contrast_threshold is not None:
        if not hasattr(p, "contrast_threshold"):
            raise ValueError(f"--contrast-threshold does not apply to method {method}")
        p = p.replace(contrast_threshold=float(contrast_threshold))
    return p


def _methods_arg(text: str) -> list[str]:
    """``--method a,b``: the names, each a reconstruction method (or alias); a usage error (exit 2)
    names the known ones."""
    from .._util.cliargs import UsageError
    from ..reconstruct.api import METHOD_ALIASES, METHODS
    methods = [m.strip() for m in text.split(",") if m.strip()]
    if not methods:
        raise UsageError(f"--method names no method ({text!r})")
    unknown = [m for m in methods if m not in METHODS and m not in METHOD_ALIASES]
    if unknown:
        raise UsageError(f"--method: unknown method(s) {', '.join(map(repr, unknown))}; expected one of "
                         f"{', '.join(list(METHODS) + list(METHOD_ALIASES))}")
    return methods


@json_output
def run_holdout_cmd(args) -> int:
    from ..formats import read
    from .realdata import HoldoutSpec, evaluate_holdout, format_holdout
    methods = _methods_arg(args.method)
    if args.task == "auto":
        tasks = ("leave_one_out", "next_frame") if args.mode == "causal" else ("leave_one_out",)
    elif args.task == "both":
        tasks = ("leave_one_out", "next_frame")
    else:
        tasks = (args.task.replace("-", "_"),)
    if "next_frame" in tasks and args.mode != "causal":
        raise ValueError(f"next-frame prediction is for causal methods: use --mode causal (got --mode {args.mode})")
    label = (lambda m: m) if args.mode == "offline" else (lambda m: f"{m}_{args.mode}")
    specs = [HoldoutSpec(label(m), m, args.mode, _holdout_params(m, args.params, args.contrast_threshold),
                         True if args.augmentation else None) for m in methods]
    well = None
    if args.well_exposed is not None:
        try:
            well = tuple(int(v) for v in args.well_exposed.split(","))
            assert len(well) == 2
        except (ValueError, AssertionError):
            raise ValueError(f"--well-exposed must be 'LO,HI' codes, got {args.well_exposed!r}") from None
    held = None if args.frames is None else [int(v) for v in args.frames.split(",") if v.strip()]
    take_sensor_profile_arg(args)
    rec = read(args.recording, format=args.format) if args.format else read(args.recording)
    thresholds = args.thresholds
    given = args.params is not None or args.contrast_threshold is not None
    if thresholds is None:  # the API's rule (DEFAULT_THRESHOLDS, as reconstruct's); the specs carry the params
        from .realdata import default_thresholds_for
        thresholds = default_thresholds_for(rec, specs)
    elif given and thresholds in ("auto", "input", "selfcal"):
        raise ValueError(f"--thresholds {thresholds} and --params/--contrast-threshold both give the thresholds; "
                         f"use one (or --thresholds params)")
    res = evaluate_holdout(rec, specs, tasks=tasks, held=held, profile=args.profile, well_exposed=well,
                           log=lambda msg: print(msg, file=sys.stderr), thresholds=thresholds)
    res["thresholds"] = str(thresholds)
    res["recording"] = str(args.recording)
    if args.json:
        print(json.dumps(res, default=lambda o: o.item() if hasattr(o, "item") else str(o)))
    else:
        print(format_holdout(res, f"{args.recording.name}: "))
    return 0


#: The files ``evaluate overexpose`` writes in --out (what --overwrite replaces).
OVEREXPOSE_OUTPUTS = ("results.json", "table.txt", "per_frame.csv", "figures/*.png")


def _overexpose_specs(args):
    import dataclasses

    from .._util.cliargs import UsageError
    from ..reconstruct.api import make_params
    from .overexpose import default_specs
    methods = _methods_arg(args.method)
    modes = [m.strip() for m in args.mode.split(",") if m.strip()]
    bad = [m for m in modes if m not in ("offline", "causal", "forward")]
    if not modes or bad:
        raise UsageError(f"--mode must be offline, causal and/or forward separated by commas, got {args.mode!r}")
    files = {}
    for item in args.params:
        key, sep, path = item.partition("=")
        if not sep or not key.strip() or not path.strip():
            raise UsageError(f"--params expects METHOD=FILE (e.g. akf=akf.toml), got {item!r}")
        if not Path(path).is_file():
            raise FileNotFoundError(f"--params {item}: {path} does not exist")
        files[key.strip()] = path.strip()
    specs, skipped = default_specs(methods, modes)
    known = {s.label for s in specs} | {s.method for s in specs}
    unknown = sorted(set(files) - known)
    if unknown:
        raise UsageError(f"--params names {unknown}, which is no method or label run here ({sorted(known)})")
    out = []
    for s in specs:
        src = files.get(s.label, files.get(s.method))
        p = None
        if src is not None or args.contrast_threshold is not None:
            p = make_params(s.method, src)
            if args.contrast_threshold is not None:
                p = p.replace(contrast_threshold=float(args.contrast_threshold))
        out.append(dataclasses.replace(s, params=p))
    return out, skipped


@json_command
def run_overexpose_cmd(args) -> int:
    from .._util.atomic import AtomicFolder, write_json_atomic, write_text_atomic
    from ..formats import read
    from .overexpose import evaluate_overexpose, format_overexpose, gain_key, plot_method, write_per_frame_csv
    specs, skipped = _overexpose_specs(args)
    try:
        frames = None if args.frames is None else [int(v) for v in args.frames.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--frames expects frame indices separated by commas (e.g. 1,2,3), got {args.frames!r}") \
            from None
    if args.profile is not None and not args.profile.is_file():
        raise FileNotFoundError(f"--profile {args.profile} does not exist")
    if args.calibrate_on_original and (args.thresholds is not None or args.sensor_profile is not None):
        from ..errors import UsageError
        raise UsageError("--calibrate-on-original calibrates the camera itself; it takes neither --thresholds nor "
                         "--sensor-profile")
    folder = AtomicFolder(args.out, outputs=OVEREXPOSE_OUTPUTS, command="evaluate overexpose",
                          overwrite=args.overwrite)
    try:
        take_sensor_profile_arg(args)
        rec = read(args.recording, format=args.format) if args.format else read(args.recording)
        thresholds = args.thresholds  # None: the API's default rule (realdata.default_thresholds_for)
        calibrate = None
        if args.calibrate_on_original:
            from .overexpose import calibrated_on_original
            calibrate = calibrated_on_original(rec, profile=None if args.profile is None else str(args.profile))
            thresholds = "params"
        from .._util.progress import progress_bars
        with progress_bars(not args.no_progress) as new_bar:  # failures logged meanwhile go above the bar
            bar = new_bar(total=len(args.gain) * len(specs), desc="overexpose", unit="method")
            res = evaluate_overexpose(rec, args.gain, specs, frames=frames,
                                      profile=None if args.profile is None else str(args.profile),
                                      thresholds=thresholds, calibrate=calibrate, skipped=skipped,
                                      keep_images=not args.no_figures,
                                      log=lambda msg: print(msg, file=sys.stderr),
                                      progress=None if bar is None else bar.update)
        images = res.pop("_images", None)
        res["recording"] = str(args.recording)
        text = format_overexpose(res, f"{args.recording.name}, ")
        figures = []
        if images is not None:
            res["_images"] = images
            for g in res["gains"]:
                for lab, row in res["by_gain"][gain_key(g)]["methods"].items():
                    if row.get("status") == "ok":
                        name = f"figures/{lab}_gain{g:g}.png"
                        plot_method(res, g, lab, folder.path / name)
                        figures.append(name)
            del res["_images"]
        res["written"] = ["results.json", "table.txt", "per_frame.csv"] + figures
        write_text_atomic(folder.path / "table.txt", text + "\n")
        write_per_frame_csv(res, folder.path / "per_frame.csv")
        write_json_atomic(folder.path / "results.json", _json_safe(res))
        out = folder.commit()
    except BaseException:
        folder.abort()
        raise
    res["out"] = str(out)
    print(text)
    print(f"\nwrote {', '.join(res['written'][:3])} and {len(figures)} figure(s) to {out}")
    args.emit_json(_json_safe(res))
    return 0
