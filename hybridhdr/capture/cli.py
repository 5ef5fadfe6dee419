"""``hybridhdr capture devices | record | brackets | sync | recover | session``."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from .._util.cliargs import COMMON, COMMON_NO_JSON, HelpFormatter, json_command, json_output, positive_float, positive_int

DESCRIPTION = "record and read hybrid data (devices, brackets, sync, recorder)"
_FMT = HelpFormatter  # common options (--debug, --no-progress, --json, -q/-v) come from COMMON


def add_parser(sub) -> None:
    p = sub.add_parser("capture", help=DESCRIPTION, formatter_class=_FMT,
                       description="Capture hybrid event/frame data: list cameras, record with a crash-safe "
                                   "recorder, capture exposure brackets, synchronise clocks, recover and "
                                   "package dataset sessions. See docs/capture.md.")
    p.set_defaults(func=lambda a: (p.print_help(), 0)[1])
    cs = p.add_subparsers(dest="capture_command", metavar="STEP")

    d = cs.add_parser("devices", help="list attached event and frame cameras (USB IDs, dv-processing, pylon)",
                      formatter_class=_FMT, parents=[COMMON],
                      description="List attached cameras: by USB vendor/product ID (pyusb: Prophesee, iniVation, "
                                  "Luxonis, FLIR, Basler, ...), DAVIS/DVXplorer through dv-processing and Basler/GenICam "
                                  "cameras through pylon. A package that is missing is named with the extra that "
                                  "installs it (exit 0). Exits 1 when every lister ran and found nothing, except with "
                                  "--json, which prints the list ([] when empty) and exits 0.")
    d.add_argument("--all", action="store_true", help="also list USB devices that are not known cameras")
    d.set_defaults(func=run_devices)

    r = cs.add_parser("record", help="record events (+ frames) through the crash-safe recorder",
                      formatter_class=_FMT, parents=[COMMON_NO_JSON],
                      description="Record an event source and optionally a frame source into a hybridhdr "
                                  "container. Data go to OUT.journal while recording; after a crash run "
                                  "'hybridhdr capture recover OUT'.")
    r.add_argument("--events", default=None,
                   help="event source: a file to replay (any readable format), 'synthetic:RATE' (events/s), "
                        "or 'prophesee' / 'device' for a live Prophesee camera")
    r.add_argument("--camera", default=None, metavar="davis[:SERIAL]",
                   help="a DAVIS or DVXplorer through dv-processing: events, triggers, IMU samples and (DAVIS) "
                        "frames from one device")
    r.add_argument("--source", action="append", default=[], metavar="URL",
                   help="a DV network stream, dv-tcp://HOST:PORT or dv-unix:///path/to/socket; repeat it, one per "
                        "stream kind (events, frames, triggers, imu)")
    r.add_argument("--frames", default=None,
                   help="frame source: a file to replay, 'oak' / 'device' for a Luxonis OAK, 'pylon[:SERIAL]' for a "
                        "Basler/GenICam camera, or 'none' to leave out a DAVIS's or DV stream's frames")
    r.add_argument("--gain-db", type=float, default=None, help="pylon: fixed gain (dB)")
    r.add_argument("--frame-rate-hz", type=positive_float, default=None,
                   help="pylon: free-running frame rate; DAVIS: APS frame rate (frame interval = 1/rate)")
    r.add_argument("--trigger", default="free", choices=("free", "software", "Line1", "Line2", "Line3", "Line4"),
                   help="pylon trigger: free-running, software (at --trigger-rate-hz) or a hardware input line")
    r.add_argument("--trigger-rate-hz", type=positive_float, default=None, help="pylon: software trigger rate")
    r.add_argument("--pixel-format", default=None, help="pylon pixel format (Mono8, Mono12, Mono16, RGB8 ...)")
    r.add_argument("--reconnect-s", type=positive_float, default=5.0,
                   help="DV inputs: how long an interrupted stream or camera is reconnected before it ends")
    r.add_argument("--sync", choices=("none", "host"), default="none",
                   help="host: after recording, put the frames on the event clock through both sources' host-clock "
                        "samples and write the sync report to OUT.sync.json (a rig without trigger wiring; with "
                        "wiring use 'capture sync')")
    r.add_argument("--out", type=Path, required=True, help="output container (.h5)")
    r.add_argument("--duration-s", type=positive_float, default=None, help="stop after this many seconds (default: "
                   "end of the replayed file, Ctrl-C for live sources)")
    r.add_argument("--pace", choices=("realtime", "fast"), default="realtime", help="replay pacing")
    r.add_argument("--speed", type=positive_float, default=1.0, help="replay speed factor (realtime pace)")
    r.add_argument("--chunk-us", type=positive_int, default=10_000, help="event chunk length (µs)")
    r.add_argument("--queue-chunks", type=positive_int, default=64, help="recorder queue capacity (chunks/frames)")
    r.add_argument("--flush-interval-s", type=positive_float, default=1.0, help="journal flush period (s)")
    r.add_argument("--on-full", choices=("auto", "block", "drop"), default="auto", help="queue-full policy")
    r.add_argument("--compression", choices=("gzip", "lzf", "none"), default="gzip", help="container compression")
    r.add_argument("--fsync", action="store_true", help="fsync the journal at each flush (power-loss safe)")
    r.add_argument("--exposure-us", type=int, default=None,
                   help="manual exposure (µs): OAK (with --iso), pylon, or the DAVIS APS")
    r.add_argument("--iso", type=int, default=None, help="OAK manual ISO (100-1600)")
    r.add_argument("--frame-sync", choices=("off", "input", "output"), default=None, help="OAK FSYNC role")
    r.add_argument("--trigger-channels", type=int, nargs="*", default=(), help="Prophesee trigger inputs to enable")
    r.add_argument("--allow-huge", action="store_true", help="lift the header size limits (docs/security.md)")
    r.set_defaults(func=run_record)

    b = cs.add_parser("brackets", help="read a bracket folder (RAW/JPEG/PNG) or capture one with an OAK",
                      formatter_class=_FMT, parents=[COMMON],
                      description="Summarise a bracket set (RAW files with EXIF exposure, JPEG/PNG with "
                                  "exposures.txt, or a brackets.json folder), optionally rewriting it as a "
                                  "brackets.json folder; or capture one from an OAK camera.")
    b.add_argument("folder", nargs="?", type=Path, help="bracket folder to read")
    b.add_argument("--device", default=None, metavar="oak|pylon[:SERIAL]", help="capture from a camera instead")
    b.add_argument("--gain-db", type=float, default=None, help="pylon: fixed gain (dB) for the bracket")
    b.add_argument("--pixel-format", default=None, help="pylon pixel format (Mono8, Mono12 ...)")
    b.add_argument("--exposures-us", type=int, nargs="+", default=None, help="exposures to capture (µs)")
    b.add_argument("--iso", type=int, default=100, help="ISO for the capture")
    b.add_argument("--frames-per-step", type=positive_int, default=1, help="frames kept per exposure")
    b.add_argument("--out", type=Path, default=None, help="write a bracket-set folder (brackets.json + PNG)")
    b.add_argument("--plot", type=Path, default=None, help="PNG contact sheet of the bracket")
    b.add_argument("--overwrite", action="store_true",
                   help="replace an existing non-empty --out set (its brackets.json and exp_*.png) and --plot "
                        "(refused without it)")
    b.set_defaults(func=run_brackets)

    s = cs.add_parser("sync", help="map frame exposures onto the event clock from trigger edges",
                      formatter_class=_FMT, parents=[COMMON_NO_JSON],
                      description="Pair trigger pulses with frames, fit offset and drift robustly, report "
                                  "jitter and missing/extra triggers, and write the recording with frame "
                                  "times on the event clock.")
    s.add_argument("recording", type=Path)
    s.add_argument("--trigger-channel", type=int, default=0, help="trigger channel of the frame strobe")
    s.add_argument("--edge-mode", choices=("both", "rising"), default="both",
                   help="both: rising = exposure start, falling = end; rising: starts only")
    s.add_argument("--use", choices=("measured", "fit"), default="measured",
                   help="frame times from the measured edges or from the fitted clock mapping")
    s.add_argument("--frame-period-us", type=float, default=None, help="frame period (default: estimated)")
    s.add_argument("--out", type=Path, default=None, help="write the synchronised recording here")
    s.add_argument("--report", type=Path, default=None, help="write the report as JSON")
    s.add_argument("--plot", type=Path, default=None, help="PNG of the fit residuals")
    s.add_argument("--overwrite", action="store_true", help="replace existing --out/--report/--plot files")
    s.set_defaults(func=run_sync)

    sv = cs.add_parser("serve-dv", help="serve an AEDAT4 recording as DV network streams (a stand-in for a live DAVIS)",
                       formatter_class=_FMT, parents=[COMMON_NO_JSON],
                       description="Serve a recording's events, frames, triggers and IMU samples with dv-processing's "
                                   "NetworkWriter, "
                                   "one stream per kind, as iniVation's DV software streams a live camera; waits for a "
                                   "client on every stream, then sends in recorded time.")
    sv.add_argument("file", type=Path, help="AEDAT4 recording")
    sv.add_argument("--events", default=None, metavar="URL",
                    help="dv-tcp://HOST:PORT or dv-unix:///path; port 0 picks a free port (printed with the others "
                         "on the 'serving ...' line, for capture record's --source)")
    sv.add_argument("--frames", default=None, metavar="URL")
    sv.add_argument("--triggers", default=None, metavar="URL")
    sv.add_argument("--imu", default=None, metavar="URL", help="the IMU samples' stream")
    sv.add_argument("--speed", type=positive_float, default=1.0, help="pace (1 = recorded rate)")
    sv.add_argument("--fast", action="store_true", help="send as fast as possible")
    sv.add_argument("--wait-clients-s", type=positive_float, default=60.0, help="how long to wait for clients")
    sv.set_defaults(func=run_serve_dv)

    v = cs.add_parser("recover", help="rebuild a recording from the journal of an interrupted capture",
                      formatter_class=_FMT, parents=[COMMON_NO_JSON],
                      description="Replay REC.h5.journal (left by a crash or kill -9) into REC.h5: everything "
                                  "up to the last flush, plus later records whose checksums are intact.")
    v.add_argument("file", type=Path, help="the recording name (REC.h5) or its journal")
    v.add_argument("--out", type=Path, default=None, help="output container (default: the recording name)")
    v.add_argument("--compression", choices=("gzip", "lzf", "none"), default="gzip", help="container compression")
    v.add_argument("--keep-journal", action="store_true", help="keep the journal after a successful recovery")
    v.add_argument("--allow-huge", action="store_true", help="lift the header size limits (docs/security.md)")
    v.set_defaults(func=run_recover)

    e = cs.add_parser("session", help="write or verify a dataset sequence folder with a manifest",
                      formatter_class=_FMT, parents=[COMMON_NO_JSON],
                      description="Package a recording, calibration, camera profile and bracket sets into one "
                                  "sequence folder with manifest.json (sha256 + size of every file); or "
                                  "verify such a folder with --verify.")
    e.add_argument("folder", nargs="?", type=Path, help="sequence folder to create")
    e.add_argument("--recording", type=Path, default=None, help="hybridhdr container to include")
    e.add_argument("--calibration", type=Path, default=None, help="calibration file")
    e.add_argument("--profile", type=Path, default=None, help="camera profile file")
    e.add_argument("--brackets", type=Path, nargs="*", default=(), help="bracket-set folders")
    e.add_argument("--reference", action="store_true",
                   help="reference calibration/profile by relative path + checksum instead of copying")
    e.add_argument("--name", default=None, help="sequence name (default: folder name)")
    e.add_argument("--notes", default="", help="free text for the manifest")
    e.add_argument("--verify", type=Path, default=None, metavar="DIR", help="verify an existing session folder")
    e.set_defaults(func=run_session)


def _comp(v):
    return None if v == "none" else v


# -- devices ----------------------------------------------------------------------------------
@json_output
def run_devices(args) -> int:
    from .devices import NoDeviceFound
    from .discovery import discover, format_device_dicts
    devs, notes = discover(include_unknown=args.all)
    for n in notes:
        print(f"note: {n}", file=sys.stderr)
    if args.json:  # a list, empty or not, is the answer
        print(json.dumps(devs))
        return 0
    if not devs:
        if notes:
            print("no device found by the installed listers (see the notes above)")
            return 0
        raise NoDeviceFound("no device found (looked for Prophesee, iniVation, Luxonis OAK, FLIR, Basler, "
                            "Allied Vision, IDS and XIMEA USB IDs, dv-processing and pylon cameras; see "
                            "docs/capture.md)")
    print(format_device_dicts(devs))
    return 0


# -- record -----------------------------------------------------------------------------------
def _event_source(args):
    given = [k for k in ("events", "camera", "source") if getattr(args, k)]
    if len(given) != 1:
        raise ValueError(f"give one event source: --events FILE|synthetic:RATE|prophesee, --camera davis[:SERIAL] "
                         f"or --source URL (one per DV stream); got {given or 'none'}")
    if args.camera or args.source:
        from .dv_backend import DvCapture
        specs = [args.camera] if args.camera else list(args.source)
        if args.camera and not (args.camera == "davis" or args.camera.startswith("davis:")):
            raise ValueError(f"--camera {args.camera!r}: expected davis or davis:SERIAL (DAVIS and DVXplorer cameras)")
        cam_controls = bool(args.camera) and args.frames in (None, "none")
        fi = None if not (cam_controls and args.frame_rate_hz) else int(round(1e6 / args.frame_rate_hz))
        cap = DvCapture(specs, exposure_us=args.exposure_us if cam_controls else None, frame_interval_us=fi,
                        reconnect_timeout_s=args.reconnect_s)
        return cap.event_source()
    spec = args.events
    if spec in ("prophesee", "device"):
        from .prophesee_backend import PropheseeEventSource
        return PropheseeEventSource(delta_t_us=args.chunk_us, trigger_channels=args.trigger_channels)
    if spec == "oak":
        raise ValueError("a Luxonis OAK is a frame camera: use --frames oak (events come from a file, "
                         "'synthetic:RATE' or 'prophesee')")
    if spec.startswith("synthetic:"):
        from .sources import SyntheticEventSource
        try:
            rate = float(spec.split(":", 1)[1])
        except ValueError:
            raise ValueError(f"--events synthetic:RATE needs a rate in events/s, got {spec!r}") from None
        return SyntheticEventSource(rate, chunk_us=args.chunk_us, pace=args.pace, duration_s=args.duration_s)
    from .sources import ReplayEventSource
    if not Path(spec).exists():
        raise FileNotFoundError(f"--events {spec}: no such file (or use 'synthetic:RATE', 'prophesee', --camera davis "
                                f"or --source URL)")
    return ReplayEventSource(spec, pace=args.pace, speed=args.speed, chunk_us=args.chunk_us)


def _frame_source(args, t_origin_us=None, ev=None):
    spec = args.frames
    if spec is None:
        cap = getattr(ev, "capture", None)
        return None if cap is None else cap.frame_source()  # a DAVIS's or a DV frame stream's frames
    if spec == "none":
        return None
    if spec in ("oak", "device"):
        from .depthai_backend import DepthaiFrameSource
        return DepthaiFrameSource(exposure_us=args.exposure_us, iso=args.iso, frame_sync=args.frame_sync)
    if spec == "pylon" or spec.startswith("pylon:"):
        from .pylon_backend import PylonFrameSource
        return PylonFrameSource(spec.split(":", 1)[1] if ":" in spec else None, exposure_us=args.exposure_us,
                                gain_db=args.gain_db, pixel_format=args.pixel_format, trigger=args.trigger,
                                software_rate_hz=args.trigger_rate_hz, frame_rate_hz=args.frame_rate_hz)
    from .sources import ReplayFrameSource
    if not Path(spec).exists():
        raise FileNotFoundError(f"--frames {spec}: no such file (or use 'oak', 'pylon[:SERIAL]', 'none')")
    return ReplayFrameSource(spec, pace=args.pace, speed=args.speed, t_origin_us=t_origin_us)


@json_command
def run_record(args) -> int:
    from .._util.limits import allow_huge
    with allow_huge(args.allow_huge):
        return _run_record(args)


def _host_sync(out: Path) -> dict:
    """Rewrite OUT with its frames on the event clock (host-clock samples); the report to OUT.sync.json."""
    import os

    from .._util.atomic import write_json_atomic
    from ..formats.container import read_recording, write_recording
    from .rig import host_clock_sync_recording
    rec2, rep = host_clock_sync_recording(read_recording(out))
    tmp = out.with_name(out.name + ".sync.partial")
    if tmp.exists():
        raise FileExistsError(f"{tmp} exists (a left-over of an interrupted sync?); delete it first")
    write_recording(rec2, tmp)
    os.replace(tmp, out)
    rp = out.with_name(out.name + ".sync.json")
    write_json_atomic(rp, rep.to_dict())
    print(rep.summary())
    return {"report": str(rp), **rep.to_dict()}


def _run_record(args) -> int:
    from .recorder import Recorder, warm_up
    from .sources import ReplayEventSource
    if args.sync == "host" and args.frames in (None, "none") and not args.source:
        raise ValueError("--sync host needs a separate frame camera (--frames pylon|oak) or DV streams")
    ev = _event_source(args)
    fr = None
    warm_up()  # before any live source opens: nothing may wait unread while the kernel compiles
    try:
        separate_camera = args.frames is not None and args.frames not in ("none",) and not Path(args.frames).exists()
        if separate_camera:  # a frame camera opens (slowly) before a live event stream starts flowing
            fr = _frame_source(args, None, ev)
            fr.open()
        elif args.frames is None and getattr(ev, "capture", None) is not None:
            fr = ev.capture.frame_source()  # a DAVIS's or a DV stream's frames: wanted before the first arrives
        ev.open()
        origin = None
        if isinstance(ev, ReplayEventSource):
            tr = ev._reader.time_range_us if hasattr(ev._reader, "time_range_us") else None
            origin = None if tr is None else tr[0]
            ev.t_origin_us = origin
        if not separate_camera and fr is None:
            fr = _frame_source(args, origin, ev)
            if fr is not None:
                fr.open()
        rec = Recorder(args.out, ev, fr, queue_chunks=args.queue_chunks, flush_interval_s=args.flush_interval_s,
                       on_full=args.on_full, compression=_comp(args.compression), fsync=args.fsync,
                       progress=not args.no_progress)
        rec.start()
        print(f"recording to {args.out} (journal {rec.journal_path.name}); Ctrl-C to stop", file=sys.stderr)
        try:
            rec.wait(args.duration_s)
        except KeyboardInterrupt:
            print("stopping ...", file=sys.stderr)
        st = rec.finish()
    except BaseException:
        for s in (fr, ev):
            if s is not None:
                s.close()
        raise
    print(f"wrote {args.out}: {st.events_written:,} events, {st.triggers_written:,} triggers, "
          f"{st.imu_written:,} IMU samples, {st.frames_written:,} frames in {st.duration_s:.1f} s; "
          f"{st.flushes} flushes")
    if st.dropped_anything or st.frames_missing_by_sequence:
        print(f"WARNING: dropped {st.events_dropped:,} events, {st.triggers_dropped:,} triggers, "
              f"{st.imu_dropped:,} IMU samples, {st.frames_dropped:,} frames (queue full); {st.frames_missing_by_sequence:,} frames missing "
              f"by sequence number; {st.source_dropped:,} items dropped by the sources (out of order or "
              f"their buffer full)", file=sys.stderr)
    for role, c in st.source_counters.items():
        if c.get("restarts"):
            print(f"WARNING: {role} inputs stopped and came back {c['restarts']} time(s) (gaps µs: {c.get('gaps_us')}); "
                  f"data sent while an input was down is not in the recording", file=sys.stderr)
        if c.get("ended"):
            print(f"note: {c['ended']} {role} input(s) ended (the stream finished, the server stopped or the camera "
                  f"went away) and did not come back within {args.reconnect_s:g} s", file=sys.stderr)
    res = {"out": str(args.out), **st.to_dict(), "dropped_anything": st.dropped_anything}
    if args.sync == "host":
        res["sync"] = _host_sync(Path(args.out))
    args.emit_json(res)
    return 0


@json_command
def run_serve_dv(args) -> int:
    import os

    from .dv_backend import serve_recording
    urls = {k: getattr(args, k) for k in ("events", "frames", "triggers", "imu") if getattr(args, k)}
    if not urls:
        raise ValueError("give at least one of --events URL, --frames URL, --triggers URL, --imu URL")
    def ready(served):  # the sockets listen now (port 0 resolved to the free port chosen)
        print(f"serving {args.file}: {', '.join(f'{k} on {v}' for k, v in served.items())}; waiting for clients",
              file=sys.stderr, flush=True)
    counts = serve_recording(args.file, urls, speed=None if args.fast else args.speed,
                             wait_clients_s=args.wait_clients_s, on_ready=ready)
    print(f"served {', '.join(f'{v:,} {k}' for k, v in counts.items())}", flush=True)
    sys.stdout.flush()
    sys.stderr.flush()
    # a dv NetworkWriter with a connected client blocks in its destructor: end without running them
    os._exit(0)


# -- brackets ---------------------------------------------------------------------------------
def _bracket_summary(bs) -> dict:
    return {"images": len(bs), "encoding": bs.encoding, "shape": list(bs.images[0].shape),
            "dtype": str(bs.images[0].dtype), "exposures_s": [float(e) for e in bs.exposures_s],
            "files": list(bs.files), "camera": bs.camera}


def _plot_brackets(images, exposures_s, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    k = len(images)
    cols = min(k, 6)
    rows = (k + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(2.2 * cols, 2.0 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for i, (im, e) in enumerate(zip(images, exposures_s)):
        a = np.asarray(im, dtype=np.float64)
        a = a / max(float(a.max()), 1e-12)
        axes.ravel()[i].imshow(a, cmap="gray" if a.ndim == 2 else None, vmin=0, vmax=1)
        axes.ravel()[i].set_title(f"{e * 1e3:.3g} ms", fontsize=8)
    fig.tight_layout()
    from .._util.atomic import atomic_path
    try:
        with atomic_path(path, ".png") as tmp:
            fig.savefig(tmp, dpi=100, format="png")
    finally:
        plt.close(fig)


@json_command
def run_brackets(args) -> int:
    from .._util.atomic import check_outputs
    folder_in = args.folder if args.device is None else None
    check_outputs({"--out": args.out, "--plot": args.plot},
                  [folder_in] + (sorted(Path(folder_in).iterdir()) if folder_in is not None and Path(folder_in).is_dir()
                                 else []),
                  overwrite=args.overwrite, command="capture brackets")
    if args.device is not None and (args.device == "pylon" or args.device.startswith("pylon:")):
        if not args.exposures_us or args.out is None:
            raise ValueError("--device pylon needs --exposures-us (µs values to capture) and --out FOLDER")
        from .pylon_backend import PylonFrameSource
        src = PylonFrameSource(args.device.split(":", 1)[1] if ":" in args.device else None, trigger="software",
                               pixel_format=args.pixel_format)
        try:
            src.open()
            items, rep = src.capture_brackets(args.exposures_us, gain_db=args.gain_db,
                                              frames_per_step=args.frames_per_step, folder=args.out,
                                              overwrite=args.overwrite)
        finally:
            src.close()
        print(f"wrote {args.out}: {len(items)} frames; exposures read back from the camera (µs): {rep['reported_us']}")
        if args.plot is not None:
            _plot_brackets([it.image for it in items], [it.exposure_us * 1e-6 for it in items], args.plot)
        args.emit_json({"out": str(args.out), "frames": len(items), **rep})
        return 0
    if args.device is not None and args.device != "oak":
        raise ValueError(f"--device {args.device!r}: expected oak, pylon or pylon:SERIAL")
    if args.device == "oak":
        if not args.exposures_us:
            raise ValueError("--device oak needs --exposures-us (µs values to capture)")
        if args.out is None:
            raise ValueError("--device oak needs --out FOLDER for the bracket set")
        from .depthai_backend import DepthaiFrameSource
        src = DepthaiFrameSource()
        try:
            items, rep = src.capture_brackets(args.exposures_us, args.iso, args.frames_per_step, args.out,
                                              overwrite=args.overwrite)
        finally:
            src.close()
        print(f"wrote {args.out}: {len(items)} frames; reported exposures (µs): {rep['reported_us']}; "
              f"frames discarded while exposure changes applied: {rep['frames_discarded']}")
        args.emit_json({"out": str(args.out), "frames": len(items), **rep})
        return 0
    if args.folder is None:
        raise ValueError("give a bracket FOLDER to read, or --device oak to capture one")
    from ..formats.brackets import read_bracket_set, write_bracket_set
    bs = read_bracket_set(args.folder)
    info = _bracket_summary(bs)
    print(f"{args.folder}: {info['images']} images {info['shape']} {info['dtype']}, encoding {info['encoding']}")
    for f, e in zip(info["files"], info["exposures_s"]):
        print(f"  {f:<32} {e:.6g} s")
    if args.plot is not None:
        _plot_brackets(bs.images, bs.exposures_s, args.plot)
    if args.out is not None:
        import numpy as np
        if bs.images[0].dtype not in (np.uint8, np.uint16):
            raise ValueError(f"the images are {bs.images[0].dtype} (linear RAW); a brackets.json folder stores "
                             f"uint8/uint16 PNG codes, so keep the RAW folder as the bracket set")
        write_bracket_set(args.out, bs.images, bs.exposures_s, encoding=bs.encoding, camera=bs.camera,
                          iso=bs.iso, gain=bs.gain, t_us=bs.t_us, overwrite=args.overwrite)
        print(f"wrote {args.out}")
    args.emit_json({**info, "out": None if args.out is None else str(args.out),
                    "plot": None if args.plot is None else str(args.plot)})
    return 0


# -- sync -------------------------------------------------------------------------------------
def _plot_sync(frames_in, frames_out, report, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    a, b = report.offset_us, 1 + report.drift_ppm * 1e-6
    fit = a + b * frames_in.t_start_us.astype(np.float64)
    res = frames_out.t_start_us - fit
    fig, ax = plt.subplots(figsize=(7, 3))
    ax.plot(frames_in.t_start_us / 1e6, res, ".", ms=3)
    ax.set_xlabel("frame clock (s)")
    ax.set_ylabel("exposure start − fit (µs)")
    ax.set_title(f"drift {report.drift_ppm:.2f} ppm, jitter RMS {report.rms_us:.2f} µs")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


@json_command
def run_sync(args) -> int:
    from .._util.atomic import check_outputs, write_json_atomic
    from ..formats.container import read_recording, write_recording
    from .sync import sync_recording
    check_outputs({"--out": args.out, "--report": args.report, "--plot": args.plot}, [args.recording],
                  overwrite=args.overwrite, command="capture sync")
    rec = read_recording(args.recording)
    rec2, rep = sync_recording(rec, channel=args.trigger_channel, edge_mode=args.edge_mode, use=args.use,
                               frame_period_us=args.frame_period_us)
    print(rep.summary())
    d = rep.to_dict()
    if args.report is not None:
        write_json_atomic(args.report, d, indent=1)
    if args.plot is not None:
        _plot_sync(rec.frames, rec2.frames, rep, args.plot)
    if args.out is not None:
        write_recording(rec2, args.out)
        print(f"wrote {args.out}")
    if args.json:
        args.emit_json({**d, "out": None if args.out is None else str(args.out)})
    else:
        print(json.dumps(d))
    return 0


# -- recover ----------------------------------------------------------------------------------
@json_command
def run_recover(args) -> int:
    from .._util.limits import allow_huge
    from .recorder import journal_path, recover
    with allow_huge(args.allow_huge):
        res = recover(args.file, args.out, compression=_comp(args.compression), progress=not args.no_progress)
    print(f"recovered {res['output']}: {res['events']:,} events, {res['triggers']:,} triggers, "
          f"{res['imu']:,} IMU samples, {res['frames']:,} frames; {res['flushes']} flushes in the journal, "
          f"{res['events_after_last_flush']:,} events after the last flush were intact; stopped at: "
          f"{res['stop_reason']}")
    if not args.keep_journal:
        journal_path(args.file).unlink()
    args.emit_json({**res, "journal_kept": bool(args.keep_journal)})
    return 0


# -- session ----------------------------------------------------------------------------------
@json_command
def run_session(args) -> int:
    from .session import create_session, verify_session
    if args.verify is not None:
        res = verify_session(args.verify)
        print(f"{args.verify}: {res['checked']} files checked; missing: {res['missing'] or 'none'}; "
              f"changed: {[c['path'] + ' (' + c['why'] + ')' for c in res['changed']] or 'none'}; "
              f"unlisted: {res['unlisted'] or 'none'}")
        print("OK" if res["ok"] else "FAILED")
        args.emit_json({"verify": str(args.verify), **res})
        return 0 if res["ok"] else 1
    if args.folder is None or args.recording is None:
        raise ValueError("give the sequence FOLDER and --recording REC.h5 (or --verify DIR)")
    out = create_session(args.folder, args.recording, calibration=args.calibration, camera_profile=args.profile,
                         brackets=args.brackets, reference=args.reference, name=args.name, notes=args.notes)
    print(f"wrote session {out}")
    args.emit_json({"session": str(out), "manifest": str(Path(out) / "manifest.json")})
    return 0
