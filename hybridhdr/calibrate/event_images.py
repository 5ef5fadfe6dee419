"""Event images of a blinking checkerboard, for calibrating an event camera.

A checkerboard shown on a monitor that blinks on and off makes every pixel on a white square fire
a burst of ON events when the board appears and a burst of OFF events when it disappears, while
pixels on black squares and off the board stay silent. Keeping, over one or more blink periods,
the pixels that fired **both** polarities gives a clean picture of the board for corner detection;
moving the board makes pixels fire one polarity only (an edge passing brightens or darkens it),
which is how motion is detected and such windows are rejected. This is the scheme of Prophesee's
``BlinkingFrameGenerator`` (Metavision SDK, "Calibration configs": ``min_num_blinking_pixels``
100, ON/OFF ratio 0.15, median radius 1), whose defaults :class:`BlinkParams` follows.

Pipeline (:func:`event_images`):

1. **Blink windows.** From trigger events when present (consecutive rising edges of the chosen
   channel, :func:`windows_from_triggers`), else from the periodicity of the event rate
   (:func:`blink_period_from_events`): the signed rate (ON − OFF events per bin) repeats with the
   blink period ``T`` and is anti-correlated at ``T/2`` (the total rate repeats every ``T/2``, so
   it is not used), so ``T`` is the highest autocorrelation peak within the allowed range, refined
   over many periods; the window phase puts the cuts half-way between an OFF burst and the next ON
   burst, so each window holds one ON and one OFF burst.
2. **Window statistics** (Numba kernel): per window, the number of *both*, *ON-only* and
   *OFF-only* pixels and the overlap of its *both* set with the previous window's.
3. **Rejection.** A window is rejected when it has fewer than ``min_both_pixels`` *both* pixels,
   or when its ON-only or its OFF-only pixels exceed ``max_single_ratio`` times its *both* pixels
   (motion, or a window cut through a burst).
4. **Pose segmentation.** Consecutive accepted windows form a static pose while the *both* sets of
   neighbouring windows overlap with an intersection-over-union of at least ``min_pose_iou``; a
   rejected window or a lower overlap (the board jumped) ends the pose. Runs shorter than
   ``min_windows_per_pose`` windows are dropped.
5. **Image.** Over the windows of a pose, the *both* pixels are accumulated (their ON + OFF event
   counts, or 1 per window with ``image_mode="binary"``), median filtered (radius
   ``median_radius``) and scaled to uint8.

Times are int64 µs and windows half-open ``[t0, t1)``; see ``docs/conventions.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..events import SensorSize, validate_events, validate_triggers

__all__ = ["BlinkParams", "BlinkPeriod", "WindowStats", "PoseImage", "BlinkResult",
           "blink_period_from_events", "blink_period_from_triggers", "windows_from_triggers",
           "windows_from_period", "window_statistics", "segment_poses", "accumulate_image",
           "event_images", "blink_image"]


@dataclass(frozen=True, kw_only=True)
class BlinkParams:
    """Parameters of the blinking-board event images.

    Defaults follow Prophesee's ``BlinkingFrameGenerator`` (Metavision SDK documentation,
    "Calibration configs") where it has an equivalent, and the setup advice in
    ``docs/calibrate.md`` (blink at 5-20 Hz, hold each pose 0.5-1 s).
    """

    #: a window needs at least this many *both* pixels (Prophesee ``min_num_blinking_pixels``)
    min_both_pixels: int = 100
    #: reject a window whose ON-only or OFF-only pixels exceed this fraction of its *both* pixels
    #: (Prophesee ON/OFF ratio 0.15)
    max_single_ratio: float = 0.15
    #: a pixel is *both* with at least this many events of each polarity in the window
    min_events_per_polarity: int = 1
    #: median filter radius in pixels (Prophesee median radius 1: a 3x3 median); 0 disables it
    median_radius: int = 1
    #: "count" (ON + OFF events of the *both* pixels; graded edges) or "binary" (windows fired)
    image_mode: str = "count"
    #: count mode: this percentile of the non-zero counts maps to white (255) and higher counts
    #: clip, so the per-pixel spread of event counts (threshold mismatch) inside the white squares
    #: does not texture them while partly covered edge pixels stay graded. With 3-8 events per
    #: pixel and transition, scaling by the 99th percentile left a texture that defeated the SB
    #: detector (``benchmarks/calibrate_rig.py``)
    count_white_percentile: float = 25.0
    #: blink period search range for the event-rate method, µs (5-20 Hz advised; 2-100 Hz accepted)
    min_period_us: int = 10_000
    max_period_us: int = 500_000
    #: bin width of the event-rate histogram, µs (period resolution before refinement)
    rate_bin_us: int = 500
    #: minimum normalised autocorrelation at the period for the blinking to count as found
    min_periodicity: float = 0.2
    #: trigger channel that marks the blinking (None: the channel with the most rising edges)
    trigger_channel: int | None = None
    #: a pose needs at least this many accepted consecutive windows
    min_windows_per_pose: int = 2
    #: consecutive windows of one pose overlap (IoU of their *both* pixel sets) at least this much
    min_pose_iou: float = 0.6

    def __post_init__(self):
        if int(self.min_both_pixels) < 1:
            raise ValueError(f"min_both_pixels must be >= 1, got {self.min_both_pixels}")
        if not 0.0 <= float(self.max_single_ratio):
            raise ValueError(f"max_single_ratio must be >= 0, got {self.max_single_ratio}")
        if int(self.min_events_per_polarity) < 1:
            raise ValueError(f"min_events_per_polarity must be >= 1, got {self.min_events_per_polarity}")
        if not 0 <= int(self.median_radius) <= 10:
            raise ValueError(f"median_radius must be in 0..10 pixels, got {self.median_radius}")
        if self.image_mode not in ("count", "binary"):
            raise ValueError(f"image_mode must be 'count' or 'binary', got {self.image_mode!r}")
        if not 0.0 < float(self.count_white_percentile) <= 100.0:
            raise ValueError(f"count_white_percentile must be in (0, 100], got {self.count_white_percentile}")
        if not 0 < int(self.min_period_us) < int(self.max_period_us):
            raise ValueError(f"need 0 < min_period_us < max_period_us, got {self.min_period_us}, "
                             f"{self.max_period_us}")
        if not 0 < int(self.rate_bin_us) <= int(self.min_period_us) // 4:
            raise ValueError(f"rate_bin_us must be in 1..min_period_us/4 = {int(self.min_period_us) // 4} "
                             f"µs, got {self.rate_bin_us}")
        if not 0.0 < float(self.min_periodicity) < 1.0:
            raise ValueError(f"min_periodicity must be in (0, 1), got {self.min_periodicity}")
        if int(self.min_windows_per_pose) < 1:
            raise ValueError(f"min_windows_per_pose must be >= 1, got {self.min_windows_per_pose}")
        if not 0.0 <= float(self.min_pose_iou) <= 1.0:
            raise ValueError(f"min_pose_iou must be in [0, 1], got {self.min_pose_iou}")


@dataclass(frozen=True)
class BlinkPeriod:
    """The blink period found: ``period_us`` (float µs), the start of the first window
    ``phase_us`` (absolute µs), the method (``"triggers"`` or ``"event_rate"``) and the
    normalised autocorrelation at the period (``periodicity``; 1 for triggers)."""

    period_us: float
    phase_us: int
    source: str
    periodicity: float = 1.0

    @property
    def frequency_hz(self) -> float:
        return 1e6 / self.period_us

    def to_dict(self) -> dict:
        return {"period_us": self.period_us, "frequency_hz": self.frequency_hz, "phase_us": self.phase_us,
                "source": self.source, "periodicity": self.periodicity}


@dataclass(frozen=True, eq=False)
class WindowStats:
    """Per-window statistics (arrays of shape (K,)): bounds in µs, event counts, pixel classes,
    overlap with the previous window, IoU and acceptance."""

    t0_us: np.ndarray
    t1_us: np.ndarray
    n_events: np.ndarray
    n_both: np.ndarray
    n_on_only: np.ndarray
    n_off_only: np.ndarray
    overlap: np.ndarray
    iou: np.ndarray
    accepted: np.ndarray

    def __len__(self) -> int:
        return int(self.t0_us.shape[0])

    @property
    def single_ratio(self) -> np.ndarray:
        """max(ON-only, OFF-only) / both per window (inf when no *both* pixel)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.maximum(self.n_on_only, self.n_off_only) / self.n_both
        return np.where(self.n_both > 0, r, np.inf)


