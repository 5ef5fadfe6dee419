"""``hybridhdr reconstruct``: HDR video from any recording the readers accept."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .._util.cliargs import (COMMON, HelpFormatter, UsageError, add_format_arg, chunk_events_count, cli_wording,
                             json_output, positive_float, positive_worker_count, worker_count)
from .._util.procs import signals_exit
from .._util.timearg import add_time_window
from ..calibrate.resolve import (DEFAULT_THRESHOLDS, THRESHOLD_KEYS, THRESHOLDS_HELP, add_sensor_profile_arg,
                                 take_sensor_profile_arg, thresholds_arg)
from .methods import METHOD_ALIASES, METHODS, methods_with

#: ``--method``: every registered method, each followed by its aliases.
METHOD_CHOICES = [c for name in METHODS for c in (name, *(a for a, n in METHOD_ALIASES.items() if n == name))]


def add_parser(subparsers) -> None:
    """Add the ``reconstruct`` subcommand (sets ``func=run``)."""
    p = subparsers.add_parser(
        "reconstruct", help="HDR video from events and frames (AKF and baselines)",
        formatter_class=HelpFormatter, parents=[COMMON], allow_abbrev=False,
        description="Reconstruct linear HDR video with the Asynchronous Kalman Filter (Wang et al., ICCV "
                    "2021) or a baseline; writes float32 EXR frames, timestamps.txt, run.json and "
                    "optional PNG/MP4 previews. With --fps the outputs stop at the last event (frame-only "
                    "methods: the last frame) unless --until says otherwise.")
    p.add_argument("recording", type=Path, help="recording (any format the readers accept)")
    p.add_argument("--method", default="akf", choices=METHOD_CHOICES, help="reconstruction method")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--mode", default="offline", choices=["offline", "causal", "forward"],
                   help="offline may use future frames; causal uses only the past")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--fps", type=positive_float, default=None,
                   help="outputs per second of recording time (default: at the frame times)")
    g.add_argument("--times-us", type=Path, default=None,
                   help="text file of output times in µs sensor time, one per line")
    p.add_argument("--until", choices=("events", "frames", "last"), default=None,
                   help="with --fps, where the outputs stop: the last event, the last frame, or whichever is "
                        "later (default: events; frames for the frame-only methods)")
    p.add_argument("--config", type=Path, default=None, help="parameters from a TOML file (run.toml)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override one parameter (repeatable), e.g. --set process_noise_per_s=5e-3")
    p.add_argument("--preset", default=None, choices=["paper", "reference_code"],
                   help="AKF parameter preset (before --config and --set)")
    p.add_argument("--contrast-threshold", type=_threshold_arg, default=None, metavar="C|auto",
                   help="contrast threshold c (log units), or 'auto': one ON and one OFF threshold estimated from "
                        "the recording's frames and events (reads it into memory once; 'hybridhdr calibrate "
                        "thresholds' gives a per-pixel map) [default: as the recording declares, else 0.1]")
    p.add_argument("--cutoff-hz", type=positive_float, default=None, help="CF / high-pass cutoff frequency (Hz)")
    a = p.add_argument_group("frame augmentation (AKF, offline mode; paper §4.1, eqs. 10-13)")
    a.add_argument("--augmentation", action="store_true",
                   help="use the augmented frame (EDI deblurring, event interpolation) as the measurement")
    a.add_argument("--no-augmentation", action="store_true",
                   help="plain frames (the default)")
    a.add_argument("--no-deblur", action="store_true", help="skip EDI deblurring of the frames")
    a.add_argument("--no-interpolation", action="store_true",
                   help="hold the (deblurred) frame instead of interpolating with events (eqs. 10, 11, 13)")
    a.add_argument("--calibration", action="store_true",
                   help="interpolate with per-pixel thresholds calibrated by eq. 12 (off by default: measured "
                        "not to pay, see AugmentParams.calibrate)")
    a.add_argument("--no-calibration", action="store_true",
                   help="interpolate with the nominal threshold (no per-pixel eq. 12; the default)")
    p.add_argument("--profile", type=Path, default=None,
                   help="camera profile JSON (default: the recording's, else built-in 8-bit for its encoding)")
    p.add_argument("--thresholds", type=thresholds_arg, default=None, metavar="FILE|auto|input|params|selfcal",
                   help=THRESHOLDS_HELP + "; --contrast-threshold auto is --thresholds auto")
    add_sensor_profile_arg(p)
    add_format_arg(p)
    p.add_argument("--cfa", choices=("RGGB", "BGGR", "GRBG", "GBRG", "none"), default=None,
                   help="colour filter array of the event and frame sensors (default: as the recording declares; "
                        "'none' forces monochrome); colour output is linear RGB")
    p.add_argument("--demosaic", choices=("log_cubic", "log_bilinear", "bilinear", "edge_aware"), default="log_cubic",
                   help="demosaicking of colour outputs")
    p.add_argument("--weights", type=Path, default=None,
                   help="network checkpoint for --method e2vid / firenet (.pth / .pth.tar; never downloaded)")
    p.add_argument("--frame-encoding", choices=("linear", "gamma2.2", "srgb"), default=None,
                   help="declare the frames' encoding (default: as the recording states)")
    add_time_window(p, "outputs")
    p.add_argument("--workers", type=positive_worker_count, default=1,
                   help="threads for the row-band parallel kernels (the two-sided AKF with >= 2 runs its backward and "
                        "forward passes at once, each with half); the output is the same bit for bit")
    p.add_argument("--device", choices=("auto", "cuda", "cpu"), default="auto",
                   help="where the AKF and CF family run: cuda (NVIDIA GPU through numba.cuda), cpu, or auto (the GPU "
                        "when numba.cuda sees one, else the CPU; default); one line on stderr and run.json say which")
    p.add_argument("--allow-huge", action="store_true",
                   help="lift the size limits on the input's frames and outputs (docs/security.md)")
    p.add_argument("--chunk-events", type=chunk_events_count, default=1 << 20, help="events per streamed chunk")
    o = p.add_argument_group("outputs (written into OUT.partial/, renamed to OUT when complete)")
    o.add_argument("--png", action="store_true", help="also write tone-mapped PNG previews")
    o.add_argument("--mp4", action="store_true", help="also write a tone-mapped MP4 preview (every output frame)")
    o.add_argument("--playback-fps", type=positive_float, default=30.0,
                   help="frame rate the MP4 preview plays at (outputs at --fps 300 play 10x slowed down at 30)")
    o.add_argument("--no-exr", action="store_true", help="skip the EXR sequence")
    o.add_argument("--exr-compression", default=None, metavar="NAME",
                   help=f"EXR compression, one of {', '.join(EXR_COMPRESSION_NAMES)} (pxr24 is lossy: 24-bit floats; "
                        f"zstd and htj2k need OpenEXR >= 3.4 to write and read) [default: none: lossless and the fastest; "
                        f"zip saves about 6 %% of the bytes for 4x the encoding time]")
    o.add_argument("--writers", type=worker_count, default=None,
                   help="writer processes encoding files while the filter runs; 0 writes in the main thread "
                        "(same bytes) [default: min(2, CPUs)]")
    o.add_argument("--overwrite", action="store_true",
                   help="OUT may be non-empty: replace the files a reconstruct run writes there (frame_*.exr, "
                        "timestamps.txt, run.json, previews), keep everything else")
    p.set_defaults(func=run)


def _threshold_arg(text):
    if str(text).strip().lower() == "auto":
        return "auto"
    try:
        return positive_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a number > 0 (log units) or 'auto', got {text!r}") from None


#: Methods ``--thresholds selfcal`` applies to (a frame model and contrast thresholds).
SELF_CALIBRATED_METHODS = methods_with(takes_thresholds=True, needs_frames=True)


def self_calibrate_run(args, params, method: str, given: bool, mode: str = "off"):
    """``(params, frame_time_offset_us, record or None, note or None)`` for ``--thresholds selfcal``.

    ``mode``: ``"auto"`` (the default ``--thresholds``) calibrates only a recording that declares no
    thresholds (nor stores a map) when the command line gives none; ``"on"`` (``--thresholds
    selfcal``) always (an error when the recording cannot tell); ``"off"`` never. The AKF takes the
    calibrated log offset and thresholds, CF and direct integration thresholds in their own log
    model; all take the frame time offset (:func:`hybridhdr.calibrate.resolve.resolve_thresholds`)."""
    if mode == "off" or method not in SELF_CALIBRATED_METHODS:
        if mode == "on" and method not in SELF_CALIBRATED_METHODS:
            raise ValueError(f"--thresholds selfcal applies to --method {'/'.join(SELF_CALIBRATED_METHODS)}, "
                             f"not {method}")
        return params, 0, None, None
    if mode == "auto" and (given or args.contrast_threshold is not None):
        return params, 0, None, None
    from ..calibrate.resolve import resolve_thresholds
    from ..formats import read
    if mode == "auto":
        from .api import recording_facts
        declared, n_frames = recording_facts(str(args.recording))
        if declared or n_frames < 3:
            return params, 0, None, None
    enc = getattr(args, "frame_encoding", None)
    rec = read(args.recording) if enc is None else read(args.recording, frame_encoding=enc)
    own_i0 = None if method == "akf" else float(params.intensity_offset)
    try:
        got = resolve_thresholds(rec, "selfcal", intensity_offset=own_i0, profile=args.profile)
    except ValueError as e:
        if mode == "on":
            raise ValueError(f"--thresholds selfcal: the recording cannot tell ({e})") from None
        return params, 0, None, f"self-calibration skipped: {e}"
    return params.replace(**got.overrides()), got.frame_time_offset_us, got.record, got.note


def estimate_run_thresholds(args, params):
    """``(params, note)`` with ``--contrast-threshold auto``'s estimate in ``params``
    (:func:`hybridhdr.calibrate.resolve.resolve_thresholds`, ``"auto"``)."""
    if not hasattr(params, "contrast_threshold_on"):
        raise ValueError(f"--contrast-threshold does not apply to --method {args.method}")
    from ..calibrate.resolve import resolve_thresholds
    from ..formats import read
    enc = getattr(args, "frame_encoding", None)
    rec = read(args.recording, getattr(args, "format", None), **({} if enc is None else {"frame_encoding": enc}))
    try:
        got = resolve_thresholds(rec, "auto", intensity_offset=params.intensity_offset, profile=args.profile)
    except ValueError as e:
        raise ValueError(f"--contrast-threshold auto: the recording cannot tell its thresholds ({e}); give "
                         f"--contrast-threshold C") from None
    return params.replace(**got.overrides()), got.note


def _events_total(source, args) -> int | None:
    """The progress bar's total: the events the recording declares (a container's count), when
    the whole recording is read (no --start/--end); None (a bar without ETA) otherwise."""
    if any(getattr(args, k, None) is not None for k in ("start", "end", "start_us", "end_us")):
        return None
    try:
        if isinstance(source, str):
            from ..formats import open_reader
            with open_reader(source, getattr(args, "format", None)) as r:
                n = getattr(r, "n_events", None)
        else:
            n = getattr(source, "n_events", None)
    except (OSError, ValueError, ImportError):
        return None  # the run itself says what is wrong with the file
    return int(n) if isinstance(n, int) and not isinstance(n, bool) and n > 0 else None


def _frames_written(bar, files_per_frame: int):
    """``VideoWriter.on_written`` (files: EXR, PNG, MP4 frames) shown as output frames written."""
    import threading
    lock = threading.Lock()
    files = [0]
    per = max(1, int(files_per_frame))

    def on_written(k: int) -> None:
        with lock:
            files[0] += int(k)
            bar.set_postfix_str(f"{files[0] // per} frames written", refresh=False)

    return on_written


#: ``--exr-compression`` names, listed without importing OpenEXR (and numpy) so that ``--help`` starts
#: fast; the names the installed OpenEXR lacks are refused when the command runs
#: (``formats.images.exr_compressions``; a test keeps the two lists equal).
EXR_COMPRESSION_NAMES = ("none", "rle", "zips", "zip", "piz", "pxr24", "zstd", "htj2k")


def _parse_value(s: str):
    low = s.strip().lower()
    if low in ("true", "false"):
        return low == "true"
    if low in ("none", "null"):
        return None
    for conv in (int, float):
        try:
            return conv(s)
        except ValueError:
            pass
    return s


def build_params(args):
    """The method's Params from --preset, --config, named flags and --set (in that order)."""
    from .methods import make_params, resolve_method
    from .params import AKFParams
    method = resolve_method(args.method)
    cls = METHODS[method].params_class
    base = make_params(method, None)
    if args.preset is not None:
        if method != "akf":
            raise ValueError(f"--preset applies to --method akf only, got --method {args.method}")
        base = getattr(AKFParams, args.preset)()
    d = base.to_dict()
    if args.config is not None:
        d.update(_toml_fields(cls, args.config))
    names = {f for f in d}
    if args.contrast_threshold is not None:
        if "contrast_threshold" not in names:
            raise ValueError(f"--contrast-threshold does not apply to --method {args.method}")
        if args.contrast_threshold != "auto":  # estimated in run(), from the recording
            d["contrast_threshold"] = args.contrast_threshold
    if args.cutoff_hz is not None:
        if "cutoff_hz" not in names:
            raise ValueError(f"--cutoff-hz does not apply to --method {args.method}")
        d["cutoff_hz"] = args.cutoff_hz
    for item in args.set:
        if "=" not in item:
            raise ValueError(f"--set expects NAME=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        k = k.strip().replace("-", "_")
        if k not in names:
            raise ValueError(f"--set: unknown parameter {k!r} for {cls.__name__}; expected one of {sorted(names)}")
        d[k] = _parse_value(v)
    if getattr(args, "weights", None) is not None:
        if "weights" not in d:
            raise ValueError(f"--weights applies to --method e2vid / firenet only, got --method {args.method}")
        d["weights"] = str(args.weights)
    return make_params(method, cls.from_dict(d))


def thresholds_given(args) -> bool:
    """True when the command line states contrast thresholds: --contrast-threshold, a --set of
    one, or a --config file naming one. Otherwise the recording's declared thresholds (or the
    method's default) apply, as for ``reconstruct(..., params=None)``."""
    if args.contrast_threshold is not None:
        return True
    for item in args.set:
        if item.split("=", 1)[0].strip().replace("-", "_") in THRESHOLD_KEYS:
            return True
    if args.config is not None:
        from .methods import resolve_method
        if any(k in THRESHOLD_KEYS for k in _toml_fields(METHODS[resolve_method(args.method)].params_class, args.config)):
            return True
    return False


def api_params(params, given: bool):
    """What ``run`` passes to the API: ``params`` itself when the command line states thresholds
    (``given``, :func:`thresholds_given`) or the method has none, else its fields without the
    thresholds, so that the API applies the thresholds the recording declares (a Params instance
    counts as stating them)."""
    if given or not hasattr(params, "contrast_threshold_on"):
        return params
    return {k: v for k, v in params.to_dict().items() if k not in THRESHOLD_KEYS}


def build_augment(args):
    """AugmentParams from the ``[augment]`` table of --config and the --no-* flags."""
    from .augment import AugmentParams
    d = {}
    if getattr(args, "config", None) is not None:
        from .._util.toml import load_toml
        t = load_toml(args.config).get("augment")
        if isinstance(t, dict):
            d["enabled"] = True  # an [augment] table asks for augmentation unless it says otherwise
            d.update(t)
    if args.augmentation or args.no_deblur or args.no_interpolation or args.no_calibration or args.calibration:
        d["enabled"] = True
    if args.no_augmentation:
        d["enabled"] = False
    if args.no_deblur:
        d["deblur"] = False
    if args.no_interpolation:
        d["interpolate"] = False
    if args.calibration:
        d["calibrate"] = True
    if args.no_calibration:
        d["calibrate"] = False
    return AugmentParams.from_dict(d)


def _toml_fields(cls, path) -> dict:
    from .._util.toml import load_toml
    d = load_toml(path)
    if cls._toml_table in d and isinstance(d[cls._toml_table], dict):
        d = d[cls._toml_table]
    d = {k: v for k, v in d.items() if not isinstance(v, dict)}
    if d.get("allow_pickle"):  # unpickling runs code from the checkpoint: only the user's own command line
        from ..errors import FormatError
        raise FormatError(path, "allow_pickle is not accepted in a --config file (it lets a checkpoint run Python "
                                "code); give --set allow_pickle=true yourself if you trust the checkpoint "
                                "(docs/security.md)")
    cls.from_dict(d)  # validates names
    return d


def output_window(args, method: str):
    """The absolute [start, end) µs of the outputs, and a note when --fps outputs were cut at the end
    of the events (or frames), from --start/--end/--absolute and --until (see the --help)."""
    from .._util.timearg import check_window, empty_window_error, resolve_window, window_given
    from ..formats.span import recording_span
    check_window(args)
    windowed = window_given(args)
    relative = windowed and args.start_us is None and args.end_us is None and not args.absolute
    if args.until is not None and args.fps is None:
        raise UsageError("--until applies to --fps outputs")
    if str(args.recording).startswith("builtin:") or not (relative or args.fps is not None or windowed):
        return resolve_window(args, None) + (None,)
    opts = {} if args.frame_encoding is None else {"frame_encoding": args.frame_encoding}
    span = recording_span(args.recording, getattr(args, "format", None), **opts)
    t0, t1 = resolve_window(args, span.origin_us)
    note = None
    if args.fps is not None and t1 is None:
        until = args.until or ("frames" if METHODS[method].frames_only or span.events is None else "events")
        ends = {"events": None if span.events is None else span.events[1],
                "frames": None if span.frames is None else span.frames[1]}
        last = max(v for v in ends.values() if v is not None) if any(v is not None for v in ends.values()) else None
        stop = last if until == "last" else ends[until]
        if stop is None:
            raise UsageError(f"--until {until}: the recording has no {until}")
        t1 = stop + 1
        if last is not None and stop < last:
            other = "frames" if until == "events" else "events"
            note = (f"note: outputs stop at the last {until[:-1]} ({(stop - span.origin_us) / 1e6:g} s from the start); "
                    f"the {other} run to {(last - span.origin_us) / 1e6:g} s: --until {other} or --until last for more")
    if windowed:
        lo = span.origin_us if t0 is None else t0
        hi_data = max(p[-1] for p in (span.events, span.frames) if p is not None) if span.origin_us is not None else None
        if hi_data is None or lo > hi_data or (t1 is not None and t1 <= span.origin_us):
            raise empty_window_error(args, t0, t1, span)
    return t0, t1, note


@json_output
def run(args) -> int:
    """Run ``hybridhdr reconstruct``; returns the exit status (2: bad arguments, 1: failed while running,
    e.g. a full disk; OUT.partial is then removed and OUT untouched)."""
    import numpy as np

    from .._version import __version__
    from .api import reconstruct_iter
    from .methods import resolve_method
    from .._util.atomic import AtomicFolder
    from ..formats.images import DEFAULT_EXR_COMPRESSION, exr_compressions
    from .output import OUTPUTS, VideoWriter
    folder = writer = None
    stage = "arguments"
    try:
        method = resolve_method(args.method)
        t_start_us, t_end_us, note = output_window(args, method)
        params = build_params(args)
        if not Path(args.recording).exists() and not str(args.recording).startswith("builtin:"):
            raise FileNotFoundError(f"recording {args.recording} not found")
        # --out is claimed (a non-empty one refused) before the threshold estimation and the
        # self-calibration, which take seconds to minutes
        folder = AtomicFolder(args.out, outputs=OUTPUTS, command="reconstruct", overwrite=args.overwrite)
        auto_note = None
        take_sensor_profile_arg(args)
        thr_source = args.thresholds  # FILE (Path), auto, input, params or None: --help, THRESHOLDS_HELP
        if args.contrast_threshold == "auto":
            if thr_source is not None:
                raise ValueError("--contrast-threshold auto and --thresholds both give the thresholds; use one")
            thr_source = "auto"
        given = thresholds_given(args)  # once: a --config file is read for it
        if thr_source in ("auto", "input", "selfcal") and given and args.contrast_threshold != "auto":
            raise ValueError(f"--thresholds {thr_source} and the thresholds given by --contrast-threshold/--set/--config "
                             f"disagree; use one (or --thresholds params)")
        if thr_source == "auto":
            params, auto_note = estimate_run_thresholds(args, params)
        by_default = thr_source is None
        if by_default:
            thr_source = "params" if given else DEFAULT_THRESHOLDS  # the one default, as evaluate holdout's
        # selfcal: always with --thresholds selfcal; by default only for a recording that declares
        # no thresholds (one that does keeps them: input)
        sc_mode = "off" if thr_source != "selfcal" else ("auto" if by_default else "on")
        params, frame_dt, selfcal_record, selfcal_note = self_calibrate_run(args, params, method, given, sc_mode)
        if selfcal_record is not None:
            auto_note, given = selfcal_note, True
            print(selfcal_note, file=sys.stderr)
        elif selfcal_note:
            print(f"note: {selfcal_note}", file=sys.stderr)
        if thr_source == "selfcal" and selfcal_record is None:
            thr_source = "input"  # declared (or the method's own, said in the output)
        run_params = api_params(params, given or thr_source in ("auto", "params"))
        map_path = thr_source if isinstance(thr_source, Path) else None
        augment = build_augment(args)
        times = None
        if args.times_us is not None:
            import io
            from .._util.limits import read_text_bounded
            times = np.loadtxt(io.StringIO(read_text_bounded(args.times_us, "--times-us file")), dtype=np.int64,
                               ndmin=1, comments="#")
        compression = (args.exr_compression or DEFAULT_EXR_COMPRESSION).lower()
        if compression not in exr_compressions():
            raise ValueError(f"--exr-compression {args.exr_compression!r}: expected one of {exr_compressions()}")
        if not args.playback_fps > 0:
            raise ValueError(f"--playback-fps must be > 0, got {args.playback_fps}")
        if args.writers is not None and args.writers < 0:
            raise ValueError(f"--writers must be >= 0, got {args.writers}")
        stage = "run"
        if note:
            print(note, file=sys.stderr)
        from .._util.progress import progress_bars
        from .request import Device
        device_line = Device.resolve(getattr(args, "device", "cpu"), method).naming_engine(
            method, args.mode, args.workers).line
        print(device_line, file=sys.stderr)  # before the bar: no line cuts through it
        with signals_exit(), progress_bars(not args.no_progress) as new_bar:  # the writer pool and OUT.partial cleaned up on SIGTERM
            # the writer pool forks here, before any other thread (progress bars, readers) starts
            writer = VideoWriter(folder.path, exr=not args.no_exr, compression=compression, png=args.png,
                                 mp4=args.mp4, playback_fps=args.playback_fps, writers=args.writers)
            info: dict = {}
            source = str(args.recording)
            if getattr(args, "frame_encoding", None) is not None or getattr(args, "format", None) is not None:
                from ..formats import open_reader
                opts = {} if args.frame_encoding is None else {"frame_encoding": args.frame_encoding}
                source = open_reader(args.recording, args.format, **opts)
            # one bar: events (each once, also in the two-sided pass) out of the recording's, with
            # an ETA when the recording declares its count; output frames written as its postfix
            bar = new_bar(total=_events_total(source, args), unit="ev", unit_scale=True,
                          desc=f"reconstruct {method}")
            progress = None
            if bar is not None:
                progress = bar.update
                writer.on_written = _frames_written(bar, (not args.no_exr) + bool(args.png) + bool(args.mp4))
            try:
                for t, img in reconstruct_iter(source, method, run_params, times_us=times, fps=args.fps,
                                               mode=args.mode, profile=args.profile, t_start_us=t_start_us,
                                               t_end_us=t_end_us, n_workers=args.workers,
                                               chunk_events=args.chunk_events, progress=progress, info=info,
                                               augment=augment, thresholds=map_path if map_path is not None else "input", cfa=args.cfa,
                                               demosaic=args.demosaic, frame_time_offset_us=frame_dt,
                                               device=getattr(args, "device", "cpu")):
                    writer.write(t, img)
                if writer.n == 0:
                    raise ValueError("no output frames in the requested time range")
                # the previews' display map as 'view' makes it (frames' encoding; events-only: centred)
                writer.set_display(frame_encoding=info.get("frame_encoding"), events_only=METHODS[method].events_only)
                written = writer.close()
                if bar is not None and bar.total and bar.n < bar.total:
                    bar.update(bar.total - bar.n)  # done: the events after the last output are not needed
            finally:
                if bar is not None:
                    bar.close()
                if not isinstance(source, str):
                    source.close()
            run_info = {"hybridhdr_version": __version__, "command": sys.argv, "method": method,
                        "method_description": METHODS[method].description, "mode": args.mode,
                        "params": info.get("params", params.to_dict()),
                        "profile": str(args.profile) if args.profile else info.get("profile", "built-in 8-bit"),
                        "n_frames": writer.n, "n_events_used": info.get("n_events_used"), "written": written,
                        "device": info.get("device", device_line)}
            n_pix = int(info.get("n_output_pixels") or 0)
            run_info["clamped_pixels"] = {"count": int(info.get("n_clamped", 0)), "of": n_pix,
                                          "floor": 1e-6, "note": "outputs below the floor (or NaN) raised to it"}
            if hasattr(params, "contrast_threshold_on"):
                used = info.get("thresholds")
                if map_path is not None and "camera_model" in info:
                    used = info.get("thresholds")  # the sensor profile's note
                elif map_path is not None:
                    used = f"per-pixel map {map_path} (--thresholds)"
                elif not (used or "").startswith("per-pixel map"):
                    used = auto_note or used or ("given on the command line" if given else
                                                 "the method's own parameters (--thresholds params)"
                                                 if thr_source == "params" else
                                                 "the method's default (none given, none declared by the recording)")
                run_info["thresholds"] = used
                run_info["thresholds_source"] = str(thr_source)
            if selfcal_record is not None:
                run_info["self_calibration"] = selfcal_record
            if "camera_model" in info:
                run_info["camera_model"] = info["camera_model"]
            for key in ("augment", "augmentation", "edi_thresholds", "two_sided", "cfa"):
                if key in info:
                    run_info[key] = info[key]
            run_info["info"] = {k: v for k, v in info.items() if k != "params"}
            with open(folder.path / "run.json", "w", encoding="utf-8") as f:
                f.write(json.dumps(run_info, indent=1, default=str) + "\n")
            out = folder.commit()
        if run_info.get("thresholds", "").startswith("the method's default"):
            print(f"note: the recording declares no contrast thresholds: used the default ON "
                  f"{run_info['params'].get('contrast_threshold')} (log units); measure them with 'hybridhdr "
                  f"calibrate thresholds' (then --thresholds FILE), estimate them with --thresholds selfcal (the "
                  f"default) or --thresholds auto, or give --contrast-threshold C", file=sys.stderr)
        if args.json:
            print(json.dumps({"method": method, "frames": writer.n, "t_first_us": writer.t_first,
                              "t_last_us": writer.t_last, "events_used": info.get("n_events_used", 0),
                              "out": str(out)}))
        else:
            print(f"{method}: {writer.n} frames {writer.t_first}..{writer.t_last} µs, "
                  f"{info.get('n_events_used', 0)} events -> {out}")
        return 0
    except BaseException as e:
        if writer is not None:
            writer.abort()
        if folder is not None:
            folder.abort()
        if isinstance(e, (KeyboardInterrupt, SystemExit)):
            raise
        if not isinstance(e, (ValueError, TypeError, OSError, ImportError)) or getattr(args, "debug", False):
            raise
        print(f"hybridhdr reconstruct: error: {cli_wording(str(e))}", file=sys.stderr)
        from .._util.timearg import EmptyWindowError
        from ..errors import FormatError
        # a bad or oversized input file (FormatError, LimitExceeded, a FIFO), or one that cannot be
        # read as the format detected or given, is not a usage error: 1, as in every other verb
        usage = ((stage == "arguments" or isinstance(e, (ValueError, TypeError, FileNotFoundError)))
                 and not isinstance(e, (EmptyWindowError, FormatError)))
        return 2 if usage else 1

