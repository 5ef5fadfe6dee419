"""The one event/frame camera model: thresholds, log offset, frame timing and noise of a hybrid camera.

Every answer this toolkit gives to "what are this camera's contrast thresholds?" comes from
:func:`estimate_camera_model`: the self-calibration of ``reconstruct`` (:mod:`.selfcal`), the
pooled figure of ``calibrate thresholds`` (:mod:`.thresholds`) and ``calibrate sensor``
(:mod:`.sensor_profile`) all call it, so one recording gives one ON/OFF pair.

Model (paper eq. 1; EDI's frame model). A DVS pixel fires an ON (OFF) event each time
``L = ln(I + I0)`` rises (falls) by ``c_on`` (``c_off``) from its reference level; a frame ``k``
exposed over ``[s_k, e_k]`` records the mean intensity over its exposure (Pan et al., "Bringing a
Blurry Frame Alive at High Frame-Rate with an Event Camera", CVPR 2019), and the events reach the
recording ``δ`` after the light (the DVS response latency plus any offset of the frames' stamps).
To first order in the log changes during an exposure (the mean of ``L`` over the exposure), the
frames' log change between frames ``k`` and ``k+1`` is

    ln(F_{k+1} + I0) − ln(F_k + I0) = c_on·W_on,k − c_off·W_off,k − (noise terms) + ε_k,

where ``W`` counts the events of ``[s_k + δ, e_{k+1} + δ)`` each weighted by ``G_{k+1}(t) −
G_k(t)``, ``G_k(t)`` the fraction of exposure ``k`` after ``t − δ`` (a step at the frame's time
for a zero exposure: plain counts between the two frame times). ``ε`` is the pixel's distance
from its reference level at the two frames (bounded by one threshold) plus the frames' own
noise. Frames integrate over their exposure while events do not: on a simulated scene with a
10 ms exposure at 20 fps, treating frames as instantaneous biases both thresholds 15-25 % low
(``benchmarks/sensor_profile.py``); the exposure weights remove most of it, and the exact
log-of-mean model (``refine_exposure``) is applied at the chosen (δ, I0).

Estimation (pooled over every pixel-interval both frames show well exposed):

* **thresholds**: least squares of the frames' log change on the weighted counts less the noise
  events expected per interval (method-of-moments correction, shot noise and leak from the
  static pixels below), exact two-variable NNLS. Standard errors by a Poisson(1) bootstrap over
  pixels. Errors-in-variables: the reverse regression (counts on frame change, the consistent
  one if the count errors were independent of the change) is *biased* here because a DVS pixel is
  a quantiser with hysteresis (after a reversal a change of up to c_on + c_off goes unreported),
  so its count error depends on the change; it overestimated c by 21 % on a simulated texture
  where the forward fit erred by 2 % (``benchmarks/sensor_profile.py`` prints both on every
  round trip, so the choice rests on a measurement, not an assumption).
* **δ and a first I0**: chosen on a grid by a criterion whose target does not change with the
  candidate: the error, in frame code units, of predicting each frame from the previous frame
  and the events between them, on pixel-intervals fixed before the search (both frames well
  exposed, at least one event in the widest window any δ opens), cross-fitted (thresholds fitted
  on the even intervals predict the odd ones and the reverse). A best value on a grid edge
  widens the grid (I0 by factors of 4, δ by half a grid width, twice) and is then reported with
  ``at_grid_edge`` and a warning naming the value; never silently. An I0 still on an edge is
  tested against the fallback inside the grid (:func:`_edge_test`, :func:`_fallback_index`): not
  significantly better, the criterion is flat there and the fallback is used, not identified
  (``i0_edge``), warned. The criterion's best is
  biased by the DVS quantiser (hysteresis: after a reversal the events come late, so a later
  window predicts better: 12 ms after the true latency at c = 0.5 on the round trip, and its best
  I0 a factor 3 above the truth there), so neither is reported as it stands:
* **I0, the band rule** (:class:`_BandRule`, :func:`_choose_i0`): the model's own premise, one
  threshold pair at every brightness. Thresholds fitted separately below and above the median
  intensity, each corrected for the quantiser by simulation like the pooled ones, agree only at
  the right I0 (a smaller I0 stretches the dark pixels' log changes, a larger one squeezes them),
  so I0 is the zero of ``ln(c_dark / c_bright)`` over ln I0: a moment condition, not a fit to
  maximise. Its standard error is a Poisson bootstrap over pixels (each replicate's zero). The
  zero is used where its sign change is significant (at most ``I0_RULE_MISSING`` of the
  replicates without a zero) and the simulated quantiser reproduces the observed events; it is
  found first at the criterion's δ, then again at the latency the binding finds (below), and only
  a zero there stands; else I0 is the criterion's (warned on an edge), everything estimated
  again from the criterion's grid (a given-up I0 leaves nothing behind). The profile's
  ``identifiable`` says whether two standard errors lie within one grid step (a factor 2).
* **latency, the binding** (:func:`_binding`): indirect inference on δ: the DVS model driven by the
  frames' own log path at the candidate (latency, I0, thresholds) goes through the same criterion;
  the latency moves by the difference between the observed and the simulated best (each the
  vertex of a parabola through the criterion near its best, not the argmin of a flat curve,
  which jumps by grid steps), the simulated search on a window centred on the observed best.
* **quantiser correction**: indirect inference (``_indirect``) on a fixed, seeded subset of at
  most ``MAX_CORRECTION_PIXELS`` pixels, iterated until the simulated statistic is within
  ``CORRECTION_TOLERANCE`` of the observed one (same seed, same bits), then shrunk toward the
  least squares by how well the simulation reproduces the statistics it was not fitted to
  (:func:`_shrink_correction`: a posterior mean, no threshold). Every simulation drives the
  quantiser along a Catmull-Rom cubic through the frames' log values (``PATH_SUBSTEPS`` points per
  frame interval, :func:`_path_counts`): a smooth scene's extremum between two frames makes the
  pixel reverse as the camera's did, which a path linear between frames never does.
* **noise**: events at static pixels (well exposed, |Δ ln I| below ``static_log_bound`` at the
  pixel and its 3×3 neighbours) per pixel-second: OFF at shot/2, ON at shot/2 + leak.

What a recording cannot tell is reported as such (``identifiable`` false with a reason).
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np

from ..camera import load_profile, profile_for_frames
from ..camera.profile import check_codes_in_profile
from ..camera.encoding import well_exposed_range
from ..camera.encoding import frames_to_codes
from ..errors import InputMismatchError

__all__ = ["CameraModel", "estimate_camera_model", "DEFAULT_INTENSITY_OFFSETS", "SCHEMA", "GridEdgeWarning",
           "shrink_per_pixel"]

SCHEMA = "hybridhdr.camera_model/1"

#: I0 tried first, as fractions of the frames' clip level (frame-linear units); widened on an edge.
DEFAULT_INTENSITY_OFFSETS = (1e-3, 2e-3, 4e-3, 8e-3, 1.6e-2, 3.2e-2, 6.4e-2, 0.128, 0.256, 0.512)
#: Lowest and highest I0 the widening goes to (below 1e-5 of the clip level the log model is ln I
#: for every code of a 16-bit frame; above 8 it is linear over the frames' range).
I0_LIMITS = (1e-5, 8.0)
#: Largest number of frame intervals used (evenly spread): bounds the work on long recordings.
MAX_INTERVALS = 64
#: Largest number of event-bearing pixel-intervals scored (an even random subset beyond it).
MAX_PIXEL_INTERVALS = 200_000
#: Steps of the time-offset grid across its span.
N_OFFSETS = 41
#: Grid widenings before a value on an edge is reported as such.
MAX_WIDEN = 2
#: Largest relative difference between the simulated quantiser's signal events and the observed ones
#: for the quantiser correction to be applied (below it the frames sample the scene's changes well
#: enough for the simulation to see what the pixels saw: 2-6 % on the round trips at 2.4 px per
#: frame, ``benchmarks/sensor_profile.py``).
SIM_EVENT_TOLERANCE = 0.15
#: Largest number of pixels the quantiser correction simulates (a fixed, seeded random subset beyond
#: it, the same at every iteration: the pooled statistic is a ratio of sums over pixels, so an even
#: subset estimates the same bias with a sampling error far below the bootstrap's).
MAX_CORRECTION_PIXELS = 20_000
#: The indirect-inference iteration stops once the simulated statistic is within this of the observed
#: one (log units; a tenth of the smallest threshold the estimator reports to three figures).
CORRECTION_TOLERANCE = 1e-3
#: Half-widths (δ steps, I0 steps) of the grid window the quantiser simulation is searched on.
BINDING_WINDOW = (8, 3)
#: Points of the cubic log path between two frames at which the quantiser simulation samples it.
PATH_SUBSTEPS = 4
#: Intensity bands of the I0 rule (split at the median intensity of the event-bearing pixel-intervals).
I0_BANDS = 2
#: Largest number of pixels the I0 rule simulates (a fixed, seeded subset, as the correction's).
MAX_I0_RULE_PIXELS = 8000
#: Simulated replicates per I0 candidate of the I0 rule.
I0_RULE_REPS = 2
#: Bootstrap replicates (over pixels) of the I0 rule's standard error.
I0_RULE_BOOT = 100
#: Largest fraction of the I0 rule's bootstrap replicates without a zero in the bracket for its sign
#: change to count (f approaching 0 from one side, as it does for large I0 where the log is linear,
#: gives about half).
I0_RULE_MISSING = 0.1
#: Poisson bootstrap replicates (over pixels) of the edge test (:func:`_edge_test`).
EDGE_TEST_BOOT = 200
#: Standard errors by which the criterion at a grid edge must beat the fallback I0 for the edge to stand.
EDGE_TEST_SE = 2.0
#: Sub-intervals of an exposure in the exact log-of-mean refinement.
EXPOSURE_BINS = 16


class GridEdgeWarning(UserWarning):
    """A calibration grid's best value lies on its edge after widening (the value is named)."""


