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
  (:func:`hybridhdr.calibrate.camera_model.estimate_camera_model`); 95 % interval by a bootstrap over
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
from .camera_model import estimate_camera_model

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
                            c_range=(0.01, 2.0), name: str = "", sensor_model: str = "",
                            keep_model: bool = False) -> SensorProfile:
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

    ev = rec.events
    pix_all = ev["y"].astype(np.int64) * w + ev["x"].astype(np.int64)
    c_range = (float(c_range[0]), float(c_range[1]))
    thr_record = {}
    # -- the camera model: thresholds, I0, frame time, latency, spread, noise (one estimator) ------
    try:
        m = estimate_camera_model(rec, profile=profile, intensity_offset=intensity_offset, well_exposed=well_exposed,
                                  c_range=c_range, static_log_bound=static_log_bound, n_boot=int(n_boot), seed=seed,
                                  per_pixel=True)
    except ValueError as e:
        m = None
        reason = f"camera model: {e}"
        for k, u in (("contrast_threshold_on", "ln"), ("contrast_threshold_off", "ln"),
                     ("threshold_mismatch_sigma", "ln"), ("intensity_offset", "frame-linear"),
                     ("time_offset_us", "us"), ("latency_us", "us"), ("shot_noise_rate_hz", "Hz"),
                     ("leak_rate_hz", "Hz")):
            est[k] = _entry(None, identifiable=False, reason=reason, method="hybridhdr.calibrate.camera_model", unit=u)
    if m is not None:
        thr_record = m.to_dict()
        method = (f"camera model (hybridhdr.calibrate.camera_model): pooled least squares of the frames' log change "
                  f"on exposure-weighted ON/OFF counts over {m.n_pixel_intervals} event-bearing pixel-intervals "
                  f"({m.n_intervals} frame intervals), noise events removed, corrected for the DVS quantiser by "
                  f"indirect inference; 1.96 bootstrap SD")
        for k, v, sd, raw in (("contrast_threshold_on", m.c_on, m.c_on_std, m.least_squares["c_on"]),
                              ("contrast_threshold_off", m.c_off, m.c_off_std, m.least_squares["c_off"])):
            ci = None if sd is None else (max(v - 1.96 * sd, 0.0), v + 1.96 * sd)
            est[k] = _entry(v, identifiable=True, method=method, unit="ln", std=sd, ci95=ci, least_squares=raw,
                            reverse_regression=m.reverse_regression.get("c_" + k.rsplit("_", 1)[-1]))
            sim[k] = float(v)
        i0_edge = m.at_grid_edge.get("intensity_offset")
        rule = m.i0_rule or {}
        if rule.get("applied"):
            # the band rule's zero (equal quantiser-corrected thresholds at every brightness), its bootstrap error
            sd_ = rule.get("ln_i0_std")
            ok_ = bool(rule.get("identifiable")) and not m.fixed["intensity_offset"]
            est["intensity_offset"] = _entry(
                m.intensity_offset, identifiable=ok_, unit="frame-linear",
                method="I0 of ln(I + I0): the zero of ln(c_dark / c_bright), the thresholds below and above the median "
                       "intensity corrected for the quantiser (indirect inference); interval: bootstrap over pixels",
                std_ln=sd_, ci95=([m.intensity_offset * math.exp(-2 * sd_), m.intensity_offset * math.exp(2 * sd_)]
                                  if sd_ is not None and math.isfinite(sd_) else None),
                reason="" if ok_ else rule.get("reason", ""))
        else:
            grid = list(m.intensity_offsets)
            k_ = grid.index(m.intensity_offset) if m.intensity_offset in grid else 0
            nb = (grid[max(k_ - 1, 0)], grid[min(k_ + 1, len(grid) - 1)])
            flat = (m.i0_edge or {}).get("used") == "fallback"
            e_ = m.i0_edge or {}
            est["intensity_offset"] = _entry(
                m.intensity_offset, identifiable=not i0_edge and not flat and not m.fixed["intensity_offset"],
                unit="frame-linear",
                method="I0 of ln(I + I0): best cross-fitted prediction of the frames' codes, corrected for the quantiser "
                       "(indirect inference); the interval is the neighbouring grid values",
                ci95=nb, reason=(f"on the edge of its grid after widening ({e_.get('improvement_se', float('nan')):.3g} "
                                 f"standard errors better than I0 = {e_.get('fallback_i0', float('nan')):.4g})"
                                 if i0_edge and e_ else "on the edge of its grid after widening") if i0_edge else
                (f"the grid criterion is flat at the {e_.get('edge')} edge (I0 = {e_.get('edge_i0', float('nan')):.4g} "
                 f"only {e_.get('improvement_se', float('nan')):.2g} standard errors better): the fallback inside the "
                 f"grid" if flat else
                 ("given, not estimated" if m.fixed["intensity_offset"] else
                  (f"the band rule was not used: {rule['reason']}" if rule.get("reason") else ""))))
        step = (m.offsets_us[1] - m.offsets_us[0]) if len(m.offsets_us) > 1 else 0
        for k, v, what in (("time_offset_us", m.time_offset_us, "the shift of the frames' times under which the events "
                                                                "predict the next frame best (includes the quantiser's "
                                                                "hysteresis lag: what a reconstruction uses)"),
                           ("latency_us", m.latency_us, "the events' delay after the light: time_offset_us less the "
                                                        "lag the same search finds on events the model simulates "
                                                        "from the frames")):
            edge_ = m.at_grid_edge.get("time_offset_us")
            est[k] = _entry(v, identifiable=v is not None and not edge_ and not m.fixed["time_offset_us"], unit="us",
                            method=what + "; the interval is one grid step either side",
                            ci95=None if v is None else (v - step, v + step),
                            reason="" if v is not None and not edge_ else "on the edge of its grid or not estimated")
        sg = m.mismatch_sigma
        smethod = ("split-half covariance: sigma^2 = cov(per-pixel estimate on the even intervals, on the odd "
                   "intervals) over pixels estimated in both (their estimation errors are independent); pixels "
                   "beyond 8 robust SDs dropped; 95 % bootstrap over pixels")
        if sg.get("on") is None or sg.get("off") is None:
            est["threshold_mismatch_sigma"] = _entry(
                None, identifiable=False, method=smethod, unit="ln", pixels_both_halves=sg.get("pixels_both_halves"),
                reason=f"{sg.get('pixels_both_halves', 0)} pixels have a per-pixel estimate in both halves of the "
                       f"usable frame intervals (need 30): the spread cannot be told from the estimation noise")
        else:
            sig = 0.5 * (sg["on"] + sg["off"])
            sd = sg.get("std")
            est["threshold_mismatch_sigma"] = _entry(
                sig, identifiable=True, method=smethod, unit="ln", std=sd,
                ci95=None if sd is None else (max(sig - 1.96 * sd, 0.0), sig + 1.96 * sd),
                sigma_on=sg["on"], sigma_off=sg["off"], pixels_both_halves=sg["pixels_both_halves"])
            sim["threshold_mismatch_sigma"] = float(sig)
        # -- shot noise and leak at static pixels (the model's own count) ------------------------------
        nz = m.noise
        T = float(nz.get("static_pixel_s", 0.0))
        n_on, n_off = int(nz.get("static_on_events", 0)), int(nz.get("static_off_events", 0))
        base = {"static_pixel_s": T, "static_on_events": n_on, "static_off_events": n_off,
                "static_log_bound": static_log_bound}
        nmethod = (f"events at static pixels (well exposed, |d ln I| < {static_log_bound:g} at the pixel and its 3x3 "
                   f"neighbours between two frames) per pixel-second; OFF at shot/2, ON at shot/2 + leak (simulator), "
                   f"constrained ML (leak >= 0); exact Poisson 95 % interval")
        if T <= 0:
            reason = "no static well-exposed pixel-interval (every usable pixel's frames change, or none is well exposed)"
            est["shot_noise_rate_hz"] = _entry(None, identifiable=False, reason=reason, method=nmethod, unit="Hz", **base)
            est["leak_rate_hz"] = _entry(None, identifiable=False, reason=reason, method=nmethod, unit="Hz", **base)
        else:
            tot = n_on + n_off
            lo, hi = poisson_ci(tot)
            base["background_activity_hz"] = tot / T
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
                # a recording whose static pixels fire more OFF than ON has leak_raw < 0: the leak is 0
                # (its constraint) and its interval clipped at 0 on both ends, never [0, negative]
                est["leak_rate_hz"] = _entry(leak, identifiable=True, method=nmethod + "; leak = (N_on - N_off)/T",
                                             unit="Hz", std=sd, ci95=(max(leak_raw - 1.96 * sd, 0.0),
                                                                      max(leak_raw + 1.96 * sd, 0.0)),
                                             unconstrained_hz=leak_raw, **base)
                sim["leak_rate_hz"] = leak
            if leak > 0:
                shot = 2 * n_off / T
                lo2, hi2 = poisson_ci(n_off)
                ci = (2 * lo2 / T, 2 * hi2 / T)
                sd = 2 * math.sqrt(n_off) / T
            else:
                shot = tot / T
                ci = (lo / T, hi / T)
                sd = math.sqrt(tot) / T
            est["shot_noise_rate_hz"] = _entry(shot, identifiable=True, method=nmethod, unit="Hz", std=sd, ci95=ci, **base)
            sim["shot_noise_rate_hz"] = shot
    ba_rate = sim.get("shot_noise_rate_hz", 0.0) + sim.get("leak_rate_hz", 0.0)

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

    names = ("contrast_threshold_on", "contrast_threshold_off", "threshold_mismatch_sigma", "intensity_offset",
             "time_offset_us", "latency_us", "shot_noise_rate_hz", "leak_rate_hz", "refractory_period_us",
             "photoreceptor_cutoff_hz", "timestamp_jitter_us")
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
    out = SensorProfile(simulator_params=sim, estimates=est, name=name, sensor=sensor, provenance=prov)
    if m is not None and keep_model:
        out.provenance["_model"] = m  # for the plot; the CLI takes it out before writing
    return out


def _f(v):
    v = float(v)
    return v if math.isfinite(v) else None
