"""The ``info``, ``convert`` and ``demo`` subcommands."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ._util.cliargs import HelpFormatter, add_format_arg, chunk_events_count, json_output
from ._util.timearg import add_time_window


def add_parsers(sub) -> None:
    fmt = HelpFormatter  # common options (--debug, --no-progress, --json, -q/-v): hybridhdr._util.cliargs.finalise
    p = sub.add_parser("info", help="summarise an event file (format, size, counts (events, frames, triggers, IMU "
                                    "samples), span, rate)",
                       formatter_class=fmt, description="Summarise an event file of any supported format.")
    p.add_argument("file", type=Path, help="event file or folder")
    add_format_arg(p)
    p.add_argument("--allow-huge", action="store_true",
                   help="lift the size limits on what file headers may ask for (sensor/frame side 8192, 4 GiB of "
                        "frames, 256 MiB packets; docs/security.md) for genuinely huge data")
    p.set_defaults(func=run_info)

    p = sub.add_parser("convert", help="convert between event formats", formatter_class=fmt,
                       description="Convert an event file; streams in chunks with bounded memory.")
    p.add_argument("input", type=Path)
    p.add_argument("output", type=Path)
    add_format_arg(p, dest="from_format")
    p.add_argument("--to", dest="to_format", default=None, help="output format (default: from extension)")
    p.add_argument("--chunk-events", type=chunk_events_count, default=1 << 20, help="events per streamed chunk")
    from ._util.cliargs import FRAME_ENCODING_CHOICES
    p.add_argument("--frame-encoding", choices=FRAME_ENCODING_CHOICES, default=None,
                   help="declare the frames' transfer function (linear; gamma2.2: code = max*I^(1/2.2); srgb: "
                        "IEC 61966-2-1), replacing what the input states or its reader assumes; stored in the "
                        "output (the container's /frames encoding). Default: as read")
    add_time_window(p, "events, triggers and frames")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUTPUT (refused without it)")
    p.add_argument("--allow-huge", action="store_true",
                   help="lift the size limits on what file headers may ask for (sensor/frame side 8192, 4 GiB of "
                        "frames, 256 MiB packets; docs/security.md) for genuinely huge data")
    p.set_defaults(func=run_convert)

    p = sub.add_parser("demo", help="run the main job on a built-in procedural recording",
                       formatter_class=fmt,
                       description="Build a procedural hybrid recording in memory, write and read it "
                                   "through every writer, print the info table, reconstruct, then run a small "
                                   "benchmark (speed-accuracy and stability charts) and the paper's Table 1 on "
                                   "simulated HDR/AHDR sets.")
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--weights-e2vid", type=Path, default=None, metavar="PATH",
                   help="E2VID checkpoint (E2VID_lightweight.pth.tar): adds the E2VID column to Table 1 "
                        "(never downloaded; omitted without it)")
    p.add_argument("--weights-firenet", type=Path, default=None, metavar="PATH",
                   help="FireNet checkpoint (firenet_1000.pth.tar): adds the FireNet column to Table 1")
    p.set_defaults(func=run_demo)


# -- info -------------------------------------------------------------------------------------
def summarise(path, format=None, chunk_events: int = 1 << 20) -> dict:
    """Stream a file once and return its summary (format, sizes, counts of events, frames, triggers
    and IMU samples, span, rate, polarity)."""
    import numpy as np

    from .formats import open_reader
    with open_reader(path, format) as r:
        n = n_on = 0
        n_trig = 0
        t_first = t_last = None
        for c in r.iter_chunks(chunk_events):
            ev = c.events
            n_trig += len(c.triggers)
            if len(ev):
                n += len(ev)
                n_on += int(np.count_nonzero(ev["p"] > 0))
                if t_first is None:
                    t_first = int(ev["t"][0])
                t_last = int(ev["t"][-1])
        frames = r.read_frames()
        info = {"file": str(path), "format": r.format_name,
                "sensor": None if r.sensor_size is None else f"{r.sensor_size.width}x{r.sensor_size.height}",
                "events": n, "t_first_us": t_first, "t_last_us": t_last,
                "span_us": None if t_first is None else t_last - t_first,
                "rate_mev_per_s": None if not n or t_last == t_first else n / (t_last - t_first),
                "on_fraction": None if not n else n_on / n,
                "frames": 0 if frames is None else len(frames), "triggers": n_trig, "imu": len(r.read_imu())}
        if frames is not None and len(frames):
            info["frame_size"] = f"{frames.shape[1]}x{frames.shape[0]}"
            info["frame_dtype"] = str(frames.images.dtype)
            info["frames_t_first_us"] = int(frames.t_start_us[0])
            info["frames_t_last_us"] = int(frames.t_end_us[-1])
        cam = r.metadata.event_camera
        if cam.model:
            info["camera"] = cam.model
        return info


def format_info(info: dict) -> str:
    def us(v):
        return "-" if v is None else f"{v:,} µs ({v / 1e6:.6f} s)"
    rows = [("file", info["file"]), ("format", info["format"]), ("sensor (WxH)", info["sensor"] or "unknown"),
            ("events", f"{info['events']:,}"), ("first t", us(info["t_first_us"])),
            ("last t", us(info["t_last_us"])), ("span", us(info["span_us"])),
            ("rate", "-" if info["rate_mev_per_s"] is None else f"{info['rate_mev_per_s']:.3f} Mev/s"),
            ("ON / OFF", "-" if info["on_fraction"] is None else
             f"{100 * info['on_fraction']:.1f}% / {100 * (1 - info['on_fraction']):.1f}%"),
            ("frames", str(info["frames"]) + (f" ({info['frame_size']}, {info['frame_dtype']})"
                                               if info.get("frames") else "")),
            ("triggers", f"{info['triggers']:,}"), ("IMU samples", f"{info.get('imu', 0):,}")]
    if "camera" in info:
        rows.insert(3, ("camera", info["camera"]))
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)


@json_output
def run_info(args) -> int:
    from ._util.limits import allow_huge
    with allow_huge(args.allow_huge):
        info = summarise(args.file, args.format)
    print(json.dumps(info) if args.json else format_info(info))
    return 0


# -- convert ----------------------------------------------------------------------------------
def convert(input, output, from_format=None, to_format=None, start_us=None, end_us=None,
            chunk_events: int = 1 << 20, progress: bool = False, frame_encoding: str | None = None) -> dict:
    """Stream ``input`` into ``output``; returns counts and what the output format could not hold.

    ``frame_encoding`` (``linear``, ``gamma2.2``, ``srgb``) declares the frames' encoding: the
    reader is opened with it (so what it derives from the encoding, such as the AKF ``.mat``
    camera profile, agrees) and the frames written carry it. The result's ``frame_encoding`` is
    the encoding of the frames written (None without frames).
    """
    from ._util.prefetch import Prefetcher
    from .camera.encoding import parse_frame_encoding, with_encoding
    from .events import slice_time
    from .formats import open_reader, open_writer, unsupported_parts
    from .model import Recording
    if start_us is not None and end_us is not None and end_us <= start_us:
        raise ValueError(f"--end-us ({end_us}) must be greater than --start-us ({start_us})")
    opts = {}
    if frame_encoding is not None:
        opts["frame_encoding"] = parse_frame_encoding(frame_encoding)
    with open_reader(input, from_format, **opts) as r:
        if r.sensor_size is None:
            raise ValueError(f"{input}: the sensor size is unknown; pass it to the reader")
        total = getattr(r, "n_events", None)
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=total, unit="ev", unit_scale=True, desc=f"convert {Path(input).name}",
                       file=sys.stderr, dynamic_ncols=True)
        n_out = n_trig = n_imu = 0
        dropped_trig = 0
        try:
            with open_writer(output, to_format, sensor_size=r.sensor_size, metadata=r.metadata) as w, \
                    Prefetcher(r.iter_chunks(chunk_events), depth=2, name="hybridhdr-convert-read") as chunks:
                # the reader decodes the next chunks in a thread while this one is written
                can_trig = "triggers" in w.supports
                for c in chunks:
                    ev, tr = slice_time(c.events, start_us, end_us), slice_time(c.triggers, start_us, end_us)
                    w.write_events(ev)
                    if can_trig:
                        w.write_triggers(tr)
                        n_trig += len(tr)
                    else:
                        dropped_trig += len(tr)
                    n_out += len(ev)
                    if bar is not None:
                        bar.update(len(c.events))
                    if end_us is not None and len(c.events) and c.events["t"][-1] >= end_us:
                        break
                chunks.close()  # the reader thread has stopped before the reader is used again
                frames = with_encoding(r.read_frames(), frame_encoding)
                if frames is not None and (start_us is not None or end_us is not None):
                    frames = frames.slice_time(start_us, end_us)
                frame_enc = None if frames is None or not len(frames) else frames.encoding
                dropped = unsupported_parts(Recording(frames=frames), w.supports)
                if "frames" in w.supports:
                    w.write_frames(frames)
                if dropped_trig:
                    dropped.append(f"{dropped_trig} triggers")
                hdr = r.read_hdr() if hasattr(r, "read_hdr") else None
                if hdr is not None and len(hdr):
                    if "hdr" in w.supports:
                        w.write_hdr(hdr)
                    else:
                        dropped.append(f"{len(hdr)} HDR references")
                imu = slice_time(r.read_imu(), start_us, end_us)
                if len(imu):
                    if "imu" in w.supports:
                        w.write_imu(imu)
                        n_imu = len(imu)
                    else:
                        dropped.append(f"{len(imu)} IMU samples")
                fmt_out = w.format_name
        finally:
            if bar is not None:
                bar.close()
    return {"events": n_out, "triggers": n_trig, "imu": n_imu, "dropped": dropped, "format": fmt_out, "frame_encoding": frame_enc}


@json_output
def run_convert(args) -> int:
    import shutil

    from ._util.limits import allow_huge
    from ._util.timearg import check_window, empty_window_error, resolve_window, window_given
    from .formats.span import recording_span
    from ._util.atomic import check_outputs
    windowed = window_given(args)
    check_window(args)
    check_outputs({"OUTPUT": args.output}, [args.input], overwrite=args.overwrite, command="convert")
    with allow_huge(args.allow_huge):
        t0 = t1 = None
        if windowed:
            relative = args.start_us is None and args.end_us is None and not args.absolute
            origin = recording_span(args.input, args.from_format, full=False).origin_us if relative else None
            t0, t1 = resolve_window(args, origin)
        res = convert(args.input, args.output, args.from_format, args.to_format, t0, t1,
                      args.chunk_events, progress=not args.no_progress, frame_encoding=args.frame_encoding)
        if windowed and res["events"] == 0 and res["frame_encoding"] is None:
            out = Path(args.output)  # an empty window is an error: the (empty) output is not kept
            if out.is_dir():
                shutil.rmtree(out)
            elif out.exists():
                out.unlink()
            raise empty_window_error(args, t0, t1, recording_span(args.input, args.from_format))
    res["window_us"] = [t0, t1]
    if args.json:
        print(json.dumps({"output": str(args.output), **res}))
    else:
        enc = "" if res["frame_encoding"] is None else f", frames encoded {res['frame_encoding']}"
        imu = f", {res['imu']:,} IMU samples" if res["imu"] else ""
        print(f"wrote {args.output} ({res['format']}): {res['events']:,} events, {res['triggers']:,} triggers{imu}{enc}")
    if args.frame_encoding is not None and res["frame_encoding"] is None:
        print(f"note: {args.input} has no frames; --frame-encoding {args.frame_encoding} had nothing to apply to",
              file=sys.stderr)
    if res["dropped"]:
        print(f"note: the {res['format']} format cannot hold {', '.join(res['dropped'])}; they were not written",
              file=sys.stderr)
    return 0


# -- demo -------------------------------------------------------------------------------------
def run_demo(args) -> int:
    import warnings

    import numpy as np

    from .evaluate.demo import demo_step, perceptual_score_note
    from .evaluate.paper import demo_evaluate
    from .formats import DataDropWarning, formats, read, write
    from .formats.container import write_recording
    from .simulate.procedural import procedural_recording
    from .simulate.render import select_variant

    for name, w in (("e2vid", args.weights_e2vid), ("firenet", args.weights_firenet)):
        if w is not None and not Path(w).is_file():  # before any work
            raise FileNotFoundError(f"--weights-{name}: {w} is not a file (hybridhdr never downloads weights; "
                                    f"see docs/reconstruct.md, 'Learned events-only baselines')")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print("hybridhdr demo: procedural hybrid recording (bright disc 1000x brighter than a textured "
          "background, 120x90, 0.5 s)")
    rec, scene = procedural_recording(seed=args.seed)
    main_path = out / "procedural.h5"
    write_recording(rec, main_path)
    print(format_info(summarise(main_path)))
    print("\nround trip through every writer:")
    rows = []
    for fmt, spec in formats().items():
        if spec.writer is None:
            continue
        ext = {"hybridhdr": ".h5", "evt2": ".raw", "evt3": ".raw", "dat": ".dat", "akf_mat": ".mat",
               "ecd": ""}.get(fmt, "." + fmt)
        path = out / f"procedural_{fmt}{ext}"
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", DataDropWarning)
            try:
                write(rec, path, fmt)
            except ImportError as e:  # a writer whose library is not installed (aedat4: dv-processing)
                rows.append((fmt, "unavailable", str(e)))
                continue
        back = read(path, fmt)
        same = np.array_equal(back.events, rec.events)
        kept = []
        if back.frames is not None and len(back.frames):
            kept.append(f"{len(back.frames)} frames")
        note = "; ".join(str(w.message).split(": ", 1)[-1] for w in caught)
        rows.append((fmt, "identical events" if same else "EVENTS DIFFER",
                     ", ".join(kept) + (f" ({note})" if note else "")))
    w = max(len(r[0]) for r in rows)
    for fmt, status, extra in rows:
        print(f"  {fmt:<{w}}  {status:<18} {extra}")
    bad = [r for r in rows if r[1] == "EVENTS DIFFER"]
    print("\nreconstruction:")
    print(demo_step(rec, out))
    print("\nevaluation (simulate, reconstruct, score):", flush=True)
    if (note := perceptual_score_note()) is not None:
        print(note, flush=True)
    try:  # the renderer is chosen here, once: its one-line note (if any) is not repeated by the workers
        select_variant()
    except ImportError:  # no Mitsuba: demo_evaluate says so
        pass
    weights = {"e2vid": args.weights_e2vid, "firenet": args.weights_firenet}
    print(demo_evaluate(out / "evaluate", seed=args.seed, progress=not args.no_progress, weights=weights))
    print(f"\noutputs in {out.resolve()}")
    return 1 if bad else 0
