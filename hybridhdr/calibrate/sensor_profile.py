"""Event-sensor parameters of a real recording with frames, as the simulator defines them.

The simulator's sensor model (``hybridhdr/simulate/sensor.py``, ``docs/simulate-sensor.md``) has
ON/OFF threshold means ``contrast_threshold_on/off`` (ln units), a per-pixel N(C, σ) mismatch
``threshold_mismatch_sigma``, ``shot_noise_rate_hz`` (ON + OFF, Poisson, per pixel),
``leak_rate_hz`` (ON only), ``refractory_period_us`` and a photoreceptor corner
``photoreceptor_cutoff_hz``; it has no timestamp jitter. :func:`estimate_sensor_profile` measures
each from the recording's own frames and events (derivations in ``docs/calibrate.md``, "Sensor
profile"), with its uncertainty and an ``identifiable`` flag saying whether the recording can
tell it:

* **threshold means**: the pooled least squares of the threshold estimator
  (:func:`hybridhdr.calibrate.thresholds.threshold_sums`); 95 % interval by a bootstrap over
  pixels (each pixel's sums re-weighted by Poisson(1) weights).
* **per-pixel spread**: the raw spread of per-pixel estimates is σ² plus each estimate's own
  noise (quantisation of the log change into whole events). The usable intervals are cut into
  two halves in time and every pixel estimated on each; the two estimates' errors are
  independent, so ``cov(ĉ_first, ĉ_second)`` over pixels estimates σ² without the noise.
* **shot noise and leak**: events at *static* pixels, well exposed in both frames of an interval
  whose log change (and that of its 3×3 neighbours) stays below ``static_log_bound``; in the
  simulator these fire OFF at ``shot/2`` and ON at ``shot/2 + leak``; constrained maximum
  likelihood (leak >= 0), exact Poisson (Garwood) intervals.
* **refractory period**: the lower edge of the same-pixel inter-event-interval histogram,
  ``min d`` with ``#ISI <= d`` minus the shot-noise pairs expected below ``d`` at least
  ``isi_quantile`` of all intervals; identifiable only when the intervals pile up at that edge
  (a refractory-limited pixel), else it is an upper bound.
* **photoreceptor bandwidth, timestamp jitter**: not identifiable from frames and events of a
  natural scene (reasons in the profile).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import InputMismatchError
from ..formats.sensor_profile import SensorProfile
from .thresholds import _nnls2, threshold_sums

__all__ = ["estimate_sensor_profile", "isi_lower_edge", "poisson_ci"]

#: Fewest pixels with a per-pixel estimate in both halves for the spread (its bootstrap needs a sample).
MIN_SPREAD_PIXELS = 30
#: Fewest static events for comparing the polarities (leak); below it only the total rate is told.
MIN_STATIC_EVENTS = 20
#: Fewest same-pixel intervals for the refractory edge.
MIN_ISIS = 200


def poisson_ci(n: int, conf: float = 0.95) -> tuple[float, float]:
    """Exact (Garwood) confidence interval of a Poisson mean from one count ``n``."""
    from scipy.stats import chi2
    a = 1.0 - conf
    lo = 0.0 if n == 0 else float(chi2.ppf(a / 2, 2 * n) / 2)
    hi = float(chi2.ppf(1 - a / 2, 2 * n + 2) / 2)
    return lo, hi


def _entry(value, *, identifiable, method, unit, reason="", std=None, ci95=None, **extra):
    def f(v):
        return None if v is None or not math.isfinite(float(v)) else float(v)
    e = {"value": f(value), "std": f(std), "ci95": None if ci95 is None else [float(ci95[0]), float(ci95[1])],
         "identifiable": bool(identifiable), "reason": reason, "method": method, "unit": unit}
    e.update(extra)
    return e


def _boot_weights(rng, n_boot: int, n: int, chunk: int = 50):
    """Poisson(1) bootstrap weights, at most ``chunk`` replicates and 4 M weights at a time (bounded memory)."""
    chunk = max(1, min(chunk, (4 << 20) // max(n, 1)))
    for k in range(0, n_boot, chunk):
        yield rng.poisson(1.0, size=(min(chunk, n_boot - k), n)).astype(np.float64)


def _ci(samples):
    s = np.asarray(samples, np.float64)
    s = s[np.isfinite(s)]
    if s.size < 2:
        return None, None
    return float(np.std(s, ddof=1)), (float(np.percentile(s, 2.5)), float(np.percentile(s, 97.5)))


def _corrected(ps, lam_on: float, lam_off: float):
    """Least-squares sums ``(soo, sff, sof, bo, bf)`` of the counts less their noise events.

    With N = S + E, E Poisson noise of mean λ per interval independent of the signal S and of ΔL:
    E[Σ(N−λ)² − Kλ] = ΣS², E[Σ(N_on−λ_on)(N_off−λ_off)] = ΣS_on·S_off, E[Σ(N−λ)·ΔL] = ΣS·ΔL
    (K usable intervals), so the corrected normal equations are those of the signal counts."""
    K, so, sf, sl = ps["n_int"], ps["n_on"], ps["n_off"], ps["sl"]
    soo = ps["soo"] - 2 * lam_on * so + K * (lam_on ** 2 - lam_on)
    sff = ps["sff"] - 2 * lam_off * sf + K * (lam_off ** 2 - lam_off)
    sof = ps["sof"] - lam_off * so - lam_on * sf + K * lam_on * lam_off
    return soo, sff, sof, ps["bo"] - lam_on * sl, ps["bf"] - lam_off * sl


def _half_estimates(ps, cs, min_intervals, min_decorrelation, c_range):
    soo, sff, sof, bo, bf = cs
    a, b = _nnls2(soo, sff, sof, bo, bf)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho2 = np.where((soo > 0) & (sff > 0), sof ** 2 / (soo * sff), 1.0)
    ok = ((ps["k_on"] >= min_intervals) & (ps["k_off"] >= min_intervals) & (1.0 - rho2 >= min_decorrelation)
          & (a >= c_range[0]) & (a <= c_range[1]) & (b >= c_range[0]) & (b <= c_range[1]))
    return a, b, ok


def _inliers(x, k: float = 8.0):
    """Within ``k`` robust SDs (1.4826 MAD) of the median."""
    med = np.median(x)
    mad = 1.4826 * np.median(np.abs(x - med))
    return np.abs(x - med) <= k * mad if mad > 0 else np.ones(x.shape, bool)


def _cov(x, y, w=None):
    if w is None:
        return float(np.mean((x - x.mean()) * (y - y.mean())))
    sw = w.sum(axis=-1, keepdims=True)
    mx = (w * x).sum(-1, keepdims=True) / sw
    my = (w * y).sum(-1, keepdims=True) / sw
    return ((w * (x - mx) * (y - my)).sum(-1) / sw[..., 0])


def isi_lower_edge(isi_us, weights=None, *, noise_rate_hz: float = 0.0, quantile: float = 1e-3, _half=None):
    """Lower edge of an inter-event-interval sample (µs), ``isi_us`` sorted ascending.

    The smallest ISI ``d`` at which the (weighted) count of ISIs <= d, less the pairs expected
    from a noise floor below the edge, reaches ``max(quantile · total, 3)``. The floor is
    ``noise_rate_hz · d`` pairs per interval (a shot-noise event within ``d`` after an event of
    the same pixel, as the simulator's noise, which ignores the refractory period), capped by the
    floor the sample itself shows below ``d/2`` (a real pixel's background events may keep their
    distance from its signal events). NaN when no ISI qualifies."""
    s = np.asarray(isi_us, np.float64)
    w = np.ones_like(s) if weights is None else np.asarray(weights, np.float64)
    tot = w.sum()
    if tot <= 0:
        return math.nan
    cw = np.cumsum(w)
    half = np.searchsorted(s, s / 2, side="right") if _half is None else _half
    below_half = np.where(half > 0, cw[np.maximum(half - 1, 0)], 0.0)
    floor = np.minimum(tot * noise_rate_hz * s * 1e-6, 2.0 * below_half)
    excess = cw - floor
    hit = np.flatnonzero(excess >= max(quantile * tot, 3.0))
    return float(s[hit[0]]) if hit.size else math.nan


def estimate_sensor_profile(recording, *, profile=None, intensity_offset: float | None = None, well_exposed=None,
                            static_log_bound: float = 0.02, isi_quantile: float = 1e-3, n_boot: int = 200,
                            seed: int = 0, min_intervals: int = 2, min_decorrelation: float = 0.05,
                            c_range=(0.01, 2.0), name: str = "", sensor_model: str = "") -> SensorProfile:
    """Estimate the event-sensor parameters of ``recording`` (module docstring).

    Parameters
    ----------
    recording : Recording or path
        Events and at least two frames registered to the event sensor.
    profile, intensity_offset, well_exposed, min_intervals, min_decorrelation, c_range
        As :func:`hybridhdr.calibrate.thresholds.estimate_thresholds`.
    static_log_bound : float
        Largest |Δ ln I| between two frames (at the pixel and its 3×3 neighbours) of a static pixel.
    isi_quantile : float
        Fraction of same-pixel intervals below the refractory edge (after the noise pairs).
    n_boot : int
        Bootstrap replicates over pixels (threshold means and spread, refractory edge).
    seed : int
        Seeds the bootstrap (same seed, same profile).
    """
    rec = recording
    if isinstance(rec, (str, Path)):
        from ..formats import read
        rec = read(rec)
    if not (isinstance(static_log_bound, (int, float)) and 0 < static_log_bound < 1):
        raise ValueError(f"static_log_bound must be in (0, 1) log units, got {static_log_bound!r}")
    if not 0 < isi_quantile < 0.5:
        raise ValueError(f"isi_quantile must be in (0, 0.5), got {isi_quantile!r}")
    if int(n_boot) < 20:
        raise ValueError(f"n_boot must be >= 20 (a 95 % interval needs replicates), got {n_boot!r}")
    if rec.frames is None or len(rec.frames) < 2:
        raise InputMismatchError("calibrate sensor needs a recording with events and at least two frames; found "
                         f"{0 if rec.frames is None else len(rec.frames)} frame(s)")
    if len(rec.events) == 0:
        raise InputMismatchError("calibrate sensor needs events; the recording has none")
    rng = np.random.default_rng(seed)
    ss = rec.sensor_size
    h, w = rec.frames.shape
    est: dict = {}
    sim: dict = {}

    # -- static pixel-intervals (collected in the threshold estimator's own pass) -------------------
    ev = rec.events
    pix_all = ev["y"].astype(np.int64) * w + ev["x"].astype(np.int64)
    on_all = ev["p"] > 0
    static = {"n_on": 0, "n_off": 0, "pixel_s": 0.0, "sum_abs_dl": 0.0, "intervals": 0, "pixel_intervals": 0,
              "dt_s": 0.0}

    def hook(t0, t1, dl, good, i0, i1):
        from scipy.ndimage import maximum_filter
        d = np.where(good, np.abs(dl), np.inf).reshape(h, w)
        st = (maximum_filter(d, size=3, mode="nearest") < static_log_bound).reshape(-1)
        k = int(st.sum())
        static["intervals"] += 1
        static["dt_s"] += (t1 - t0) * 1e-6
        if not k:
            return
        p_ = pix_all[i0:i1]
        sel = st[p_]
        o_ = on_all[i0:i1][sel]
        static["n_on"] += int(o_.sum())
        static["n_off"] += int((~o_).sum())
        static["pixel_s"] += k * (t1 - t0) * 1e-6
        static["sum_abs_dl"] += float(np.abs(dl[st]).sum())
        static["pixel_intervals"] += k

    # -- thresholds: pooled means, per-pixel spread (split halves) ----------------------------------
    c_range = (float(c_range[0]), float(c_range[1]))
    thr_record = {}
    try:
        tm, sums, halves = threshold_sums(rec, profile=profile, intensity_offset=intensity_offset,
                                          well_exposed=well_exposed, min_intervals=min_intervals,
                                          min_decorrelation=min_decorrelation, c_range=c_range, parts=2,
                                          interval_hook=hook)
    except ValueError as e:
        tm = None
        reason = f"threshold estimator: {e}"
        for k in ("contrast_threshold_on", "contrast_threshold_off"):
            est[k] = _entry(None, identifiable=False, reason=reason, method="pooled frame/event NNLS", unit="ln")
        est["threshold_mismatch_sigma"] = _entry(None, identifiable=False, reason=reason,
                                                 method="split-half covariance", unit="ln")
    # -- shot noise and leak at static pixels --------------------------------------------------------
    T = static["pixel_s"]
    n_on, n_off = static["n_on"], static["n_off"]
    c_mean = 0.5 * (tm.fallback_on + tm.fallback_off) if tm is not None else math.nan
    contam = static["sum_abs_dl"] / c_mean / T if T > 0 and math.isfinite(c_mean) else None
    base = {"static_pixel_s": T, "static_on_events": n_on, "static_off_events": n_off,
            "static_pixel_intervals": static["pixel_intervals"], "static_log_bound": static_log_bound,
            "signal_contamination_bound_hz": contam}
    nmethod = (f"events at static pixels (well exposed, |d ln I| < {static_log_bound:g} at the pixel and its 3x3 "
               f"neighbours between two frames) per pixel-second; OFF at shot/2, ON at shot/2 + leak (simulator), "
               f"constrained ML (leak >= 0); exact Poisson 95 % interval")
    if T <= 0:
        reason = "no static well-exposed pixel-interval (every usable pixel's frames change, or none is well exposed)"
        est["shot_noise_rate_hz"] = _entry(None, identifiable=False, reason=reason, method=nmethod, unit="Hz", **base)
        est["leak_rate_hz"] = _entry(None, identifiable=False, reason=reason, method=nmethod, unit="Hz", **base)
        ba_rate = 0.0
    else:
        tot = n_on + n_off
        ba_rate = tot / T
        lo, hi = poisson_ci(tot)
        base["background_activity_hz"] = ba_rate
        base["background_activity_ci95"] = [lo / T, hi / T]
        base["on_fraction"] = n_on / tot if tot else None
        if tot < MIN_STATIC_EVENTS:
            est["leak_rate_hz"] = _entry(
                None, identifiable=False, method=nmethod, unit="Hz", upper_bound_hz=hi / T, **base,
                reason=f"{tot} events at static pixels (need {MIN_STATIC_EVENTS} to compare ON with OFF); "
                       f"the leak is at most the total rate's upper bound")
            leak = 0.0
        else:
            leak_raw = (n_on - n_off) / T
            sd = math.sqrt(tot) / T
            leak = max(leak_raw, 0.0)
            est["leak_rate_hz"] = _entry(leak, identifiable=True, method=nmethod + "; leak = (N_on - N_off)/T",
                                         unit="Hz", std=sd, ci95=(max(leak_raw - 1.96 * sd, 0.0), leak_raw + 1.96 * sd),
                                         unconstrained_hz=leak_raw, **base)
            sim["leak_rate_hz"] = leak
        if leak > 0:
            shot = 2 * n_off / T
            lo, hi = poisson_ci(n_off)
            ci = (2 * lo / T, 2 * hi / T)
            sd = 2 * math.sqrt(n_off) / T
        else:
            shot = tot / T
            ci = (lo / T, hi / T)
            sd = math.sqrt(tot) / T
        est["shot_noise_rate_hz"] = _entry(shot, identifiable=True, method=nmethod, unit="Hz", std=sd, ci95=ci, **base)
        sim["shot_noise_rate_hz"] = shot

    if tm is not None:
        pv = tm.provenance
        # noise events (shot/2 per polarity, leak ON) in the counts: method-of-moments correction
        dt = static["dt_s"] / max(static["intervals"], 1)
        lam_on = (0.5 * sim.get("shot_noise_rate_hz", 0.0) + sim.get("leak_rate_hz", 0.0)) * dt
        lam_off = 0.5 * sim.get("shot_noise_rate_hz", 0.0) * dt
        cs = _corrected(sums, lam_on, lam_off)
        used = np.flatnonzero(sums["n_int"] > 0)
        S = np.stack([c[used] for c in cs], axis=1)
        g_on, g_off = (float(v) for v in _nnls2(*S.sum(axis=0)))
        boot = []
        for W in _boot_weights(rng, int(n_boot), used.size):
            a, b = _nnls2(*(W @ S).T)
            boot.append(np.stack([a, b], 1))
        boot = np.concatenate(boot)
        method = (f"pooled NNLS of frame log change on ON/OFF counts over {pv['n_pixel_intervals']} well-exposed "
                  f"pixel-intervals ({pv['intervals_used']} frame intervals), its moments corrected for the noise "
                  f"events expected per interval (ON {lam_on:.3g}, OFF {lam_off:.3g}: shot noise and leak from the "
                  f"static pixels); 95 % bootstrap over {used.size} pixels")
        # how much the noise correction moves them: the shot rate at its 95 % bounds, and with the
        # sub-bound signal that may hide in the static events removed
        sens = {}
        sh = est.get("shot_noise_rate_hz", {})
        if sh.get("value") and sh.get("ci95"):
            cands = {"shot_ci95_low": sh["ci95"][0], "shot_ci95_high": sh["ci95"][1],
                     "shot_less_contamination": max(sh["value"] - (sh.get("signal_contamination_bound_hz") or 0), 0)}
            for label, rate in cands.items():
                lo_ = (0.5 * rate + sim.get("leak_rate_hz", 0.0)) * dt
                ct = [c[used].sum() for c in _corrected(sums, lo_, 0.5 * rate * dt)]
                sens[label] = [float(v) for v in _nnls2(*ct)]
        for j, (k, v, raw) in enumerate((("contrast_threshold_on", g_on, tm.fallback_on),
                                         ("contrast_threshold_off", g_off, tm.fallback_off))):
            sd, ci = _ci(boot[:, j])
            ok = c_range[0] <= v <= c_range[1]
            est[k] = _entry(v if ok else None, identifiable=ok, method=method, unit="ln", std=sd, ci95=ci,
                            uncorrected=raw, noise_correction_sensitivity={lab: vv[j] for lab, vv in sens.items()},
                            per_pixel_median=_f(np.nanmedian(tm.c_on if j == 0 else tm.c_off)),
                            per_pixel_estimated=int(tm.valid.sum()),
                            reason="" if ok else f"the noise-corrected estimate {v:.4g} is outside c_range {c_range}: "
                                                 f"the static pixels' noise rate explains most of the events")
            if ok:
                sim[k] = float(v)
        thr_record = {"intervals_used": pv["intervals_used"], "pixel_intervals": pv["n_pixel_intervals"],
                      "residual_rms_log": pv["residual_rms_log"], "profile": pv["profile"],
                      "intensity_offset": pv["intensity_offset"], "well_exposed_codes": pv["well_exposed_codes"]}
        # spread: per-pixel estimates on the two halves of the usable intervals
        a1, b1, ok1 = _half_estimates(halves[0], _corrected(halves[0], lam_on, lam_off), min_intervals,
                                      min_decorrelation, c_range)
        a2, b2, ok2 = _half_estimates(halves[1], _corrected(halves[1], lam_on, lam_off), min_intervals,
                                      min_decorrelation, c_range)
        both = np.flatnonzero(ok1 & ok2)
        af, bf_, v = _half_estimates(sums, cs, min_intervals, min_decorrelation, c_range)
        raw_on = _f(np.std(af[v], ddof=1)) if v.sum() > 1 else None
        raw_off = _f(np.std(bf_[v], ddof=1)) if v.sum() > 1 else None
        smethod = ("split-half covariance: sigma^2 = (cov(c_on first half, c_on second half) + same for OFF) / 2 "
                   "over pixels estimated in both halves of the usable frame intervals (estimation noise of the "
                   "two halves is independent, so it drops out), pixels beyond 8 robust SDs dropped; 95 % "
                   "bootstrap over pixels")
        if both.size < MIN_SPREAD_PIXELS:
            est["threshold_mismatch_sigma"] = _entry(
                None, identifiable=False, method=smethod, unit="ln", raw_std_on=raw_on, raw_std_off=raw_off,
                pixels_both_halves=int(both.size), per_pixel_estimated=int(v.sum()),
                reason=f"{both.size} pixels have a per-pixel estimate in both halves of the "
                       f"{pv['intervals_used']} usable frame interval(s) (need {MIN_SPREAD_PIXELS}; each half needs "
                       f"{min_intervals} intervals with ON and with OFF events per pixel): the raw spread of per-pixel "
                       f"estimates cannot be told from their estimation noise")
        else:
            # gross outliers (a pixel whose few events fit badly) would dominate a covariance: drop
            # pixels beyond 8 robust SDs in either half (never a normal pixel; 0.3-1.3 % of the round
            # trip's pixels, whose sigma was +17 % with them on one seed of five, +2 % without; 5 robust
            # SDs dropped 5 % and cut into the true spread: -8 %)
            keep = _inliers(a1[both]) & _inliers(a2[both]) & _inliers(b1[both]) & _inliers(b2[both])
            n_out = int((~keep).sum())
            both = both[keep]
            x_on, y_on, x_off, y_off = a1[both], a2[both], b1[both], b2[both]
            c_on_ = _cov(x_on, y_on)
            c_off_ = _cov(x_off, y_off)
            s2 = 0.5 * (c_on_ + c_off_)
            bs = []
            for W in _boot_weights(rng, int(n_boot), both.size):
                bs.append(np.sqrt(np.maximum(0.5 * (_cov(x_on, y_on, W) + _cov(x_off, y_off, W)), 0.0)))
            sd, ci = _ci(np.concatenate(bs))
            sig = math.sqrt(max(s2, 0.0))
            var_raw = 0.5 * ((raw_on or 0.0) ** 2 + (raw_off or 0.0) ** 2)
            est["threshold_mismatch_sigma"] = _entry(
                sig, identifiable=True, method=smethod, unit="ln", std=sd, ci95=ci,
                sigma_on=math.sqrt(max(c_on_, 0.0)), sigma_off=math.sqrt(max(c_off_, 0.0)),
                raw_std_on=raw_on, raw_std_off=raw_off,
                estimation_noise_std=math.sqrt(max(var_raw - s2, 0.0)),
                pixels_both_halves=int(both.size), outlier_pixels_dropped=n_out)
            sim["threshold_mismatch_sigma"] = sig

    # -- refractory period: lower edge of the same-pixel ISI histogram ------------------------------
    order = np.lexsort((ev["t"], pix_all))
    ps = pix_all[order]
    ts = ev["t"][order]
    same = ps[1:] == ps[:-1]
    isi = np.diff(ts)[same]
    isi_pix = ps[1:][same]
    o = np.argsort(isi, kind="stable")
    isi, isi_pix = isi[o].astype(np.float64), isi_pix[o]
    rmethod = (f"lower edge of the same-pixel inter-event-interval histogram: smallest ISI d with #ISI <= d, less "
               f"the noise pairs expected below d (background rate x d per interval, at most twice the ISIs below "
               f"d/2), >= {isi_quantile:g} of all ISIs; identifiable when the ISIs pile up at the edge (#ISI in "
               f"[d, 1.5d) >= #ISI in [1.5d, 2d)); 95 % bootstrap over pixels")
    if isi.size < MIN_ISIS:
        est["refractory_period_us"] = _entry(None, identifiable=False, method=rmethod, unit="us", n_isi=int(isi.size),
                                             reason=f"{isi.size} same-pixel intervals (need {MIN_ISIS})")
    else:
        edge = isi_lower_edge(isi, noise_rate_hz=ba_rate, quantile=isi_quantile)
        upix, inv = np.unique(isi_pix, return_inverse=True)
        half = np.searchsorted(isi, isi / 2, side="right")
        bs = []
        for W in _boot_weights(rng, int(n_boot), upix.size, chunk=20):
            for wrow in W:
                bs.append(isi_lower_edge(isi, wrow[inv], noise_rate_hz=ba_rate, quantile=isi_quantile, _half=half))
        sd, ci = _ci(bs)
        m1 = int(np.count_nonzero((isi >= edge) & (isi < 1.5 * edge)))
        m2 = int(np.count_nonzero((isi >= 1.5 * edge) & (isi < 2 * edge)))
        pile = m1 >= m2 and m1 > 0
        extra = {"n_isi": int(isi.size), "isi_in_edge_to_1.5edge": m1, "isi_in_1.5edge_to_2edge": m2,
                 "isi_percentiles_us": {str(q): float(np.percentile(isi, q)) for q in (0.1, 1, 5, 50)}}
        if pile:
            est["refractory_period_us"] = _entry(edge, identifiable=True, method=rmethod, unit="us", std=sd,
                                                 ci95=ci, **extra)
            sim["refractory_period_us"] = int(round(edge))
        else:
            est["refractory_period_us"] = _entry(
                None, identifiable=False, method=rmethod, unit="us", upper_bound_us=edge, upper_bound_std=sd,
                upper_bound_ci95=list(ci) if ci else None, **extra,
                reason=f"the same-pixel intervals rise gradually from their lower edge {edge:.0f} us (fewer in "
                       f"[d, 1.5d) than in [1.5d, 2d): {m1} < {m2}), so the edge is set by the scene's own speed, not "
                       f"by a blind time: the refractory period is at most {edge:.0f} us")

    # -- not identifiable from frames + events of a natural scene -----------------------------------
    fps = None
    tau = np.sort(np.asarray(rec.frames.t_mid_us))
    if tau.size > 1 and np.median(np.diff(tau)) > 0:
        fps = 1e6 / float(np.median(np.diff(tau)))
    est["photoreceptor_cutoff_hz"] = _entry(
        None, identifiable=False, method="none", unit="Hz",
        reason="needs a stimulus of known timing (a step or flicker at several intensities: the corner is the event "
               "delay's intensity dependence); frames" + (f" at {fps:.3g} Hz" if fps else "") + " of a natural scene "
               "cannot separate the photoreceptor's lag from the scene's own motion")
    est["timestamp_jitter_us"] = _entry(
        None, identifiable=False, method="none", unit="us",
        reason="needs a periodic stimulus of known phase (a blinking LED: the spread of one pixel's event times "
               "across periods); the simulator has no jitter tier (timestamps are exact crossings rounded to 1 us)")

    names = ("contrast_threshold_on", "contrast_threshold_off", "threshold_mismatch_sigma", "shot_noise_rate_hz",
             "leak_rate_hz", "refractory_period_us", "photoreceptor_cutoff_hz", "timestamp_jitter_us")
    est = {k: est[k] for k in names}
    sim = {k: sim[k] for k in names if k in sim}
    prov = {"hybridhdr_version": __version__, "estimator": "hybridhdr.calibrate.sensor_profile",
            "source_file": str(rec.metadata.provenance.get("source_file", "")) if rec.metadata else "",
            "n_events": int(len(ev)), "n_frames": int(len(rec.frames)),
            "event_span_us": [int(ev["t"][0]), int(ev["t"][-1])], "thresholds": thr_record,
            "n_boot": int(n_boot), "seed": int(seed), "static_log_bound": static_log_bound,
            "isi_quantile": isi_quantile}
    sensor = {"model": sensor_model, "width": int(ss.width if ss is not None else w),
              "height": int(ss.height if ss is not None else h)}
    return SensorProfile(simulator_params=sim, estimates=est, name=name, sensor=sensor, provenance=prov)


def _f(v):
    v = float(v)
    return v if math.isfinite(v) else None
