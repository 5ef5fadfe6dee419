"""Per-pixel, per-polarity contrast thresholds estimated from a recording's frames and events.

Model (derivation in ``docs/calibrate.md``, "Contrast thresholds"). Between two consecutive frame
times τ_k < τ_{k+1} (mid-exposures) an ideal DVS pixel with thresholds c_on, c_off fires
N_on,k ON and N_off,k OFF events, and its log intensity changes by

    ΔL_k = L(τ_{k+1}) − L(τ_k) = c_on·N_on,k − c_off·N_off,k + (r_{k+1} − r_k),

where r is the pixel's distance from its last reference level (|r| below one threshold), so the
error of one interval is bounded and telescopes over consecutive intervals. The frames measure
L(τ_k) as ``L^F_k = log(s_k·I_k + I0)``, with ``I_k = CRF⁻¹(code)`` in frame-linear units from the
camera profile, ``s_k`` the exposure × gain ratio to the median frame (1 when the exposures are
equal or unknown) and I0 a small offset (:data:`DEFAULT_INTENSITY_OFFSET`, 1e-3 of the clip
level; the simulator's ``log_eps`` has the same size). Only intervals whose two frames both see
the pixel well exposed (codes 20-235 of 8 bits, scaled to other depths) are used, and only
intervals inside the events' time span (their counts are complete).

Per pixel, least squares with non-negativity,

    (ĉ_on, ĉ_off) = argmin_{a, b >= 0} Σ_k (ΔL_k − a·N_on,k + b·N_off,k)²,

accumulated interval by interval in five sums (memory O(H·W), not O(K·H·W)) and solved in closed
form (the 2×2 normal equations; when the unconstrained solution has a negative component, the
best of the two one-variable solutions on the boundary: exact NNLS for two unknowns).

Minimum information: a pixel is **estimable** when at least ``min_intervals`` (2) usable
intervals hold ON events and at least ``min_intervals`` hold OFF events, its ON and OFF count
columns are not (nearly) proportional (``1 − ρ² >= min_decorrelation``, ρ the uncentred
correlation of the two columns; proportional counts leave only c_on·N_on − c_off·N_off
determined), and both estimates lie in ``c_range`` (a threshold at the NNLS bound 0 is not
physical). Other pixels are NaN in :class:`ThresholdMap` and counted by reason.

Fallback (global estimate): the same least squares pooled over every usable (pixel, interval)
pair, i.e. the five sums added over the pixels; :meth:`ThresholdMap.filled` puts it in every NaN
pixel. Stored as ``fallback_on``/``fallback_off``.

The map and its sidecar file ``thresholds.npz`` are :mod:`hybridhdr.formats.thresholds`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .._util.atomic import atomic_path
from ..camera import load_profile, profile_for_frames
from ..camera.encoding import DEFAULT_INTENSITY_OFFSET, frames_to_codes, well_exposed_range
from ..formats.thresholds import METHOD, ThresholdMap

__all__ = ["estimate_thresholds", "threshold_sums", "pooled_thresholds", "plot_thresholds"]

# -- estimation ----------------------------------------------------------------------------------

def _nnls2(soo, sff, sof, bo, bf):
    """Exact 2-variable NNLS of Σ(ΔL − a·N_on + b·N_off)² from its sums (vectorised).

    Sums: soo = ΣN_on², sff = ΣN_off², sof = ΣN_on·N_off, bo = ΣN_on·ΔL, bf = ΣN_off·ΔL.
    Returns (a, b) >= 0 (0 where a sum is empty).
    """
    soo, sff, sof, bo, bf = (np.asarray(v, np.float64) for v in (soo, sff, sof, bo, bf))
    det = soo * sff - sof * sof
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(det > 0, (sff * bo - sof * bf) / det, -1.0)
        b = np.where(det > 0, (sof * bo - soo * bf) / det, -1.0)
        # boundary candidates: b = 0 -> a = bo/soo; a = 0 -> b = -bf/sff
        a1 = np.where(soo > 0, np.maximum(bo / soo, 0.0), 0.0)
        b2 = np.where(sff > 0, np.maximum(-bf / sff, 0.0), 0.0)
    # objective minus the constant ΣΔL²: f(a, b) = soo a² + sff b² − 2 sof a b − 2 bo a + 2 bf b
    f1 = soo * a1 ** 2 - 2 * bo * a1
    f2 = sff * b2 ** 2 + 2 * bf * b2
    inner = (a >= 0) & (b >= 0) & (det > 0)
    use1 = f1 <= f2
    a_out = np.where(inner, a, np.where(use1, a1, 0.0))
    b_out = np.where(inner, b, np.where(use1, 0.0, b2))
    return a_out, b_out


def estimate_thresholds(recording, *, profile=None, intensity_offset: float | None = None, well_exposed=None,
                        min_intervals: int = 2, min_decorrelation: float = 0.05, c_range=(0.01, 2.0),
                        require_event_coverage: bool = True, progress=None) -> ThresholdMap:
    """Estimate per-pixel ON/OFF thresholds from frames and events (module docstring).

    Parameters are those of :func:`threshold_sums`, which also returns the per-pixel sums.
    """
    return threshold_sums(recording, profile=profile, intensity_offset=intensity_offset, well_exposed=well_exposed,
                          min_intervals=min_intervals, min_decorrelation=min_decorrelation, c_range=c_range,
                          require_event_coverage=require_event_coverage, progress=progress)[0]


def threshold_sums(recording, *, profile=None, intensity_offset: float | None = None, well_exposed=None,
                   min_intervals: int = 2, min_decorrelation: float = 0.05, c_range=(0.01, 2.0),
                   require_event_coverage: bool = True, progress=None, parts: int = 1, interval_hook=None):
    """:func:`estimate_thresholds` and its least-squares sums: ``(ThresholdMap, sums, part_sums)``.

    ``sums`` maps ``soo, sff, sof, bo, bf, sll`` (ΣN_on², ΣN_off², ΣN_on·N_off, ΣN_on·ΔL,
    ΣN_off·ΔL, ΣΔL²), ``n_int`` (usable intervals) and the rest below to per-pixel arrays (H·W,); the
    pooled estimate is :func:`_nnls2` of their totals, so a bootstrap over pixels re-weights them.
    ``part_sums`` holds the same sums over ``parts`` consecutive blocks of the usable intervals
    (in time order; ``parts=1``: one block, the totals), for split-sample estimates, with ``k_on``,
    ``k_off`` (usable intervals with ON / OFF events), ``n_on``, ``n_off`` (ΣN_on, ΣN_off) and
    ``sl`` (ΣΔL); ``sums`` holds them too. ``interval_hook(tau0_us, tau1_us, dL, good,
    i0, i1)``, if given, is called for every usable interval with the frames' log change ``dL``
    (H·W,), the pixels both frames see well exposed and the slice ``[i0, i1)`` of its events.

    Parameters
    ----------
    recording : Recording or path
        Needs events and at least two frames registered to the event sensor (same size).
    profile : CameraProfile, path or None
        Camera profile for ``I = CRF⁻¹(code)``; None: the recording's declared profile
        (``provenance["camera_profile"]``), else the built-in one for the frames' encoding.
    intensity_offset : float, optional
        I0 in frame-linear units; default :data:`hybridhdr.camera.encoding.DEFAULT_INTENSITY_OFFSET`.
    well_exposed : (lo, hi), optional
        Codes counted as well exposed (inclusive); default 20-235 scaled to the bit depth.
    min_intervals : int
        Usable intervals with ON events, and with OFF events, a pixel needs.
    min_decorrelation : float
        Smallest ``1 − ρ²`` of the ON and OFF count columns (identifiability).
    c_range : (float, float)
        Estimates outside it are not accepted (log units).
    require_event_coverage : bool
        Use only intervals inside the events' time span (first to last event).
    """

    rec = recording
    if isinstance(rec, (str, Path)):
        from ..formats import read
        rec = read(rec)
    if rec.frames is None or len(rec.frames) < 2:
        raise ValueError("threshold estimation needs at least two frames; the recording has "
                         f"{0 if rec.frames is None else len(rec.frames)}")
    if len(rec.events) == 0:
        raise ValueError("threshold estimation needs events; the recording has none")
    i0 = DEFAULT_INTENSITY_OFFSET if intensity_offset is None else float(intensity_offset)
    if not (math.isfinite(i0) and i0 > 0):
        raise ValueError(f"intensity_offset must be finite and > 0, got {intensity_offset}")
    lo_c, hi_c = (float(v) for v in c_range)
    if not 0 < lo_c < hi_c:
        raise ValueError(f"c_range must satisfy 0 < lo < hi, got {c_range}")
    if int(min_intervals) < 1:
        raise ValueError(f"min_intervals must be >= 1, got {min_intervals}")
    if profile is None:
        prov = rec.metadata.provenance if rec.metadata is not None else {}
        profile = prov.get("camera_profile") if isinstance(prov, dict) else None
        if not (profile is None or isinstance(profile, (str, Path)) or hasattr(profile, "intensity")):
            from ..camera import CameraProfile
            profile = CameraProfile.from_dict(profile) if isinstance(profile, dict) else None
    fr = rec.frames
    prof = profile_for_frames(load_profile(profile), fr)
    h, w = fr.shape
    ss = rec.sensor_size
    if ss is not None and tuple(ss.shape) != (h, w):
        raise ValueError(f"frames are {w}x{h} but the event sensor is {ss.width}x{ss.height}; register them first")
    codes = frames_to_codes(fr, (h, w))
    lo, hi = well_exposed_range(prof.max_code) if well_exposed is None else (int(well_exposed[0]),
                                                                            int(well_exposed[1]))
    # frame order by τ (mid-exposure); frames sharing a τ keep the last one (as reconstruct)
    tau = fr.t_mid_us
    order = np.argsort(tau, kind="stable")
    keep = np.ones(len(order), bool)
    keep[:-1] = tau[order][1:] != tau[order][:-1]
    order = order[keep]
    tau = tau[order]
    # exposure x gain relative to the median frame (1 when unknown or equal)
    expo = fr.exposure_us.astype(np.float64)[order]
    gain = np.ones(len(order)) if fr.gain is None else np.asarray(fr.gain, np.float64)[order]
    e = expo * gain
    if np.all(e > 0) and np.ptp(e) > 0:
        scale = float(np.median(e)) / e
        scale_note = "exposure x gain normalised to the median frame"
    else:
        scale = np.ones(len(order))
        scale_note = "none (equal or unknown exposures)"
    ev = rec.events
    t = ev["t"]
    t0_ev, t1_ev = int(t[0]), int(t[-1])
    pix = ev["y"].astype(np.int64) * w + ev["x"].astype(np.int64)
    on = ev["p"] > 0
    n = h * w
    sums = {k: np.zeros(n, np.float64) for k in ("soo", "sff", "sof", "bo", "bf", "sll")}
    n_on = np.zeros(n, np.int64)
    n_off = np.zeros(n, np.int64)
    k_on = np.zeros(n, np.int64)
    k_off = np.zeros(n, np.int64)
    n_int = np.zeros(n, np.int64)
    used = []

    def logf(j):
        c = np.asarray(codes[order[j]]).reshape(-1)
        good = (c >= lo) & (c <= hi)
        return np.log(prof.intensity(c) * scale[j] + i0), good

    if int(parts) < 1:
        raise ValueError(f"parts must be >= 1, got {parts}")
    usable = [j for j in range(len(tau) - 1)
              if (not require_event_coverage) or (tau[j] >= t0_ev and tau[j + 1] <= t1_ev)]
    part_of = {j: (i * int(parts)) // max(len(usable), 1) for i, j in enumerate(usable)}
    part_sums = [{k: np.zeros(n, np.float64) for k in ("soo", "sff", "sof", "bo", "bf", "sll", "n_int", "k_on",
                                                       "k_off", "n_on", "n_off", "sl")}
                 for _ in range(int(parts))]
    Lk, gk = logf(0)
    idx = np.searchsorted(t, tau)
    for j in range(len(tau) - 1):
        L1, g1 = logf(j + 1)
        if j in part_of:
            a, b = idx[j], idx[j + 1]
            p_ = pix[a:b]
            o_ = on[a:b]
            non = np.bincount(p_[o_], minlength=n).astype(np.float64)
            noff = np.bincount(p_[~o_], minlength=n).astype(np.float64)
            m = gk & g1
            if interval_hook is not None:
                interval_hook(int(tau[j]), int(tau[j + 1]), L1 - Lk, m, int(a), int(b))
            dl = np.where(m, L1 - Lk, 0.0)
            non = np.where(m, non, 0.0)
            noff = np.where(m, noff, 0.0)
            sums["soo"] += non * non
            sums["sff"] += noff * noff
            sums["sof"] += non * noff
            sums["bo"] += non * dl
            sums["bf"] += noff * dl
            sums["sll"] += dl * dl
            ps = part_sums[part_of[j]]
            for k, v in (("soo", non * non), ("sff", noff * noff), ("sof", non * noff), ("bo", non * dl),
                         ("bf", noff * dl), ("sll", dl * dl), ("n_int", m), ("k_on", non > 0),
                         ("k_off", noff > 0), ("n_on", non), ("n_off", noff), ("sl", dl)):
                ps[k] += v
            n_on += non.astype(np.int64)
            n_off += noff.astype(np.int64)
            k_on += non > 0
            k_off += noff > 0
            n_int += m
            used.append(j)
        Lk, gk = L1, g1
        if progress is not None:
            progress(j + 1, len(tau) - 1)
    if not used:
        raise ValueError(f"no frame interval lies inside the events' span ({t0_ev}..{t1_ev} µs; frames at "
                         f"{tau[:5].tolist()}... µs); pass require_event_coverage=False to use them anyway")
    a, b = _nnls2(sums["soo"], sums["sff"], sums["sof"], sums["bo"], sums["bf"])
    with np.errstate(invalid="ignore", divide="ignore"):
        rho2 = np.where((sums["soo"] > 0) & (sums["sff"] > 0), sums["sof"] ** 2 / (sums["soo"] * sums["sff"]), 1.0)
    few = (k_on < min_intervals) | (k_off < min_intervals)
    degenerate = ~few & (1.0 - rho2 < min_decorrelation)
    out_of_range = ~few & ~degenerate & ((a < lo_c) | (a > hi_c) | (b < lo_c) | (b > hi_c))
    valid = ~few & ~degenerate & ~out_of_range
    c_on = np.where(valid, a, np.nan).reshape(h, w)
    c_off = np.where(valid, b, np.nan).reshape(h, w)
    tot = {k: float(v.sum()) for k, v in sums.items()}
    ga, gb = _nnls2(tot["soo"], tot["sff"], tot["sof"], tot["bo"], tot["bf"])
    ga, gb = float(ga), float(gb)
    if not (lo_c <= ga <= hi_c and lo_c <= gb <= hi_c):
        raise ValueError(f"the pooled estimate (c_on {ga:.4g}, c_off {gb:.4g}) is outside c_range {c_range}: the "
                         f"recording has too little usable information (well-exposed pixel pairs with events of both "
                         f"polarities: ON events {int(n_on.sum())}, OFF events {int(n_off.sum())})")
    # residual RMS per usable pixel-interval, at the per-pixel estimates (global fallback elsewhere)
    af = np.where(valid, a, ga)
    bf_ = np.where(valid, b, gb)
    res2 = (sums["sll"] - 2 * af * sums["bo"] + 2 * bf_ * sums["bf"] + af ** 2 * sums["soo"] + bf_ ** 2 * sums["sff"]
            - 2 * af * bf_ * sums["sof"])
    n_pi = int(n_int.sum())
    prov = {"recording": str(rec.metadata.provenance.get("source_file", "")) if rec.metadata else "",
            "profile": prof.name, "intensity_offset": i0, "well_exposed_codes": [int(lo), int(hi)],
            "min_intervals": int(min_intervals), "min_decorrelation": float(min_decorrelation),
            "c_range": [lo_c, hi_c], "require_event_coverage": bool(require_event_coverage),
            "exposure_normalisation": scale_note, "n_frames": int(len(tau)), "intervals_used": len(used),
            "first_interval": [int(tau[used[0]]), int(tau[used[0] + 1])],
            "last_interval": [int(tau[used[-1]]), int(tau[used[-1] + 1])],
            "pooled_on": ga, "pooled_off": gb, "fallback": "pooled least squares over all usable pixel-intervals",
            "n_pixel_intervals": n_pi, "events_in_usable_intervals": int(n_on.sum() + n_off.sum()),
            "residual_rms_log": float(math.sqrt(max(float(res2.sum()), 0.0) / n_pi)) if n_pi else float("nan"),
            "not_estimable": {"too_few_intervals": int(few.sum()), "on_off_proportional": int(degenerate.sum()),
                              "outside_c_range_or_zero": int(out_of_range.sum())},
            "n_estimated": int(valid.sum()), "n_fallback": int((~valid).sum())}
    if isinstance(rec.metadata.provenance, dict) and "contrast_threshold" in rec.metadata.provenance:
        prov["declared_contrast_threshold"] = rec.metadata.provenance["contrast_threshold"]
    tm = ThresholdMap(c_on=c_on, c_off=c_off, fallback_on=ga, fallback_off=gb, n_on=n_on.reshape(h, w),
                      n_off=n_off.reshape(h, w), n_intervals=n_int.reshape(h, w), method=METHOD, provenance=prov)
    prov.update({k: v for k, v in tm.summary().items() if k.startswith(("median", "q25", "q75", "fraction"))})
    tot_sums = {k: sum(ps[k] for ps in part_sums) for k in part_sums[0]}
    return tm, tot_sums, part_sums


def pooled_thresholds(recording, *, profile=None, intensity_offset: float | None = None) -> tuple[float, float, dict]:
    """``(c_on, c_off, record)``: one ON and one OFF threshold for the whole sensor, pooled over
    every usable pixel-interval of ``recording`` (:func:`estimate_thresholds`' fallback pair) in
    the log model ``ln(I + intensity_offset)`` of the method that will use them. ``record`` says
    how many frame intervals and pixel-intervals the estimate rests on. Raises ValueError when
    the recording cannot tell them (fewer than two frames, no events, no usable interval).

    On ``ecd_slider_depth`` (leave-one-frame-out, ``benchmarks/accuracy.py``), pooled thresholds
    estimated this way give the causal AKF an MSE of 1.28e-2 against 1.63e-2 with the default
    c = 0.1, the two-sided AKF 7.85e-3 against 8.41e-3."""
    tm = estimate_thresholds(recording, profile=profile, intensity_offset=intensity_offset)
    pv = tm.provenance
    record = {"intervals": int(pv.get("intervals_used", 0)), "pixel_intervals": int(pv.get("n_pixel_intervals", 0)),
              "intensity_offset": float(pv.get("intensity_offset", intensity_offset or DEFAULT_INTENSITY_OFFSET))}
    return float(tm.fallback_on), float(tm.fallback_off), record


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
