"""``hybridhdr calibrate thresholds``: per-pixel ON/OFF contrast thresholds from frames and events."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from .._util.cliargs import COMMON, HelpFormatter, add_format_arg, json_output, positive_int


def register(steps) -> None:
    p = steps.add_parser(
        "thresholds", help="per-pixel ON/OFF contrast thresholds from a recording's frames and events",
        formatter_class=HelpFormatter, parents=[COMMON],
        description="Estimate ON and OFF contrast thresholds (natural-log units) on the one camera model "
                    "(hybridhdr.calibrate.camera_model, the same estimate as the self-calibration and 'calibrate "
                    "sensor'): the pooled pair, and per pixel where the data identify it, shrunk toward the pooled "
                    "pair by its own uncertainty (empirical Bayes). Prints a summary and writes "
                    "OUT/thresholds.npz (read by hybridhdr.formats.thresholds.load_thresholds), "
                    "OUT/thresholds.png (ON and OFF histograms) and OUT/report.json. See docs/calibrate.md.")
    p.add_argument("recording", type=Path, metavar="RECORDING", help="recording with events and frames (any "
                                                                     "readable format)")
    p.add_argument("--out", type=Path, default=Path("thresholds"), help="output folder")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the files a previous run wrote in a non-empty --out (refused without it)")
    add_format_arg(p)
    p.add_argument("--profile", type=Path, default=None,
                   help="camera profile JSON (default: the recording's declared one, else the built-in profile of "
                        "the frames' encoding)")
    p.add_argument("--intensity-offset", type=float, default=None,
                   help="I0 of L = log(I + I0), frame-linear units (default: the camera model's own, estimated)")
    p.add_argument("--well-exposed", default=None, metavar="LO,HI",
                   help="well-exposed codes, inclusive (default 20,235 scaled to the bit depth)")
    p.add_argument("--min-intervals", type=positive_int, default=2,
                   help="usable frame intervals with ON events, and with OFF events, a pixel needs")
    p.add_argument("--min-decorrelation", type=float, default=0.05,
                   help="smallest 1 - rho^2 of a pixel's ON and OFF count columns")
    p.add_argument("--c-range", default="0.01,2.0", metavar="LO,HI", help="accepted thresholds (log units)")
    p.add_argument("--store", action="store_true",
                   help="also store the map in RECORDING (a hybridhdr container), where reconstruct uses it")
    p.set_defaults(func=run_thresholds)


def _pair(s, name, cast):
    try:
        a, b = (cast(v) for v in s.split(","))
    except ValueError:
        raise SystemExit(f"{name} must be two numbers 'LO,HI', got {s!r}") from None
    return a, b


@json_output
def run_thresholds(args) -> int:
    from .._util.atomic import write_json_atomic
    from .._version import __version__
    from ..formats import read
    from .camera_model import GridEdgeWarning
    from .thresholds import estimate_thresholds, plot_thresholds

    from .._util.atomic import check_outputs, refuse_overwriting_inputs
    check_outputs({"--out": args.out}, [args.recording, args.profile], overwrite=args.overwrite,
                  command="calibrate thresholds")
    refuse_overwriting_inputs({f"--out ({n})": args.out / n for n in ("thresholds.npz", "thresholds.png", "report.json")},
                              [args.recording, args.profile])
    t0 = time.perf_counter()
    rec = read(args.recording, format=args.format) if args.format else read(args.recording)
    import warnings
    with warnings.catch_warnings(record=True) as wl:
        warnings.simplefilter("always", GridEdgeWarning)
        tm = estimate_thresholds(
            rec, profile=args.profile, intensity_offset=args.intensity_offset,
            well_exposed=None if args.well_exposed is None else _pair(args.well_exposed, "--well-exposed", int),
            min_intervals=args.min_intervals, min_decorrelation=args.min_decorrelation,
            c_range=_pair(args.c_range, "--c-range", float))
    notes = [str(w.message) for w in wl if issubclass(w.category, GridEdgeWarning)]
    for n_ in notes:
        print(f"warning: {n_}", file=sys.stderr)
    tm.provenance["warnings"] = notes
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    tm.provenance.update(command=sys.argv, hybridhdr_version=__version__, input=str(args.recording))
    tm.save(out / "thresholds.npz")
    if args.store:
        from ..formats.container import store_thresholds
        store_thresholds(args.recording, tm)
    plot_thresholds(tm, out / "thresholds.png",
                    title=f"{args.recording.name}: {int(tm.valid.sum())} of {tm.valid.size} pixels estimated "
                          f"({100 * tm.valid.mean():.2f} %)")
    s = tm.summary()
    report = {**tm.provenance, **s, "time_s": time.perf_counter() - t0,
              "written": ["thresholds.npz", "thresholds.png", "report.json"]}
    write_json_atomic(out / "report.json", report, default=lambda o: o.item() if hasattr(o, "item") else str(o))
    if args.json:
        print(json.dumps(report, default=lambda o: o.item() if hasattr(o, "item") else str(o)))
        return 0
    pv = tm.provenance
    print(f"{args.recording}: {pv['intervals_used']} frame intervals used ({pv['n_pixel_intervals']} well-exposed "
          f"pixel-intervals with events), profile {pv['profile']}, I0 {pv['intensity_offset']:g}, frames stand for "
          f"their stamp {pv['time_offset_us']:+d} us")
    print(f"  pooled (camera model)   ON {tm.fallback_on:.4f} +- {pv['pooled_on_std'] or float('nan'):.2g}   "
          f"OFF {tm.fallback_off:.4f} +- {pv['pooled_off_std'] or float('nan'):.2g}")
    print(f"  estimated pixels        {s['n_estimated']} of {s['n_pixels']} ({100 * s['fraction_estimated']:.2f} %)")
    for pol in ("on", "off"):
        print(f"  {pol.upper():<3} median (IQR)        {s['median_' + pol]:.4f} ({s['q25_' + pol]:.4f}-"
              f"{s['q75_' + pol]:.4f})   pooled fallback {s['fallback_' + pol]:.4f}")
    ne = pv["not_estimable"]
    print(f"  not estimable: {ne['too_few_intervals']} too few intervals with both polarities, "
          f"{ne['not_identified_otherwise']} otherwise not identified; they get the pooled pair")
    print(f"wrote {out / 'thresholds.npz'}, {out / 'thresholds.png'}, {out / 'report.json'}")
    return 0