@dataclass(frozen=True, eq=False)
class PoseImage:
    """One static pose: its time span ``[t0_us, t1_us)``, the windows used and the uint8 image."""

    t0_us: int
    t1_us: int
    image: np.ndarray
    windows: tuple[int, int]

    @property
    def n_windows(self) -> int:
        return self.windows[1] - self.windows[0]


@dataclass(frozen=True, eq=False)
class BlinkResult:
    """Result of :func:`event_images`: the poses, the period and the window statistics."""

    poses: list[PoseImage]
    period: BlinkPeriod
    stats: WindowStats
    params: BlinkParams = field(default_factory=BlinkParams)

    def summary(self) -> dict:
        acc = self.stats.accepted
        return {"period": self.period.to_dict(), "n_windows": len(self.stats),
                "n_accepted": int(acc.sum()), "n_rejected": int((~acc).sum()),
                "n_poses": len(self.poses),
                "poses": [{"t0_us": p.t0_us, "t1_us": p.t1_us, "n_windows": p.n_windows} for p in self.poses]}


def _kernels():
    from . import _kernels
    return _kernels


class _Columns(tuple):
    """Validated contiguous ``(t, x, y, p)`` copies, made once per call chain (see conventions)."""


def _columns(events, sensor_size=None):
    if isinstance(events, _Columns):
        return events
    validate_events(events, sensor_size)
    return _Columns((np.ascontiguousarray(events["t"]), np.ascontiguousarray(events["x"]),
                     np.ascontiguousarray(events["y"]), np.ascontiguousarray(events["p"])))


