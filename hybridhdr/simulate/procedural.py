"""The procedural generator: analytic scenes with known ground truth (no rendering, no downloads).

* :func:`procedural_recording`: a dim textured background (a sum of two gratings) and a bright
  disc, ``bright_ratio`` times brighter, that moves across it. Events are ideal log-intensity
  crossings of a contrast threshold with linearly interpolated timestamps; frames integrate
  linear intensity over their exposure, pass a gamma-2.2 response, clip and quantise to 8 bits,
  so the disc saturates the frames while the events keep its detail: the situation the AKF is
  built for. It feeds ``hybridhdr demo``, the benchmarks' ``sim_procedural`` datasets
  (:class:`hybridhdr.simulate.datasets.ProceduralSource` runs it through the simulator's sensor
  and camera models) and the tests.
* :func:`edge_sweep_recording`, :func:`colour_edge_sweep_recording`: a bright edge sweeping a
  textured background (monochrome or through a Bayer mosaic), for the accuracy suites.
* :func:`hdr_scene`, :func:`random_homography`, :func:`render_frame`: a textured HDR scene seen
  by 8-bit gamma frames through random homographies, for the photometric calibration.

The physically based scenes (Mitsuba 3) are :mod:`hybridhdr.simulate.scene`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera.cfa import mosaic, parse_cfa
from ..camera.encoding import LUMINANCE_WEIGHTS
from ..events import EVENT_DTYPE, SensorSize, empty_events, empty_triggers
from ..model import CameraInfo, Frames, HDRReferences, Metadata, Recording
from .source import AnalyticSceneSource

__all__ = ["ProceduralScene", "procedural_recording", "EdgeSweepScene", "edge_sweep_recording", "ideal_events",
           "ColourEdgeSweepScene", "colour_edge_sweep_recording", "hdr_scene", "random_homography", "render_frame",
           "SensorCalibrationScene", "sensor_calibration_recording"]


@dataclass(frozen=True)
class ProceduralScene:
    """Analytic HDR scene: linear intensity ``I(x, y, t)`` (arbitrary linear units, > 0).

    Parameters
    ----------
    sensor_size : SensorSize
    background : float
        Mean background intensity.
    bright_ratio : float
        Disc intensity / background mean (HDR: 1e3 by default).
    disc_radius_px : float
    speed_px_per_s : float
        Disc speed along x (it bounces between the borders).
    """

    sensor_size: SensorSize = SensorSize(90, 120)
    background: float = 0.1
    bright_ratio: float = 1.0e3
    disc_radius_px: float = 12.0
    speed_px_per_s: float = 150.0

    def intensity(self, t_us) -> np.ndarray:
        """Linear intensity at time ``t_us`` (µs), float64 array of shape (H, W)."""
        h, w = self.sensor_size.shape
        t = float(t_us) * 1e-6
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        bg = self.background * (1.0 + 0.6 * np.sin(2 * np.pi * xx / 23.0 + 0.7 * t)
                                * np.cos(2 * np.pi * yy / 17.0))
        span = max(w - 2 * self.disc_radius_px, 1.0)
        s = (self.speed_px_per_s * t) % (2 * span)
        cx = self.disc_radius_px + (s if s < span else 2 * span - s)
        cy = h / 2.0
        r = np.hypot(xx - cx, yy - cy)
        # soft edge over ~1.5 px so that the scene is band-limited
        edge = 1.0 / (1.0 + np.exp((r - self.disc_radius_px) / 0.75))
        disc = self.background * self.bright_ratio * (0.75 + 0.25 * np.cos(xx / 3.0 - 2 * t)) * edge
        return bg + disc


def _level_crossings(L_ref, L_prev, L_new, c, t_prev, t_new, pix_x, pix_y, tol):
    """Ideal events of one sampling step: every crossing of a reference level ``L_ref ± k c`` by
    the log intensity moving linearly from ``L_prev`` (at ``t_prev``) to ``L_new`` (at ``t_new``),
    timestamped by linear interpolation (at most ``t_new - 1``). Returns the unsorted batch (or
    None) and the new reference levels."""
    d = (L_new - L_ref).ravel()
    n = np.floor(np.abs(d) / c + tol).astype(np.int64)
    idx = np.flatnonzero(n)
    if not idx.size:
        return None, L_ref
    sign = np.sign(d[idx])
    reps = n[idx]
    pix = np.repeat(idx, reps)
    k = np.arange(reps.sum()) - np.repeat(np.cumsum(reps) - reps, reps) + 1
    sgn = np.repeat(sign, reps)
    lvl = L_ref.ravel()[pix] + sgn * k * c
    lp, ln = L_prev.ravel()[pix], L_new.ravel()[pix]
    frac = np.clip((lvl - lp) / np.where(ln != lp, ln - lp, 1.0), 0.0, 1.0)
    te = t_prev + np.floor(frac * (t_new - t_prev)).astype(np.int64)
    te = np.minimum(te, t_new - 1)
    b = np.empty(pix.size, dtype=EVENT_DTYPE)
    b["t"], b["x"], b["y"], b["p"] = te, pix_x[pix], pix_y[pix], sgn
    Lr = L_ref.ravel().copy()
    Lr[idx] += sign * reps * c
    return b, Lr.reshape(L_ref.shape)


def procedural_recording(sensor_size=SensorSize(90, 120), duration_us: int = 500_000, *,
                         contrast_threshold: float = 0.2, frame_rate_hz: float = 20.0,
                         exposure_us: int = 5_000, step_us: int = 250, t0_us: int = 0,
                         seed: int | None = 0, scene: ProceduralScene | None = None,
                         hdr_rate_hz: float | None = None):
    """Build a procedural hybrid recording and its HDR ground truth.

    Parameters
    ----------
    sensor_size : SensorSize or (height, width)
    duration_us : int
        Length in µs.
    contrast_threshold : float
        Event threshold in natural-log units (same for ON and OFF).
    frame_rate_hz : float
        Frame rate of the frame camera; exposures of ``exposure_us`` centred on each frame time.
    step_us : int
        Time step at which the scene is sampled for events (crossings are interpolated inside).
    seed : int or None
        Seeds the per-pixel initial reference levels (uniform in one threshold), so that events
        do not fire in lock-step across pixels.
    hdr_rate_hz : float, optional
        If given, HDR ground-truth references are stored at that rate (default: at frame times).

    Returns
    -------
    recording : Recording
        Events, 8-bit gamma frames and HDR references (float32 linear intensity).
    scene : ProceduralScene
        Call ``scene.intensity(t_us)`` for the ground truth at any time.
    """
    ss = SensorSize.from_any(sensor_size)
    if duration_us <= 0 or step_us <= 0 or exposure_us <= 0 or frame_rate_hz <= 0:
        raise ValueError("duration_us, step_us, exposure_us and frame_rate_hz must be > 0")
    if not contrast_threshold > 0:
        raise ValueError(f"contrast_threshold must be > 0 (log units), got {contrast_threshold}")
    scene = scene or ProceduralScene(ss)
    if scene.sensor_size != ss:
        scene = ProceduralScene(ss, scene.background, scene.bright_ratio, scene.disc_radius_px,
                                scene.speed_px_per_s)
    rng = np.random.default_rng(seed)
    c = float(contrast_threshold)
    h, w = ss.shape
    L_prev = np.log(scene.intensity(t0_us))
    L_ref = L_prev - c * rng.uniform(0.0, 1.0, size=L_prev.shape) + c / 2
    pix_y, pix_x = np.mgrid[0:h, 0:w]
    pix_y, pix_x = pix_y.ravel(), pix_x.ravel()
    batches = []
    t_prev = t0_us
    for t_new in range(t0_us + step_us, t0_us + duration_us + 1, step_us):
        L_new = np.log(scene.intensity(t_new))
        b, L_ref = _level_crossings(L_ref, L_prev, L_new, c, t_prev, t_new, pix_x, pix_y, 0.0)
        if b is not None:
            batches.append(b[np.argsort(b["t"], kind="stable")])
        L_prev, t_prev = L_new, t_new
    events = np.concatenate(batches) if batches else empty_events()

    # frames: mean linear intensity over the exposure, gamma 2.2, 8-bit, clipped
    period = 1e6 / frame_rate_hz
    mids = t0_us + np.arange(0.0, duration_us + 1, period)
    mids = mids[(mids - exposure_us / 2 >= t0_us) & (mids + exposure_us / 2 <= t0_us + duration_us)]
    ts = np.round(mids - exposure_us / 2).astype(np.int64)
    te = ts + int(exposure_us)
    gain = 1.0 / (4.0 * scene.background)  # background mean lands at ~1/4 of full scale (linear)
    images = np.empty((len(ts), h, w), np.uint8)
    for k, (a, b) in enumerate(zip(ts, te)):
        sub = np.linspace(a, b, 6)
        lin = np.mean([scene.intensity(s) for s in sub], axis=0) * gain
        images[k] = np.round(255.0 * np.clip(lin, 0, 1) ** (1 / 2.2)).astype(np.uint8)
    frames = Frames(images, ts, te, encoding="gamma")
    if hdr_rate_hz is None:
        t_hdr = (ts + te) // 2
    else:
        t_hdr = t0_us + np.arange(0, duration_us + 1, 1e6 / hdr_rate_hz).astype(np.int64)
    hdr_images = np.zeros((len(t_hdr), h, w), np.float32)
    for k, t in enumerate(t_hdr):
        hdr_images[k] = scene.intensity(t)
    hdr = HDRReferences(hdr_images, t_hdr)
    md = Metadata(event_camera=CameraInfo(ss, "procedural ideal DVS"),
                  frame_camera=CameraInfo(ss, "procedural 8-bit gamma-2.2 camera"),
                  provenance={"generator": "hybridhdr.simulate.procedural.procedural_recording", "seed": seed,
                              "contrast_threshold": c, "frame_rate_hz": frame_rate_hz,
                              "exposure_us": int(exposure_us), "step_us": int(step_us),
                              "frame_gain": gain, "crf": "gamma 1/2.2, 8-bit"})
    return Recording(events, ss, frames, empty_triggers(),
                     hdr, md), scene


# -- edge sweep: a bright textured object sweeping across a textured background ----------------

class _Waves:
    """A seeded sum of plane waves in (u, y), clipped to [-1, 1]; evaluated on the pixel grid
    shifted by ``x0`` along u through precomputed complex exponentials (cheap per time step)."""

    def __init__(self, rng, n_waves: int, max_cycles_per_px: float, shape):
        k = rng.uniform(0.02, max_cycles_per_px, n_waves) * 2 * np.pi
        ang = rng.uniform(0, np.pi, n_waves)
        ph = rng.uniform(0, 2 * np.pi, n_waves)
        self.kx, ky = k * np.cos(ang), k * np.sin(ang)
        yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
        self.e = np.exp(1j * (self.kx[:, None, None] * xx + ky[:, None, None] * yy + ph[:, None, None]))
        self.n = n_waves

    def __call__(self, x0: float = 0.0) -> np.ndarray:
        v = np.tensordot(np.exp(-1j * self.kx * x0), self.e, axes=1).imag
        return np.clip(v / self.n * 1.6, -1.0, 1.0)


@dataclass(frozen=True)
class EdgeSweepScene:
    """Analytic HDR scene in **frame-linear units** (1.0 = the frames' clip level at their exposure).

    A textured background (``background_range``, well exposed) and a bright rectangular object
    whose own texture spans ``object_range`` (3-12x the frames' clip level by default) moving
    along x at constant speed, its texture moving with it; soft edges (logistic, ``edge_px``).
    ``seed`` draws both textures (sums of five plane waves each, spatial frequencies up to
    ``max_cycles_per_px``).
    """

    sensor_size: SensorSize = SensorSize(48, 64)
    seed: int = 0
    object_range: tuple = (3.0, 12.0)
    background_range: tuple = (0.06, 0.5)
    object_size_px: tuple = (28.0, 20.0)  # (height, width)
    x_start_px: float = -12.0
    speed_px_per_s: float = 80.0
    edge_px: float = 0.5
    max_cycles_per_px: tuple = (0.12, 0.15)  # (background, object) texture bandwidth

    def _tex(self):
        rng = np.random.default_rng([int(self.seed), 11])
        h, w = self.sensor_size.shape
        bg = _Waves(rng, 5, self.max_cycles_per_px[0], (h, w))()
        lb0, lb1 = np.log(self.background_range[0]), np.log(self.background_range[1])
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        oh, _ = self.object_size_px
        y0 = (h - oh) / 2.0
        ay = self._sig(yy[:, :1] - y0 + 0.5) * self._sig(y0 + oh - 0.5 - yy[:, :1])  # (H, 1)
        return {"bg": np.exp(lb0 + (lb1 - lb0) * 0.5 * (1 + bg)), "ob": _Waves(rng, 5, self.max_cycles_per_px[1], (h, w)),
                "x": xx[:1], "ay": ay}

    def _sig(self, z):
        return 1.0 / (1.0 + np.exp(-z / self.edge_px))

    def log_intensity(self, t_us, tex=None) -> np.ndarray:
        """ln I at time ``t_us`` (µs), float64 (H, W)."""
        tx = tex or self._tex()
        lo0, lo1 = np.log(self.object_range[0]), np.log(self.object_range[1])
        x0 = self.x_start_px + self.speed_px_per_s * float(t_us) * 1e-6
        u = tx["x"] - x0  # (1, W)
        lo = lo0 + (lo1 - lo0) * 0.5 * (1 + tx["ob"](x0))
        ow = self.object_size_px[1]
        a = tx["ay"] * (self._sig(u + 0.5) * self._sig(ow - 0.5 - u))
        return np.log((1 - a) * tx["bg"] + a * np.exp(lo))

    def intensity(self, t_us, tex=None) -> np.ndarray:
        """Linear intensity (frame-linear units) at ``t_us``, float64 (H, W)."""
        return np.exp(self.log_intensity(t_us, tex))

    def object_mask(self, t_us) -> np.ndarray:
        """Pixels whose centre lies inside the object at ``t_us`` (bool (H, W))."""
        h, w = self.sensor_size.shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        x0 = self.x_start_px + self.speed_px_per_s * float(t_us) * 1e-6
        oh, ow = self.object_size_px
        y0 = (h - oh) / 2.0
        return (xx - x0 >= 0) & (xx - x0 <= ow - 1) & (yy >= y0) & (yy <= y0 + oh - 1)


def ideal_events(log_intensity, times_us, contrast_threshold: float) -> np.ndarray:
    """Ideal DVS events of a sampled log intensity: each pixel's reference starts on the grid of
    multiples of c nearest ``ln I(t0)`` and moves by ±c per event, so every event marks ``ln I``
    crossing a multiple of c; crossing times are linearly interpolated between the samples.

    Parameters
    ----------
    log_intensity : callable t_us -> (H, W) float64 ln I
    times_us : increasing int64 sample times (the first sets the initial references)
    contrast_threshold : float, c (log units)
    """
    c = float(contrast_threshold)
    times_us = np.asarray(times_us, dtype=np.int64)
    L_prev = log_intensity(int(times_us[0]))
    h, w = L_prev.shape
    L_ref = c * np.round(L_prev / c)
    pix_y, pix_x = np.mgrid[0:h, 0:w]
    pix_y, pix_x = pix_y.ravel(), pix_x.ravel()
    batches = []
    t_prev = int(times_us[0])
    for t_new in times_us[1:]:
        t_new = int(t_new)
        L_new = log_intensity(t_new)
        # tolerance: a level reached to rounding error counts as crossed
        b, L_ref = _level_crossings(L_ref, L_prev, L_new, c, t_prev, t_new, pix_x, pix_y, 1e-9)
        if b is not None:
            batches.append(b[np.lexsort((b["x"], b["y"], b["t"]))])
        L_prev, t_prev = L_new, t_new
    return np.concatenate(batches) if batches else empty_events()


def edge_sweep_recording(seed: int = 0, *, sensor_size=SensorSize(48, 64), duration_us: int = 800_000,
                         contrast_threshold: float = 0.1, frame_rate_hz: float = 20.0, exposure_us: int = 5_000,
                         step_us: int = 200, object_range=(3.0, 12.0), speed_px_per_s: float = 80.0,
                         hdr_at: str = "frames"):
    """The edge-sweep case: a bright textured object (``object_range`` × the frames' clip level)
    sweeping across a textured background; ideal events; 8-bit gamma-2.2 frames.

    Deterministic: the same arguments give the same bits. The scene is defined in frame-linear
    units, so the frames are ``round(255·clip(mean_exposure(I), 0, 1)^(1/2.2))`` (exposure mean
    by the trapezoid rule over 11 samples) and the HDR references (``I`` at each frame's
    mid-exposure) are already in the reconstruction's units. Events: :func:`ideal_events` of the
    analytic ``ln I`` sampled every ``step_us`` (the object moves 0.016 px per 200 µs at 80 px/s).

    Returns
    -------
    recording : Recording
    scene : EdgeSweepScene
    """
    ss = SensorSize.from_any(sensor_size)
    if duration_us <= 0 or step_us <= 0 or exposure_us <= 0 or frame_rate_hz <= 0:
        raise ValueError("duration_us, step_us, exposure_us and frame_rate_hz must be > 0")
    scene = EdgeSweepScene(ss, seed=int(seed), object_range=tuple(float(v) for v in object_range),
                           speed_px_per_s=float(speed_px_per_s))
    tex = scene._tex()
    ts = np.arange(0, int(duration_us) + 1, int(step_us), dtype=np.int64)
    events = ideal_events(lambda t: scene.log_intensity(t, tex), ts, contrast_threshold)
    period = 1e6 / frame_rate_hz
    mids = np.arange(period / 2, duration_us + 1, period)
    mids = mids[(mids - exposure_us / 2 >= 0) & (mids + exposure_us / 2 <= duration_us)]
    t0 = np.round(mids - exposure_us / 2).astype(np.int64)
    t1 = t0 + int(exposure_us)
    h, w = ss.shape
    images = np.empty((len(t0), h, w), np.uint8)
    wts = np.ones(11)
    wts[[0, -1]] = 0.5
    wts /= wts.sum()
    for k, (a, b) in enumerate(zip(t0, t1)):
        lin = sum(wi * scene.intensity(t, tex) for wi, t in zip(wts, np.linspace(a, b, 11)))
        images[k] = np.round(255.0 * np.clip(lin, 0, 1) ** (1 / 2.2)).astype(np.uint8)
    frames = Frames(images, t0, t1, encoding="gamma")
    t_hdr = (t0 + t1) // 2
    if hdr_at != "frames":
        raise ValueError(f"hdr_at must be 'frames', got {hdr_at!r}")
    hdr = HDRReferences(np.stack([scene.intensity(t, tex) for t in t_hdr]).astype(np.float32), t_hdr)
    md = Metadata(event_camera=CameraInfo(ss, "ideal DVS (edge sweep)"),
                  frame_camera=CameraInfo(ss, "8-bit gamma-2.2 camera (edge sweep)"),
                  provenance={"generator": "hybridhdr.simulate.procedural.edge_sweep_recording", "seed": int(seed),
                              "contrast_threshold": float(contrast_threshold), "frame_rate_hz": float(frame_rate_hz),
                              "exposure_us": int(exposure_us), "step_us": int(step_us),
                              "object_range": list(scene.object_range), "speed_px_per_s": float(speed_px_per_s),
                              "crf": "gamma 1/2.2, 8-bit", "gt_units": "frame_linear"})
    return Recording(events, ss, frames, empty_triggers(), hdr, md), scene


# -- colour edge sweep: the same sweep in RGB, seen by a Bayer camera and by a monochrome one ----

@dataclass(frozen=True)
class ColourEdgeSweepScene:
    """:class:`EdgeSweepScene` in linear RGB (frame-linear units per channel).

    The background keeps the grey scene's texture and gets a colour texture of its own: channel
    ``c`` is multiplied by ``exp(background_tint · w_c)`` with ``w_c`` a seeded sum of plane
    waves in [-1, 1] (one per channel). The object is ``object_rgb`` times the grey object's
    intensity: the default ``(1, f, f)`` with ``f = 0.02`` is a saturated red whose G and B are
    50× (34 dB) below R, a floor that keeps their logarithms finite.
    """

    base: EdgeSweepScene = EdgeSweepScene()
    object_rgb: tuple = (1.0, 0.02, 0.02)
    background_tint: float = 0.5
    tint_max_cycles_per_px: float = 0.1

    def _tex(self):
        tx = self.base._tex()
        rng = np.random.default_rng([int(self.base.seed), 12])
        h, w = self.base.sensor_size.shape
        tint = np.stack([_Waves(rng, 5, self.tint_max_cycles_per_px, (h, w))() for _ in range(3)], axis=-1)
        tx["bg_rgb"] = tx["bg"][..., None] * np.exp(self.background_tint * tint)
        return tx

    def rgb(self, t_us, tex=None) -> np.ndarray:
        """Linear RGB at ``t_us`` (µs), float64 (H, W, 3)."""
        tx = tex or self._tex()
        b = self.base
        lo0, lo1 = np.log(b.object_range[0]), np.log(b.object_range[1])
        x0 = b.x_start_px + b.speed_px_per_s * float(t_us) * 1e-6
        u = tx["x"] - x0
        lo = lo0 + (lo1 - lo0) * 0.5 * (1 + tx["ob"](x0))
        ow = b.object_size_px[1]
        a = (tx["ay"] * (b._sig(u + 0.5) * b._sig(ow - 0.5 - u)))[..., None]
        return (1 - a) * tx["bg_rgb"] + a * np.exp(lo)[..., None] * np.asarray(self.object_rgb, np.float64)

    def luminance(self, t_us, tex=None) -> np.ndarray:
        """Rec. 709 luminance of :meth:`rgb`, float64 (H, W)."""
        return self.rgb(t_us, tex) @ np.asarray(LUMINANCE_WEIGHTS)

    def object_mask(self, t_us) -> np.ndarray:
        return self.base.object_mask(t_us)


def colour_edge_sweep_recording(seed: int = 0, *, cfa: str | None = "RGGB", frames: str = "mosaic",
                                sensor_size=SensorSize(48, 64), duration_us: int = 800_000,
                                contrast_threshold: float = 0.1, frame_rate_hz: float = 20.0,
                                exposure_us: int = 5_000, step_us: int = 200, object_range=(3.0, 12.0),
                                speed_px_per_s: float = 80.0, object_rgb=(1.0, 0.02, 0.02),
                                background_tint: float = 0.5, band_limited: bool = False):
    """The edge sweep of :func:`edge_sweep_recording` in colour (:class:`ColourEdgeSweepScene`).

    ``cfa`` a Bayer pattern: a colour camera whose event pixels each see their own channel
    (ideal events of the mosaic of ln RGB) and whose frames are the raw mosaic
    (``frames="mosaic"``, (K, H, W), ``metadata.frame_camera.cfa`` set) or full RGB
    (``frames="rgb"``, (K, H, W, 3), as if demosaicked perfectly); HDR references are linear RGB
    (K, H, W, 3). ``cfa=None``: a monochrome camera on the same scene (events and frames of its
    Rec. 709 luminance; references luminance). Frames are 8-bit gamma 2.2, per channel as
    :func:`edge_sweep_recording`.

    ``band_limited=True`` gives the scene what a Bayer camera's optical low-pass filter passes:
    edges over 1.5 px instead of 0.5 and textures up to 0.05 cycles/px instead of 0.10-0.15
    (R and B are sampled every 2 px, so their Nyquist limit is 0.25 cycles/px and bilinear
    interpolation is accurate only well below it).

    Returns
    -------
    recording : Recording
    scene : ColourEdgeSweepScene
    """
    pattern = parse_cfa(cfa)
    if frames not in ("mosaic", "rgb"):
        raise ValueError(f"frames must be 'mosaic' or 'rgb', got {frames!r}")
    ss = SensorSize.from_any(sensor_size)
    if duration_us <= 0 or step_us <= 0 or exposure_us <= 0 or frame_rate_hz <= 0:
        raise ValueError("duration_us, step_us, exposure_us and frame_rate_hz must be > 0")
    bl = dict(edge_px=1.5, max_cycles_per_px=(0.05, 0.05)) if band_limited else {}
    base = EdgeSweepScene(ss, seed=int(seed), object_range=tuple(float(v) for v in object_range),
                          speed_px_per_s=float(speed_px_per_s), **bl)
    scene = ColourEdgeSweepScene(base, tuple(float(v) for v in object_rgb), float(background_tint),
                                 0.05 if band_limited else 0.1)
    tex = scene._tex()

    def view(t):  # what the camera's pixels see: the own channel, or luminance
        return mosaic(scene.rgb(t, tex), pattern) if pattern else scene.luminance(t, tex)

    ts = np.arange(0, int(duration_us) + 1, int(step_us), dtype=np.int64)
    events = ideal_events(lambda t: np.log(view(t)), ts, contrast_threshold)
    period = 1e6 / frame_rate_hz
    mids = np.arange(period / 2, duration_us + 1, period)
    mids = mids[(mids - exposure_us / 2 >= 0) & (mids + exposure_us / 2 <= duration_us)]
    t0 = np.round(mids - exposure_us / 2).astype(np.int64)
    t1 = t0 + int(exposure_us)
    wts = np.ones(11)
    wts[[0, -1]] = 0.5
    wts /= wts.sum()
    full_rgb = pattern is not None and frames == "rgb"
    images = []
    for a, b in zip(t0, t1):
        lin = sum(wi * (scene.rgb(t, tex) if full_rgb else view(t)) for wi, t in zip(wts, np.linspace(a, b, 11)))
        images.append(np.round(255.0 * np.clip(lin, 0, 1) ** (1 / 2.2)).astype(np.uint8))
    fr = Frames(np.stack(images), t0, t1, encoding="gamma")
    t_hdr = (t0 + t1) // 2
    ref = (lambda t: scene.rgb(t, tex)) if pattern else (lambda t: scene.luminance(t, tex))
    hdr = HDRReferences(np.stack([ref(t) for t in t_hdr]).astype(np.float32), t_hdr)
    kind = f"Bayer {pattern}" if pattern else "monochrome"
    md = Metadata(event_camera=CameraInfo(ss, f"ideal {kind} DVS (colour edge sweep)", cfa=pattern),
                  frame_camera=CameraInfo(ss, f"8-bit gamma-2.2 {kind} camera (colour edge sweep)",
                                          cfa=pattern),
                  provenance={"generator": "hybridhdr.simulate.procedural.colour_edge_sweep_recording",
                              "seed": int(seed), "cfa": pattern, "frames": frames if pattern else "luminance",
                              "contrast_threshold": float(contrast_threshold), "frame_rate_hz": float(frame_rate_hz),
                              "exposure_us": int(exposure_us), "step_us": int(step_us),
                              "object_range": list(base.object_range), "object_rgb": list(scene.object_rgb),
                              "background_tint": scene.background_tint, "band_limited": bool(band_limited),
                              "speed_px_per_s": float(speed_px_per_s),
                              "crf": "gamma 1/2.2, 8-bit", "gt_units": "frame_linear"})
    return Recording(events, ss, fr, empty_triggers(), hdr, md), scene


# -- photometric calibration: a textured HDR scene seen through random homographies ------------------------

def hdr_scene(height: int, width: int, seed: int = 0, log_std: float = 1.2) -> np.ndarray:
    """float32 radiance ``exp(L)`` with ``L`` a sum of smooth random fields at 3, 8 and 24 px
    scales, standardised to ``log_std`` natural-log units (about 2 decades from the 1st to the
    99th percentile)."""
    import cv2
    rng = np.random.default_rng(seed)
    L = np.zeros((height, width))
    for s in (3, 8, 24):
        n = rng.normal(0.0, 1.0, (height // s + 2, width // s + 2))
        L += cv2.resize(n, (width, height), interpolation=cv2.INTER_CUBIC)
    L = (L - L.mean()) / L.std() * log_std
    return np.exp(L).astype(np.float32)


def random_homography(height: int, width: int, rng, shift_px: float = 8.0, rot_deg: float = 3.0,
                      scale: float = 0.03, persp: float = 2e-5) -> np.ndarray:
    """Small rotation about the centre, scale, perspective and translation (normalised H)."""
    a = np.deg2rad(rng.uniform(-rot_deg, rot_deg))
    c, s = np.cos(a), np.sin(a)
    cx, cy = width / 2.0, height / 2.0
    T1 = np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1.0]])
    T2 = np.array([[1, 0, cx], [0, 1, cy], [0, 0, 1.0]])
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    k = rng.uniform(1 - scale, 1 + scale)
    S = np.diag([k, k, 1.0])
    P = np.array([[1, 0, 0], [0, 1, 0], [rng.uniform(-persp, persp), rng.uniform(-persp, persp), 1.0]])
    Tr = np.array([[1, 0, rng.uniform(-shift_px, shift_px)], [0, 1, rng.uniform(-shift_px, shift_px)], [0, 0, 1.0]])
    H = Tr @ T2 @ P @ R @ S @ T1
    return H / H[2, 2]


def render_frame(radiance: np.ndarray, H: np.ndarray, exposure: float, rng, *, gamma: float = 2.2,
                 noise_dn: float = 0.5) -> np.ndarray:
    """8-bit frame of ``radiance`` warped by ``H`` (reference -> frame), times ``exposure``,
    through ``z = 255 clip(X)^(1/gamma)`` with Gaussian read noise of ``noise_dn`` codes."""
    import cv2
    h, w = radiance.shape[:2]
    warped = cv2.warpPerspective(radiance, H, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    z = 255.0 * np.clip(warped * exposure, 0, 1) ** (1.0 / gamma) + rng.normal(0.0, noise_dn, warped.shape)
    return np.clip(np.round(z), 0, 255).astype(np.uint8)


# -- sensor calibration scene: moving texture, static patch, saturated flicker -------------------

@dataclass(frozen=True)
class SensorCalibrationScene:
    """Analytic scene for the sensor-profile round trip (``calibrate sensor``): three regions with
    known roles, in radiance units where 1.0 fills the frames at the default camera below.

    * ``x < texture_width``: a texture (three plane waves, radiance 0.06-0.66, well exposed)
      translating at ``speed_px_per_s``: the threshold estimator's frame intervals;
    * the rest, rows ``y < static_height``: a constant patch (radiance 0.3): only shot noise and
      leak fire there;
    * the rest, rows below: a patch that flickers between radiance 2 and ``2·e^flicker_ln``
      (saturating the frames) with ramps linear in ln I over ``ramp_us``, every
      ``flicker_period_us``: bursts whose same-pixel intervals pile up at the refractory period.
    """

    sensor_size: SensorSize = SensorSize(32, 64)
    seed: int = 0
    texture_width: int = 36
    static_height: int = 18
    speed_px_per_s: float = 60.0
    flicker_ln: float = 12.0
    ramp_us: int = 1500
    flicker_period_us: int = 40_000

    def _waves(self):
        rng = np.random.default_rng([int(self.seed), 29])
        kx = rng.uniform(0.04, 0.1, 3) * 2 * np.pi * rng.choice([-1, 1], 3)
        ky = rng.uniform(-0.05, 0.05, 3) * 2 * np.pi
        return kx, ky, rng.uniform(0, 2 * np.pi, 3)

    def flicker_log(self, t_us) -> float:
        """ln I of the flicker patch above its low level at ``t_us`` (0 .. flicker_ln)."""
        ph = float(t_us) % self.flicker_period_us
        half = self.flicker_period_us / 2
        r = self.ramp_us
        if ph < r:
            return self.flicker_ln * ph / r
        if ph < half:
            return self.flicker_ln
        if ph < half + r:
            return self.flicker_ln * (1 - (ph - half) / r)
        return 0.0

    def intensity(self, t_us) -> np.ndarray:
        h, w = self.sensor_size.shape
        kx, ky, ph = self._waves()
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        x0 = self.speed_px_per_s * float(t_us) * 1e-6
        s = sum(np.sin(kx[i] * (xx - x0) + ky[i] * yy + ph[i]) for i in range(3)) / 3
        out = np.exp(np.log(0.2) + 1.2 * s)
        right = xx >= self.texture_width
        out[right & (yy < self.static_height)] = 0.3
        out[right & (yy >= self.static_height)] = 2.0 * np.exp(self.flicker_log(t_us))
        return out

    def region(self, name: str) -> np.ndarray:
        """Mask of ``"texture"``, ``"static"`` or ``"flicker"`` (bool (H, W))."""
        h, w = self.sensor_size.shape
        yy, xx = np.mgrid[0:h, 0:w]
        right = xx >= self.texture_width
        masks = {"texture": ~right, "static": right & (yy < self.static_height),
                 "flicker": right & (yy >= self.static_height)}
        if name not in masks:
            raise ValueError(f"region must be one of {sorted(masks)}, got {name!r}")
        return masks[name]


class _CalibrationSource(AnalyticSceneSource):
    """:class:`SensorCalibrationScene` as a ``RadianceSource`` (simulate/source.py)."""

    def max_image_speed_px_per_s(self, t0_us: int, t1_us: int) -> float:
        return float(self.scene.speed_px_per_s)

    def describe(self) -> dict:
        return {"source": "hybridhdr.simulate.procedural.SensorCalibrationScene", "seed": self.scene.seed,
                "speed_px_per_s": self.scene.speed_px_per_s, "flicker_ln": self.scene.flicker_ln,
                "ramp_us": self.scene.ramp_us, "flicker_period_us": self.scene.flicker_period_us}


def sensor_calibration_recording(sensor, *, seed: int = 0, duration_us: int = 2_000_000,
                                 scene: SensorCalibrationScene | None = None, frame_rate_hz: float = 25.0,
                                 exposure_us: int = 2000, render_rate_hz: float = 4000.0):
    """Simulate :class:`SensorCalibrationScene` through the simulator's sensor (``sensor``: preset
    name, ``EventSensorParams``, profile path or ``builtin:NAME``) and an 8-bit gamma-2.2 frame camera
    (radiance 1 fills the well over ``exposure_us``), rendered at a fixed ``render_rate_hz``.

    Returns ``(recording, scene, sensor_params)``; the recording's provenance holds the sensor's
    parameters and the simulated per-pixel thresholds are reproducible from the seed."""
    from .camera import FrameCameraParams
    from .pipeline import simulate
    from .sampling import SamplingParams
    sc = scene or SensorCalibrationScene(seed=int(seed))
    cam = FrameCameraParams(frame_rate_hz=frame_rate_hz, exposure_us=int(exposure_us), crf="gamma",
                            electrons_per_radiance_s=1e4 / (int(exposure_us) * 1e-6))
    res = simulate(_CalibrationSource(sc, duration_us), sensor=sensor, camera=cam,
                   sampling=SamplingParams(mode="fixed", fixed_rate_hz=render_rate_hz), seed=seed, progress=False)
    return res.recording, sc, res.recording.metadata.provenance.get("sensor")