@dataclasses.dataclass
class CameraModel:
    """The result of :func:`estimate_camera_model` (module docstring)."""

    c_on: float
    c_off: float
    c_on_std: float | None
    c_off_std: float | None
    intensity_offset: float
    time_offset_us: int
    score: float
    score_nominal: float
    n_pixel_intervals: int
    n_intervals: int
    excluded_frames: tuple
    offsets_us: tuple
    intensity_offsets: tuple
    score_grid: tuple
    at_grid_edge: dict
    exposure_model: str
    noise: dict
    uncorrected: dict
    least_squares: dict
    quantiser_correction: dict | None
    mismatch_sigma: dict
    bands: dict
    latency_us: int | None
    r2: float
    r2_nominal: float
    reverse_regression: dict
    fixed: dict
    i0_rule: dict | None = None  # the band rule's record (profile over I0, zero, applicability)
    i0_edge: dict | None = None  # the criterion's best I0 on its grid edge: the flatness test and the fallback
    per_pixel: dict | None = None  # arrays (not serialised): per-pixel sums at the chosen model

    def to_dict(self) -> dict:
        """JSON-ready record (``run.json``'s ``self_calibration``, the profile's provenance)."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "per_pixel"}
        d["schema"] = SCHEMA
        d["excluded_frames"] = [int(k) for k in self.excluded_frames]
        d["offsets_us"] = [int(v) for v in self.offsets_us]
        d["intensity_offsets"] = [float(v) for v in self.intensity_offsets]
        d["score_grid"] = [[_f(v) for v in row] for row in self.score_grid]
        return d

    def akf_overrides(self) -> dict:
        return {"intensity_offset": float(self.intensity_offset), "contrast_threshold_on": float(self.c_on),
                "contrast_threshold_off": float(self.c_off)}


def _f(v):
    v = float(v)
    return v if math.isfinite(v) else None


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


def _geom_grid(values):
    v = tuple(sorted({float(x) for x in values}))
    if not v or any(not (math.isfinite(x) and x > 0) for x in v):
        raise ValueError(f"intensity_offsets must be finite and > 0, got {values}")
    return v


class _Data:
    """Frames, events and the fixed pixel-intervals of one estimate (module docstring)."""

    def __init__(self, rec, profile, exclude_frames, well_exposed):
        fr = rec.frames
        if fr is None or len(fr) < 3:
            raise InputMismatchError("the camera model needs at least three frames (two frame intervals: one to fit, one to "
                             f"check); the recording has {0 if fr is None else len(fr)}"
                             + (" (fewer than two frames give nothing to calibrate against)"
                                if fr is None or len(fr) < 2 else ""))
        ev = rec.events
        if len(ev) == 0:
            raise InputMismatchError("the camera model needs events; the recording has none")
        excl = sorted({int(k) for k in exclude_frames})
        for k in excl:
            if not 0 <= k < len(fr):
                raise ValueError(f"exclude_frames: frame {k} is not among the recording's {len(fr)} frames")
        self.excl = tuple(excl)
        keep = np.setdiff1d(np.arange(len(fr)), np.asarray(excl, np.int64))
        sub = fr.select(keep)
        tau = sub.t_mid_us.astype(np.int64)
        order = np.argsort(tau, kind="stable")
        self.tau = tau[order]
        if np.any(np.diff(self.tau) <= 0):
            raise ValueError("the camera model needs frames with distinct times")
        self.s = sub.t_start_us.astype(np.float64)[order]
        self.e = sub.t_end_us.astype(np.float64)[order]
        self.has_exposure = bool(np.any(self.e > self.s))
        h, w = sub.shape
        ss = rec.sensor_size
        if ss is not None and tuple(ss.shape) != (h, w):
            raise ValueError(f"frames are {w}x{h} but the event sensor is {ss.width}x{ss.height}; register them first")
        self.h, self.w, self.n = h, w, h * w
        if profile is None:
            prov = rec.metadata.provenance if rec.metadata is not None else {}
            profile = prov.get("camera_profile") if isinstance(prov, dict) else None
            if isinstance(profile, dict):
                from ..camera import CameraProfile
                profile = CameraProfile.from_dict(profile)
            elif not (profile is None or isinstance(profile, str) or hasattr(profile, "intensity")):
                profile = None
        self.prof = profile_for_frames(load_profile(profile), sub)
        self.lo, self.hi = (well_exposed_range(self.prof.max_code) if well_exposed is None
                            else (int(well_exposed[0]), int(well_exposed[1])))
        self.lut = self.prof.intensity(np.arange(self.prof.max_code + 1)).astype(np.float64)
        self.codes = frames_to_codes(sub, (h, w))
        check_codes_in_profile(self.codes, self.prof)  # codes past the profile's table: refused, never an index error
        self.order = order
        self.scale = sub.exposure_scale()[order]  # each frame in the median frame's units (as the filters read it)
        self.t = ev["t"]
        self.pix = ev["y"].astype(np.int64) * w + ev["x"].astype(np.int64)
        self.on = ev["p"] > 0
        self.t0_ev, self.t1_ev = int(self.t[0]), int(self.t[-1])
        self._fc = {}

    def frame(self, k):
        """(codes (n,), well-exposed mask (n,)) of frame k (sorted order)."""
        if k not in self._fc:
            c = np.asarray(self.codes[self.order[k]]).reshape(-1)
            self._fc[k] = (c, (c >= self.lo) & (c <= self.hi))
        return self._fc[k]

    def G(self, k, t):
        """Fraction of exposure k after time t (a step at τ_k for a zero exposure)."""
        s, e = self.s[k], self.e[k]
        if e > s:
            return np.clip((e - t) / (e - s), 0.0, 1.0)
        return (t < self.tau[k]).astype(np.float64)

    def covered(self, d0, d1):
        return [j for j in range(len(self.tau) - 1)
                if min(self.s[j], self.tau[j]) + d0 >= self.t0_ev and max(self.e[j + 1], self.tau[j + 1]) + d1 <= self.t1_ev]

    def window(self, j, d):
        """Event slice [a, b) that can weigh in interval j at offset d."""
        a, b = _find(self.t, [min(self.s[j], self.tau[j]) + d, max(self.e[j + 1], self.tau[j + 1]) + d])
        return int(a), int(b)

    def weighted_counts(self, j, d, idx):
        """Exposure-weighted ON and OFF counts of interval j at offset d, at pixels idx."""
        a, b = self.window(j, d)
        tt = self.t[a:b].astype(np.float64) - d
        wt = self.G(j + 1, tt) - self.G(j, tt)
        p_, o_ = self.pix[a:b], self.on[a:b]
        non = np.bincount(p_[o_], wt[o_], minlength=self.n)
        noff = np.bincount(p_[~o_], wt[~o_], minlength=self.n)
        return non[idx], noff[idx]


def _find(t, x):
    """``np.searchsorted(t, x)`` (left) for integer event times ``t`` and real bounds ``x``: the bounds
    are rounded up to t's integer type first (the same positions for integer times), so that numpy does
    not cast the whole event array to float at every call (the hot path of every grid search)."""
    x = np.ceil(np.asarray(x, np.float64))
    if np.issubdtype(t.dtype, np.integer):
        info = np.iinfo(t.dtype)
        x = np.clip(x, info.min, info.max).astype(t.dtype)
    return np.searchsorted(t, x)


_LOOKUPS: dict = {}  # per inverse-CRF table: its nearest-code lookup (_codes_of)


def _codes_of(lut, x):
    """Nearest code of intensities x under the inverse-CRF table lut (monotone): the number of
    code midpoints below x. A linear table (midpoints evenly spaced to 1e-9) takes the numba
    lookup (:func:`._kernels.nearest_codes`: the same result, about 3x faster; it is the
    estimator's inner loop), any other numpy's binary search."""
    key = (lut.size, float(lut[1]), float(lut[-2]))
    look = _LOOKUPS.get(key)
    if look is None:  # the table's lookup, made once (the kernel imported here, never per call)
        mids = np.ascontiguousarray(0.5 * (lut[1:] + lut[:-1]), np.float64)
        d = np.diff(mids)
        if d.size > 0 and float(d.min()) > 0 and float(d.max() - d.min()) <= 1e-9 * float(d.mean()):
            from ._kernels import nearest_codes
            m0, step = float(mids[0]), float(d.mean())

            def look(v):
                va = np.asarray(v, np.float64)
                return nearest_codes(mids, m0, step, np.ascontiguousarray(va).reshape(-1)).reshape(va.shape)
        else:
            def look(v):
                return np.searchsorted(mids, v).astype(np.float64)
        _LOOKUPS[key] = look
    return look(x)


def _noise_rates(D, ints, i0, static_log_bound):
    """Static-pixel event rates (ON, OFF per pixel-second) and their record (module docstring)."""
    from scipy.ndimage import maximum_filter
    n_on = n_off = 0
    T = 0.0
    k_int = 0
    for j in ints:
        c0, g0 = D.frame(j)
        c1, g1 = D.frame(j + 1)
        dl = np.log(D.lut[c1.astype(np.int64)] * D.scale[j + 1] + i0) - np.log(D.lut[c0.astype(np.int64)] * D.scale[j] + i0)
        dd = np.where(g0 & g1, np.abs(dl), np.inf).reshape(D.h, D.w)
        st = (maximum_filter(dd, size=3, mode="nearest") < static_log_bound).reshape(-1)
        k = int(st.sum())
        if not k:
            continue
        a, b = _find(D.t, [D.tau[j], D.tau[j + 1]])
        sel = st[D.pix[a:b]]
        o_ = D.on[a:b][sel]
        n_on += int(o_.sum())
        n_off += int((~o_).sum())
        T += k * (D.tau[j + 1] - D.tau[j]) * 1e-6
        k_int += 1
    rec = {"static_pixel_s": T, "static_on_events": n_on, "static_off_events": n_off, "intervals": k_int,
           "static_log_bound": static_log_bound}
    if T <= 0:
        return 0.0, 0.0, {**rec, "identifiable": False,
                          "reason": "no static well-exposed pixel-interval: noise rates not measured, no correction"}
    return n_on / T, n_off / T, {**rec, "identifiable": True, "rate_on_hz": n_on / T, "rate_off_hz": n_off / T}


def _collect(D, ints, i0s, d0, d1, cap=None):
    """Per interval: fixed pixels (well exposed, an event in the widest window) and their logs per I0.
    More than ``cap`` (:data:`MAX_PIXEL_INTERVALS`) such pixel-intervals in all: an even random
    subset of them (seeded by the data's size: same data, same subset), which bounds the work."""
    cap = MAX_PIXEL_INTERVALS if cap is None else cap
    idxs, goods = [], []
    for j in ints:
        _, g0 = D.frame(j)
        _, g1 = D.frame(j + 1)
        good = g0 & g1
        a, b = _find(D.t, [min(D.s[j], D.tau[j]) + d0, max(D.e[j + 1], D.tau[j + 1]) + d1])
        hit = np.zeros(D.n, bool)
        hit[D.pix[a:b]] = True
        idxs.append(np.flatnonzero(good & hit))
        goods.append(good)
    total = sum(i.size for i in idxs)
    if total > cap:
        # the same fraction of every well-exposed pixel-interval, with or without events, so the noise
        # moments (counts of pixel-intervals, Σ ΔL) stay those of the subset
        rng = np.random.default_rng([len(ints), int(total), 38])
        keep = [rng.random(D.n) < cap / total for _ in ints]
        goods = [g & k for g, k in zip(goods, keep)]
        idxs = [i[k[i]] for i, k in zip(idxs, keep)]
    rows = []
    for j, idx, good in zip(ints, idxs, goods):
        c0, _ = D.frame(j)
        c1, _ = D.frame(j + 1)
        I0_ = D.lut[c0[idx].astype(np.int64)] * D.scale[j]
        I1_ = D.lut[c1[idx].astype(np.int64)] * D.scale[j + 1]
        L0 = np.stack([np.log(I0_ + v) for v in i0s])
        L1 = np.stack([np.log(I1_ + v) for v in i0s])
        # all well-exposed pixels: count and Σ ΔL per I0 (noise-correction moments)
        I0a = D.lut[c0[good].astype(np.int64)] * D.scale[j]
        I1a = D.lut[c1[good].astype(np.int64)] * D.scale[j + 1]
        sl_all = np.array([float(np.sum(np.log(I1a + v) - np.log(I0a + v))) for v in i0s])
        rows.append({"j": j, "idx": idx, "L0": L0, "L1": L1, "code1": c1[idx].astype(np.float64),
                     "K": int(good.sum()), "sl_all": sl_all, "dt_s": (D.tau[j + 1] - D.tau[j]) * 1e-6})
    return rows


def _moments(rows, counts):
    """Per row: count moments (independent of I0) and count-by-log-change products per I0."""
    out = []
    for r, (no, nf) in zip(rows, counts):
        dl = r["L1"] - r["L0"]
        out.append((float(no @ no), float(nf @ nf), float(no @ nf), float(no.sum()), float(nf.sum()),
                    dl @ no, dl @ nf))
    return out


def _sums(rows, mom, ii, lam_on_hz, lam_off_hz, sel=None):
    """Noise-corrected least-squares sums (soo, sff, sof, bo, bf) over the rows q with sel[q], at I0 index ii
    (the counts less Poisson noise of the expected per-interval means: E[Σ(N−λ)² − Kλ] = ΣS² etc.)."""
    S = np.zeros(5)
    for q, (r, (oo, ff, of, so, sf, bo, bf)) in enumerate(zip(rows, mom)):
        if sel is not None and not sel[q]:
            continue
        lo, lf, K = lam_on_hz * r["dt_s"], lam_off_hz * r["dt_s"], r["K"]
        sl = r["sl_all"][ii]
        S += (oo - 2 * lo * so + K * (lo * lo - lo), ff - 2 * lf * sf + K * (lf * lf - lf),
              of - lf * so - lo * sf + K * lo * lf, bo[ii] - lo * sl, bf[ii] - lf * sl)
    return S


def _c(S):
    return tuple(float(np.asarray(v).reshape(-1)[0]) for v in _nnls2(*S))


def _code_errors(D, rows, counts, ii, i0, c_by_fold, lam_on_hz, lam_off_hz):
    """``(row, error)`` per pixel-interval row with pixels: the code error of predicting frame k+1
    from frame k and the events, each row's thresholds fitted on the other fold (cross-fitted)."""
    for q, (r, (no, nf)) in enumerate(zip(rows, counts)):
        if not r["idx"].size:
            continue
        con, coff = c_by_fold[1 - (q % 2)]
        lo, lf = lam_on_hz * r["dt_s"], lam_off_hz * r["dt_s"]
        lhat = r["L0"][ii] + con * (no - lo) - coff * (nf - lf)
        ihat = np.maximum(np.exp(lhat) - i0, 0.0) / D.scale[r["j"] + 1]
        yield r, _codes_of(D.lut, ihat) - r["code1"]


def _score(D, rows, counts, ii, i0, c_by_fold, lam_on_hz, lam_off_hz):
    """Σ squared code error of predicting frame k+1 from frame k and the events (cross-fitted), and n."""
    se = 0.0
    m = 0
    for _, err in _code_errors(D, rows, counts, ii, i0, c_by_fold, lam_on_hz, lam_off_hz):
        se += float(err @ err)
        m += err.size
    return se, m


def _search(D, ints, i0s, offs, lam_on, lam_off, c_range, progress):
    rows = _collect(D, ints, i0s, offs[0], offs[-1])
    npi = int(sum(r["idx"].size for r in rows))
    score = np.full((len(offs), len(i0s)), np.nan)
    coefs = np.full((len(offs), len(i0s), 2), np.nan)
    for a_i, d in enumerate(offs):
        counts = [D.weighted_counts(r["j"], d, r["idx"]) for r in rows]
        mom = _moments(rows, counts)
        for ii, i0 in enumerate(i0s):
            cf = [_c(_sums(rows, mom, ii, lam_on, lam_off, [(q % 2) == f for q in range(len(rows))])) for f in (0, 1)]
            se, m = _score(D, rows, counts, ii, i0, cf, lam_on, lam_off)
            score[a_i, ii] = math.sqrt(se / m) if m else np.nan
            coefs[a_i, ii] = _c(_sums(rows, mom, ii, lam_on, lam_off))
        if progress is not None:
            progress(a_i + 1, len(offs))
    return rows, npi, score, coefs


def _band_homogeneity(D, rows, counts, i0s, n_bands=4):
    """Per I0: how much the least-squares thresholds differ between intensity bands (relative
    weighted variance), and the band estimates. Bands are quartiles of the pixel-intervals' mean
    frame intensity (frame-linear: the same for every I0). With I0 right, the model's one
    threshold pair holds at every brightness; too small an I0 stretches the dark log changes
    (dark thresholds too large), too large compresses them."""
    inten = np.concatenate([0.5 * (np.exp(r["L0"][0]) + np.exp(r["L1"][0])) - i0s[0] for r in rows])
    edges = np.quantile(inten, np.linspace(0, 1, n_bands + 1)[1:-1]) if inten.size else np.zeros(n_bands - 1)
    band = np.searchsorted(edges, inten)
    No = np.concatenate([c[0] for c in counts])
    Nf = np.concatenate([c[1] for c in counts])
    out, per = [], []
    for ii in range(len(i0s)):
        dl = np.concatenate([r["L1"][ii] - r["L0"][ii] for r in rows])
        cs, ws = [], []
        for b in range(n_bands):
            m = band == b
            no, nf, y = No[m], Nf[m], dl[m]
            if m.sum() < 10:
                continue
            cs.append(_c((no @ no, nf @ nf, no @ nf, no @ y, nf @ y)))
            ws.append(float(no @ no + nf @ nf))
        cs = np.asarray(cs)
        ws = np.asarray(ws)
        if len(cs) < 2 or ws.sum() <= 0:
            out.append(np.nan)
            per.append([])
            continue
        mean = (ws[:, None] * cs).sum(0) / ws.sum()
        out.append(float((ws[:, None] * ((cs - mean) / np.maximum(mean, 1e-6)) ** 2).sum() / ws.sum()))
        per.append(cs.tolist())
    return np.asarray(out), per, edges.tolist()


def _fallback_index(i0s):
    """The I0 used when the recording does not identify it: the grid value nearest the grid's geometric
    centre (the minimax choice in ln I0 over the values searched: no searched value lies further than
    half the grid's log span from it), never an edge of a grid of three or more values."""
    lg = np.log(np.asarray(i0s, np.float64))
    k = int(np.argmin(np.abs(lg - 0.5 * (lg[0] + lg[-1]))))
    return int(np.clip(k, 1, len(i0s) - 2)) if len(i0s) > 2 else k


def _cv_errors(D, rows, d, ii, i0, r_on, r_off):
    """Per pixel-interval: the squared code error of the grid criterion (:func:`_score`) at (d, I0 index
    ii), and the pixel of each (concatenated over the rows)."""
    counts = [D.weighted_counts(r["j"], d, r["idx"]) for r in rows]
    mom = _moments(rows, counts)
    cf = [_c(_sums(rows, mom, ii, r_on, r_off, [(q % 2) == f for q in range(len(rows))])) for f in (0, 1)]
    errs, pix = [], []
    for r, e in _code_errors(D, rows, counts, ii, i0, cf, r_on, r_off):
        errs.append(e * e)
        pix.append(r["idx"])
    return np.concatenate(errs), np.concatenate(pix)


def _edge_test(D, rows, offs, i0s, best, fallback, r_on, r_off, seed):
    """Does the criterion's best I0, on an edge of its grid, beat the fallback I0 inside it (each at its
    own best frame offset) by more than the sampling error? Paired squared code errors on the same
    pixel-intervals; the standard error of their mean difference by a Poisson(1) bootstrap over
    pixels (a pixel's intervals share its texture, so pixels, not pixel-intervals, are resampled).
    ``significant`` when the improvement exceeds :data:`EDGE_TEST_SE` standard errors."""
    (a_e, i_e), (a_f, i_f) = best, fallback
    e_edge, pix = _cv_errors(D, rows, int(offs[a_e]), i_e, float(i0s[i_e]), r_on, r_off)
    e_fb, _ = _cv_errors(D, rows, int(offs[a_f]), i_f, float(i0s[i_f]), r_on, r_off)
    diff = e_fb - e_edge  # > 0: the edge predicts better
    u, inv = np.unique(pix, return_inverse=True)
    per_pix = np.bincount(inv, diff, minlength=u.size)
    n_pix = np.bincount(inv, minlength=u.size).astype(np.float64)
    rng = np.random.default_rng([int(seed), 41])
    W = rng.poisson(1.0, size=(EDGE_TEST_BOOT, u.size)).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        boot = (W @ per_pix) / (W @ n_pix)
    mean = float(diff.mean()) if diff.size else float("nan")
    se = float(np.nanstd(boot, ddof=1)) if diff.size else float("nan")
    z = mean / se if se > 0 else (math.inf if mean > 0 else 0.0)
    return {"edge": "lower" if i_e == 0 else "upper", "edge_i0": float(i0s[i_e]), "fallback_i0": float(i0s[i_f]),
            "edge_time_offset_us": int(offs[a_e]), "fallback_time_offset_us": int(offs[a_f]),
            "rms_edge": _f(math.sqrt(e_edge.mean())) if e_edge.size else None,
            "rms_fallback": _f(math.sqrt(e_fb.mean())) if e_fb.size else None,
            "mean_squared_improvement": _f(mean), "std_error": _f(se), "improvement_se": _f(z),
            "pixels": int(u.size), "pixel_intervals": int(diff.size), "significant": bool(z > EDGE_TEST_SE),
            "identifiable": bool(z > EDGE_TEST_SE),
            "method": "paired squared code errors of the cross-fitted frame prediction, edge I0 against the grid "
                      "value nearest the grid's geometric centre; Poisson bootstrap over pixels"}


def _default_offsets(period_us, fraction=0.5, n=N_OFFSETS):
    half = max(int(round(period_us * fraction)), 1)
    return tuple(sorted(set(int(round(v)) for v in np.linspace(-half, half, n))))


def _refine_exposure(D, rows, d, i0s, ii, c, lam_on, lam_off, iters=4):
    """Thresholds under the exact log-of-mean exposure model (EDI) at offset d, from c (fixed point).

    ln(F_k + I0) = L(τ_k + d) + B_k, B_k = ln mean_{t in exposure} exp(E_k(t)), E_k(t) the signed
    event integral from τ_k to t (sub-bins of the exposure); the frames' log change less
    B_{k+1} − B_k is regressed on the plain counts between the shifted frame times."""
    M = EXPOSURE_BINS
    need = sorted({r["j"] for r in rows} | {r["j"] + 1 for r in rows})
    plain = []
    for r in rows:
        a, b = _find(D.t, [D.tau[r["j"]] + d, D.tau[r["j"] + 1] + d])
        p_, o_ = D.pix[a:b], D.on[a:b]
        plain.append((np.bincount(p_[o_], minlength=D.n)[r["idx"]].astype(np.float64),
                      np.bincount(p_[~o_], minlength=D.n)[r["idx"]].astype(np.float64)))
    sub = {}
    for k in need:
        s, e = D.s[k], D.e[k]
        if e <= s:
            continue
        a, b = _find(D.t, [s + d, e + d])
        tt = (D.t[a:b] - d - s) / (e - s)
        bins = np.clip((tt * M).astype(np.int64), 0, M - 1)
        sub[k] = (bins, D.pix[a:b], D.on[a:b], (D.tau[k] - s) / (e - s))
    con, coff = c
    # only pixels with events inside an exposure have B != 0: work on those (compact index)
    compact = {k: (bins, *np.unique(p_, return_inverse=True), o_, mid) for k, (bins, p_, o_, mid) in sub.items()}
    for _ in range(iters):
        B = {}
        for k, (bins, u, inv, o_, mid) in compact.items():
            if not u.size:
                continue
            inc = np.zeros((M, u.size))
            np.add.at(inc, (bins, inv), np.where(o_, con, -coff))
            cum = np.cumsum(inc, 0) - 0.5 * inc
            # E relative to τ_k: the cumulative at the mid-exposure (interpolated between sub-bins)
            pos = mid * M - 0.5
            i_ = int(np.clip(math.floor(pos), 0, M - 2))
            fr_ = float(np.clip(pos - i_, 0.0, 1.0))
            ref = (1 - fr_) * cum[i_] + fr_ * cum[i_ + 1]
            full = np.zeros(D.n)
            full[u] = np.log(np.exp(cum - ref).mean(0))
            B[k] = full
        rows_b = []
        for r in rows:
            bb = B.get(r["j"] + 1, 0.0)
            ba = B.get(r["j"], 0.0)
            bb = bb[r["idx"]] if isinstance(bb, np.ndarray) else 0.0
            ba = ba[r["idx"]] if isinstance(ba, np.ndarray) else 0.0
            corr = float(np.sum(bb - ba)) if isinstance(bb, np.ndarray) or isinstance(ba, np.ndarray) else 0.0
            rows_b.append({**r, "L1": r["L1"] - bb, "L0": r["L0"] - ba, "sl_all": r["sl_all"] - corr})
        con, coff = _c(_sums(rows_b, _moments(rows_b, plain), ii, lam_on, lam_off))
    return (con, coff), plain, rows_b


def _with_i0(D, ints, offs, rows, score, coefs, i0s, v, r_on, r_off, c_range):
    """The grid with I0 = v added (its criterion column, its rows' logs on the same pixel-intervals;
    ``rows`` updated in place). Returns (score, coefs, i0s)."""
    if v in i0s:
        return score, coefs, i0s
    rows1, _, sc1, cf1 = _search(D, ints, (v,), offs, r_on, r_off, c_range, None)
    pos = int(np.searchsorted(i0s, v))
    for r, r1 in zip(rows, rows1):
        if not np.array_equal(r["idx"], r1["idx"]):
            raise AssertionError("camera model: the added I0's pixel-intervals differ from the grid's")
    for r, r1 in zip(rows, rows1):
        for key in ("L0", "L1", "sl_all"):
            r[key] = np.insert(r[key], pos, r1[key][0], 0)
    return np.insert(score, pos, sc1[:, 0], 1), np.insert(coefs, pos, cf1[:, 0], 1), i0s[:pos] + (v,) + i0s[pos:]


def estimate_camera_model(recording, *, profile=None, exclude_frames=(), offsets_us=None,
                          intensity_offsets=DEFAULT_INTENSITY_OFFSETS, intensity_offset: float | None = None,
                          time_offset_us: int | None = None, well_exposed=None, c_range=(0.01, 3.0),
                          static_log_bound: float = 0.02, noise_correction: bool = True, n_boot: int = 100,
                          seed: int = 0, max_intervals: int = MAX_INTERVALS, refine_exposure: bool = True,
                          per_pixel: bool = False, quantiser_correction: bool = True, progress=None) -> CameraModel:
    """Estimate (c_on, c_off, I0, δ) and the noise rates of a recording (module docstring).

    Parameters
    ----------
    recording : Recording or path
        Events and at least three frames registered to the event sensor.
    profile : CameraProfile, path or None
        Camera profile for ``I = CRF⁻¹(code)``; None: the recording's declared one, else built-in.
    exclude_frames : sequence of int
        Frames left out before anything is estimated (leave-one-out scoring).
    offsets_us : sequence of int, optional
        δ grid (µs added to the frames' times); default ±half the median frame period, 41 steps.
    intensity_offsets : sequence of float
        I0 grid, frame-linear units.
    intensity_offset, time_offset_us : optional
        Fix I0 or δ instead of searching (a method with its own log model, a declared latency).
    c_range : (float, float)
        Thresholds outside it are an error (the recording has too little information).
    per_pixel : bool
        Also return per-pixel sums (``CameraModel.per_pixel``) for :func:`shrink_per_pixel`.
    """
    rec = recording
    if isinstance(rec, (str, bytes)) or hasattr(rec, "__fspath__"):
        from ..formats import read
        rec = read(rec)
    D = _Data(rec, profile, exclude_frames, well_exposed)
    period = float(np.median(np.diff(D.tau)))
    i0s = (float(intensity_offset),) if intensity_offset is not None else _geom_grid(intensity_offsets)
    if intensity_offset is not None and not (math.isfinite(intensity_offset) and intensity_offset > 0):
        raise ValueError(f"intensity_offset must be finite and > 0, got {intensity_offset}")
    user_offs = offsets_us is not None or time_offset_us is not None
    if time_offset_us is not None:
        offs = (int(time_offset_us),)
    elif offsets_us is not None:
        offs = tuple(sorted({int(v) for v in offsets_us}))
        if not offs:
            raise ValueError("offsets_us is empty")
    else:
        offs = None
        for frac in (0.5, 0.25, 0.125):
            offs = _default_offsets(period, frac)
            if len(D.covered(offs[0], offs[-1])) >= 2:
                break
    edge = {"time_offset_us": False, "intensity_offset": False}
    notes = []
    for attempt in range(MAX_WIDEN + 1):
        ints = D.covered(offs[0], offs[-1])
        if len(ints) < 2:
            raise ValueError(f"the camera model needs two frame intervals inside the events' span ({D.t0_ev}.."
                             f"{D.t1_ev} µs) for every offset tried ({offs[0]}..{offs[-1]} µs); found {len(ints)}")
        if len(ints) > max_intervals:
            ints = [ints[i] for i in np.linspace(0, len(ints) - 1, max_intervals).round().astype(int)]
        if noise_correction:
            ref_i0 = i0s[len(i0s) // 2]
            r_on, r_off, noise = _noise_rates(D, ints, ref_i0, static_log_bound)
        else:
            r_on, r_off, noise = 0.0, 0.0, {"identifiable": False, "reason": "noise correction off"}
        rows, npi, score, coefs = _search(D, ints, i0s, offs, r_on, r_off, c_range, progress)
        if npi == 0:
            raise ValueError("the camera model found no pixel-interval both frames show well exposed with events")
        if not np.isfinite(score).any():
            raise ValueError("the camera model: no grid point could be scored")
        a_i, ii = np.unravel_index(np.nanargmin(score), score.shape)
        widen = False
        if attempt == MAX_WIDEN:
            break
        if intensity_offset is None and len(i0s) > 1:
            if ii == len(i0s) - 1 and i0s[-1] < I0_LIMITS[1]:
                i0s = i0s + tuple(v for v in (i0s[-1] * 4, i0s[-1] * 16) if v <= I0_LIMITS[1])
                widen = True
            elif ii == 0 and i0s[0] > I0_LIMITS[0]:
                i0s = tuple(v for v in (i0s[0] / 16, i0s[0] / 4) if v >= I0_LIMITS[0]) + i0s
                widen = True
        if time_offset_us is None and len(offs) > 1 and a_i in (0, len(offs) - 1):
            span = offs[-1] - offs[0]
            step = max(span // (len(offs) - 1), 1)
            new = offs + tuple(range(offs[-1] + step, offs[-1] + span // 2 + 1, step)) if a_i else \
                tuple(range(offs[0] - span // 2, offs[0], step)) + offs
            if len(D.covered(new[0], new[-1])) >= 2:
                offs = tuple(sorted(set(new)))
                widen = True
        if not widen or attempt == MAX_WIDEN:
            break
        notes.append(f"grid widened (best at I0 {i0s[ii] if ii < len(i0s) else float('nan'):.4g}, δ {offs[a_i]} µs)")
    i0_rule = None
    i0s_all = i0s  # the criterion's grid after widening (an I0 on its edge is warned)
    i0_edge = None
    if intensity_offset is None and len(i0s) > 2 and ii in (0, len(i0s) - 1):
        # the criterion's best I0 on an edge of its widened grid: does it beat an I0 inside the grid by more
        # than its sampling error? If not, the criterion is flat there and I0 falls back inside the grid
        i_fb = _fallback_index(i0s)
        a_fb = int(np.nanargmin(score[:, i_fb]))
        i0_edge = _edge_test(D, rows, offs, i0s, (int(a_i), int(ii)), (a_fb, i_fb), r_on, r_off, seed)
        if not i0_edge["significant"]:
            a_i, ii = a_fb, i_fb
    # the criterion's state: where every fallback from the band rule starts again, so that an I0 the rule
    # tried and gave up leaves nothing behind (not the frame offset best at that I0, nor its fit)
    crit = (score, coefs, i0s, int(a_i), int(ii), [dict(r) for r in rows])
    try_rule = quantiser_correction and intensity_offset is None and len(i0s) > 1
    for use_rule in ((True, False) if try_rule else (False,)):
        score, coefs, i0s, a_i, ii, rows = crit[:5] + ([dict(r) for r in crit[5]],)
        d = int(offs[a_i])
        rule_used = False
        if use_rule:
            # I0 by the band rule (one threshold pair at every brightness, quantiser-corrected), where the
            # simulated quantiser sees what the pixels saw; else the criterion's I0 (the second pass)
            i0s_grid, d_rule = i0s, d
            # (at the criterion's offset, which holds the quantiser's lag: the simulated events are compared with
            # the first look's tolerance, as the correction's; the strict one is the correction's own, at the end)
            i0_hat, i0_rule = _choose_i0(_BandRule(D, ints, d, {}, r_on, r_off, seed), i0s,
                                         tolerance=2 * SIM_EVENT_TOLERANCE)
            if i0_hat is None or not i0_rule["applied"]:
                continue
            score, coefs, i0s = _with_i0(D, ints, offs, rows, score, coefs, i0s, i0_hat, r_on, r_off, c_range)
            ii = i0s.index(i0_hat)
            a_i = int(np.nanargmin(score[:, ii]))
            d = int(offs[a_i])
            rule_used = True
        # per intensity band, the thresholds at the chosen model (the plot; a check of the log model)
        counts_d = [D.weighted_counts(r["j"], d, r["idx"]) for r in rows]
        h_score, h_bands, h_edges = _band_homogeneity(D, rows, counts_d, i0s)
        homog = {"relative_spread": [_f(v) for v in h_score], "bands_c": h_bands, "band_edges": h_edges,
                 "intensity_offsets": list(i0s)}
        i0 = float(i0s[ii])
        counts = [D.weighted_counts(r["j"], d, r["idx"]) for r in rows]
        mom = _moments(rows, counts)
        c = _c(_sums(rows, mom, ii, r_on, r_off))
        unc = _c(_sums(rows, mom, ii, 0.0, 0.0))
        exposure_model = "instantaneous (zero or unknown exposure)"
        fit_rows, fit_counts = rows, counts
        if D.has_exposure:
            exposure_model = "mean intensity over the exposure, first order (exposure-weighted counts)"
            if refine_exposure:
                c, fit_counts, fit_rows = _refine_exposure(D, rows, d, i0s, ii, c, r_on, r_off)
                exposure_model = "mean intensity over the exposure (EDI, log of the mean; fixed point)"
        # reverse regression (counts on frame change), reported as the errors-in-variables bracket
        rev = _reverse(fit_rows, fit_counts, ii)
        lo_c, hi_c = (float(v) for v in c_range)
        if not (lo_c <= c[0] <= hi_c and lo_c <= c[1] <= hi_c):
            raise ValueError(f"the camera model's thresholds (c_on {c[0]:.4g}, c_off {c[1]:.4g}) are outside c_range "
                             f"{tuple(c_range)}: the recording has too little usable information ({npi} pixel-intervals "
                             f"with events in {len(ints)} frame intervals)")
        pp = _per_pixel_sums(D, fit_rows, fit_counts, ii, r_on, r_off)
        sd = _bootstrap(pp, n_boot, seed)
        sig = _mismatch(pp)
        ls = c
        ii_rec = None
        latency = None
        if quantiser_correction:
            c2, ii_rec, latency, ii = _binding(D, rows, ints, i0s, offs, d, ii, sig, r_on, r_off, seed,
                                               intensity_offset is None and not rule_used, time_offset_us is None,
                                               score_col=score[:, ii] if len(offs) > 4 else None)
            if rule_used and c2 is None:
                # the correction was not applied: neither is the band rule that rests on the same simulation
                i0_rule = {**i0_rule, "applied": False, "reason": "the quantiser correction was not applied at the "
                                                                    "band rule's I0: " + str(ii_rec.get("reason", ""))}
                continue
            if rule_used and latency is not None:
                # the band rule again at the latency the binding found (its counts between the frame times
                # shifted by the latency, not by the criterion's lagged best), and the thresholds there; the
                # simulated quantiser has just passed the correction's strict check at this latency
                i0_hat2, rec2 = _choose_i0(_BandRule(D, ints, latency, {}, r_on, r_off, seed), i0s_grid,
                                           around=i0_hat, tolerance=math.inf)
                first = {"time_offset_us": d_rule, "intensity_offset": i0_hat,
                         **{k: v for k, v in i0_rule.items() if k not in ("method", "profile")}}
                if i0_hat2 is None or not rec2["applied"]:
                    # no zero at the latency: the first pass's (at an offset holding the quantiser's lag) is not
                    # trusted either; I0 is the criterion's, everything estimated again there
                    i0_rule = {**{k: v for k, v in rec2.items() if k != "applied"}, "applied": False,
                               "time_offset_us": latency, "first_pass": first}
                    continue
                i0_rule = {**rec2, "time_offset_us": latency, "first_pass": first}
                score, coefs, i0s = _with_i0(D, ints, offs, rows, score, coefs, i0s, i0_hat2, r_on, r_off, c_range)
                ii = i0s.index(i0_hat2)
                c2, rec3 = _indirect(D, ints, i0_hat2, _ls_at(D, rows, latency, ii, r_on, r_off), sig, r_on, r_off,
                                     seed=seed)
                ii_rec = {**ii_rec, **{k: v for k, v in rec3.items() if k in _FINAL_INDIRECT_KEYS}}
            i0 = float(i0s[ii])
            if c2 is not None:
                # shrunk toward the least squares by how well the simulation reproduces what it was not fitted to
                check = _correction_check(D, ints, float(i0s[ii]), c2, sig, r_on, r_off, latency, seed)
                c2, shrink_rec = _shrink_correction(c2, ii_rec, check, _observed_signal(D, ints, latency, r_on, r_off))
                ii_rec = {**ii_rec, "shrinkage": shrink_rec,
                          "simulated_to_observed_events": shrink_rec["simulated_to_observed_events"]}
                c = c2
                # the per-pixel least squares of the two halves carry the pooled fit's quantiser bias: scale
                # their spread by the same factor as the thresholds
                for j, k in enumerate(("on", "off")):
                    if sig.get(k) is not None and ls[j] > 0:
                        sig[k] = sig[k] * c[j] / ls[j]
                if sig.get("std") is not None and ls[0] + ls[1] > 0:
                    sig["std"] = sig["std"] * (c[0] + c[1]) / (ls[0] + ls[1])
                sig["scaled_by_quantiser_correction"] = True
                if sd[0] is not None:
                    # the correction's own simulation noise adds to the sampling error: its statistic pools
                    # replicates x simulated pixels where the observed one pools all the pixels
                    frac = D.n / (ii_rec["replicates"] * ii_rec.get("pixels_simulated", D.n))
                    sd = tuple(v * math.sqrt(1 + frac) for v in sd)
            if not (lo_c <= c[0] <= hi_c and lo_c <= c[1] <= hi_c):
                raise ValueError(f"the camera model's corrected thresholds (c_on {c[0]:.4g}, c_off {c[1]:.4g}) are "
                                 f"outside c_range {tuple(c_range)}: the recording has too little usable information")
        break
    if time_offset_us is None and len(offs) > 1 and a_i in (0, len(offs) - 1):
        edge["time_offset_us"] = True
        warnings.warn(f"camera model: the best frame time offset {d} µs lies on the edge of its grid "
                      f"({offs[0]}..{offs[-1]} µs) after widening", GridEdgeWarning, stacklevel=2)
    if i0_edge is not None and not rule_used:
        e_ = i0_edge
        i0_edge = {**e_, "used": "fallback" if not e_["significant"] else "edge"}
        if not e_["significant"]:
            # flat at the edge: not identified, the documented fallback inside the grid (named, warned)
            warnings.warn(f"camera model: the grid criterion is flat at the {e_['edge']} edge of the I0 grid "
                          f"({min(i0s_all):.4g}..{max(i0s_all):.4g}): I0 = {e_['edge_i0']:.4g} predicts the frames "
                          f"{e_['improvement_se']:.2g} standard errors better than I0 = {e_['fallback_i0']:.4g} "
                          f"(needs {EDGE_TEST_SE:g}); the recording does not identify I0, the fallback "
                          f"{e_['fallback_i0']:.4g} inside the grid is used", GridEdgeWarning, stacklevel=2)
    if intensity_offset is None and not rule_used and len(i0s) > 1 and float(i0s[ii]) in (min(i0s_all), max(i0s_all)):
        edge["intensity_offset"] = True
        lim = "lower" if float(i0s[ii]) == min(i0s_all) else "upper"
        why = (f"; it predicts the frames {i0_edge['improvement_se']:.3g} standard errors better than the fallback "
               f"I0 = {i0_edge['fallback_i0']:.4g} inside the grid" if i0_edge is not None else "")
        warnings.warn(f"camera model: the best log offset I0 = {i0:.4g} lies on the {lim} edge of its grid "
                      f"({min(i0s_all):.4g}..{max(i0s_all):.4g}) after widening: the recording does not bound it"
                      + why, GridEdgeWarning, stacklevel=2)
    a0 = int(np.argmin(np.abs(np.asarray(offs))))
    from ..camera.encoding import DEFAULT_INTENSITY_OFFSET
    i_def = int(np.argmin(np.abs(np.log(np.asarray(i0s)) - math.log(DEFAULT_INTENSITY_OFFSET))))
    r2 = _r2(D, rows, d, ii, r_on, r_off)
    r2_nominal = _r2(D, rows, int(offs[a0]), i_def, r_on, r_off)
    fixed = {"intensity_offset": intensity_offset is not None, "time_offset_us": time_offset_us is not None,
             "user_grid": bool(user_offs), "notes": notes}
    return CameraModel(
        c_on=float(c[0]), c_off=float(c[1]), c_on_std=sd[0], c_off_std=sd[1], intensity_offset=i0, time_offset_us=d,
        score=float(score[a_i, ii]), score_nominal=float(score[a0, i_def]), n_pixel_intervals=npi,
        n_intervals=len(ints), excluded_frames=D.excl, offsets_us=tuple(offs), intensity_offsets=tuple(i0s),
        score_grid=tuple(tuple(float(v) for v in row) for row in score), at_grid_edge=edge,
        exposure_model=exposure_model,
        noise={**noise, "rate_on_hz": r_on, "rate_off_hz": r_off, "shot_noise_rate_hz": 2 * r_off,
               "leak_rate_hz": max(r_on - r_off, 0.0)},
        uncorrected={"c_on": unc[0], "c_off": unc[1]}, least_squares={"c_on": ls[0], "c_off": ls[1]},
        quantiser_correction=ii_rec, mismatch_sigma=sig, bands=homog, latency_us=latency, r2=r2, r2_nominal=r2_nominal, reverse_regression=rev, fixed=fixed, i0_rule=i0_rule, i0_edge=i0_edge,
        per_pixel=pp if per_pixel else None)


def _mismatch(pp, min_intervals=2, min_pixels=30, n_boot=100, seed=0):
    """Per-polarity spread of the pixels' thresholds: covariance of the even and odd intervals'
    per-pixel estimates (their estimation errors are independent, so they drop out)."""
    out = {}
    ests = []
    for hs in pp["halves"]:
        a, b = _nnls2(hs["soo"], hs["sff"], hs["sof"], hs["bo"], hs["bf"])
        ok = (hs["k_on"] >= min_intervals) & (hs["k_off"] >= min_intervals) & (a > 0) & (b > 0)
        ests.append((a, b, ok))
    both = ests[0][2] & ests[1][2]
    xs, ys = [], []
    if both.sum() < min_pixels:
        out["on"] = out["off"] = None
    else:
        keep = np.ones(int(both.sum()), bool)
        for j in range(2):
            allv = np.concatenate([ests[0][j][both], ests[1][j][both]])
            med = np.median(allv)
            mad = 1.4826 * np.median(np.abs(allv - med))
            if mad > 0:
                keep &= (np.abs(ests[0][j][both] - med) <= 8 * mad) & (np.abs(ests[1][j][both] - med) <= 8 * mad)
        for j, name in enumerate(("on", "off")):
            x, y = ests[0][j][both][keep], ests[1][j][both][keep]
            out[name] = math.sqrt(max(float(np.mean((x - x.mean()) * (y - y.mean()))), 0.0))
            xs.append(x)
            ys.append(y)
    out["pixels_both_halves"] = int(both.sum())
    if len(xs) == 2 and xs[0].size == xs[1].size:
        rng = np.random.default_rng([int(seed), 37])
        bs = []
        for _ in range(int(n_boot)):
            i = rng.integers(0, xs[0].size, xs[0].size)
            v = [float(np.mean((x[i] - x[i].mean()) * (y[i] - y[i].mean()))) for x, y in zip(xs, ys)]
            bs.append(0.5 * (math.sqrt(max(v[0], 0.0)) + math.sqrt(max(v[1], 0.0))))
        out["std"] = float(np.std(bs, ddof=1))
    return out


def _ls_stat(G, DL, N_on, N_off, dts, lam_on, lam_off):
    """The pooled noise-corrected forward least squares of the frames' log change ``DL`` on the
    counts (all (intervals, pixels) arrays; ``G`` the well-exposed mask, ``DL`` zero outside it)
    over the intervals of durations ``dts`` (s), as the observed statistic is computed. Returns the
    statistic (c_on, c_off) and the signal events (ON, OFF: the counts less the expected noise)."""
    no, nf = np.where(G, N_on, 0.0), np.where(G, N_off, 0.0)
    lo, lf, K = lam_on * dts, lam_off * dts, G.sum(1).astype(np.float64)
    so, sf = no.sum(1), nf.sum(1)
    sd = DL.sum(1)
    S = np.array([np.sum((no * no).sum(1) - 2 * lo * so + K * (lo * lo - lo)),
                  np.sum((nf * nf).sum(1) - 2 * lf * sf + K * (lf * lf - lf)),
                  np.sum((no * nf).sum(1) - lf * so - lo * sf + K * lo * lf),
                  np.sum((no * DL).sum(1) - lo * sd), np.sum((nf * DL).sum(1) - lf * sd)])
    return np.array(_c(S)), np.array([float(np.sum(so - lo * K)), float(np.sum(sf - lf * K))])


def _ls_sums_per_pixel(G, DL, N_on, N_off, dts, lam_on, lam_off):
    """Per-pixel (5, pixels) noise-corrected sums whose sum over the pixels is :func:`_ls_stat`'s."""
    no, nf = np.where(G, N_on, 0.0), np.where(G, N_off, 0.0)
    lo, lf = (lam_on * dts)[:, None], (lam_off * dts)[:, None]
    g = G.astype(np.float64)
    return np.stack([(no * no - 2 * lo * no + g * (lo * lo - lo)).sum(0), (nf * nf - 2 * lf * nf + g * (lf * lf - lf)).sum(0),
                     (no * nf - lf * no - lo * nf + g * lo * lf).sum(0), ((no - lo) * DL).sum(0), ((nf - lf) * DL).sum(0)])


def _path_counts(Ls, rel, dts, c, sigma, draw, r_on, r_off, substeps=None):
    """Counts of the DVS quantiser (eq. 1: an event each time the log leaves [ref − c_off, ref + c_on],
    the reference moving by one threshold) driven by the frames' log path ``Ls`` (frames, pixels),
    for the frame intervals ``rel`` (indices into Ls) of durations ``dts`` (s), plus Poisson noise
    events at the rates given. ``draw`` = (initial phase u, N(0,1) for ON and OFF thresholds, noise seed).

    Between frames the path is the Catmull-Rom cubic through the neighbouring frames, sampled at
    ``substeps`` points (:data:`PATH_SUBSTEPS`): a smooth scene's extremum between two frames makes the
    pixel reverse (an ON and an OFF run in one interval) as the camera's pixels did, which a path
    linear between frames never does (with it the quantiser correction left the thresholds 3 % low
    at c = 0.5 on the round trip, ``benchmarks/sensor_profile.py``)."""
    M = PATH_SUBSTEPS if substeps is None else int(substeps)
    u, z_on, z_off, sd = draw
    n = Ls.shape[1]
    con = np.maximum(c[0] + sigma[0] * z_on, 0.01)
    coff = np.maximum(c[1] + sigma[1] * z_off, 0.01)
    ref = Ls[0] - (u * (con + coff) - coff)   # initial phase uniform over the hysteresis band
    nr = np.random.default_rng(sd)
    want = {k: q for q, k in enumerate(rel)}
    K = Ls.shape[0]
    N_on, N_off = [None] * len(rel), [None] * len(rel)
    for k in range(max(rel) + 1):
        p0, p1, p2, p3 = Ls[max(k - 1, 0)], Ls[k], Ls[k + 1], Ls[min(k + 2, K - 1)]
        a1, a2, a3 = 0.5 * (p2 - p0), 0.5 * (2 * p0 - 5 * p1 + 4 * p2 - p3), 0.5 * (3 * (p1 - p2) + p3 - p0)
        up = np.zeros(n)
        dn = np.zeros(n)
        for m in range(1, M + 1):
            s_ = m / M
            x = p2 if m == M else p1 + s_ * (a1 + s_ * (a2 + s_ * a3))
            u_ = np.floor(np.maximum(x - ref, 0.0) / con)
            d_ = np.floor(np.maximum(ref - x, 0.0) / coff)
            ref = ref + u_ * con - d_ * coff
            up += u_
            dn += d_
        if k in want:
            q = want[k]
            N_on[q] = up + (nr.poisson(r_on * dts[q], n) if r_on > 0 else 0)
            N_off[q] = dn + (nr.poisson(r_off * dts[q], n) if r_off > 0 else 0)
    return np.stack(N_on), np.stack(N_off)


def _indirect(D, ints, i0, c_obs, sigma, r_on, r_off, *, reps=4, iters=6, seed=0, c_init=None):
    """Indirect inference (Gouriéroux, Monfort & Renault, J. Applied Econometrics 1993): the
    thresholds whose *simulated* pooled least-squares statistic equals the observed one.

    The simulation is the DVS model itself (eq. 1, a quantiser with hysteresis: an event each time
    ln(I + I0) leaves [ref − c_off, ref + c_on], the reference moving by one threshold) run on the
    frames' own log path (cubic between frames, :func:`_path_counts`), each pixel with a random initial phase and,
    when the spread is identified, its own N(c, σ) thresholds, plus Poisson noise events at the
    measured rates. The simulated counts pass through the same statistic as the observed ones,
    so the quantiser's and the pooling's biases (attenuation where a pixel fires few events per
    interval, hysteresis after reversals, the lower thresholds of busier pixels) cancel; the
    thresholds are updated by the statistic's difference until it vanishes."""
    k0, k1 = ints[0], ints[-1] + 1
    rng = np.random.default_rng([int(seed), 35])
    sub = (np.sort(rng.choice(D.n, MAX_CORRECTION_PIXELS, replace=False)) if D.n > MAX_CORRECTION_PIXELS
           else np.arange(D.n))
    n = sub.size
    Ls, goods_all = [], []
    for k in range(k0, k1 + 1):
        c_, g_ = D.frame(k)
        Ls.append(np.log(D.lut[c_[sub].astype(np.int64)] * D.scale[k] + i0))
        goods_all.append(g_[sub])
    Ls = np.stack(Ls)
    rel = [j - k0 for j in ints]
    goods = [goods_all[j] & goods_all[j + 1] for j in rel]
    dts = [(D.tau[j + 1] - D.tau[j]) * 1e-6 for j in ints]
    s_on = sigma.get("on") or 0.0
    s_off = sigma.get("off") or 0.0
    draws = [(rng.random(n), rng.standard_normal(n), rng.standard_normal(n), int(rng.integers(1 << 31)))
             for _ in range(reps)]
    tot_scale = D.n / n  # the subset's event totals, scaled to all pixels
    Gm = np.stack(goods)
    DLm = np.where(Gm, Ls[[j + 1 for j in rel]] - Ls[rel], 0.0)
    dts_a = np.asarray(dts, np.float64)
    c = np.array(c_obs if c_init is None else c_init, float)
    history = []
    totals = []
    converged = False  # unit steps converge slowly on a flat binding (recorded; the shrinkage weighs the slope)
    for _ in range(iters):
        stats = []
        totals = []
        for u, z_on, z_off, sd in draws:
            N_on, N_off = _path_counts(Ls, rel, dts, c, (s_on, s_off), (u, z_on, z_off, sd), r_on, r_off)
            st, tot = _ls_stat(Gm, DLm, np.stack(N_on), np.stack(N_off), dts_a, r_on, r_off)
            stats.append(st)
            totals.append(tot_scale * tot)
        sim = np.mean(stats, 0)
        history.append([float(c[0]), float(c[1]), float(sim[0]), float(sim[1])])
        gap = np.asarray(c_obs) - sim
        if np.all(np.abs(gap) <= CORRECTION_TOLERANCE):
            converged = True
            break  # the simulated statistic matches the observed one: c is the answer
        c = np.maximum(c + gap, 0.01)
    tot_pol = np.mean(totals, 0) if totals else None
    return (float(c[0]), float(c[1])), {"method": "indirect inference on a simulated DVS quantiser (hysteresis) "
                                                  "over the frames' own log path", "replicates": reps,
                                        "pixels_simulated": int(n), "iterations": history, "converged": converged,
                                        "sigma_used": [s_on, s_off],
                                        "observed_statistic": [float(v) for v in c_obs], "i0": float(i0),
                                        "simulated_signal_events": float(tot_pol.sum()) if totals else None,
                                        "simulated_signal_events_on_off": [float(v) for v in tot_pol] if totals else None}


class _BandRule:
    """I0 from the model's own premise: ONE threshold pair at every brightness.

    With the wrong I0 the log changes of the dark pixels are stretched (I0 too small) or squeezed
    (too large) relative to the bright ones, so thresholds estimated separately below and above the
    median intensity differ; at the right I0 they agree. Each band's least-squares thresholds carry
    the DVS quantiser's bias, so each is corrected by simulation exactly as the pooled ones
    (:func:`_indirect`: the quantiser on the frames' log path at the candidate I0, the same
    statistic on the simulated counts, the band's bias = simulated statistic − simulated
    thresholds). ``f(I0) = ln((c_on + c_off)_dark / (c_on + c_off)_bright)`` of the corrected
    band thresholds is a moment condition, not a fit to maximise: its zero is the estimate, and
    its target (equal thresholds) does not move with the candidate. Bands are fixed before the
    search by the frames' linear intensity (the same for every I0); counts are the plain counts
    between the frame times shifted by ``d``, on a fixed seeded subset of pixels."""

    def __init__(self, D, ints, d, sig, r_on, r_off, seed):
        k0, k1 = ints[0], ints[-1] + 1
        rng = np.random.default_rng([int(seed), 39])
        sub = (np.sort(rng.choice(D.n, MAX_I0_RULE_PIXELS, replace=False)) if D.n > MAX_I0_RULE_PIXELS
               else np.arange(D.n))
        self.I = np.stack([D.lut[D.frame(k)[0][sub].astype(np.int64)] * D.scale[k] for k in range(k0, k1 + 1)])
        self.rel = [j - k0 for j in ints]
        nxt = [r + 1 for r in self.rel]
        self.G = np.stack([D.frame(j)[1][sub] & D.frame(j + 1)[1][sub] for j in ints])
        self.dts = np.asarray([(D.tau[j + 1] - D.tau[j]) * 1e-6 for j in ints], np.float64)
        no, nf = [], []
        for j in ints:
            a, b = _find(D.t, [D.tau[j] + d, D.tau[j + 1] + d])
            p_, o_ = D.pix[a:b], D.on[a:b]
            no.append(np.bincount(p_[o_], minlength=D.n)[sub].astype(np.float64))
            nf.append(np.bincount(p_[~o_], minlength=D.n)[sub].astype(np.float64))
        self.No, self.Nf = np.stack(no), np.stack(nf)
        inten = 0.5 * (self.I[nxt] + self.I[self.rel])
        act = self.G & ((self.No + self.Nf) > 0)
        self.n_active = int(act.sum())
        edges = np.quantile(inten[act], np.linspace(0, 1, I0_BANDS + 1)[1:-1]) if act.any() else np.zeros(I0_BANDS - 1)
        self.band = np.searchsorted(edges, inten)
        self.edges = [float(v) for v in edges]
        self.sig = (sig.get("on") or 0.0, sig.get("off") or 0.0)
        self.r_on, self.r_off = r_on, r_off
        n = sub.size
        self.draws = [(rng.random(n), rng.standard_normal(n), rng.standard_normal(n), int(rng.integers(1 << 31)))
                      for _ in range(I0_RULE_REPS)]
        self.pixels = int(n)
        self.W = rng.poisson(1.0, size=(I0_RULE_BOOT, n)).astype(np.float64)
        self.last_boot = None
        self.pooled_bias = {}

    def __call__(self, i0):
        """(f(I0), pooled corrected (c_on, c_off), per-band corrected thresholds (bands, 2), simulated to
        observed signal events)."""
        Ls = np.log(self.I + i0)
        nxt = [r + 1 for r in self.rel]
        DL = np.where(self.G, Ls[nxt] - Ls[self.rel], 0.0)
        masks = [self.G & (self.band == b) for b in range(I0_BANDS)]
        stat = lambda G_, no, nf: _ls_stat(G_, np.where(G_, DL, 0.0), no, nf, self.dts, self.r_on, self.r_off)[0]
        c_obs = stat(self.G, self.No, self.Nf)
        # one indirect-inference step: the pooled quantiser bias of the nearest I0 already simulated (the
        # least squares themselves at the first), then the band biases at the corrected thresholds
        near = min(self.pooled_bias, key=lambda v: abs(math.log(v / i0)), default=None)
        passes = 1 if near is not None else 2
        c = np.maximum(c_obs - (self.pooled_bias[near] if near is not None else 0.0), 0.01)
        for it in range(passes):
            sims = [_path_counts(Ls, self.rel, self.dts, c, self.sig, dr, self.r_on, self.r_off) for dr in self.draws]
            if it < passes - 1:
                c = np.maximum(c + c_obs - np.mean([stat(self.G, *s) for s in sims], 0), 0.01)
        self.pooled_bias[i0] = np.mean([stat(self.G, *s) for s in sims], 0) - c
        bias = [np.mean([stat(G_, *s) for s in sims], 0) - c for G_ in masks]
        cb = np.array([stat(G_, self.No, self.Nf) - b for G_, b in zip(masks, bias)])
        tot = cb.sum(1)
        f = math.log(tot[0] / tot[-1]) if tot[0] > 0 and tot[-1] > 0 else float("nan")
        # the observed band statistics under a Poisson(1) bootstrap over pixels (the same weights at every
        # I0: each replicate has its own zero), the simulated biases held
        fb = []
        for G_, b in zip(masks, bias):
            P = _ls_sums_per_pixel(G_, np.where(G_, DL, 0.0), self.No, self.Nf, self.dts, self.r_on, self.r_off)
            a_, b_ = _nnls2(*(self.W @ P.T).T)
            fb.append((a_ - b[0]) + (b_ - b[1]))
        with np.errstate(invalid="ignore", divide="ignore"):
            self.last_boot = np.log(np.where((fb[0] > 0) & (fb[-1] > 0), fb[0] / fb[-1], np.nan))
        # signal events (noise removed) the simulation fires against the observed ones: its applicability
        noise = float((self.r_on + self.r_off) * (self.G.sum(1) * self.dts).sum())
        obs = float(np.where(self.G, self.No + self.Nf, 0.0).sum()) - noise
        sim = float(np.mean([np.where(self.G, a + b, 0.0).sum() for a, b in sims])) - noise
        return f, c, cb, (sim / obs if obs > 0 else float("nan"))


def _choose_i0(rule, i0s, around=None, tolerance=SIM_EVENT_TOLERANCE):
    """The zero of the band rule's f over log I0 (:class:`_BandRule`) on the criterion's grid (widened
    there when its best lay on an edge), with its bootstrap standard error. Returns (I0 or None,
    record); the record's ``applied`` says whether the zero is used (a significant sign change
    where the simulated quantiser reproduces the observed events), ``identifiable`` whether it is
    determined to a grid step (two standard errors within a factor 2)."""
    grid = list(i0s)
    prof = {}

    boot = {}

    def f(v):
        if v not in prof:
            prof[v] = rule(v)
            boot[v] = rule.last_boot
        return prof[v][0]

    def falls(g):
        v_ = [f(x) for x in g]
        return [k for k in range(len(g) - 1) if v_[k] > 0 >= v_[k + 1]]

    # where to look: around a zero already found (within two grid steps), else every other grid value,
    # then the grid values between the coarse ones that bracket the zero (f is smooth in ln I0)
    cross = []
    if around is not None:
        near = [v for v in grid if abs(math.log(v / around)) <= 2 * math.log(4.0) / 2 + 1e-9]
        if len(near) >= 2 and falls(near):
            grid = near
            cross = falls(grid)
    if not cross:
        coarse = sorted(set(grid[::2]) | {grid[-1]})
        cc = falls(coarse)
        if cc:
            lo_, hi_ = coarse[cc[0]], coarse[cc[0] + 1]
            grid = [v for v in grid if lo_ <= v <= hi_]
        else:
            grid = coarse
        cross = falls(grid)
    vals = np.array([f(v) for v in grid])
    rec = {"method": "equal quantiser-corrected thresholds below and above the median intensity "
                     "(f = ln(c_dark / c_bright) = 0, linear in ln I0 between grid points)",
           "pixels": rule.pixels, "pixel_intervals_with_events": rule.n_active, "band_edges": rule.edges,
           "profile": [[float(v), _f(prof[v][0]), [[_f(x) for x in row] for row in prof[v][2]]] for v in sorted(prof)]}
    if not cross:
        rec["identifiable"] = False
        rec["applied"] = False
        rec["reason"] = (f"ln(c_dark / c_bright) does not change sign over I0 {grid[0]:.3g}..{grid[-1]:.3g} "
                         f"(from {_f(vals[0])} to {_f(vals[-1])}): the recording does not identify I0")
        return None, rec
    k = cross[0] if len(cross) == 1 else cross[int(np.argmax([vals[k] - vals[k + 1] for k in cross]))]
    x0, x1 = math.log(grid[k]), math.log(grid[k + 1])
    w = vals[k] / (vals[k] - vals[k + 1])
    i0 = math.exp(x0 + w * (x1 - x0))
    _, _, _, ratio = rule(i0)
    # its standard error in ln I0: each bootstrap replicate's zero in the bracket (robust spread)
    fa, fb_ = boot[grid[k]], boot[grid[k + 1]]
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(fa - fb_ > 0, x0 + fa / (fa - fb_) * (x1 - x0), np.nan)
    bad = float(np.mean(~np.isfinite(z)))  # replicates without a falling crossing here
    zf = z[np.isfinite(z)]
    se = 1.4826 * float(np.median(np.abs(zf - np.median(zf)))) if zf.size >= 10 else float("inf")
    step = math.log(2.0)
    crossing = bad <= I0_RULE_MISSING
    ident = bool(crossing and 2 * se <= step)
    rec.update({"identifiable": ident, "crossings": len(cross), "bracket": [grid[k], grid[k + 1]],
                "ln_i0_std": _f(se), "bootstrap_without_zero": bad,
                "simulated_to_observed_events": _f(ratio),
                "event_tolerance": _f(tolerance), "applied": bool(crossing and abs(ratio - 1.0) <= tolerance)})
    if not crossing:
        rec["reason"] = (f"f's sign change at I0 {i0:.4g} is not significant: {bad:.0%} of the bootstrap replicates "
                         f"(over pixels) have no zero there (at most {I0_RULE_MISSING:.0%}); I0 is the criterion's")
    elif not rec["applied"]:
        rec["reason"] = (f"at the zero (I0 {i0:.4g}) the quantiser simulated on the frames' log path fires {ratio:.2f}x "
                         f"the observed signal events (tolerance {tolerance:.0%}): the frames undersample the "
                         f"scene's changes, the band corrections cannot be trusted; I0 is the criterion's")
    elif not ident:
        rec["reason"] = (f"I0 {i0:.4g} is used but not identified to a grid step: its bootstrap standard error in ln I0 "
                         f"is {se:.3g} (identified when two standard errors are within a factor 2, ln 2 = {step:.3f})")
    return float(i0), rec


class _SimData:
    """A :class:`_Data` view with other events (the quantiser simulation's)."""

    def __init__(self, D, ev):
        self.__dict__.update(D.__dict__)
        self.t = ev["t"]
        self.pix = ev["y"].astype(np.int64) * D.w + ev["x"].astype(np.int64)
        self.on = ev["p"] > 0

    frame = _Data.frame
    G = _Data.G
    covered = _Data.covered
    window = _Data.window
    weighted_counts = _Data.weighted_counts


def _r2(D, rows, d, ii, r_on, r_off):
    """Fraction of the frames' log-change variance (event-bearing pixel-intervals) the least-squares
    fit at (d, I0 index ii) explains."""
    counts = [D.weighted_counts(r["j"], d, r["idx"]) for r in rows]
    c = _c(_sums(rows, _moments(rows, counts), ii, r_on, r_off))
    res = tot = 0.0
    dls = [r["L1"][ii] - r["L0"][ii] for r in rows]
    allv = np.concatenate(dls) if dls else np.zeros(0)
    if allv.size < 2:
        return float("nan")
    mu = allv.mean()
    for r, (no, nf), dl in zip(rows, counts, dls):
        lo, lf = r_on * r["dt_s"], r_off * r["dt_s"]
        e = dl - c[0] * (no - lo) + c[1] * (nf - lf)
        res += float(e @ e)
        tot += float((dl - mu) @ (dl - mu))
    return 1.0 - res / tot if tot > 0 else float("nan")


def _ls_at(D, rows, d, ii, r_on, r_off):
    counts = [D.weighted_counts(r["j"], d, r["idx"]) for r in rows]
    return _c(_sums(rows, _moments(rows, counts), ii, r_on, r_off))


#: What the final quantiser correction's record carries from its last :func:`_indirect` run.
_FINAL_INDIRECT_KEYS = ("iterations", "converged", "simulated_signal_events", "simulated_signal_events_on_off",
                        "observed_statistic", "i0")


def _reverse_stat(G, DL, N_on, N_off):
    """The reverse regression (:func:`_reverse`: instruments (ΔL+, ΔL−) for (N_on, N_off)) on
    (intervals, pixels) arrays; NaN where it is singular."""
    no, nf = np.where(G, N_on, 0.0), np.where(G, N_off, 0.0)
    dl = np.where(G, DL, 0.0)
    zp, zn = np.maximum(dl, 0), np.maximum(-dl, 0)
    a = np.array([[np.sum(no * zp), -np.sum(nf * zp)], [np.sum(no * zn), -np.sum(nf * zn)]])
    y = np.array([np.sum(dl * zp), np.sum(dl * zn)])
    try:
        return np.linalg.solve(a, y)
    except np.linalg.LinAlgError:
        return np.full(2, np.nan)


def _correction_check(D, ints, i0, c_ind, sigma, r_on, r_off, d, seed, reps=4):
    """The statistics the quantiser correction did not fit, observed and simulated at its answer.

    On the correction's own pixel subset and draws (the same seeded stream as :func:`_indirect`),
    with the plain counts between the frame times shifted by ``d``: the forward least squares and
    the reverse regression of the observed counts, and the reverse regression of the counts the
    quantiser simulated at ``c_ind`` fires. Returns a dict of (ON, OFF) pairs."""
    k0, k1 = ints[0], ints[-1] + 1
    rng = np.random.default_rng([int(seed), 35])
    sub = (np.sort(rng.choice(D.n, MAX_CORRECTION_PIXELS, replace=False)) if D.n > MAX_CORRECTION_PIXELS
           else np.arange(D.n))
    n = sub.size
    Ls = np.stack([np.log(D.lut[D.frame(k)[0][sub].astype(np.int64)] * D.scale[k] + i0) for k in range(k0, k1 + 1)])
    rel = [j - k0 for j in ints]
    G = np.stack([D.frame(j)[1][sub] & D.frame(j + 1)[1][sub] for j in ints])
    DL = np.where(G, Ls[[r + 1 for r in rel]] - Ls[rel], 0.0)
    dts = np.asarray([(D.tau[j + 1] - D.tau[j]) * 1e-6 for j in ints], np.float64)
    no, nf = [], []
    for j in ints:
        a, b = _find(D.t, [D.tau[j] + d, D.tau[j + 1] + d])
        p_, o_ = D.pix[a:b], D.on[a:b]
        no.append(np.bincount(p_[o_], minlength=D.n)[sub].astype(np.float64))
        nf.append(np.bincount(p_[~o_], minlength=D.n)[sub].astype(np.float64))
    No, Nf = np.stack(no), np.stack(nf)
    sim_r = []
    for _ in range(reps):
        draw = (rng.random(n), rng.standard_normal(n), rng.standard_normal(n), int(rng.integers(1 << 31)))
        a_, b_ = _path_counts(Ls, rel, list(dts), c_ind, (sigma.get("on") or 0.0, sigma.get("off") or 0.0), draw,
                              r_on, r_off)
        sim_r.append(_reverse_stat(G, DL, a_, b_))
    return {"forward_observed": _ls_stat(G, DL, No, Nf, dts, r_on, r_off)[0],
            "reverse_observed": _reverse_stat(G, DL, No, Nf), "reverse_simulated": np.mean(sim_r, 0)}


def _binding_slope(history):
    """Per polarity, the slope of the simulated statistic against the thresholds along the correction's
    iterations (a secant from the first to the last simulated point: common random numbers make the
    simulated statistic a smooth function of c). Where c moved by less than two
    :data:`CORRECTION_TOLERANCE` the slope is not measured and taken as 1 (the statistic's own scale)."""
    h = np.asarray(history, np.float64)
    out = np.ones(2)
    if h.ndim == 2 and h.shape[0] >= 2:
        dc = h[-1, :2] - h[0, :2]
        ds = h[-1, 2:4] - h[0, 2:4]
        for p in range(2):
            if abs(dc[p]) >= 2 * CORRECTION_TOLERANCE:
                out[p] = ds[p] / dc[p]
    return out


def _shrink_correction(c_ind, rec, check, obs_events):
    """The quantiser correction shrunk toward the least squares it corrects, per polarity, by how
    well the simulation reproduces the event statistics it was not fitted to; returns (c, record).

    The correction ``δ = c_ind − c_ls`` estimates the least squares' bias ``b`` from a simulation
    fitted to one statistic, the forward least squares. Two more statistics of the same counts are
    left out of the fit, and a right simulation reproduces them too: the signal events per polarity
    (simulated to observed ratio ``r``) and the reverse regression (simulated ``rev_s`` to observed
    ``rev_o``; forward and reverse are both consistent under a right simulation, so their
    disagreement measures misspecification, as in Hausman's test, Econometrica 1978). Their relative
    misfit ``ρ = √(ln² r + ln²(rev_o / rev_s))`` is taken as the relative error of the simulated
    forward statistic, and an error ``e`` in a statistic moves the indirect-inference estimate by
    ``e / slope``, the slope of the simulated statistic in c (the delta method of Gouriéroux, Monfort &
    Renault 1993; :func:`_binding_slope`): ``σ = ρ·c_ls / slope``. A flat binding (slope well below 1:
    the counts say little about c) magnifies any misfit. The bias has the errors-in-variables
    bracket as its scale (forward and reverse regressions bound the truth under classical
    measurement error: Frisch 1934; Klepper & Leamer, Econometrica 1984): ``τ = |rev_o − c_ls|``.
    Under a normal prior N(0, τ²) for b and δ ~ N(b, σ²), the posterior mean of b is ``w·δ`` with
    ``w = τ² / (τ² + σ²)`` and variance ``w·σ²``. So a simulation that reproduces what it was not
    fitted to keeps its correction (w near 1 on the simulator round trips), and one that does not
    gives way to the least squares smoothly, with no threshold on any ratio: a short procedural
    recording whose frames undersample the scene (0.80x / 0.89x the observed ON / OFF events, the
    reverse regression 10-12 % off) keeps about a quarter of its ON correction and none of its OFF
    one. A slope that is not positive (the statistic does not grow with c) leaves the correction
    unidentified: w = 0."""
    c_ind = np.asarray(c_ind, np.float64)
    c_ls = np.asarray(rec["observed_statistic"], np.float64)
    fwd, rev_o, rev_s = (np.asarray(check[k], np.float64) for k in ("forward_observed", "reverse_observed",
                                                                      "reverse_simulated"))
    sim = np.asarray(rec.get("simulated_signal_events_on_off") or (np.nan, np.nan), np.float64)
    slope = _binding_slope(rec.get("iterations") or [])
    delta = c_ind - c_ls
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(obs_events > 0, sim / obs_events, np.nan)
        rt = float(sim.sum() / obs_events.sum()) if obs_events.sum() > 0 else float("nan")
        rho = np.sqrt(np.log(ratio) ** 2 + np.log(rev_o / rev_s) ** 2)
        sig = np.where(slope > 0, rho * c_ls / slope, np.inf)
        tau = np.abs(rev_o - fwd)
        w = tau ** 2 / (tau ** 2 + sig ** 2)
    # a statistic that cannot be computed leaves the correction unverified: not applied
    w = np.where(np.isfinite(w), w, 0.0)
    out = c_ls + w * delta
    return (float(out[0]), float(out[1])), {
        "method": "posterior mean of the least squares' bias: prior N(0, tau^2), tau the errors-in-variables bracket "
                  "|reverse - forward|; the correction's error sigma = rho * c_ls / slope, rho the simulation's "
                  "relative misfit of the events per polarity and the reverse regression (not fitted); "
                  "weight tau^2 / (tau^2 + sigma^2)",
        "weight": [float(v) for v in w], "correction": [float(v) for v in delta], "sigma": [_f(v) for v in sig],
        "tau": [_f(v) for v in tau], "relative_misfit": [_f(v) for v in rho], "binding_slope": [_f(v) for v in slope],
        "posterior_std": [_f(v) for v in np.sqrt(w * np.where(np.isfinite(sig), sig, 0.0) ** 2)],
        "unshrunk": [float(v) for v in c_ind], "least_squares": [float(v) for v in c_ls],
        "reverse_observed": [_f(v) for v in rev_o], "reverse_simulated": [_f(v) for v in rev_s],
        "simulated_to_observed_events_on_off": [_f(v) for v in ratio], "simulated_to_observed_events": _f(rt)}


def _observed_signal(D, ints, dd, r_on, r_off):
    """Signal events (ON, OFF) the well-exposed pixel-intervals hold between the frame times shifted by
    ``dd``, less the noise events expected there (the simulated statistic's counterpart)."""
    tot = np.zeros(2)
    for j in ints:
        _, g0 = D.frame(j)
        _, g1 = D.frame(j + 1)
        g = g0 & g1
        a, b = _find(D.t, [D.tau[j] + dd, D.tau[j + 1] + dd])
        sel = g[D.pix[a:b]]
        n_on = float(np.count_nonzero(D.on[a:b][sel]))
        k = float(np.count_nonzero(g)) * (D.tau[j + 1] - D.tau[j]) * 1e-6
        tot += (n_on - r_on * k, float(np.count_nonzero(sel)) - n_on - r_off * k)
    return tot


def _vertex(xs, ys, half=4):
    """Abscissa of the least-squares parabola's vertex through the ``2·half + 1`` points around the
    minimum of ``ys`` (the minimum's own abscissa if the parabola does not open upward), kept within them."""
    ys = np.asarray(ys, np.float64)
    a = int(np.nanargmin(ys))
    lo, hi = max(a - half, 0), min(a + half + 1, len(ys))
    x = np.asarray(xs[lo:hi], np.float64) - float(xs[a])
    y = ys[lo:hi]
    ok = np.isfinite(y)
    if ok.sum() < 3:
        return float(xs[a])
    pc = np.polyfit(x[ok], y[ok], 2)
    if pc[0] <= 0:
        return float(xs[a])
    return float(xs[a]) + float(np.clip(-pc[1] / (2 * pc[0]), x[ok][0], x[ok][-1]))


def _binding(D, rows, ints, i0s, offs, d_obs, ii_obs, sig, r_on, r_off, seed, free_i0, free_d, iters=3,
             score_col=None):
    """Indirect inference on the whole estimate (δ, I0, c_on, c_off).

    The grid criterion's best (δ̂, Î0) and the least-squares thresholds are biased by the DVS
    quantiser itself (hysteresis: a reversal's first events come late, so later windows predict
    better; thresholds attenuated where few events fall per interval). The binding function
    θ -> (δ̂, Î0) is measured by simulation: events of the DVS model driven by the frames' own log
    path with the candidate θ (:func:`simulate_quantiser_events`) go through the same grid
    search; θ moves by the difference between the observed and the simulated estimates until they
    agree. At each θ the thresholds are :func:`_indirect`'s on the observed counts between the
    frame times shifted by θ's latency."""
    c_span = (float(D.tau[ints[0]]), float(D.tau[ints[-1] + 1]))

    def observed_signal(dd, i_):
        return float(_observed_signal(D, ints, dd, r_on, r_off).sum())

    d, ii = float(d_obs), int(ii_obs)
    step = float(np.median(np.diff(offs))) if len(offs) > 1 else 1000.0
    # the observed estimate as the vertex of a parabola through the criterion near its best (a smooth
    # function of the data: the argmin of a flat curve jumps by steps)
    d_obs_v = float(d_obs) if score_col is None else _vertex(offs, score_col)
    d = d_obs_v
    # a cheap first look (one iteration, two replicates at the least-squares thresholds): a quantiser
    # that fires far from the observed events on the frames' path will not be trusted at the end either
    ls0 = _ls_at(D, rows, int(round(d)), ii, r_on, r_off)
    _, pre = _indirect(D, ints, float(i0s[ii]), ls0, sig, r_on, r_off, reps=2, iters=1, seed=seed)
    obs0 = observed_signal(int(round(d)), ii)
    ratio0 = pre["simulated_signal_events"] / obs0 if obs0 > 0 and pre["simulated_signal_events"] else float("nan")
    if not (abs(ratio0 - 1.0) <= 2 * SIM_EVENT_TOLERANCE):
        return None, {"method": pre["method"], "applied": False, "simulated_to_observed_events": _f(ratio0),
                      "reason": f"the quantiser simulated on the frames' own log path fires {ratio0:.2f}x the observed "
                                f"signal events at the least-squares thresholds (first look, tolerance "
                                f"{2 * SIM_EVENT_TOLERANCE:.0%}): the frames undersample the scene's changes; the "
                                f"least-squares thresholds and the grid's offset and I0 are reported"}, None, int(ii_obs)
    hist = []
    c, rec = None, None
    converged = False
    for it in range(iters + 1):
        ls = _ls_at(D, rows, int(round(d)), ii, r_on, r_off)
        final = it == iters or converged or not (free_i0 or free_d)
        # on the way, a rough correction (it only drives the simulated search); the full one at the end
        c, rec = _indirect(D, ints, float(i0s[ii]), ls, sig, r_on, r_off, seed=seed, c_init=c,
                           **({} if final else {"reps": 2, "iters": 2}))
        if final:
            break
        ev = simulate_quantiser_events(D, float(i0s[ii]), c[0], c[1], sigma=(sig.get("on") or 0.0, sig.get("off") or 0.0),
                                       latency_us=int(round(d)), rate_on_hz=r_on, rate_off_hz=r_off, seed=seed + it,
                                       k_range=(ints[0], ints[-1] + 1))
        ev = ev[(ev["t"] >= D.t0_ev) & (ev["t"] <= D.t1_ev)]
        if len(ev) == 0:
            break
        S = _SimData(D, ev)
        # the simulated search: δ on a window of the grid's step centred on the observed estimate, not
        # clipped to the grid (the simulated criterion's best lies there when θ is right), and I0 on a
        # window of the grid (only θ's I0 when I0 is not free)
        a_obs = int(np.argmin(np.abs(np.asarray(offs) - d_obs)))
        oi = [int(offs[a_obs] + step * k) for k in range(-BINDING_WINDOW[0], BINDING_WINDOW[0] + 1)]
        ij = (list(range(max(ii_obs - BINDING_WINDOW[1], 0), min(ii_obs + BINDING_WINDOW[1] + 1, len(i0s))))
              if free_i0 else [ii])
        _, _, sc, _ = _search(S, ints, tuple(i0s[k] for k in ij), tuple(oi), r_on, r_off, None, None)
        if not np.isfinite(sc).any():
            break
        a_s, i_s = np.unravel_index(np.nanargmin(sc), sc.shape)
        d_sim = _vertex(oi, sc[:, i_s])
        i_s = ij[i_s]
        hist.append({"theta": [d, float(i0s[ii])], "c": list(c), "simulated_estimate": [_f(d_sim), float(i0s[i_s])]})
        nd = d + (d_obs_v - d_sim) if free_d else d
        ni = int(np.clip(ii + (ii_obs - i_s), 0, len(i0s) - 1)) if free_i0 else ii
        converged = abs(nd - d) < 0.5 * step and ni == ii
        d, ii = float(np.clip(nd, offs[0], offs[-1])), ni
    obs = observed_signal(int(round(d)), ii)
    simd = rec.get("simulated_signal_events")
    ratio = simd / obs if simd is not None and obs > 0 else float("nan")
    rec = {**rec, "binding_iterations": hist, "span_us": list(c_span), "observed_signal_events": obs,
           "simulated_to_observed_events": _f(ratio)}
    if not (abs(ratio - 1.0) <= SIM_EVENT_TOLERANCE):
        # the frames do not sample the motion finely enough for the simulated quantiser to see what the
        # pixels saw (it misses the changes between frames): no correction, said so
        rec["applied"] = False
        rec["reason"] = (f"the quantiser simulated on the frames' own log path fires {ratio:.2f}x the observed signal "
                         f"events (tolerance {SIM_EVENT_TOLERANCE:.0%}): the frames undersample the scene's changes, "
                         f"so the correction cannot be trusted; the least-squares thresholds and the grid's offset "
                         f"and I0 are reported")
        return None, rec, None, int(ii_obs)
    rec["applied"] = True
    return c, rec, int(round(d)), ii


def _reverse(rows, counts, ii):
    """Reverse regression: counts on the frame change (both polarities), the other EIV bound."""
    a = np.zeros((2, 2))
    y = np.zeros(2)
    for r, (no, nf) in zip(rows, counts):
        dl = r["L1"][ii] - r["L0"][ii]
        zp, zn = np.maximum(dl, 0), np.maximum(-dl, 0)
        a += [[no @ zp, -(nf @ zp)], [no @ zn, -(nf @ zn)]]
        y += [dl @ zp, dl @ zn]
    try:
        v = np.linalg.solve(a, y)
        return {"c_on": _f(v[0]), "c_off": _f(v[1]),
                "method": "instruments (ΔL+, ΔL−) for (N_on, N_off): the reverse regression's bound"}
    except np.linalg.LinAlgError:
        return {"c_on": None, "c_off": None, "method": "singular"}


def _per_pixel_sums(D, rows, counts, ii, r_on, r_off):
    """Per-pixel noise-corrected sums over the event-bearing pixel-intervals (a pixel's intervals
    without events add only the noise moments λ² − λ, left out here), two halves (even/odd intervals) too."""
    keys = ("soo", "sff", "sof", "bo", "bf", "sll", "n", "k_on", "k_off")
    tot = {k: np.zeros(D.n) for k in keys}
    halves = [{k: np.zeros(D.n) for k in keys} for _ in range(2)]
    for q, (r, (no, nf)) in enumerate(zip(rows, counts)):
        idx = r["idx"]
        if not idx.size:
            continue
        dl = r["L1"][ii] - r["L0"][ii]
        lo, lf = r_on * r["dt_s"], r_off * r["dt_s"]
        vals = {"soo": (no - lo) ** 2 - lo, "sff": (nf - lf) ** 2 - lf, "sof": (no - lo) * (nf - lf),
                "bo": (no - lo) * dl, "bf": (nf - lf) * dl, "sll": dl * dl, "n": np.ones(idx.size),
                "k_on": (no > 0.5).astype(float), "k_off": (nf > 0.5).astype(float)}
        for k, v in vals.items():
            np.add.at(tot[k], idx, v)
            np.add.at(halves[q % 2][k], idx, v)
    return {"tot": tot, "halves": halves, "shape": (D.h, D.w), "profile": D.prof.name}


def _bootstrap(pp, n_boot, seed):
    if pp is None or n_boot < 2:
        return None, None
    tot = pp["tot"]
    used = np.flatnonzero(tot["n"] > 0)
    if used.size < 2:
        return None, None
    S = np.stack([tot[k][used] for k in ("soo", "sff", "sof", "bo", "bf")], 1)
    rng = np.random.default_rng(seed)
    out = []
    chunk = max(1, min(50, (4 << 20) // used.size))
    for k in range(0, n_boot, chunk):
        W = rng.poisson(1.0, size=(min(chunk, n_boot - k), used.size)).astype(np.float64)
        a, b = _nnls2(*(W @ S).T)
        out.append(np.stack([a, b], 1))
    bs = np.concatenate(out)
    return _f(np.std(bs[:, 0], ddof=1)), _f(np.std(bs[:, 1], ddof=1))


def shrink_per_pixel(model: CameraModel, *, min_intervals: int = 2, min_decorrelation: float = 0.05,
                     c_range=(0.01, 3.0), tau2=None):
    """Per-pixel thresholds shrunk toward the pooled ones by their own uncertainty (empirical Bayes).

    Each identified pixel's least-squares pair ``ĉ_i`` (its own noise-corrected sums) has a
    sampling variance ``s_i² = σ_res²·[(XᵀX)⁻¹]`` (σ_res² the pooled residual variance per
    pixel-interval); the pixels' true spread ``τ²`` is the covariance of two independent halves'
    estimates (even and odd intervals: their errors are independent, so it drops out). The
    posterior mean under a normal prior N(pooled, τ²) is ``pooled + τ²/(τ² + s_i²)·(ĉ_i − pooled)``
    (James & Stein 1961; Efron & Morris, JASA 1973). A pixel the data do not identify keeps the
    pooled value, and so does every pixel when the halves show no spread (τ² <= 0). ``tau2``
    (ON, OFF) replaces the measured spread (a prior known from another recording).

    Returns ``(c_on (H, W), c_off (H, W), identified (H, W) bool, record)``."""
    tau2_given = tau2
    pp = model.per_pixel
    if pp is None:
        raise ValueError("shrink_per_pixel needs a model estimated with per_pixel=True")
    h, w = pp["shape"]
    pooled = (model.c_on, model.c_off)

    def est(s):
        a, b = _nnls2(s["soo"], s["sff"], s["sof"], s["bo"], s["bf"])
        det = s["soo"] * s["sff"] - s["sof"] ** 2
        with np.errstate(invalid="ignore", divide="ignore"):
            rho2 = np.where((s["soo"] > 0) & (s["sff"] > 0), s["sof"] ** 2 / (s["soo"] * s["sff"]), 1.0)
        ok = ((s["k_on"] >= min_intervals) & (s["k_off"] >= min_intervals) & (1 - rho2 >= min_decorrelation)
              & (det > 0) & (a >= c_range[0]) & (a <= c_range[1]) & (b >= c_range[0]) & (b <= c_range[1]))
        return a, b, ok, det

    t = pp["tot"]
    a, b, ok, det = est(t)
    res = t["sll"] - 2 * a * t["bo"] + 2 * b * t["bf"] + a * a * t["soo"] + b * b * t["sff"] - 2 * a * b * t["sof"]
    dof = t["n"][ok].sum() - 2 * ok.sum()
    s2 = float(res[ok].sum() / dof) if ok.any() and dof > 0 else math.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        v_on = np.where(ok, s2 * t["sff"] / det, np.inf)
        v_off = np.where(ok, s2 * t["soo"] / det, np.inf)
    a1, b1, ok1, _ = est(pp["halves"][0])
    a2, b2, ok2, _ = est(pp["halves"][1])
    # the per-pixel least squares carry the pooled least squares' quantiser bias: where the pooled
    # value was corrected, each pixel's estimate (and its spread and variance) is scaled by the same
    # factor, so that the shrinkage pulls toward the pooled value on one scale
    qc = model.quantiser_correction or {}
    ls_ = model.least_squares or {}
    k_on = k_off = 1.0
    if qc.get("applied") and (ls_.get("c_on") or 0) > 0 and (ls_.get("c_off") or 0) > 0:
        k_on, k_off = model.c_on / ls_["c_on"], model.c_off / ls_["c_off"]
    a, a1, a2, v_on = a * k_on, a1 * k_on, a2 * k_on, v_on * k_on ** 2
    b, b1, b2, v_off = b * k_off, b1 * k_off, b2 * k_off, v_off * k_off ** 2
    both = ok1 & ok2
    tau2 = {}
    for name, x, y in (("on", a1, a2), ("off", b1, b2)):
        if both.sum() >= 30:
            xx, yy = x[both], y[both]
            tau2[name] = float(np.mean((xx - xx.mean()) * (yy - yy.mean())))
        else:
            tau2[name] = 0.0
    if tau2_given is not None:
        tau2 = {"on": float(tau2_given[0]), "off": float(tau2_given[1])}
    out = []
    for j, (name, c, v) in enumerate((("on", a, v_on), ("off", b, v_off))):
        t2 = max(tau2[name], 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            k = np.where(ok & np.isfinite(v), t2 / (t2 + v), 0.0) if t2 > 0 else np.zeros(c.shape)
        out.append((pooled[j] + k * (np.where(ok, c, pooled[j]) - pooled[j])).reshape(h, w))
    record = {"method": "empirical Bayes: pooled + tau^2/(tau^2 + s_i^2) (c_i - pooled); tau^2 = covariance of two "
                        "halves' per-pixel estimates; s_i^2 from the pooled residual variance",
              "identified_pixels": int(ok.sum()), "pixels_both_halves": int(both.sum()),
              "tau2_on": tau2["on"], "tau2_off": tau2["off"], "residual_var": _f(s2) if np.isfinite(s2) else None,
              "quantiser_scale": [float(k_on), float(k_off)],
              "profile": pp.get("profile", "")}
    return out[0], out[1], ok.reshape(h, w), record


def simulate_quantiser_events(D, i0, c_on, c_off, *, sigma=(0.0, 0.0), latency_us=0, rate_on_hz=0.0,
                              rate_off_hz=0.0, seed=0, k_range=None):
    """Events of the DVS model (eq. 1) driven by the frames' own log path ``ln(I_k + I0)``, cubic
    between frame times (:func:`_path_counts`), each pixel with a random initial phase and N(c, σ) thresholds,
    stamped ``latency_us`` late, plus Poisson noise events: the recording the camera model says
    this camera would have made of what its frames show (EVENT_DTYPE, sorted)."""
    from ..events import EVENT_DTYPE
    rng = np.random.default_rng([int(seed), 36])
    k0, k1 = (0, len(D.tau) - 1) if k_range is None else k_range
    con = np.maximum(c_on + sigma[0] * rng.standard_normal(D.n), 0.01)
    coff = np.maximum(c_off + sigma[1] * rng.standard_normal(D.n), 0.01)

    def L(k):
        c_, _ = D.frame(k)
        return np.log(D.lut[c_.astype(np.int64)] * D.scale[k] + i0)

    Lk = {k: L(k) for k in range(max(k0 - 1, 0), min(k1 + 1, len(D.tau) - 1) + 1)}

    def samples():
        # the Catmull-Rom cubic through the neighbouring frames (as :func:`_path_counts`), PATH_SUBSTEPS
        # points per frame interval, linear between them
        for k in range(k0, k1):
            p0, p1, p2, p3 = Lk[max(k - 1, min(Lk))], Lk[k], Lk[k + 1], Lk[min(k + 2, max(Lk))]
            a1, a2, a3 = 0.5 * (p2 - p0), 0.5 * (2 * p0 - 5 * p1 + 4 * p2 - p3), 0.5 * (3 * (p1 - p2) + p3 - p0)
            ta, tb = float(D.tau[k]), float(D.tau[k + 1])
            for m in range(1, PATH_SUBSTEPS + 1):
                s_ = m / PATH_SUBSTEPS
                yield ta + s_ * (tb - ta), (p2 if m == PATH_SUBSTEPS else p1 + s_ * (a1 + s_ * (a2 + s_ * a3)))

    x0 = Lk[k0]
    t0 = float(D.tau[k0])
    ref = x0 - (rng.random(D.n) * (con + coff) - coff)
    ts, ps, pol = [], [], []
    for t1, x1 in samples():
        up = np.floor(np.maximum(x1 - ref, 0.0) / con).astype(np.int64)
        dn = np.floor(np.maximum(ref - x1, 0.0) / coff).astype(np.int64)
        slope = np.where(x1 != x0, (t1 - t0) / np.where(x1 != x0, x1 - x0, 1.0), 0.0)
        for cnt, sign, cc in ((up, 1, con), (dn, -1, coff)):
            pix = np.repeat(np.arange(D.n), cnt)
            if pix.size:
                m = np.arange(pix.size) - np.repeat(np.cumsum(cnt) - cnt, cnt) + 1
                lev = ref[pix] + sign * m * cc[pix]
                tt = t0 + (lev - x0[pix]) * slope[pix]
                ts.append(np.clip(tt, t0, t1))
                ps.append(pix)
                pol.append(np.full(pix.size, sign, np.int8))
        ref = ref + up * con - dn * coff
        x0, t0 = x1, t1
    span = (float(D.tau[k0]), float(D.tau[k1]))
    for rate, sign in ((rate_on_hz, 1), (rate_off_hz, -1)):
        if rate > 0:
            m = int(rng.poisson(rate * D.n * (span[1] - span[0]) * 1e-6))
            ts.append(rng.uniform(span[0], span[1], m))
            ps.append(rng.integers(0, D.n, m))
            pol.append(np.full(m, sign, np.int8))
    t = np.concatenate(ts) if ts else np.zeros(0)
    ev = np.zeros(t.size, EVENT_DTYPE)
    ev["t"] = np.rint(t + latency_us).astype(np.int64)
    p_ = np.concatenate(ps) if ps else np.zeros(0, np.int64)
    ev["x"] = p_ % D.w
    ev["y"] = p_ // D.w
    ev["p"] = np.concatenate(pol) if pol else np.zeros(0, np.int8)
    return ev[np.argsort(ev["t"], kind="stable")]


def plot_camera_model(recording, model: CameraModel, path, *, profile=None, title: str | None = None):
    """PNG of the model: per intensity band (quartiles of the pixel-intervals' mean frame intensity)
    the frames' log change against the change the events predict (c_on·N_on − c_off·N_off at the
    chosen δ and I0, noise removed) with the identity line and the band's own least-squares
    thresholds; the residuals; the criterion over (δ, I0) with the choice; every value with its
    uncertainty."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pathlib import Path

    from .._util.atomic import atomic_path

    rec = recording
    if isinstance(rec, (str, bytes)) or hasattr(rec, "__fspath__"):
        from ..formats import read
        rec = read(rec)
    D = _Data(rec, profile, model.excluded_frames, None)
    ints = D.covered(model.time_offset_us, model.time_offset_us)
    if len(ints) > MAX_INTERVALS:
        ints = [ints[i] for i in np.linspace(0, len(ints) - 1, MAX_INTERVALS).round().astype(int)]
    d = int(model.time_offset_us)
    rows = _collect(D, ints, (model.intensity_offset,), d, d)
    r_on, r_off = model.noise.get("rate_on_hz", 0.0), model.noise.get("rate_off_hz", 0.0)
    xs, ys, inten = [], [], []
    for r in rows:
        no, nf = D.weighted_counts(r["j"], d, r["idx"])
        lo, lf = r_on * r["dt_s"], r_off * r["dt_s"]
        xs.append(model.c_on * (no - lo) - model.c_off * (nf - lf))
        ys.append(r["L1"][0] - r["L0"][0])
        inten.append(0.5 * (np.exp(r["L0"][0]) + np.exp(r["L1"][0])) - model.intensity_offset)
    x = np.concatenate(xs) if xs else np.zeros(0)
    y = np.concatenate(ys) if ys else np.zeros(0)
    it = np.concatenate(inten) if inten else np.zeros(0)
    edges = np.quantile(it, [0.25, 0.5, 0.75]) if it.size else np.zeros(3)
    band = np.searchsorted(edges, it)
    fig, axes = plt.subplots(2, 3, figsize=(13, 8), dpi=100)
    lim = float(np.percentile(np.abs(np.concatenate([x, y])), 99.5)) * 1.1 if x.size else 1.0
    bounds = [0.0, *edges.tolist(), float(it.max()) if it.size else 1.0]
    for b in range(4):
        ax = axes.flat[[0, 1, 3, 4][b]]
        m = band == b
        if m.sum():
            ax.hexbin(x[m], y[m], gridsize=45, extent=(-lim, lim, -lim, lim), bins="log", cmap="viridis", mincnt=1)
        ax.plot([-lim, lim], [-lim, lim], color="tab:red", lw=1.2, label="model (identity)")
        cb = (model.bands or {}).get("bands_c") or []
        ib = list((model.bands or {}).get("intensity_offsets") or [])
        k = ib.index(model.intensity_offset) if model.intensity_offset in ib else None
        extra = ""
        if k is not None and k < len(cb) and b < len(cb[k]):
            extra = f"\nthis band's own LS: ON {cb[k][b][0]:.3f}, OFF {cb[k][b][1]:.3f}"
        ax.set_title(f"intensity {bounds[b]:.3g}-{bounds[b + 1]:.3g} (frame-linear), {int(m.sum())} "
                     f"pixel-intervals{extra}", fontsize=8.5)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_xlabel("events' predicted change c_on N_on - c_off N_off (ln)", fontsize=8)
        ax.set_ylabel("frames' log change (ln)", fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    ax = axes[0, 2]
    res = y - x
    if res.size:
        ax.hist(np.clip(res, -lim, lim), bins=80, color="tab:gray")
    ax.axvline(0, color="tab:red", lw=1)
    ax.set_title(f"residuals: RMS {float(np.sqrt(np.mean(res ** 2))) if res.size else float('nan'):.3f} ln "
                 f"(one threshold of quantisation at each end)", fontsize=8.5)
    ax.set_xlabel("frames' log change - predicted (ln)", fontsize=8)
    ax.set_ylabel("pixel-intervals", fontsize=8)
    ax = axes[1, 2]
    sg = np.array(model.score_grid, float)
    if sg.size and np.isfinite(sg).any():
        im = ax.imshow(sg.T, aspect="auto", origin="lower", cmap="magma_r",
                       extent=(model.offsets_us[0] / 1e3, model.offsets_us[-1] / 1e3, -0.5, len(model.intensity_offsets) - 0.5))
        fig.colorbar(im, ax=ax, label="cross-fitted RMS code error")
        ii = list(model.intensity_offsets).index(model.intensity_offset) if model.intensity_offset in model.intensity_offsets else 0
        ax.plot([model.time_offset_us / 1e3], [ii], "c*", ms=12, label=f"chosen: {model.time_offset_us} us")
        yt = list(range(0, len(model.intensity_offsets), max(1, len(model.intensity_offsets) // 6)))
        ax.set_yticks(yt)
        ax.set_yticklabels([f"{model.intensity_offsets[i]:.2g}" for i in yt], fontsize=7)
        ax.legend(fontsize=7, loc="best", framealpha=0.6)  # "best" keeps clear of the star (an I0 on the top edge)
    ax.set_xlabel("frame time offset (ms)", fontsize=8)
    ax.set_ylabel("I0 (frame-linear)", fontsize=8)
    sd_on = f" +- {model.c_on_std:.3f}" if model.c_on_std is not None else ""
    sd_off = f" +- {model.c_off_std:.3f}" if model.c_off_std is not None else ""
    sg_ = model.mismatch_sigma or {}
    sig = ("sigma ON %.3f OFF %.3f" % (sg_["on"], sg_["off"])) if sg_.get("on") is not None else "sigma not identified"
    lat = f"{model.latency_us} us" if model.latency_us is not None else "not identified"
    ax.set_title(f"ON {model.c_on:.3f}{sd_on}, OFF {model.c_off:.3f}{sd_off} (ln), I0 {model.intensity_offset:.3g}\n"
                 f"offset {model.time_offset_us} us, latency {lat}, {sig}", fontsize=8.5)
    fig.suptitle(title or f"camera model: {model.n_pixel_intervals} event-bearing pixel-intervals in "
                          f"{model.n_intervals} frame intervals", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