# ----------------------------------------------------------------------------------------------
# blink period and windows


def _pick_channel(triggers, channel):
    rising = triggers[triggers["edge"] > 0]
    if channel is None:
        if rising.size == 0:
            raise ValueError("triggers hold no rising edge; expected one rising edge per blink period")
        chans, counts = np.unique(rising["channel"], return_counts=True)
        channel = int(chans[np.argmax(counts)])
    return int(channel), rising[rising["channel"] == channel]["t"].astype(np.int64)


def windows_from_triggers(triggers, channel: int | None = None):
    """Blink windows ``[r_i, r_i + T)`` starting at each rising edge of one trigger channel.

    ``T`` is the median spacing of the rising edges (the blink period); a next rising edge that
    comes earlier than ``r_i + T`` ends the window there. The trigger is expected to rise when the
    board appears (or at any fixed phase of the blink: the window still spans one period). Gaps in
    the triggers (between poses) simply have no windows.

    Parameters
    ----------
    triggers : ndarray of dtype TRIGGER_DTYPE
    channel : int or None
        Channel to use; None picks the channel with the most rising edges.

    Returns
    -------
    t0_us, t1_us : ndarray of int64
    period : BlinkPeriod
    """
    validate_triggers(triggers)
    channel, r = _pick_channel(triggers, channel)
    if r.size < 2:
        raise ValueError(f"need at least 2 rising trigger edges on channel {channel} to find the blink "
                         f"period, found {r.size}")
    d = np.diff(r)
    period = float(np.median(d))
    if period <= 0:
        raise ValueError(f"rising trigger edges on channel {channel} are not increasing (median spacing "
                         f"{period} µs)")
    P = int(round(period))
    t1 = r + P
    t1[:-1] = np.minimum(t1[:-1], r[1:])  # a slightly early next edge closes the window
    return r, t1, BlinkPeriod(period, int(r[0]), "triggers", 1.0)


def blink_period_from_triggers(triggers, channel: int | None = None) -> BlinkPeriod:
    """Blink period (median spacing of rising edges) from trigger events; see :func:`windows_from_triggers`."""
    return windows_from_triggers(triggers, channel)[2]


def _parabolic(y, i):
    """Sub-bin position of the peak of ``y`` at ``i`` by a parabola through three samples."""
    if i <= 0 or i >= len(y) - 1:
        return float(i)
    a, b, c = y[i - 1], y[i], y[i + 1]
    den = a - 2 * b + c
    return float(i) if den == 0 else i + 0.5 * (a - c) / den


