"""Frames of unequal exposure read in one unit (``Frames.exposure_scale``) against read as they are.

Usage: ``python benchmarks/exposure_units.py [--quick]``. Prints a table, then ONE JSON object on
the last line.

``builtin:window_scenery`` is simulated twice (96x72, 1 s, 25 fps, seed 1; ``--quick`` 0.6 s):
with a fixed 10 ms exposure and with auto-exposure (``--auto-exposure``: the exposure follows the
scene's brightness, here 10 ms down to about 6.6 ms). Each method reconstructs every fourth HDR
ground-truth time inside the frames and is scored by the log RMSE after one ``a·log x + b`` fit
per sequence (``evaluate.accuracy.log_errors``, every pixel). On the auto-exposure recording
each method runs twice: as the toolkit reads it (every frame in the units of the median
exposure), and "as read" (the same codes with every exposure stamp set to the median, so each
code is read as it is: what the filters did before). The ratio is the first over the second.
The fixed-exposure recording is the reference (its frames read the same either way).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

METHODS = (("akf", "offline"), ("akf", "causal"), ("cf", "causal"), ("frames_zoh", "causal"))


def _simulate(path: Path, duration_s: float, auto: bool) -> None:
    from hybridhdr.cli import main
    args = ["simulate", "builtin:window_scenery", "--out", str(path), "--width", "96", "--height", "72",
            "--duration-s", str(duration_s), "--fps", "25", "--seed", "1", "--no-progress", "-q", "--overwrite"]
    if main(args + (["--auto-exposure"] if auto else [])) != 0:
        raise RuntimeError(f"simulate failed: {' '.join(args)}")


def _as_read(rec):
    """The same codes with every exposure stamp set to the median exposure (read as they are)."""
    import dataclasses

    from hybridhdr.model import Frames
    fr = rec.frames
    med = int(np.median(fr.exposure_us))
    mid = fr.t_mid_us
    return dataclasses.replace(rec, frames=Frames(fr.images, mid - med // 2, mid - med // 2 + med, fr.gain, fr.iso,
                                                  fr.encoding))


def _scores(rec) -> dict:
    import warnings

    from hybridhdr.evaluate.accuracy import log_errors
    from hybridhdr.reconstruct import reconstruct
    h = rec.hdr
    t = h.t_us
    keep = (t > rec.frames.t_mid_us[1]) & (t < rec.frames.t_mid_us[-2])
    t = t[keep][::4]
    ref = np.asarray(h.images, np.float64)[keep][::4]
    ref = ref.mean(-1) if ref.ndim == 4 else ref
    out = {}
    for method, mode in METHODS:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            v = reconstruct(rec, method, times_us=t, mode=mode)
        x = np.asarray(v.frames, np.float64)
        x = x.mean(-1) if x.ndim == 4 else x
        out[f"{method}_{mode}"] = log_errors(x, ref, {"well_exposed": np.ones(ref.shape, bool)})["log_rmse_well_exposed"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="0.6 s recordings (else 1 s)")
    args = ap.parse_args()
    import hybridhdr
    t0 = time.perf_counter()
    dur = 0.6 if args.quick else 1.0
    res = {"benchmark": "exposure_units", "quick": bool(args.quick), "duration_s": dur, "scores": {}}
    with tempfile.TemporaryDirectory() as tmp:
        fixed, auto = Path(tmp) / "fixed.h5", Path(tmp) / "auto.h5"
        _simulate(fixed, dur, False)
        _simulate(auto, dur, True)
        rf, ra = hybridhdr.read(fixed), hybridhdr.read(auto)
        ex = ra.frames.exposure_us
        res["auto_exposure_us"] = [int(ex.min()), int(ex.max())]
        res["scores"]["fixed_exposure"] = _scores(rf)
        res["scores"]["auto_one_unit"] = _scores(ra)
        res["scores"]["auto_as_read"] = _scores(_as_read(ra))
    res["ratio_one_unit_over_as_read"] = {k: res["scores"]["auto_one_unit"][k] / res["scores"]["auto_as_read"][k]
                                          for k in res["scores"]["auto_one_unit"]}
    res["runtime_s"] = round(time.perf_counter() - t0, 1)
    print(f"log RMSE after a*log x + b (window_scenery 96x72, {dur:g} s; auto-exposure {res['auto_exposure_us'][0]}-"
          f"{res['auto_exposure_us'][1]} µs)")
    print(f"  {'method':<20} {'fixed exposure':>15} {'auto, one unit':>15} {'auto, as read':>14} {'ratio':>7}")
    for k in res["scores"]["fixed_exposure"]:
        s = res["scores"]
        print(f"  {k:<20} {s['fixed_exposure'][k]:>15.4f} {s['auto_one_unit'][k]:>15.4f} {s['auto_as_read'][k]:>14.4f} "
              f"{res['ratio_one_unit_over_as_read'][k]:>7.3f}")
    print(f"runtime {res['runtime_s']} s")
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
