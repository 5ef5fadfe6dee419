"""``hybridhdr calibrate sensor``: the event-sensor profile of a recording, as the simulator defines it."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from .._util.cliargs import COMMON, HelpFormatter, add_format_arg, json_output, positive_int


def register(steps) -> None:
    p = steps.add_parser(
        "sensor", help="event-sensor profile (thresholds, mismatch, noise, leak, refractory) of a recording",
        formatter_class=HelpFormatter, parents=[COMMON],
        description="Estimate a recording's event-sensor parameters as the simulator defines them (ON/OFF "
                    "threshold means and per-pixel spread, shot-noise and leak rates, refractory period; the "
                    "photoreceptor bandwidth and timestamp jitter are reported as not identifiable), each with a 95 %% "
                    "interval and an identifiable flag, and write them as a sensor profile JSON that "
                    "'hybridhdr simulate --sensor PROFILE' reads. See docs/calibrate.md, 'Sensor profile'.")
    p.add_argument("recording", type=Path, metavar="REC", help="recording with events and frames (any readable format)")
    p.add_argument("--out", type=Path, required=True, help="profile JSON to write (atomically)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file (refused without it)")
    add_format_arg(p)
    p.add_argument("--profile", type=Path, default=None,
                   help="camera profile JSON of the frames (default: the recording's declared one, else the built-in "
                        "profile of the frames' encoding)")
    p.add_argument("--name", default="", help="profile name stored in the file")
    p.add_argument("--sensor-model", default="", help="sensor model stored in the file (e.g. DAVIS240C)")
    p.add_argument("--static-log-bound", type=float, default=0.02,
                   help="largest |d ln I| between two frames of a static pixel (and its 3x3 neighbours), log units")
    p.add_argument("--bootstrap", type=positive_int, default=200, help="bootstrap replicates over pixels (>= 20)")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed")
    p.add_argument("--plot", type=Path, default=None, metavar="PNG",
                   help="picture of the camera model (per intensity band the frames' log change against the events' "
                        "predicted change with the fitted thresholds, residuals, the criterion over frame offset and "
                        "I0, every value's uncertainty); default: OUT with the suffix .png")
    p.add_argument("--no-plot", action="store_true", help="do not draw the picture")
    p.set_defaults(func=run_sensor)


@json_output
def run_sensor(args) -> int:
    from .._util.atomic import check_outputs, write_json_atomic
    from ..formats import read
    from .sensor_profile import estimate_sensor_profile

    check_outputs({"--out": args.out}, [args.recording, args.profile], overwrite=args.overwrite,
                  command="calibrate sensor")
    t0 = time.perf_counter()
    rec = read(args.recording, format=args.format) if args.format else read(args.recording)
    import warnings

    from .camera_model import GridEdgeWarning
    with warnings.catch_warnings(record=True) as wl:
        warnings.simplefilter("always", GridEdgeWarning)
        prof = estimate_sensor_profile(rec, profile=args.profile, static_log_bound=args.static_log_bound,
                                       n_boot=args.bootstrap, seed=args.seed, name=args.name,
                                       sensor_model=args.sensor_model, keep_model=not args.no_plot)
    notes = [str(w.message) for w in wl if issubclass(w.category, GridEdgeWarning)]
    for n_ in notes:
        print(f"warning: {n_}", file=sys.stderr)
    prof.provenance["warnings"] = notes
    plot = None
    model = prof.provenance.pop("_model", None)
    if not args.no_plot and model is not None:
        from .camera_model import plot_camera_model
        plot = args.plot or args.out.with_suffix(".png")
        plot.parent.mkdir(parents=True, exist_ok=True)
        plot_camera_model(rec, model, plot, profile=args.profile, title=f"{args.recording.name}: camera model")
        prof.provenance["plot"] = str(plot)
    prof.provenance.update(command=["hybridhdr", *sys.argv[1:]], input=str(args.recording))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(args.out, prof.to_dict(), indent=1)
    if args.json:
        print(json.dumps({**prof.to_dict(), "written": str(args.out), "time_s": round(time.perf_counter() - t0, 3)}))
        return 0
    print(f"{args.recording}: {len(rec.events)} events, {len(rec.frames)} frames")
    for k, e in prof.estimates.items():
        if e["identifiable"]:
            ci = e["ci95"]
            ci_s = f" (95 % {ci[0]:.4g} .. {ci[1]:.4g})" if ci else ""
            sd = f" +- {e['std']:.2g}" if e["std"] is not None else ""
            print(f"  {k:<26} {e['value']:.4g} {e['unit']}{sd}{ci_s}")
        else:
            ub = e.get("upper_bound_us")
            print(f"  {k:<26} not identifiable" + (f" (at most {ub:.0f} us)" if ub else "") + f": {e['reason']}")
    if plot is not None:
        print(f"wrote {plot} (the model: frames' log change against the events, per intensity band)")
    print(f"wrote {args.out} (simulator fields: {', '.join(sorted(prof.simulator_params)) or 'none'}) in "
          f"{time.perf_counter() - t0:.1f} s")
    return 0