def blink_period_from_events(events, params: BlinkParams = BlinkParams()) -> BlinkPeriod:
    """Blink period and window phase from the periodicity of the signed event rate.

    The events are binned (``rate_bin_us``) into the signed rate s = ON − OFF per bin; its
    normalised autocorrelation (via FFT, biased estimator, so the first period has the highest
    peak among its multiples) is searched for its maximum over lags in
    ``[min_period_us, max_period_us]``. The period is refined by locating the peaks near all its
    multiples that fit in half the recording (parabolic interpolation) and fitting a line through
    the origin. The phase: the events' times folded modulo the period give the ON and the OFF
    burst phases (maximum and minimum of the folded signed rate); windows start half-way through
    the quiet gap from the OFF burst to the next ON burst.

    Raises
    ------
    ValueError
        When the recording is shorter than two maximum periods' worth of the found period or the
        autocorrelation at the best lag is below ``min_periodicity`` (no blinking found).
    """
    t, _, _, p = _columns(events)
    if t.size < 2:
        raise ValueError(f"need events to find the blink period, got {t.size}")
    k = _kernels()
    # (the biased autocorrelation of a periodic signal decays as 1 - lag/n; a multiple m*T counts
    # in the refinement below when its peak keeps at least half of that expected height)
    t0 = int(t[0])
    bin_us = int(params.rate_bin_us)
    n_bins = int((int(t[-1]) - t0) // bin_us + 1)
    min_lag = int(math.ceil(params.min_period_us / bin_us))
    max_lag = int(params.max_period_us // bin_us)
    if n_bins < 2 * min_lag + 2:
        raise ValueError(f"recording spans {(int(t[-1]) - t0)} µs; finding a blink period needs at least "
                         f"two periods of min_period_us = {params.min_period_us} µs")
    s = np.zeros(n_bins, np.float64)
    tot = np.zeros(n_bins, np.float64)
    k.binned_signed_rate(t, p, np.int64(t0), np.int64(bin_us), n_bins, s, tot)
    s_raw = s.copy()
    s -= s.mean()
    nfft = 1 << int(math.ceil(math.log2(2 * n_bins)))
    f = np.fft.rfft(s, nfft)
    acf = np.fft.irfft(f * np.conj(f), nfft)[:n_bins]
    if acf[0] <= 0:
        raise ValueError("the signed event rate is constant; no blinking found")
    acf = acf / acf[0]
    hi = min(max_lag, n_bins // 2)
    if hi <= min_lag:
        raise ValueError(f"recording spans {(int(t[-1]) - t0)} µs, too short to search blink periods "
                         f"from {params.min_period_us} µs (needs two periods)")
    lag = min_lag + int(np.argmax(acf[min_lag:hi + 1]))
    strength = float(acf[lag])
    if strength < params.min_periodicity:
        raise ValueError(f"no periodic blinking found: the best autocorrelation of the signed event rate "
                         f"for periods {params.min_period_us}-{params.max_period_us} µs is {strength:.3f} "
                         f"at {lag * bin_us} µs, expected at least min_periodicity = {params.min_periodicity}")
    coarse = _parabolic(acf, lag)
    # refine with the multiples that fit in half the recording
    ms, lags = [], []
    m = 1
    while m * coarse <= n_bins // 2 and m <= 200:
        c = int(round(m * coarse))
        lo, hi2 = max(1, c - 2), min(n_bins - 2, c + 2)
        if lo >= hi2:
            break
        j = lo + int(np.argmax(acf[lo:hi2 + 1]))
        if acf[j] > 0.5 * strength * max(0.0, 1.0 - c / n_bins) / max(1e-9, 1.0 - lag / n_bins):
            ms.append(m)
            lags.append(_parabolic(acf, j))
        m += 1
    ms_a, lags_a = np.asarray(ms, float), np.asarray(lags, float)
    period_bins = float(np.dot(ms_a, lags_a) / np.dot(ms_a, ms_a)) if ms else coarse
    period_us = period_bins * bin_us
    # phase from the signed rate folded modulo the period (bin resolution is ample: the cut goes
    # in a quiet gap of about half a period)
    n_phase = max(8, int(round(period_us / bin_us)))
    centres = (np.arange(n_bins) + 0.5) * bin_us
    idx = np.minimum((np.mod(centres, period_us) / period_us * n_phase).astype(np.int64), n_phase - 1)
    fold = np.bincount(idx, weights=s_raw, minlength=n_phase)
    i_on, i_off = int(np.argmax(fold)), int(np.argmin(fold))
    gap = (i_on - i_off) % n_phase
    start_phase = ((i_off + gap / 2.0) % n_phase) / n_phase * period_us
    return BlinkPeriod(period_us, int(round(t0 + start_phase)), "event_rate", strength)


def windows_from_period(period: BlinkPeriod, t_first_us: int, t_last_us: int):
    """Consecutive windows of one period, aligned on ``period.phase_us``, covering [t_first, t_last]."""
    T = float(period.period_us)
    k0 = math.floor((t_first_us - period.phase_us) / T)
    k1 = math.ceil((t_last_us + 1 - period.phase_us) / T)
    edges = np.round(period.phase_us + T * np.arange(k0, k1 + 1)).astype(np.int64)
    return edges[:-1], edges[1:]


# ----------------------------------------------------------------------------------------------
# window statistics, poses, images


def _run_kernel(events, sensor_size, t0_us, t1_us, params, use=None, image=None):
    ss = SensorSize.from_any(sensor_size)
    if ss is None:
        raise ValueError("sensor_size (height, width) of the event camera is required")
    t, x, y, p = _columns(events, ss)
    t0_us = np.ascontiguousarray(t0_us, np.int64)
    t1_us = np.ascontiguousarray(t1_us, np.int64)
    if t0_us.shape != t1_us.shape or t0_us.ndim != 1:
        raise ValueError(f"window bounds must be two 1-D arrays of equal length, got {t0_us.shape} "
                         f"and {t1_us.shape}")
    if np.any(t1_us < t0_us):
        i = int(np.flatnonzero(t1_us < t0_us)[0])
        raise ValueError(f"window {i} ends ({t1_us[i]} µs) before it starts ({t0_us[i]} µs)")
    i0 = np.searchsorted(t, t0_us, side="left").astype(np.int64)
    i1 = np.searchsorted(t, t1_us, side="left").astype(np.int64)
    k = _kernels()
    stats = np.zeros((t0_us.shape[0], k.N_STATS), np.int64)
    use = np.zeros(t0_us.shape[0], np.bool_) if use is None else np.ascontiguousarray(use, np.bool_)
    out = np.zeros(ss.n_pixels, np.float64) if image is None else image
    k.blink_window_stats(x, y, p, i0, i1, np.int64(ss.width), np.int64(ss.n_pixels), use,
                         np.int64(params.min_events_per_polarity), params.image_mode == "binary", out, stats)
    return stats, out.reshape(ss.shape)


def window_statistics(events, sensor_size, t0_us, t1_us, params: BlinkParams = BlinkParams()) -> WindowStats:
    """Classify each window's pixels (both / ON-only / OFF-only) and accept or reject the window.

    Acceptance (step 3 of the module notes): ``n_both >= min_both_pixels`` and
    ``max(n_on_only, n_off_only) <= max_single_ratio * n_both``.
    """
    k = _kernels()
    st, _ = _run_kernel(events, sensor_size, t0_us, t1_us, params)
    both = st[:, k.S_BOTH]
    prev = np.concatenate([[0], both[:-1]])
    union = both + prev - st[:, k.S_OVERLAP]
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = np.where(union > 0, st[:, k.S_OVERLAP] / np.maximum(union, 1), 0.0)
    lim = params.max_single_ratio * both
    accepted = ((both >= params.min_both_pixels) & (st[:, k.S_ON_ONLY] <= lim) & (st[:, k.S_OFF_ONLY] <= lim))
    return WindowStats(np.asarray(t0_us, np.int64), np.asarray(t1_us, np.int64), st[:, k.S_EVENTS], both,
                       st[:, k.S_ON_ONLY], st[:, k.S_OFF_ONLY], st[:, k.S_OVERLAP], iou, accepted)


def segment_poses(stats: WindowStats, params: BlinkParams = BlinkParams()) -> list[tuple[int, int]]:
    """Runs ``[k0, k1)`` of window indices forming static poses (step 4 of the module notes).

    A pose is a maximal run of accepted windows, each (after the first) adjacent in time to the
    previous one (``t0[k] == t1[k-1]``) and overlapping it with IoU >= ``min_pose_iou``; runs with
    fewer than ``min_windows_per_pose`` windows are dropped.
    """
    runs = []
    start = None
    n = len(stats)
    for k in range(n + 1):
        cont = False
        if k < n and stats.accepted[k]:
            cont = (start is not None and stats.t0_us[k] == stats.t1_us[k - 1]
                    and stats.iou[k] >= params.min_pose_iou)
            if not cont:
                if start is not None:
                    runs.append((start, k))
                start = k
            continue
        if start is not None:
            runs.append((start, k))
            start = None
    return [r for r in runs if r[1] - r[0] >= params.min_windows_per_pose]


def _finish_image(acc: np.ndarray, n_windows: int, params: BlinkParams) -> np.ndarray:
    img = acc / max(1, n_windows)
    if params.median_radius > 0:
        from scipy.ndimage import median_filter
        img = median_filter(img, size=2 * params.median_radius + 1, mode="nearest")
    nz = img[img > 0]
    if nz.size == 0:
        return np.zeros(img.shape, np.uint8)
    top = float(np.percentile(nz, params.count_white_percentile)) if params.image_mode == "count" else 1.0
    return np.clip(np.round(img / top * 255.0), 0, 255).astype(np.uint8)


def accumulate_image(events, sensor_size, t0_us, t1_us, params: BlinkParams = BlinkParams()) -> np.ndarray:
    """uint8 event image of the *both* pixels over the given windows (no rejection; see step 5).

    In ``count`` mode the accumulated counts are scaled so that the ``count_white_percentile``
    percentile of the non-zero pixels maps to 255 (higher counts clip); in ``binary`` mode, 255 means "fired both polarities in every
    window".
    """
    use = np.ones(np.asarray(t0_us).shape[0], np.bool_)
    _, acc = _run_kernel(events, sensor_size, t0_us, t1_us, params, use=use)
    return _finish_image(acc, int(use.size), params)


def blink_windows(events, triggers=None, params: BlinkParams = BlinkParams()):
    """Blink windows ``(t0_us, t1_us, BlinkPeriod)`` from triggers when given (non-empty), else the event rate."""
    if triggers is not None and len(triggers):
        return windows_from_triggers(triggers, params.trigger_channel)
    cols = _columns(events)
    period = blink_period_from_events(cols, params)
    t = cols[0]
    w0, w1 = windows_from_period(period, int(t[0]), int(t[-1]))
    return w0, w1, period


def event_images(events, sensor_size, triggers=None, params: BlinkParams = BlinkParams(),
                 progress: bool = False) -> BlinkResult:
    """Segment a blinking-board recording into static poses and make one event image per pose.

    Parameters
    ----------
    events : ndarray of shape (N,), dtype EVENT_DTYPE
        Events sorted by ``t`` (µs).
    sensor_size : SensorSize or (height, width)
    triggers : ndarray of dtype TRIGGER_DTYPE, optional
        Rising edge once per blink period; when absent or empty the period comes from the event rate.
    params : BlinkParams
    progress : bool
        Show a tqdm bar over the poses.

    Returns
    -------
    BlinkResult
        ``poses`` is a list of :class:`PoseImage` (``t0_us``, ``t1_us``, uint8 ``image`` of shape
        (H, W)); ``period`` the blink period found; ``stats`` the per-window statistics.
    """
    if not isinstance(params, BlinkParams):
        raise TypeError(f"params must be BlinkParams, got {type(params).__name__}")
    cols = _columns(events, sensor_size)
    if cols[0].size == 0:
        raise ValueError("no events: a blinking-board recording is expected")
    w0, w1, period = blink_windows(cols, triggers, params)
    stats = window_statistics(cols, sensor_size, w0, w1, params)
    runs = segment_poses(stats, params)
    poses = []
    it = runs
    if progress:
        from tqdm import tqdm
        it = tqdm(runs, desc="event images", unit="pose")
    for a, b in it:
        img = accumulate_image(cols, sensor_size, w0[a:b], w1[a:b], params)
        poses.append(PoseImage(int(w0[a]), int(w1[b - 1]), img, (int(a), int(b))))
    return BlinkResult(poses, period, stats, params)


def blink_image(events, sensor_size, triggers=None, params: BlinkParams = BlinkParams()) -> np.ndarray:
    """Event image of one static pose: all accepted blink windows of ``events`` accumulated.

    Raises ``ValueError`` when every window is rejected (saying how many were and why).
    """
    cols = _columns(events, sensor_size)
    if cols[0].size == 0:
        raise ValueError("no events: a blinking-board recording is expected")
    w0, w1, _ = blink_windows(cols, triggers, params)
    st = window_statistics(cols, sensor_size, w0, w1, params)
    if not st.accepted.any():
        raise ValueError(f"all {len(st)} blink windows were rejected (max both pixels "
                         f"{int(st.n_both.max(initial=0))}, need {params.min_both_pixels}; min single-polarity "
                         f"ratio {float(st.single_ratio.min(initial=np.inf)):.2f}, allowed "
                         f"{params.max_single_ratio})")
    return accumulate_image(cols, sensor_size, w0[st.accepted], w1[st.accepted], params)


