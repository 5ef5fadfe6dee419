"""The demo's reconstruction step: AKF and CF on a recording with ground truth, scored and previewed."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..formats.images import tone_map, write_png_previews
from ..reconstruct.api import reconstruct
from .metrics import ssim

__all__ = ["demo_step", "perceptual_score_note"]


def demo_step(recording, out_dir) -> str:
    """Run AKF and CF on ``recording``, write PNG previews, return a short text summary.

    Scoring (HDR-aware, documented in the summary): both the reconstruction and the reference are
    compared in log intensity, the reconstruction shifted by the constant that best matches the
    reference (a linear gain, since filters fed by 8-bit frames recover intensity up to the
    camera's scale), then mapped to [0, 1] by the reference's log range; MSE and SSIM (Gaussian
    window σ = 1.5, data range 1, border cropped: :func:`hybridhdr.evaluate.metrics.ssim`) are
    computed on those. The reference is the recording's HDR references when present, else its
    frames.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    hdr = recording.hdr
    if hdr is not None and len(hdr):
        times, ref = hdr.t_us, hdr.images if hdr.images.ndim == 3 else hdr.images.mean(axis=3)
        ref_name = "HDR reference"
    else:
        fr = recording.frames
        times, ref = fr.t_mid_us, fr.images.astype(np.float64) / float(np.iinfo(fr.images.dtype).max
                                                                            if fr.images.dtype.kind == "u" else 1.0)
        ref_name = "frames"
    t0 = int(recording.frames.t_mid_us.min())
    keep = times >= t0
    times, ref = times[keep], np.asarray(ref[keep], dtype=np.float64)
    tiny = 1e-6 * float(ref.max() or 1.0)
    log_ref = np.log(np.maximum(ref, tiny))
    lo, hi = float(log_ref.min()), float(log_ref.max())
    span = (hi - lo) or 1.0
    lines = [f"reconstruct: {len(times)} times, scored against the {ref_name} in log intensity "
             f"(gain-matched, log range {span:.2f} = {np.exp(span):.3g}:1 mapped to [0, 1])"]
    _, lim = tone_map(ref)
    for method in ("akf", "cf"):
        v = reconstruct(recording, method, times_us=times, thresholds="input")  # the simulated sensor's, else the defaults
        log_rec = np.log(np.maximum(v.frames.astype(np.float64), tiny))
        shift = float(np.mean(log_ref - log_rec))  # least-squares log offset = linear gain
        a = np.clip((log_rec + shift - lo) / span, 0, 1)
        b = (log_ref - lo) / span
        mse = float(np.mean((a - b) ** 2))
        ssim_ab = ssim(a, b, data_range=1.0)
        gain = float(np.exp(shift))
        write_png_previews(type(v)(v.frames * gain, v.t_us), out / f"reconstruct_{method}",
                           every=max(1, len(v) // 5), limits=lim)
        lines.append(f"  {method:4s} MSE {mse:.4g}  SSIM {ssim_ab:.3f}  (gain {gain:.3g}) -> "
                     f"{out / ('reconstruct_' + method)}")
    return "\n".join(lines)


def perceptual_score_note() -> str | None:
    """The line ``hybridhdr demo`` prints when it cannot compute the perceptual score, else None.

    ColorVideoVDP (the JOD row of Table 1, the JOD panels of the charts) runs on PyTorch, which
    ``make demo`` does not install (the ``demo`` extra); those cells then read ``n/a``.
    """
    from .cvvdp_metric import cvvdp_available

    if cvvdp_available():
        return None
    return ("perceptual score skipped: the JOD (ColorVideoVDP) column and chart panels are n/a, since cvvdp "
            "and PyTorch are not installed (pip install -e '.[evaluate]' adds them)")
