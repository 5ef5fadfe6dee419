"""``hybridhdr view``: an MP4 of a recording's events beside its frames and, optionally, a reconstruction.

Each output frame at time ``t`` shows, side by side and scaled to one height:

* **events**: the events of ``[t - accumulate, t)`` on a dark background, ON white and OFF blue
  (Metavision's colours; the last event of a pixel wins);
* **frame** (when the recording has frames): the latest frame whose exposure ended by ``t``,
  grey (RGB for colour frames), codes scaled by the dtype's range;
* **reconstruction** (``--recon DIR``, a ``hybridhdr reconstruct`` output folder): the latest
  output at or before ``t``, with one display map for the whole clip (:func:`recon_display_map`,
  from a sample of up to 64 outputs): shown **linearly like the frame panel** (``v = I / hi``,
  ``hi = max(1, 99.5th percentile)``: 1.0 is the frame camera's clip level in the frame-linear
  units of the frame-anchored methods, so equal intensities look alike in both panels; gamma 2.2
  when the frames are gamma/sRGB-encoded) unless it is an HDR video: brighter than the frame's
  clip level (99.5th percentile of the finite positive pixels above 1) and spanning more than
  :data:`hybridhdr.formats.images.LOG_MAP_RATIO` (99.5th over 5th percentile); that gets the preview log map
  (:func:`hybridhdr.formats.images.tone_map`). The log map on an ordinary scene lifted its
  dark tail to mid grey and washed the panel out;

above a time bar (elapsed fraction, time from the start and sensor time). Output times are
``start + k / fps``; like ``reconstruct --fps`` the clip stops at the last event unless
``--until frames|last``. The MP4 plays at ``--playback-fps`` (H.264 through imageio-ffmpeg, as
the reconstruct previews).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy is imported where it is used (the command starts fast)
    import numpy as np

from ._util.atomic import atomic_path
from ._util.cliargs import COMMON, HelpFormatter, add_format_arg, image_side, json_output, positive_float
from ._util.timearg import add_time_window, time_arg

BACKGROUND = (30, 37, 52)  # RGB
ON_COLOUR = (255, 255, 255)
OFF_COLOUR = (64, 126, 200)
BAR_HEIGHT = 28
LABEL_HEIGHT = 20
def recon_display_map(sample, *, gamma: float = 1.0, events_only: bool = False) -> dict:
    """How the reconstruction panel shows intensities (see the module notes): the shared preview
    display map of :func:`hybridhdr.formats.images.display_map`, from a sample of outputs."""
    from .formats.images import display_map
    return display_map(sample, gamma=gamma, events_only=events_only)


def add_parser(sub) -> None:
    p = sub.add_parser("view", help="MP4 of the events (ON/OFF colours, time bar) beside the frames and a "
                                    "reconstruction", formatter_class=HelpFormatter, parents=[COMMON],
                       allow_abbrev=False, description=__doc__.split("\n\n", 1)[1].replace("``", "'"))
    p.add_argument("recording", type=Path, metavar="RECORDING", help="recording (any format the readers accept)")
    p.add_argument("--out", type=Path, required=True, help="output MP4 file")
    add_format_arg(p)
    p.add_argument("--recon", type=Path, default=None, metavar="DIR",
                   help="a 'hybridhdr reconstruct' output folder (timestamps.txt + EXR) shown as a third panel")
    p.add_argument("--fps", type=positive_float, default=None,
                   help="output frames per second of recording time (default: 30, raised so the clip has at "
                        "least 60 frames)")
    p.add_argument("--accumulate", type=time_arg, default=None, metavar="TIME",
                   help="events shown per frame: those of the last TIME (e.g. 10ms; at most 1/fps; default 1/fps)")
    p.add_argument("--playback-fps", type=positive_float, default=30.0, help="frame rate the MP4 plays at")
    p.add_argument("--until", choices=("events", "frames", "last"), default="events",
                   help="where the clip stops: the last event, the last frame, or whichever is later")
    p.add_argument("--height", type=image_side, default=None,
                   help="panel height in pixels (default: the sensor's, doubled until at least 360)")
    p.add_argument("--still", type=Path, default=None, metavar="PNG",
                   help="also write the clip's middle frame as a PNG (e.g. for documentation)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out (and --still) file")
    add_time_window(p, "the clip")
    p.set_defaults(func=run)


# -- panels ---------------------------------------------------------------------------------------

def _grey_frame(img) -> np.ndarray:
    """A frame as uint8 RGB (H, W, 3): integer codes scaled by the dtype's range, floats clipped to [0, 1]."""
    import numpy as np
    a = np.asarray(img)
    if np.issubdtype(a.dtype, np.integer):
        f = a.astype(np.float64) / float(np.iinfo(a.dtype).max)
    else:
        f = np.nan_to_num(a.astype(np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    u8 = np.round(255 * np.clip(f, 0, 1)).astype(np.uint8)
    return np.repeat(u8[..., None], 3, axis=2) if u8.ndim == 2 else u8


def _fit(img, height: int) -> np.ndarray:
    import cv2
    h, w = img.shape[:2]
    if h == height:
        return img
    width = max(1, int(round(w * height / h)))
    interp = cv2.INTER_NEAREST if height > h else cv2.INTER_AREA
    return cv2.resize(img, (width, height), interpolation=interp)


def _label(panel, text) -> np.ndarray:
    import cv2
    import numpy as np
    strip = np.full((LABEL_HEIGHT, panel.shape[1], 3), 16, np.uint8)
    cv2.putText(strip, text, (6, LABEL_HEIGHT - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (235, 235, 235), 1, cv2.LINE_AA)
    return np.concatenate([strip, panel], axis=0)


def _time_bar(width, frac, text) -> np.ndarray:
    import cv2
    import numpy as np
    bar = np.full((BAR_HEIGHT, width, 3), 16, np.uint8)
    x = int(round(np.clip(frac, 0, 1) * (width - 1)))
    bar[BAR_HEIGHT - 6:BAR_HEIGHT - 2, :] = 60
    bar[BAR_HEIGHT - 6:BAR_HEIGHT - 2, :x + 1] = (240, 180, 40)
    cv2.putText(bar, text, (6, BAR_HEIGHT - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (235, 235, 235), 1, cv2.LINE_AA)
    return bar


class _Recon:
    """Outputs of a reconstruct folder, tone-mapped with limits over (a sample of) all of them."""

    def __init__(self, folder: Path):
        import numpy as np

        from .formats.images import read_exr, read_timestamps
        tsf = Path(folder) / "timestamps.txt"
        if not tsf.is_file():
            raise FileNotFoundError(f"--recon {folder}: expected timestamps.txt written by 'hybridhdr reconstruct'")
        self.t, names = read_timestamps(tsf)
        self.paths = [Path(folder) / n for n in names]
        missing = [p for p in self.paths if not p.is_file()]
        if missing:
            raise FileNotFoundError(f"--recon {folder}: {len(missing)} files of timestamps.txt are missing "
                                    f"(e.g. {missing[0].name}; a --no-exr run cannot be viewed)")
        self._read = read_exr
        pick = np.unique(np.linspace(0, len(self.paths) - 1, min(len(self.paths), 64)).astype(int))
        self._sample = np.stack([read_exr(self.paths[i]) for i in pick])
        self.events_only = _events_only_run(Path(folder))
        self.display = recon_display_map(self._sample, events_only=self.events_only)
        self._cache = (None, None)

    def set_frame_encoding(self, encoding) -> None:
        """Show the linear map with the frames' transfer (gamma 2.2 for gamma/sRGB codes), as the
        reconstruct previews do (:func:`hybridhdr.formats.images.display_gamma`)."""
        from .formats.images import display_gamma
        self.display = recon_display_map(self._sample, gamma=display_gamma(encoding), events_only=self.events_only)
        self._cache = (None, None)

    def at(self, t_us) -> np.ndarray | None:
        import numpy as np

        from .formats.images import apply_display_map
        i = int(np.searchsorted(self.t, t_us, side="right")) - 1
        if i < 0:
            return None
        if self._cache[0] != i:
            u8 = apply_display_map(self._read(self.paths[i]), self.display)
            self._cache = (i, np.repeat(u8[..., None], 3, axis=2) if u8.ndim == 2 else u8)
        return self._cache[1]


def _events_only_run(folder: Path) -> bool:
    """True when the folder's run.json names an events-only method (high-pass, E2VID, FireNet):
    its outputs get the centred log map (display_map_centred), as its previews do."""
    from ._util.limits import read_json_bounded
    from .errors import FormatError
    from .reconstruct.api import METHODS
    run = folder / "run.json"
    if not (run.exists() or run.is_symlink()):
        return False
    try:  # a regular file of at most 16 MiB, nesting bounded: a FIFO or /dev/zero is refused
        d = read_json_bounded(run, "--recon run.json", limit=16 << 20)
    except FormatError:
        raise
    except (OSError, ValueError):
        return False
    method = d.get("method") if isinstance(d, dict) else None
    if not isinstance(method, str):
        return False
    return method in METHODS and METHODS[method].events_only


# -- the clip -------------------------------------------------------------------------------------

def _event_canvases(reader, shape, times, acc_us, chunk_events=1 << 20):
    """Yield, for each output time t (ascending), the RGB event image of [t - acc_us, t)."""
    import numpy as np
    h, w = shape
    canvas = np.empty((h, w, 3), np.uint8)
    canvas[:] = BACKGROUND
    on, off = np.array(ON_COLOUR, np.uint8), np.array(OFF_COLOUR, np.uint8)
    k = 0
    for c in reader.iter_chunks(chunk_events):
        ev = c.events
        while len(ev) and k < len(times):
            t_k = times[k]
            lo = int(np.searchsorted(ev["t"], t_k - acc_us, side="left"))
            hi = int(np.searchsorted(ev["t"], t_k, side="left"))
            sel = ev[lo:hi]
            if len(sel):
                canvas[sel["y"], sel["x"]] = np.where((sel["p"] > 0)[:, None], on, off)
            if hi == len(ev):  # frame k may get more events from the next chunk
                break
            yield canvas
            canvas = np.empty((h, w, 3), np.uint8)
            canvas[:] = BACKGROUND
            k += 1
            ev = ev[lo:]  # later windows start later
        if k >= len(times):
            return
    while k < len(times):
        yield canvas
        canvas = np.empty((h, w, 3), np.uint8)
        canvas[:] = BACKGROUND
        k += 1


@json_output
def run(args) -> int:
    import numpy as np
    from ._util.limits import check_fps_outputs
    from ._util.timearg import check_window, empty_window_error, resolve_window
    from .formats.span import recording_span
    from .formats import open_reader
    from .formats.images import MP4Stream, write_png

    check_window(args)
    if args.out.suffix.lower() != ".mp4":
        raise ValueError(f"--out {args.out}: expected an .mp4 file name")
    from ._util.atomic import check_outputs
    check_outputs({"--out": args.out, "--still": args.still},
                  [args.recording] + ([args.recon / "timestamps.txt"] if args.recon is not None else []),
                  overwrite=args.overwrite, command="view")
    recon = _Recon(args.recon) if args.recon is not None else None
    span = recording_span(args.recording, args.format)
    if span.origin_us is None:
        raise ValueError(f"{args.recording}: no events or frames to show")
    t0, t1 = resolve_window(args, span.origin_us)
    ends = {"events": None if span.events is None else span.events[1],
            "frames": None if span.frames is None else span.frames[2]}
    last = max(v for v in ends.values() if v is not None)
    stop = last if args.until == "last" else ends[args.until]
    if stop is None:
        raise ValueError(f"--until {args.until}: {args.recording} has no {args.until}")
    start = span.origin_us if t0 is None else t0
    end = stop + 1 if t1 is None else t1
    if end <= start or start > last:
        raise empty_window_error(args, t0, t1, span)
    fps = args.fps or max(30.0, 60e6 / (end - start))
    check_fps_outputs(start, end, fps)
    dt = 1e6 / fps
    times = start + np.round(np.arange(1, int(np.ceil((end - start) / dt)) + 1) * dt).astype(np.int64)
    acc = int(round(dt)) if args.accumulate is None else int(args.accumulate)
    if not 0 < acc <= round(dt):
        raise ValueError(f"--accumulate must be > 0 and at most 1/fps ({dt:g} µs), got {acc} µs")
    with open_reader(args.recording, args.format) as r:
        if r.sensor_size is None:
            raise ValueError(f"{args.recording}: the sensor size is unknown")
        shape = (r.sensor_size.height, r.sensor_size.width)
        frames = r.read_frames()
        if frames is not None and not len(frames):
            frames = None
        if recon is not None:
            rshape = tuple(recon._sample.shape[1:3])
            if rshape != shape:  # as evaluate metrics does: outputs of another recording are refused
                raise ValueError(f"--recon {args.recon}: its outputs are {rshape[1]}x{rshape[0]} (width x height) but "
                                 f"{args.recording} is {shape[1]}x{shape[0]}; give the reconstruction of this "
                                 f"recording")
        if recon is not None and frames is not None:
            recon.set_frame_encoding(frames.encoding)
        height = args.height or shape[0] * 2 ** max(0, int(np.ceil(np.log2(360 / shape[0]))))
        blank_frame = None
        if frames is not None:
            blank_frame = np.zeros(_fit(_grey_frame(frames.images[0]), height).shape, np.uint8)
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(out, ".mp4") as tmp:
            still_at = len(times) // 2
            still = None
            bar = None
            if not args.no_progress:
                from tqdm import tqdm
                bar = tqdm(total=len(times), unit="frame", desc=f"view {Path(args.recording).name}", file=sys.stderr)
            stream = None
            try:
                for k, canvas in enumerate(_event_canvases(r, shape, times, acc)):
                    t = int(times[k])
                    panels = [_label(_fit(canvas, height), f"events, last {acc / 1e3:g} ms (ON white, OFF blue)")]
                    if frames is not None:
                        i = int(np.searchsorted(frames.t_end_us, t, side="right")) - 1
                        img = blank_frame if i < 0 else _fit(_grey_frame(frames.images[i]), height)
                        panels.append(_label(img, "frame" if i < 0 else f"frame {i} ({(int(frames.t_end_us[i]) - span.origin_us) / 1e6:.3f} s)"))
                    if recon is not None:
                        rimg = recon.at(t)
                        rimg = np.zeros((height, panels[0].shape[1], 3), np.uint8) if rimg is None else _fit(rimg, height)
                        how = ("log map, centred" if recon.display.get("centre") else
                               "log map" if recon.display["mode"] == "log" else "linear, as the frame")
                        panels.append(_label(rimg, f"reconstruction ({args.recon.name}; {how})"))
                    row = np.concatenate(panels, axis=1)
                    rel = (t - span.origin_us) / 1e6
                    img = np.concatenate([row, _time_bar(row.shape[1], (t - start) / (end - start),
                                                         f"t = {rel:.4f} s   (sensor {t:,} us)   frame {k + 1}/{len(times)}")],
                                         axis=0)
                    if stream is None:
                        stream = MP4Stream(tmp, img.shape, args.playback_fps)
                    stream.write(img)
                    if k == still_at:
                        still = img
                    if bar is not None:
                        bar.update(1)
                if stream is not None:
                    stream.close()
                    stream = None
                if args.still is not None and still is not None:
                    # the still and the MP4 are written both or neither: the PNG is committed while
                    # the MP4 is still at its temporary name, which a failure here removes
                    args.still.parent.mkdir(parents=True, exist_ok=True)
                    with atomic_path(args.still, ".png") as tmp_still:
                        write_png(tmp_still, still)
            except BaseException:
                if stream is not None:
                    stream.abort()  # ffmpeg killed and waited for before the temporary MP4 is removed
                raise
            finally:
                if bar is not None:
                    bar.close()
    res = {"out": str(out), "frames": len(times), "fps": fps, "playback_fps": args.playback_fps,
           "accumulate_us": acc, "t_first_us": int(times[0]), "t_last_us": int(times[-1]),
           "panels": ["events"] + (["frames"] if frames is not None else []) + (["reconstruction"] if recon else []),
           "size": [int(still.shape[1]), int(still.shape[0])] if still is not None else None}
    if recon is not None:
        res["recon_display"] = recon.display
    if args.json:
        import json
        print(json.dumps(res))
    else:
        print(f"wrote {out}: {len(times)} frames ({fps:g} per second of recording, {acc / 1e3:g} ms of events each), "
              f"{(times[-1] - times[0]) / 1e6:g} s of recording, plays at {args.playback_fps:g} fps; panels: "
              f"{', '.join(res['panels'])}")
    return 0
