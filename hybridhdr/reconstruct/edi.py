"""EDI: the event-based double integral (Pan et al., CVPR 2019) for deblurring frames with events.

A frame exposed over ``[t_s, t_e)`` (T = t_e - t_s) records the mean of the latent intensity. In
the log-offset domain of the AKF (events are crossings of ``c`` in log(I + I0)), the latent image
at time t is ``I(t) + I0 = (I(t_s) + I0) exp(c E(t))``, with E(t) the signed event count of the
pixel in ``[t_s, t)``. Averaging over the exposure (the double integral),

    B + I0 = (I(t_s) + I0) · (1/T) ∫_{t_s}^{t_e} exp(c E(t)) dt,

so ``log(I(t_s) + I0) = log(B + I0) - log J`` with ``J = (1/T) ∫ exp(c E) dt``, normalised by the
**true exposure T** (not by the span of the events, as the authors' code does, which biases
pixels with few events), and ``log(I(t) + I0) = log(I(t_s) + I0) + c E(t)`` anywhere in the
exposure.

The threshold c is either given or estimated per frame by minimising a sharpness energy
λ·TV(L) - ρ(edges(L), edges(M)) (total variation of the latent log image minus the normalised
correlation of its Sobel edges with those of the event map M) over a bounded interval with a
golden-section search, as Pan et al. do with a Fibonacci search in their code.

References
----------
L. Pan, C. Scheerlinck, X. Yu, R. Hartley, M. Liu, Y. Dai, "Bringing a Blurry Frame Alive at
High Frame-Rate with an Event Camera", CVPR 2019, doi:10.1109/CVPR.2019.00698.
Z. Wang, Y. Ng, C. Scheerlinck, R. Mahony, "An Asynchronous Kalman Filter for Hybrid Event
Cameras", ICCV 2021, doi:10.1109/ICCV48922.2021.00050 (§4.1, uses EDI for frame augmentation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _augment_kernels as AK
from .event_arrays import EventArrays
from ..camera.encoding import frames_to_codes
from .params import DEFAULT_INTENSITY_OFFSET, _ParamsMixin

__all__ = ["EDIParams", "edi_integral", "edi_log_latent", "edi_latent", "exposure_log_corrections",
           "sharpness_energy", "estimate_threshold", "golden_section_minimize", "EDIEngine"]

_GOLD = (math.sqrt(5.0) - 1.0) / 2.0  # 0.618...


@dataclass(frozen=True, kw_only=True)
class EDIParams(_ParamsMixin):
    """Parameters of EDI deblurring (Pan et al., CVPR 2019, doi:10.1109/CVPR.2019.00698).

    Parameters
    ----------
    contrast_threshold : float or None
        c in natural-log units; ``None`` estimates it per frame by the sharpness search.
    threshold_min, threshold_max : float
        Bounds of the search, log units (``davis-EDI-rs`` searches [0.1, 0.5]; we start at 0.05
        to cover sensitive biases).
    tv_weight : float
        λ of the sharpness energy λ·TV - edge correlation (Pan et al.'s ``TVnorm.m``: 0.2).
    search_tolerance : float
        Width of the final bracket of the golden-section search, log units.
    intensity_offset : float
        I0 of the log-offset domain log(I + I0) (AKF eq. 8), scaled-irradiance units.
    """

    _toml_table = "edi"

    contrast_threshold: float | None = None  # c, log units; None: per-frame search
    threshold_min: float = 0.05  # log units
    threshold_max: float = 0.5  # log units (ac-freeman/davis-EDI-rs)
    tv_weight: float = 0.2  # λ, Pan et al.'s TVnorm.m
    search_tolerance: float = 1e-3  # log units
    intensity_offset: float = DEFAULT_INTENSITY_OFFSET  # I0, AKF eq. 8

    def __post_init__(self):
        self._threshold_search()
        self._num("search_tolerance", lo=0, lo_open=True)
        self._num("intensity_offset", lo=0, lo_open=True)


def _check_exposure(t_start_us, t_end_us):
    for name, v in (("t_start_us", t_start_us), ("t_end_us", t_end_us)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise TypeError(f"{name} must be an int (µs), got {type(v).__name__}")
    if t_end_us < t_start_us:
        raise ValueError(f"exposure must have t_end_us >= t_start_us, got {t_start_us}..{t_end_us} µs")


def edi_integral(events: EventArrays, t_start_us: int, t_end_us: int, contrast_threshold: float, *,
                 thresholds=None):
    """J = (1/T) ∫_{t_s}^{t_e} exp(c E(t)) dt per pixel, and the signed count over the exposure.

    ``thresholds = (c_on, c_off)`` (scalars or float64 arrays of shape (H*W,)): ON and OFF events step the
    log intensity by their own thresholds, ``exp(c_on N_on(t) - c_off N_off(t))``, and
    ``contrast_threshold`` is unused.

    Parameters
    ----------
    events : EventArrays
    t_start_us, t_end_us : int
        Exposure ``[t_s, t_e)`` in µs; T = t_e - t_s (the true exposure; T = 0 gives J = 1).
    contrast_threshold : float
        c in log units.

    Returns
    -------
    J : ndarray of shape (H*W,), float64
        Dimensionless mean of exp(c E(t)) over the exposure (the EDI denominator).
    count : ndarray of shape (H*W,), int64
        Σσ of each pixel's events in ``[t_s, t_e)``.
    """
    _check_exposure(t_start_us, t_end_us)
    n = events.shape[0] * events.shape[1]
    count = np.zeros(n, np.int64)
    if t_end_us == t_start_us:
        return np.ones(n), count
    acc = np.zeros(n)
    t_last = np.full(n, float(t_start_us))
    i0, i1 = events.window(t_start_us, t_end_us)
    if thresholds is None:
        AK.edi_walk(events.t, events.x, events.y, events.p, i0, i1, events.shape[1], t_start_us, t_end_us,
                    float(contrast_threshold), count, t_last, acc)
    else:
        c_on, c_off = (np.ascontiguousarray(np.broadcast_to(np.asarray(c, np.float64), (n,))) for c in thresholds)
        AK.edi_walk_asym(events.t, events.x, events.y, events.p, i0, i1, events.shape[1], t_start_us, t_end_us,
                         c_on, c_off, count, np.zeros(n), t_last, acc)
    return acc / float(t_end_us - t_start_us), count


def edi_log_latent(blurred, events: EventArrays, t_start_us: int, t_end_us: int, contrast_threshold: float, *,
                   intensity_offset: float = DEFAULT_INTENSITY_OFFSET, log_blurred=None, thresholds=None):
    """Latent log image at the exposure start, log(I(t_s) + I0) = log(B + I0) - log J.

    Parameters
    ----------
    blurred : ndarray of shape (H, W) or (H*W,), float
        B, the frame's linear intensity (scaled irradiance, CRF already inverted).
    events, t_start_us, t_end_us, contrast_threshold
        As in :func:`edi_integral`.
    intensity_offset : float
        I0 (AKF eq. 8).
    log_blurred : ndarray of shape (H*W,), optional
        log(B + I0) precomputed (e.g. with the bias correction of eq. 8); overrides ``blurred``.
    thresholds : (c_on, c_off), optional
        Per-pixel ON and OFF thresholds (:func:`edi_integral`).

    Returns
    -------
    log_start : ndarray of shape (H*W,), float64
        log(I(t_s) + I0).
    count : ndarray of shape (H*W,), int64
        Σσ over the exposure, so that log(I(t_e) + I0) = log_start + c·count.
    """
    J, count = edi_integral(events, t_start_us, t_end_us, contrast_threshold, thresholds=thresholds)
    if log_blurred is None:
        b = np.asarray(blurred, dtype=np.float64).ravel()
        if b.shape[0] != J.shape[0]:
            raise ValueError(f"blurred frame has {b.shape[0]} pixels, the sensor {J.shape[0]}")
        log_blurred = np.log(b + float(intensity_offset))
    return log_blurred - np.log(J), count


def exposure_log_corrections(frames, events: EventArrays, c_on: float, c_off: float, *, min_events: int = 0) -> dict:
    """Per frame, the log correction that makes its exposure mean the latent image at mid-exposure.

    A frame exposed over ``[s_k, e_k)`` records the mean of the intensity over its exposure,
    ``B_k + I0 = (I(τ_k) + I0) · J_k`` with ``J_k = (1/T_k) ∫_{s_k}^{e_k} exp(E(τ_k, t)) dt`` and
    ``E(τ_k, t) = c_on N_on − c_off N_off`` the log change the pixel's events report from τ_k to t
    (negative before τ_k): the double integral of EDI (Pan et al., CVPR 2019) taken at the
    mid-exposure τ_k = ``frames.t_mid_us`` instead of at the exposure start. So

        ln(I(τ_k) + I0) = ln(B_k + I0) − ln J_k,

    whatever I0 (J is a ratio of intensities plus I0). ``−ln J_k`` is 0 at a pixel without events
    in the exposure (and for a frame without an exposure, ``t_end == t_start``), and elsewhere
    of the order of the log change within the exposure. A clipped frame bounds the exposure
    mean, so the same correction moves its bound.

    Parameters
    ----------
    frames : Frames
        With ``t_start_us`` / ``t_end_us`` the exposures (τ_k their midpoints).
    events : EventArrays
        The events (at least those inside the exposures), time-sorted.
    c_on, c_off : float
        ON and OFF thresholds (log units, > 0) of the filter's log model.
    min_events : int
        Correct a pixel only when at least this many events fell in the exposure (0: every pixel
        with one). Each event reads a log change of exactly c, so the correction carries a
        quantisation error of about c/√12, while a frame blurred by a ramp of Δ = n c is off its
        mid-exposure value by only ``ln(sinh(Δ/2)/(Δ/2)) ≈ Δ²/24``: below
        :func:`~hybridhdr.reconstruct.augment.deblur_min_events` events the correction costs more
        than it saves (the same rule as frame augmentation's deblurring).

    Returns
    -------
    dict ``{k: (pixels int64 (m,), correction float64 (m,))}`` for the frames k with an exposure
    and at least one pixel with ``max(min_events, 1)`` events inside it; the pixels are flattened
    row-major, only those (every other pixel's correction is 0).
    """
    if isinstance(min_events, bool) or not isinstance(min_events, (int, np.integer)) or min_events < 0:
        raise ValueError(f"min_events must be an int >= 0, got {min_events!r}")
    c_on, c_off = float(c_on), float(c_off)
    if not (math.isfinite(c_on) and math.isfinite(c_off) and c_on > 0 and c_off > 0):
        raise ValueError(f"c_on and c_off must be finite and > 0 (log units), got {c_on!r}, {c_off!r}")
    h, w = events.shape
    n = h * w
    out = {}
    s_all = np.asarray(frames.t_start_us, np.int64)
    e_all = np.asarray(frames.t_end_us, np.int64)
    mids = np.asarray(frames.t_mid_us, np.int64)
    for k in range(len(s_all)):
        s, e, tau = int(s_all[k]), int(e_all[k]), int(mids[k])
        if e <= s:
            continue
        i0, i1 = events.window(s, e)
        if i1 <= i0:
            continue
        pix = events.y[i0:i1].astype(np.int64) * w + events.x[i0:i1].astype(np.int64)
        n_ev = np.bincount(pix, minlength=n)
        touched = np.flatnonzero(n_ev >= max(int(min_events), 1))
        if touched.size == 0:
            continue
        count = np.zeros(n, np.int64)
        level = np.zeros(n)
        t_last = np.full(n, float(s))
        acc = np.zeros(n)
        c_on_a = np.full(n, c_on)
        c_off_a = np.full(n, c_off)
        AK.edi_walk_asym(events.t, events.x, events.y, events.p, i0, i1, w, s, e, c_on_a, c_off_a, count,
                         level, t_last, acc)
        j_start = acc[touched] / float(e - s)  # (1/T) ∫ exp(E(s_k, t)) dt
        # E(s_k, τ_k): the log change the events report from the exposure start to its middle
        j1 = i0 + int(np.searchsorted(events.t[i0:i1], tau, side="left"))
        step = np.where(events.p[i0:j1] > 0, c_on, -c_off)
        e_mid = np.bincount(pix[:j1 - i0], weights=step, minlength=n)[touched]
        # J_k = J_start · exp(−E(s_k, τ_k)): −ln J_k = E(s_k, τ_k) − ln J_start
        out[k] = (touched, e_mid - np.log(j_start))
    return out


def edi_latent(blurred, events: EventArrays, t_start_us: int, t_end_us: int, contrast_threshold: float,
               at_us: int, *, intensity_offset: float = DEFAULT_INTENSITY_OFFSET) -> np.ndarray:
    """Deblurred linear image I(t) at ``at_us`` ∈ [t_s, t_e] (EDI, Pan et al. 2019).

    ``I(t) + I0 = (B + I0) exp(c E(t)) / J`` (the double integral, normalised by the true
    exposure T). Returns float64 of shape (H, W) in the units of ``blurred``.

    Examples
    --------
    >>> import numpy as np
    >>> from hybridhdr.reconstruct.edi import edi_latent
    >>> from hybridhdr.reconstruct.event_arrays import EventArrays
    >>> ev = EventArrays([500], [0], [0], [1], (1, 1))      # one ON event half-way through
    >>> B = 0.5 * (0.2 + 1) + 0.5 * (0.2 + 1) * np.exp(0.1) - 1   # blurred from I(t_s) = 0.2
    >>> round(float(edi_latent(np.array([[B]]), ev, 0, 1000, 0.1, 0)[0, 0]), 12)
    0.2
    """
    if not t_start_us <= at_us <= t_end_us:
        raise ValueError(f"at_us must lie in the exposure [{t_start_us}, {t_end_us}] µs, got {at_us}")
    c = float(contrast_threshold)
    ls, _ = edi_log_latent(blurred, events, t_start_us, t_end_us, c, intensity_offset=intensity_offset)
    e, _ = events.counts(t_start_us, at_us)
    return (np.exp(ls + c * e) - float(intensity_offset)).reshape(events.shape)


def _sobel_mag(img):
    from scipy.ndimage import sobel
    return np.hypot(sobel(img, axis=0, mode="nearest"), sobel(img, axis=1, mode="nearest"))


def sharpness_energy(log_image, event_map, tv_weight: float = 0.2) -> float:
    """λ·TV(L) - ρ(|∇L|, M): lower is sharper (after Pan et al. 2019).

    Parameters
    ----------
    log_image : ndarray of shape (H, W)
        Latent log image L at the reference time τ.
    event_map : ndarray of shape (H, W)
        Events per pixel in a short window around τ, M: it marks where the edges are at τ.
    tv_weight : float
        λ.

    Returns
    -------
    float
        ``tv_weight * mean(|∂x L| + |∂y L|) - corr``, where ``corr`` is the normalised
        correlation (in [0, 1]) of the Sobel gradient magnitude of L with M (0 when either is
        flat).

    Notes
    -----
    TV alone favours small c (the blurred image has the least variation); the correlation
    term rewards edges where the events say they are at τ. Over- and under-corrected images
    gain ghost edges, which raise TV faster than they raise the correlation, so the energy has
    its minimum at the true c on scenes with separated edges (tests/reconstruct/test_edi.py).
    Unlike Pan et al., M is not Sobel-filtered: it is already an edge map, and its own edges
    lie half a pixel either side of the true edges.
    """
    L = np.asarray(log_image, dtype=np.float64)
    tv = 0.0
    if L.shape[1] > 1:
        tv += float(np.abs(np.diff(L, axis=1)).sum())
    if L.shape[0] > 1:
        tv += float(np.abs(np.diff(L, axis=0)).sum())
    tv /= L.size
    gl = _sobel_mag(L)
    gm = np.asarray(event_map, dtype=np.float64)
    den = math.sqrt(float((gl * gl).sum()) * float((gm * gm).sum()))
    corr = float((gl * gm).sum()) / den if den > 0 else 0.0
    return float(tv_weight) * tv - corr


def golden_section_minimize(f, lo: float, hi: float, tol: float, max_iter: int = 200):
    """Minimise a unimodal ``f`` on ``[lo, hi]`` by golden-section search.

    Returns ``(x_best, f_best, n_evaluations)``; the bracket shrinks by 0.618 per evaluation until
    its width is below ``tol``. The end points are evaluated too, so a minimum on the boundary of
    a monotone ``f`` is found.
    """
    if not hi > lo:
        raise ValueError(f"golden-section bracket must have hi > lo, got [{lo}, {hi}]")
    a, b = float(lo), float(hi)
    x1 = b - _GOLD * (b - a)
    x2 = a + _GOLD * (b - a)
    f1, f2 = f(x1), f(x2)
    n = 2
    while b - a > tol and n < max_iter:
        if f1 <= f2:
            b, x2, f2 = x2, x1, f1
            x1 = b - _GOLD * (b - a)
            f1 = f(x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + _GOLD * (b - a)
            f2 = f(x2)
        n += 1
    cands = [(f1, x1), (f2, x2), (f(lo), float(lo)), (f(hi), float(hi))]
    fb, xb = min(cands)
    return xb, fb, n + 2


def estimate_threshold(blurred, events: EventArrays, t_start_us: int, t_end_us: int, *,
                       bounds=(0.05, 0.5), tv_weight: float = 0.2, tol: float = 1e-3,
                       intensity_offset: float = DEFAULT_INTENSITY_OFFSET, log_blurred=None,
                       event_window_fraction: float = 0.125):
    """Contrast threshold of one frame minimising :func:`sharpness_energy` of its EDI latent image.

    The energy is evaluated on the latent log image at mid-exposure τ,
    ``log(B + I0) - log J(c) + c E(τ)``, against the map of events in
    ``[τ - f T/2, τ + f T/2)`` with ``f = event_window_fraction``, by golden-section search
    within ``bounds`` to a bracket of ``tol``.

    Returns
    -------
    c : float
        The estimate, in log units, within ``bounds``.
    energy : float
        The energy at ``c``.
    """
    _check_exposure(t_start_us, t_end_us)
    lo, hi = float(bounds[0]), float(bounds[1])
    if not 0 < lo < hi:
        raise ValueError(f"bounds must satisfy 0 < lo < hi (log units), got {bounds}")
    shape = events.shape
    mid = (int(t_start_us) + int(t_end_us)) // 2
    e_mid, _ = events.counts(t_start_us, mid)
    half = max(int(round(float(event_window_fraction) * (t_end_us - t_start_us) / 2)), 1)
    _, m = events.counts(mid - half, mid + half)
    emap = m.reshape(shape).astype(np.float64)

    def energy(c):
        ls, _ = edi_log_latent(blurred, events, t_start_us, t_end_us, c, intensity_offset=intensity_offset,
                               log_blurred=log_blurred)
        return sharpness_energy((ls + c * e_mid).reshape(shape), emap, tv_weight)

    c, f, _ = golden_section_minimize(energy, lo, hi, tol)
    return c, f


def _nearest_frame(t_us: int, t_start, t_end) -> int:
    """Index of the exposure containing ``t_us`` or, between exposures, the nearest one."""
    k = int(np.searchsorted(t_start, t_us, side="right")) - 1
    if k < 0:
        return 0
    if t_us <= t_end[k] or k + 1 >= len(t_start):
        return k
    return k if t_us - t_end[k] <= t_start[k + 1] - t_us else k + 1


class EDIEngine:
    """``method="edi"``: high-rate video from each blurred frame and its events.

    The output at t uses the frame whose exposure contains t (or the nearest exposure):
    ``log(I(t) + I0) = log(I(t_s) + I0) + c·Σσ[t_s, t)`` (Pan et al.'s EDI, extended outside the
    exposure by integrating events, with a negative sum for t < t_s). Needs the events in memory.
    Conforms to the engine protocol of :func:`hybridhdr.reconstruct._engine.drive` with
    ``uses_events = False`` (it reads its own in-memory events).
    """

    uses_events = False

    def __init__(self, shape, frames, events: EventArrays, profile, params: EDIParams):
        self.shape = (int(shape[0]), int(shape[1]))
        self.params = params
        codes = frames_to_codes(frames, self.shape)
        order = np.argsort(frames.t_start_us, kind="stable")
        self.t_start = frames.t_start_us[order]
        self.t_end = frames.t_end_us[order]
        self._codes = codes[order]
        self._escale = frames.exposure_scale()[order]  # each frame in the median frame's units (as the AKF)
        self.profile = profile
        self.events = events
        self.n_events = len(events)
        self.thresholds: dict[int, float] = {}
        self._cache: dict[int, np.ndarray] = {}

        class _Times:  # what drive() and reconstruct_iter read: frame times
            pass
        self.m = _Times()
        self.m.times_us = np.unique(frames.t_mid_us)

    def close(self):
        self._cache.clear()

    def start(self, t_start_us=None) -> int:
        return int(self.t_start[0])

    def next_switch_us(self):
        return None

    def process(self, *args) -> None:
        return None

    def _frame(self, k: int) -> np.ndarray:
        if k not in self._cache:
            pr = self.params
            B = self.profile.intensity(self._codes[k]).ravel()
            if self._escale[k] != 1.0:
                B = B * self._escale[k]
            ts, te = int(self.t_start[k]), int(self.t_end[k])
            c = pr.contrast_threshold
            if c is None:
                c, _ = estimate_threshold(B, self.events, ts, te, bounds=(pr.threshold_min, pr.threshold_max),
                                          tv_weight=pr.tv_weight, tol=pr.search_tolerance,
                                          intensity_offset=pr.intensity_offset)
            ls, _ = edi_log_latent(B, self.events, ts, te, c, intensity_offset=pr.intensity_offset)
            self.thresholds[k] = float(c)
            if len(self._cache) > 2:
                self._cache.pop(min(self._cache))
            self._cache[k] = ls
        return self._cache[k]

    def output(self, t_us: int) -> np.ndarray:
        k = _nearest_frame(int(t_us), self.t_start, self.t_end)
        ls = self._frame(k)
        c = self.thresholds[k]
        ts = int(self.t_start[k])
        if t_us >= ts:
            e, _ = self.events.counts(ts, int(t_us))
        else:
            e, _ = self.events.counts(int(t_us), ts)
            e = -e
        img = np.exp(ls + c * e) - self.params.intensity_offset
        return img.astype(np.float32).reshape(self.shape)
