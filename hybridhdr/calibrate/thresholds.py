"""Per-pixel, per-polarity contrast thresholds of a recording, on the one camera model.

The pooled pair is the camera model's (:mod:`hybridhdr.calibrate.camera_model`: the same estimate
as the self-calibration and ``calibrate sensor``). Per pixel, the same least squares on the
pixel's own intervals, where the data identify it (at least ``min_intervals`` event-bearing
intervals with ON events and with OFF events, ON and OFF count columns not proportional, both
estimates in ``c_range``), shrunk toward the pooled pair by its own uncertainty (empirical Bayes,
:func:`hybridhdr.calibrate.camera_model.shrink_per_pixel`): a pixel with few events keeps almost
the pooled value, and when the pixels show no spread beyond their estimation noise every pixel
keeps it. Other pixels are NaN in :class:`ThresholdMap` (the fallback fills them).

The map and its sidecar file ``thresholds.npz`` are :mod:`hybridhdr.formats.thresholds`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import InputMismatchError
from .._util.atomic import atomic_path
from ..formats.thresholds import METHOD, ThresholdMap
from .camera_model import _nnls2  # noqa: F401  (the closed-form NNLS lives with the estimator)

__all__ = ["estimate_thresholds", "pooled_thresholds", "plot_thresholds"]

# -- estimation ----------------------------------------------------------------------------------

def estimate_thresholds(recording, *, profile=None, intensity_offset: float | None = None, well_exposed=None,
                        min_intervals: int = 2, min_decorrelation: float = 0.05, c_range=(0.01, 2.0),
                        progress=None, model=None) -> ThresholdMap:
    """Per-pixel ON/OFF thresholds of ``recording``: the camera model's pooled pair as the fallback
    and, where the data identify a pixel, its own pair shrunk toward the pooled one by its
    uncertainty (:func:`hybridhdr.calibrate.camera_model.shrink_per_pixel`).

    Parameters
    ----------
    recording : Recording or path
        Needs events and at least three frames registered to the event sensor (same size).
    profile : CameraProfile, path or None
        Camera profile for ``I = CRF⁻¹(code)``; None: the recording's declared profile, else the
        built-in one for the frames' encoding.
    intensity_offset : float, optional
        I0 of the log model; default: the camera model's own (estimated).
    well_exposed : (lo, hi), optional
        Codes counted as well exposed (inclusive); default 20-235 scaled to the bit depth.
    min_intervals : int
        Event-bearing intervals with ON events, and with OFF events, a pixel needs.
    min_decorrelation : float
        Smallest ``1 − ρ²`` of a pixel's ON and OFF count columns (identifiability).
    c_range : (float, float)
        Estimates outside it are not accepted (log units).
    model : CameraModel, optional
        An estimate already made for this recording with ``per_pixel=True``.
    """
    from .camera_model import estimate_camera_model, shrink_per_pixel
    rec = recording
    if isinstance(rec, (str, Path)):
        from ..formats import read
        rec = read(rec)
    lo_c, hi_c = (float(v) for v in c_range)
    if not 0 < lo_c < hi_c:
        raise ValueError(f"c_range must satisfy 0 < lo < hi, got {c_range}")
    if int(min_intervals) < 1:
        raise ValueError(f"min_intervals must be >= 1, got {min_intervals}")
    if intensity_offset is not None and not (math.isfinite(float(intensity_offset)) and float(intensity_offset) > 0):
        raise ValueError(f"intensity_offset must be finite and > 0, got {intensity_offset}")
    if rec.frames is None or len(rec.frames) < 3:
        raise InputMismatchError("threshold estimation needs at least three frames; the recording has "
                         f"{0 if rec.frames is None else len(rec.frames)}")
    if len(rec.events) == 0:
        raise InputMismatchError("threshold estimation needs events; the recording has none")
    m = model if model is not None else estimate_camera_model(
        rec, profile=profile, intensity_offset=intensity_offset, well_exposed=well_exposed, c_range=(lo_c, hi_c),
        per_pixel=True, progress=progress)
    con, coff, ident, shrink = shrink_per_pixel(m, min_intervals=int(min_intervals),
                                                min_decorrelation=float(min_decorrelation), c_range=(lo_c, hi_c))
    h, w = con.shape
    tot = m.per_pixel["tot"]
    few = ((tot["k_on"] < min_intervals) | (tot["k_off"] < min_intervals)).reshape(h, w)
    ga, gb = float(m.c_on), float(m.c_off)
    prov = {"recording": str(rec.metadata.provenance.get("source_file", "")) if rec.metadata else "",
            "profile": shrink.get("profile", ""), "intensity_offset": float(m.intensity_offset),
            "time_offset_us": int(m.time_offset_us), "well_exposed_codes": list(well_exposed) if well_exposed else None,
            "min_intervals": int(min_intervals), "min_decorrelation": float(min_decorrelation), "c_range": [lo_c, hi_c],
            "intervals_used": int(m.n_intervals), "n_pixel_intervals": int(m.n_pixel_intervals),
            "pooled_on": ga, "pooled_off": gb, "pooled_on_std": m.c_on_std, "pooled_off_std": m.c_off_std,
            "fallback": "the camera model's pooled thresholds (hybridhdr.calibrate.camera_model)",
            "per_pixel": {k: v for k, v in shrink.items() if k != "profile"},
            "not_estimable": {"too_few_intervals": int(few.sum()), "not_identified_otherwise": int((~ident & ~few).sum())},
            "n_estimated": int(ident.sum()), "n_fallback": int((~ident).sum()),
            "camera_model": m.to_dict()}
    if rec.metadata is not None and isinstance(rec.metadata.provenance, dict) \
            and "contrast_threshold" in rec.metadata.provenance:
        prov["declared_contrast_threshold"] = rec.metadata.provenance["contrast_threshold"]
    tm = ThresholdMap(c_on=np.where(ident, con, np.nan), c_off=np.where(ident, coff, np.nan), fallback_on=ga,
                      fallback_off=gb, n_intervals=tot["n"].reshape(h, w).astype(np.int64), method=METHOD,
                      provenance=prov)
    prov.update({k: v for k, v in tm.summary().items() if k.startswith(("median", "q25", "q75", "fraction"))})
    return tm


def pooled_thresholds(recording, *, profile=None, intensity_offset: float | None = None) -> tuple[float, float, dict]:
    """``(c_on, c_off, record)``: one ON and one OFF threshold for the whole sensor, the camera
    model's (:func:`hybridhdr.calibrate.camera_model.estimate_camera_model`), in the log model
    ``ln(I + intensity_offset)`` of the method that will use them (None: the model's own I0 and
    frame time offset; a number: that I0 with the frames at their stamps, as the run uses them).
    ``record`` says how many frame intervals and pixel-intervals the estimate rests on. Raises
    ValueError when the recording cannot tell them."""
    from .camera_model import estimate_camera_model
    if intensity_offset is None:
        m = estimate_camera_model(recording, profile=profile)
    else:
        # the method's own log model, with the frames at their stamps: a run given these thresholds
        # ("auto") does not shift its frames, so they are estimated as it will use them
        m = estimate_camera_model(recording, profile=profile, intensity_offset=float(intensity_offset),
                                  time_offset_us=0)
    record = {"intervals": int(m.n_intervals), "pixel_intervals": int(m.n_pixel_intervals),
              "intensity_offset": float(m.intensity_offset), "time_offset_us": int(m.time_offset_us)}
    return float(m.c_on), float(m.c_off), record


# -- plot -----------------------------------------------------------------------------------------

def plot_thresholds(tm: ThresholdMap, path, title: str | None = None) -> Path:
    """PNG with the ON and OFF histograms of the estimated pixels (medians and fallbacks marked)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v = tm.valid
    on, off = tm.c_on[v], tm.c_off[v]
    s = tm.summary()
    fig, ax = plt.subplots(figsize=(7.5, 4.5), dpi=110)
    if on.size:
        allv = np.concatenate([on, off])
        hi = float(np.percentile(allv, 99.5)) * 1.1
        bins = np.linspace(0.0, max(hi, 1e-3), 60)
        ax.hist(np.clip(on, None, bins[-1]), bins=bins, alpha=0.55, color="tab:red",
                label=f"ON  (median {s['median_on']:.3f})")
        ax.hist(np.clip(off, None, bins[-1]), bins=bins, alpha=0.55, color="tab:blue",
                label=f"OFF (median {s['median_off']:.3f})")
        ax.axvline(s["median_on"], color="tab:red", lw=1.5)
        ax.axvline(s["median_off"], color="tab:blue", lw=1.5)
    else:
        ax.text(0.5, 0.5, "no pixel estimable", transform=ax.transAxes, ha="center")
    ax.axvline(tm.fallback_on, color="tab:red", ls="--", lw=1.2, label=f"ON fallback (pooled) {tm.fallback_on:.3f}")
    ax.axvline(tm.fallback_off, color="tab:blue", ls="--", lw=1.2,
               label=f"OFF fallback (pooled) {tm.fallback_off:.3f}")
    ax.set_xlabel("contrast threshold c (natural-log units, Δ ln I per event)")
    ax.set_ylabel("pixels")
    from matplotlib.ticker import MaxNLocator
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_title(title or f"per-pixel thresholds: {s['n_estimated']} of {s['n_pixels']} pixels estimated "
                          f"({100 * s['fraction_estimated']:.1f} %)", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
