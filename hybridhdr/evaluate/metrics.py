"""Image-quality metrics for reconstructed HDR video, with an explicit normalisation policy.

All metrics take **linear intensities**. A reconstruction and its reference rarely share units:
frame-anchored methods (AKF, CF, direct, frames, EDI) return intensity in the camera profile's
scaled-irradiance units (brightest frame code = 1, ``hybridhdr.reconstruct.Video``), while
references are scene radiance; events-only methods (``highpass``) return a *relative* intensity
exp(L̂) with an unknown offset and gain in log. Scoring therefore goes through three steps,
each stated in the result:

1. **Normalisation** (``normalise``), fitted once per sequence by least squares over all matched
   frames and all finite pixels:

   - ``"none"``: the reconstruction as is (use when both are in the same absolute units);
   - ``"scale"``: ``g·x``, g fitted in log intensity (an unknown camera gain/exposure);
   - ``"affine"``: ``g·x^a``, i.e. affine in log intensity (a relative, events-only
     reconstruction: log intensity up to an offset, and a scale if its threshold is off);
   - ``"scale_linear"``, ``"affine_linear"``: the same fitted by linear least squares.

   Fits in log weigh all pixels alike; a linear fit on an HDR scene is decided by its brightest
   pixels (:func:`fit_normalisation`).

   Default (:data:`DEFAULT_NORMALISE`): ``"none"`` for every method, as the paper scores
   ("on the un-altered reconstruction and raw HDR intensities", Table 1). The evaluation's
   simulated references are in the reconstruction's **frame-linear units** (1.0 = the frame
   camera's clip level at the frame's exposure; :func:`hybridhdr.simulate.units.reference_to_frame_units`),
   so no fit is needed. The fits stay available by name (``normalise="scale"`` etc.), e.g. for
   events-only ``highpass``, whose output is relative, or for references in other units.
2. **Range**: both are divided by the reference's maximum over the sequence (one common
   constant, so an unaltered reconstruction keeps its units relative to the reference), so
   the reference lies in [0, 1]. By default (``clip="none"``, :data:`DEFAULT_CLIP`) the
   reconstruction is **not clipped**: scoring is symmetric, an overshoot costs as much as an
   undershoot of the same size, as in the AKF authors' evaluation
   (``ziweiWWANG/Event-Asynchronous-Filter: code/eval/anal_hdr_results.m`` scores the raw
   output ``td_img*255`` against the reference, ``computeMSE_range01.m`` divides both by 255
   and clips neither). ``clip="reference_max"`` keeps the former policy by name: the
   reconstruction clipped to [0, 1] (as EVREAL does, ``ercanburak/EVREAL:utils/eval_metrics.py``),
   which makes overshoot above the reference maximum free. MSE, PSNR and SSIM then use
   **data range 1**; PU21 clips luminance at 10 000 cd/m² whatever the policy.
3. **Absolute luminance** for PU21 and HDR-VDP: the [0, 1] images are multiplied by
   ``peak_luminance_cd_m2`` (default 4000 cd/m², as ``I/max·4000`` in the PU21 usage notes)
   before encoding.

Metrics
-------
- :func:`mse`, :func:`psnr` (``10·log10(R²/MSE)``, R = data range).
- :func:`ssim`: mean SSIM with a Gaussian window (σ = 1.5, truncated at 3.5σ, reflect
  boundary), population covariance, K1 = 0.01, K2 = 0.03, the border of width
  ``int(3.5σ + 0.5)`` cropped before averaging: the settings of scikit-image's
  ``structural_similarity(..., gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=R)``, which match Wang et al. 2004 (doi:10.1109/TIP.2003.819861). Own
  implementation with :func:`scipy.ndimage.gaussian_filter`; equal to scikit-image to 1e-6
  (tested).
- :func:`global_ssim`: **global SSIM**, a single window over the whole image. ``variant="eaf"``
  reproduces the AKF follow-up's evaluation code (``ziweiWWANG/Event-Asynchronous-Filter:
  code/eval/computeSSIM.m``: per-column means, whole-image *sample* covariance, L = 255, and a
  MATLAB ``/`` between row vectors, i.e. a least-squares ratio); ``variant="standard"`` uses the
  whole-image means, population variances and covariance. It is *not* comparable with
  windowed SSIM.
- :func:`pu21_encode`, :func:`pu_psnr`, :func:`pu_ssim`: PU21 (Mantiuk & Azimi, "PU21: A novel
  perceptually uniform encoding for adapting existing quality metrics for HDR", PCS 2021,
  doi:10.1109/PCS50896.2021.9477471). ``V = p6·(((p0 + p1·Y^p3)/(1 + p2·Y^p3))^p4 − p5)`` with
  Y clipped to [0.005, 10000] cd/m²; PU-PSNR and PU-SSIM use a peak / data range of 256 as in
  the authors' ``gfxdisp/pu21:matlab/pu21_metric.m`` (``peak="pu_max"`` uses PU(10000)).
- :func:`jod_score`: ColorVideoVDP JOD (:mod:`hybridhdr.evaluate.cvvdp_metric`), the default
  perceptual metric: on at most :data:`JOD_MAX_FRAMES` (8) evenly spaced matched frames per
  sequence, each scored as an image against its reference (the mean JOD), on the [0, 1] pair
  (step 2), with the display model stated (``jod_display_line``). Without cvvdp/PyTorch the
  score is NaN with ``jod_note`` = :data:`JOD_NA`.
- :func:`hdrvdp_q`: HDR-VDP 3 Q through the user's own installation (GNU Octave or MATLAB),
  kept for exact comparison with the paper's Q.
- :func:`score_akf2021`: the AKF authors' evaluation protocol on their HDR/AHDR sequences.
- :func:`log_pair`: ``log_mse`` and ``log_ssim``, MSE and SSIM on log intensity mapped to [0, 1]
  by the reference's log range (floored at 1e-4 of the reference maximum): HDR-aware, every
  decade weighs alike; the linear metrics are decided by the brightest pixels.
- :func:`match_frames`: pair reconstructed frames with references by timestamp.
- :func:`score_video`: everything above on a matched sequence, plus the count of non-finite
  reconstructed pixels (numerical failures).
"""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .._util.checks import check_shape
from . import cvvdp_metric

__all__ = ["NORMALISE_MODES", "DEFAULT_NORMALISE", "CLIP_POLICIES", "DEFAULT_CLIP", "default_normalise", "mse", "psnr",
           "ssim", "ssim_map", "global_ssim",
           "PU21_PARAMS", "pu21_encode", "pu_psnr", "pu_ssim", "match_frames", "fit_normalisation",
           "normalise_pair", "apply_normalisation", "log_pair", "score_video", "pixels_per_degree", "HDRVDPResult", "hdrvdp_q",
           "find_hdrvdp", "HDRVDPNotFound", "JOD_MAX_FRAMES", "JOD_NA", "jod_frame_indices", "jod_score",
           "score_akf2021", "AKF2021"]

NORMALISE_MODES = ("none", "scale", "affine", "scale_linear", "affine_linear")
#: Per-method default normalisation (methods not listed: "none", the unaltered reconstruction, as
#: in the paper's Table 1). The learned events-only methods output a relative intensity in
#: [0, 1] (the display-referred scale of their training frames), so they are scored after a
#: fitted gain ("scale"); reports label such runs.
DEFAULT_NORMALISE: dict = {"e2vid": "scale", "firenet": "scale"}


#: Range policies of :func:`normalise_pair`: ``"none"`` (default: the reconstruction as it is,
#: symmetric) and ``"reference_max"`` (the reconstruction clipped to [0, 1] of the reference maximum).
CLIP_POLICIES = ("none", "reference_max")
DEFAULT_CLIP = "none"


def default_normalise(method: str) -> str:
    """The default normalisation for a reconstruction method: ``"none"`` (see the module docstring)."""
    return DEFAULT_NORMALISE.get(method, "none")


def _pair(a, b, name="images"):
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"{name}: test and reference must have the same shape, got {a.shape} and {b.shape}")
    if a.size == 0:
        raise ValueError(f"{name}: empty images (shape {a.shape})")
    return a, b


def mse(test, reference) -> float:
    """Mean squared error over all pixels (and frames)."""
    a, b = _pair(test, reference, "mse")
    return float(np.mean((a - b) ** 2))


def psnr(test, reference, data_range: float = 1.0) -> float:
    """PSNR in dB, ``10·log10(data_range² / MSE)``; ``inf`` for identical images."""
    if not data_range > 0:
        raise ValueError(f"data_range must be > 0, got {data_range}")
    m = mse(test, reference)
    if m == 0:
        return math.inf
    return float(10.0 * math.log10(data_range ** 2 / m))


def _ssim2d(x, y, data_range, sigma, truncate, k1, k2):
    s, r = _ssim_map2d(x, y, data_range, sigma, truncate, k1, k2)
    return float(s[r:s.shape[0] - r, r:s.shape[1] - r].mean(dtype=np.float64))


def ssim_map(test, reference, data_range: float = 1.0, *, sigma: float = 1.5, truncate: float = 3.5,
             k1: float = 0.01, k2: float = 0.03) -> tuple[np.ndarray, int]:
    """The per-pixel SSIM map of :func:`ssim` (same settings) and its border width ``r``.

    For (K, H, W) input the maps are stacked. :func:`ssim` is the mean of the map with the border
    of width ``r`` cropped; a masked SSIM is the mean over the mask's pixels (border cropped).
    """
    a, b = _pair(test, reference, "ssim_map")
    if a.ndim == 2:
        return _ssim_map2d(a, b, data_range, sigma, truncate, k1, k2)
    check_shape(a, "K H W", "ssim_map: images (or (H, W))")
    maps = [_ssim_map2d(x, y, data_range, sigma, truncate, k1, k2) for x, y in zip(a, b)]
    return np.stack([m for m, _ in maps]), maps[0][1] if maps else int(truncate * sigma + 0.5)


def _ssim_map2d(x, y, data_range, sigma, truncate, k1, k2):
    from scipy.ndimage import gaussian_filter
    r = int(truncate * sigma + 0.5)
    if min(x.shape) < 2 * r + 1:
        raise ValueError(f"ssim: images must be at least {2 * r + 1}x{2 * r + 1} px for sigma={sigma}, "
                         f"got {x.shape[1]}x{x.shape[0]}")

    def f(z):
        return gaussian_filter(z, sigma, truncate=truncate, mode="reflect")
    ux, uy = f(x), f(y)
    vx = f(x * x) - ux * ux
    vy = f(y * y) - uy * uy
    vxy = f(x * y) - ux * uy
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return s, r


def ssim(test, reference, data_range: float = 1.0, *, sigma: float = 1.5, truncate: float = 3.5,
         k1: float = 0.01, k2: float = 0.03) -> float:
    """Mean SSIM with a Gaussian window (Wang et al. 2004, doi:10.1109/TIP.2003.819861).

    Parameters
    ----------
    test, reference : ndarray of shape (H, W) or (K, H, W)
        For (K, H, W) the per-frame SSIMs are averaged.
    data_range : float
        R in C1 = (K1 R)², C2 = (K2 R)².

    Notes
    -----
    Same value as ``skimage.metrics.structural_similarity(test, reference,
    gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=R)`` per frame
    (tested to 1e-6).
    """
    a, b = _pair(test, reference, "ssim")
    if not data_range > 0:
        raise ValueError(f"data_range must be > 0, got {data_range}")
    if a.ndim == 2:
        return _ssim2d(a, b, data_range, sigma, truncate, k1, k2)
    if a.ndim == 3:
        return float(np.mean([_ssim2d(x, y, data_range, sigma, truncate, k1, k2) for x, y in zip(a, b)]))
    raise ValueError(f"ssim: expected images of shape (H, W) or (K, H, W), got {a.shape}")


def global_ssim(test, reference, data_range: float = 255.0, *, variant: str = "eaf") -> float:
    """Global SSIM: one window over the whole image (the AKF follow-up's evaluation).

    Parameters
    ----------
    test, reference : ndarray (H, W) or (K, H, W)
        For ``variant="eaf"`` the follow-up scales the reconstruction by 255 and uses L = 255.
    variant : {"eaf", "standard"}
        ``"eaf"``: as ``ziweiWWANG/Event-Asynchronous-Filter:code/eval/computeSSIM.m``: column
        means μ (row vectors), the 2×2 *sample* covariance of the flattened images, and MATLAB's
        right division of the numerator row vector by the denominator row vector, which is the
        least-squares scalar ``sum(n·d)/sum(d·d)``. ``"standard"``: whole-image means,
        population variances and covariance, one window.
    """
    a, b = _pair(test, reference, "global_ssim")
    if variant not in ("eaf", "standard"):
        raise ValueError(f"variant must be 'eaf' or 'standard', got {variant!r}")
    if a.ndim == 3:
        return float(np.mean([global_ssim(x, y, data_range, variant=variant) for x, y in zip(a, b)]))
    check_shape(a, "H W", "global_ssim: images (or (K, H, W))")
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    if variant == "standard":
        mx, my = a.mean(), b.mean()
        vx, vy = a.var(), b.var()
        vxy = np.mean((a - mx) * (b - my))
        return float(((2 * mx * my + c1) * (2 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2)))
    mu1, mu2 = a.mean(axis=0), b.mean(axis=0)
    cov = np.cov(a.ravel(), b.ravel())  # sample covariance (N - 1), as MATLAB cov
    num = (2 * mu1 * mu2 + c1) * (2 * cov[0, 1] + c2)
    den = (mu1 ** 2 + mu2 ** 2 + c1) * (cov[0, 0] + cov[1, 1] + c2)
    return float(np.dot(num, den) / np.dot(den, den))


# -- PU21 ---------------------------------------------------------------------------------------

#: PU21 parameters p0..p6 (Mantiuk & Azimi 2021, doi:10.1109/PCS50896.2021.9477471; values as in
#: ``docs/calibrate.md`` and the authors' ``gfxdisp/pu21``).
PU21_PARAMS = {
    "banding_glare": (0.353487901, 0.3734658629, 8.277049286e-05, 0.9062562627, 0.09150303166,
                      0.9099517204, 596.3148142),
    "banding": (1.070275272, 0.4088273932, 0.153224308, 0.2520326168, 1.063512885, 1.14115047,
                521.4527484),
}
PU21_L_MIN_CD_M2 = 0.005
PU21_L_MAX_CD_M2 = 10000.0
#: Peak / data range used by the authors' ``pu21_metric.m`` for PSNR and SSIM on PU values.
PU21_METRIC_PEAK = 256.0


def pu21_encode(luminance_cd_m2, variant: str = "banding_glare") -> np.ndarray:
    """PU21 encoding of absolute luminance (cd/m²): ``p6·(((p0 + p1 Y^p3)/(1 + p2 Y^p3))^p4 − p5)``.

    Y is clipped to [0.005, 10000] cd/m² first. About 0 at 0.005 cd/m² and ≈ 256 near
    100 cd/m² (the range of an SDR display); NaN stays NaN.
    """
    if variant not in PU21_PARAMS:
        raise ValueError(f"unknown PU21 variant {variant!r}; expected one of {sorted(PU21_PARAMS)}")
    p0, p1, p2, p3, p4, p5, p6 = PU21_PARAMS[variant]
    y = np.clip(np.asarray(luminance_cd_m2, dtype=np.float64), PU21_L_MIN_CD_M2, PU21_L_MAX_CD_M2)
    yp = y ** p3
    return p6 * (((p0 + p1 * yp) / (1.0 + p2 * yp)) ** p4 - p5)


def _pu_peak(peak, variant):
    if peak == "pu_max":
        return float(pu21_encode(PU21_L_MAX_CD_M2, variant))
    if isinstance(peak, (int, float)) and peak > 0:
        return float(peak)
    raise ValueError(f"peak must be a positive number or 'pu_max', got {peak!r}")


def pu_psnr(test_cd_m2, reference_cd_m2, *, peak=PU21_METRIC_PEAK, variant: str = "banding_glare") -> float:
    """PSNR (dB) of PU21-encoded absolute luminance; peak 256 as ``gfxdisp/pu21`` (or "pu_max")."""
    a, b = _pair(test_cd_m2, reference_cd_m2, "pu_psnr")
    return psnr(pu21_encode(a, variant), pu21_encode(b, variant), _pu_peak(peak, variant))


def pu_ssim(test_cd_m2, reference_cd_m2, *, peak=PU21_METRIC_PEAK, variant: str = "banding_glare") -> float:
    """SSIM (Gaussian σ = 1.5) of PU21-encoded absolute luminance, data range 256 (or "pu_max")."""
    a, b = _pair(test_cd_m2, reference_cd_m2, "pu_ssim")
    return ssim(pu21_encode(a, variant), pu21_encode(b, variant), _pu_peak(peak, variant))


# -- matching and normalisation -----------------------------------------------------------------

def match_frames(video_t_us, ref_t_us, tolerance_us: int) -> tuple[np.ndarray, np.ndarray]:
    """Pair each reference time with the nearest reconstructed frame within ``tolerance_us``.

    Parameters
    ----------
    video_t_us, ref_t_us : array_like of int64 (µs), non-decreasing
    tolerance_us : int
        Largest accepted ``|t_video − t_ref|`` in µs (inclusive). Ties pick the earlier frame.

    Returns
    -------
    video_index, ref_index : int64 arrays of equal length
        References with no frame within the tolerance are left out.
    """
    v = np.asarray(video_t_us)
    r = np.asarray(ref_t_us)
    for name, t in (("video_t_us", v), ("ref_t_us", r)):
        if t.ndim != 1 or (t.size and t.dtype.kind not in "iu"):
            raise TypeError(f"{name} must be a 1-D integer array of µs, got shape {t.shape} dtype {t.dtype}")
        if t.size > 1 and np.any(np.diff(t) < 0):
            i = int(np.flatnonzero(np.diff(t) < 0)[0]) + 1
            raise ValueError(f"{name} must be non-decreasing; index {i} has {int(t[i])} after {int(t[i - 1])}")
    if isinstance(tolerance_us, bool) or not isinstance(tolerance_us, (int, np.integer)) or tolerance_us < 0:
        raise ValueError(f"tolerance_us must be an int >= 0 (µs), got {tolerance_us!r}")
    if v.size == 0 or r.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    v = v.astype(np.int64)
    r = r.astype(np.int64)
    j = np.searchsorted(v, r, side="left")
    lo = np.clip(j - 1, 0, v.size - 1)
    hi = np.clip(j, 0, v.size - 1)
    dlo, dhi = np.abs(r - v[lo]), np.abs(v[hi] - r)
    best = np.where(dlo <= dhi, lo, hi)
    d = np.minimum(dlo, dhi)
    ok = d <= tolerance_us
    return best[ok].astype(np.int64), np.flatnonzero(ok).astype(np.int64)


def fit_normalisation(test, reference, mode: str) -> tuple[float, float]:
    """Least-squares ``(gain, offset)`` or ``(gain, exponent)`` mapping ``test`` onto ``reference``.

    ``"none"`` → (1, 0).

    ``"scale"`` → ``(g, 0)`` with ``log g = mean(log r − log x)`` over pixels where both are
    positive and finite: the least-squares fit of a gain **in log intensity**. A camera gain is
    multiplicative; a linear least-squares fit would be decided by the few brightest pixels of an
    HDR scene (a saturated frame then sets the gain of the whole image), the log fit weighs every
    pixel alike.

    ``"affine"`` → ``(g, a)`` with ``log r ≈ a·log x + log g`` (least squares in log intensity):
    an events-only reconstruction recovers log intensity up to an offset, and up to a scale when
    its contrast threshold is off, so it maps as ``r = g·x^a``.

    ``"scale_linear"`` → ``(<x,r>/<x,x>, 0)``; ``"affine_linear"`` → linear regression
    ``(gain, offset)``: for data whose units are already nearly right.

    A degenerate fit (no usable pixel, constant input) falls back to the identity or to matching
    the means.
    """
    if mode not in NORMALISE_MODES:
        raise ValueError(f"normalise must be one of {NORMALISE_MODES}, got {mode!r}")
    a, b = _pair(test, reference, "normalise")
    if mode == "none":
        return 1.0, 0.0
    ok = np.isfinite(a) & np.isfinite(b)
    if mode in ("scale", "affine"):
        ok &= (a > 0) & (b > 0)
        if not ok.any():
            return 1.0, (0.0 if mode == "scale" else 1.0)
        lx, lr = np.log(a[ok]), np.log(b[ok])
        if mode == "scale":
            return float(np.exp(np.mean(lr - lx))), 0.0
        mx, mr = float(lx.mean()), float(lr.mean())
        vx = float(np.mean((lx - mx) ** 2))
        if vx <= 0:
            return float(np.exp(mr - mx)), 1.0
        e = float(np.mean((lx - mx) * (lr - mr)) / vx)
        return float(np.exp(mr - e * mx)), e
    x, r = a[ok], b[ok]
    if x.size == 0:
        return 1.0, 0.0
    if mode == "scale_linear":
        xx = float(np.dot(x, x))
        return (float(np.dot(x, r) / xx) if xx > 0 else 1.0), 0.0
    mx, mr = float(x.mean()), float(r.mean())
    vx = float(np.mean((x - mx) ** 2))
    if vx <= 0:
        return 1.0, mr - mx
    g = float(np.mean((x - mx) * (r - mr)) / vx)
    return g, mr - g * mx


def apply_normalisation(test, gain: float, second: float, mode: str) -> np.ndarray:
    """Apply a :func:`fit_normalisation` result (``second`` = offset, or exponent for "affine")."""
    x = np.asarray(test, dtype=np.float64)
    if mode == "affine":
        with np.errstate(invalid="ignore"):
            return gain * np.where(x > 0, np.abs(x), 0.0) ** second
    return gain * x + second


def normalise_pair(test, reference, mode: str = "none", clip: str = DEFAULT_CLIP):
    """Apply the policy of the module docstring: fit, divide by the reference max, clip by ``clip``.

    Returns ``(test01, ref01, info)``: the reference in [0, 1], the test as the fit and the
    division leave it (``clip="none"``, default: symmetric scoring) or clipped to [0, 1]
    (``clip="reference_max"``), NaN kept; ``info`` holds the gain, offset, the reference maximum
    (the unit of the [0, 1] range) and the clip policy.
    """
    if clip not in CLIP_POLICIES:
        raise ValueError(f"clip must be one of {CLIP_POLICIES}, got {clip!r}")
    a, b = _pair(test, reference, "normalise")
    g, o = fit_normalisation(a, b, mode)
    ref_max = float(np.nanmax(b)) if np.isfinite(b).any() else float("nan")
    if not ref_max > 0:
        raise ValueError(f"the reference must have a positive maximum, got {ref_max}")
    t = apply_normalisation(a, g, o, mode) / ref_max
    if clip == "reference_max":
        with np.errstate(invalid="ignore"):
            t = np.where(np.isnan(t), np.nan, np.clip(t, 0.0, 1.0))
    second = "exponent" if mode == "affine" else "offset"
    return t, np.clip(b / ref_max, 0.0, 1.0), {"gain": g, "offset": o if second == "offset" else 0.0,
                                                "exponent": o if second == "exponent" else 1.0,
                                                "reference_max": ref_max, "normalise": mode, "clip": clip}


def log_pair(test01, ref01, floor: float = 1e-4, clip: str = DEFAULT_CLIP):
    """Log intensity of [0, 1] images mapped to [0, 1] by the reference's log range.

    ``v = (log max(I, floor) − lo)/(hi − lo)`` with ``lo``, ``hi`` the min and max of the
    reference's ``log max(I, floor)``; the test is floored at ``lo`` (a log needs a floor) and,
    with ``clip="reference_max"`` only, clipped at 1; NaN kept. This is the HDR-aware scoring of
    ``hybridhdr demo`` (every decade of intensity weighs alike), used for ``log_mse`` and
    ``log_ssim``.
    """
    if not 0 < floor < 1:
        raise ValueError(f"log floor must be in (0, 1), got {floor}")
    if clip not in CLIP_POLICIES:
        raise ValueError(f"clip must be one of {CLIP_POLICIES}, got {clip!r}")
    a, b = _pair(test01, ref01, "log_pair")
    lr = np.log(np.maximum(b, floor))
    with np.errstate(invalid="ignore"):
        lt = np.log(np.where(np.isnan(a), np.nan, np.maximum(a, floor)))
    lo, hi = float(lr.min()), float(lr.max())
    span = (hi - lo) or 1.0
    top = 1.0 if clip == "reference_max" else np.inf
    with np.errstate(invalid="ignore"):
        t = np.where(np.isnan(lt), np.nan, np.clip((lt - lo) / span, 0.0, top))
    return t, (lr - lo) / span


#: At most this many matched frames per sequence are scored with ColorVideoVDP (evenly spaced).
JOD_MAX_FRAMES = 8
#: The JOD cell when cvvdp or PyTorch is not installed.
JOD_NA = "n/a (install hybridhdr[evaluate])"


def jod_frame_indices(n: int, max_frames: int = JOD_MAX_FRAMES) -> np.ndarray:
    """``min(n, max_frames)`` evenly spaced indices of ``n`` frames, first and last included."""
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 1:
        raise ValueError(f"max_frames must be an int >= 1, got {max_frames!r}")
    if n <= 0:
        return np.zeros(0, np.int64)
    return np.unique(np.rint(np.linspace(0, n - 1, min(n, int(max_frames)))).astype(np.int64))


def jod_score(test01, ref01, *, max_frames: int = JOD_MAX_FRAMES, display: str | None = None) -> dict:
    """ColorVideoVDP JOD of (K, H, W) sequences already in [0, 1] (:func:`normalise_pair`).

    At most ``max_frames`` evenly spaced frames (:func:`jod_frame_indices`), each scored as an
    image (they are not consecutive, so cvvdp's temporal channels are not used), averaged.
    Returns ``jod`` (10 = identical), ``jod_frames``, ``jod_display``, ``jod_display_line`` (the
    display model and viewing distance), ``jod_seconds``; without cvvdp/PyTorch ``jod`` is NaN
    and ``jod_note`` says :data:`JOD_NA` (never an exception).
    """
    a, b = _pair(test01, ref01, "jod_score")
    if a.ndim == 2:
        a, b = a[None], b[None]
    idx = jod_frame_indices(a.shape[0], max_frames)
    display = display or cvvdp_metric.DEFAULT_DISPLAY
    out = {"jod_frames": int(idx.size), "jod_display": display}
    if not (np.isfinite(a[idx]).all() and np.isfinite(b[idx]).all()):
        out.update(jod=float("nan"), jod_note="non-finite pixels")
        return out
    try:
        r = cvvdp_metric.cvvdp_jod(a[idx], b[idx], fps=0.0, display=display)
    except cvvdp_metric.CVVDPNotAvailable:
        out.update(jod=float("nan"), jod_note=JOD_NA)
        return out
    out.update(jod=r.jod, jod_display_line=r.display_line(), jod_seconds=r.seconds, jod_note="")
    return out


def score_video(test_frames, reference_frames, *, normalise: str = "none", peak_luminance_cd_m2: float = 4000.0,
                pu21: bool = True, hdrvdp: dict | None = None, log_floor: float = 1e-4,
                jod: dict | bool | None = None, per_frame: bool = False, clip: str = DEFAULT_CLIP) -> dict:
    """All metrics on matched sequences (K, H, W) of linear intensity.

    Parameters
    ----------
    test_frames, reference_frames : ndarray of shape (K, H, W)
        Already matched in time (:func:`match_frames`). NaN/Inf in ``test_frames`` are counted
        in ``n_nonfinite`` and make the metrics NaN (a numerical failure is never hidden).
    normalise : {"none", "scale", "affine", "scale_linear", "affine_linear"}
        ``"none"`` (default): the unaltered reconstruction; the others fit a gain (and offset or
        exponent) first (:func:`fit_normalisation`).
    peak_luminance_cd_m2 : float
        Luminance of the reference maximum for PU21 and HDR-VDP (cd/m²).
    clip : {"none", "reference_max"}
        ``"none"`` (default): the reconstruction is not clipped (symmetric scoring, as the AKF
        authors' evaluation); ``"reference_max"``: clipped to [0, 1] of the reference maximum.
    hdrvdp : dict, optional
        Keyword arguments for :func:`hdrvdp_q` (e.g. ``{"hdrvdp_dir": ...}``); when given, Q is
        the mean over frames and its settings are stored under ``q_*``.

    log_floor : float
        Floor of the [0, 1] intensities before the log of ``log_mse``/``log_ssim`` (1e-4: a
        10 000:1 range).
    jod : dict or bool, optional
        ColorVideoVDP JOD (:func:`jod_score`) on the same [0, 1] pair: ``True`` or keyword
        arguments (``max_frames``, ``display``); ``None``/``False``: not computed.
    per_frame : bool
        Also return ``frames``: one dict per frame (``index``, ``n_nonfinite``, ``mse``,
        ``psnr_db``, ``ssim``, ``log_mse``, ``log_ssim``, ``pu_psnr_db``, ``pu_ssim`` and, with
        HDR-VDP, ``q``), scored on the same normalised pair as the aggregates (one gain and one
        log range for the whole sequence): the mean of the per-frame MSE and SSIM is the
        aggregate MSE and SSIM.

    Returns
    -------
    dict with ``mse``, ``psnr_db``, ``ssim``, ``global_ssim`` (EAF variant, on ×255),
    ``log_mse``, ``log_ssim`` (:func:`log_pair`),
    ``pu_psnr_db``, ``pu_ssim``, ``n_frames``, ``n_nonfinite``, ``gain``, ``offset``,
    ``reference_max``, ``normalise``, (with ``hdrvdp``) ``q`` plus its settings and (with
    ``per_frame``) ``frames``.
    """
    a, b = _pair(test_frames, reference_frames, "score_video")
    check_shape(a, "K H W", "score_video: sequences")
    if not peak_luminance_cd_m2 > 0:
        raise ValueError(f"peak_luminance_cd_m2 must be > 0, got {peak_luminance_cd_m2}")
    n_bad = int(np.count_nonzero(~np.isfinite(a)))
    t01, r01, info = normalise_pair(a, b, normalise, clip)
    out = {"n_frames": int(a.shape[0]), "n_nonfinite": n_bad}
    out.update(info)
    out["mse"] = mse(t01, r01)
    out["psnr_db"] = psnr(t01, r01, 1.0) if np.isfinite(out["mse"]) else float("nan")
    out["ssim"] = ssim(t01, r01, 1.0)
    out["global_ssim"] = global_ssim(t01 * 255.0, r01 * 255.0, 255.0, variant="eaf")
    lt_, lr_ = log_pair(t01, r01, log_floor, clip)
    out["log_mse"] = mse(lt_, lr_)
    out["log_ssim"] = ssim(lt_, lr_, 1.0)
    if pu21:
        lt, lr = t01 * peak_luminance_cd_m2, r01 * peak_luminance_cd_m2
        out["pu_psnr_db"] = pu_psnr(lt, lr) if n_bad == 0 else float("nan")
        out["pu_ssim"] = pu_ssim(lt, lr) if n_bad == 0 else float("nan")
        out["peak_luminance_cd_m2"] = float(peak_luminance_cd_m2)
    if hdrvdp is not None:
        kw = dict(hdrvdp)
        kw.setdefault("luminance_scale_cd_m2", peak_luminance_cd_m2)
        hdrvdp_res = None
        if n_bad:
            out["q"] = float("nan")
        else:
            res = hdrvdp_res = hdrvdp_q(t01, r01, **kw)
            out["q"] = res.q
            out.update({f"q_{k}": v for k, v in asdict(res).items() if k not in ("q", "q_frames")})
    if jod:
        kw = dict(jod) if isinstance(jod, dict) else {}
        out.update(jod_score(t01, r01, **kw))
    if per_frame:
        frames = []
        for k in range(a.shape[0]):
            bad = int(np.count_nonzero(~np.isfinite(a[k])))
            m = mse(t01[k], r01[k])
            f = {"index": k, "n_nonfinite": bad, "mse": m,
                 "psnr_db": psnr(t01[k], r01[k], 1.0) if np.isfinite(m) else float("nan"),
                 "ssim": ssim(t01[k], r01[k], 1.0), "log_mse": mse(lt_[k], lr_[k]), "log_ssim": ssim(lt_[k], lr_[k], 1.0)}
            if pu21:
                lt, lr = t01[k] * peak_luminance_cd_m2, r01[k] * peak_luminance_cd_m2
                f["pu_psnr_db"] = pu_psnr(lt, lr) if bad == 0 else float("nan")
                f["pu_ssim"] = pu_ssim(lt, lr) if bad == 0 else float("nan")
            if hdrvdp is not None:
                f["q"] = _frame_q(hdrvdp_res, k)
            frames.append(f)
        out["frames"] = frames
    return out


def _frame_q(res, k: int) -> float:
    """Frame ``k``'s HDR-VDP Q from a result's ``q_frames`` (NaN when not reported)."""
    qf = tuple(getattr(res, "q_frames", ()) or ())
    return float(qf[k]) if k < len(qf) else float("nan")


# -- the AKF authors' protocol ------------------------------------------------------------------

#: The AKF authors' evaluation (``hybridhdr evaluate metrics --protocol akf2021``).
AKF2021 = {"frame_unit": 255.0, "hdrvdp_task": "side-by-side", "hdrvdp_color_encoding": "luminance",
           "display_diagonal_in": 21.0, "display_resolution": (640, 480), "viewing_distance_m": 1.0,
           "luminance_scale_cd_m2": 255.0}


def score_akf2021(test_frames, reference_frames, *, hdrvdp: dict | None = None, per_frame: bool = False) -> dict:
    """Score as the AKF authors' evaluation of their HDR/AHDR sequences (Wang et al., ICCV 2021).

    - the **unaltered** reconstruction (frame-linear units: 1.0 = frame code 255, as the AKF
      outputs) against the reference's **channel mean / 255** (``HDR_mat`` is stored in code
      units), no normalisation, no clipping;
    - pixels where the reference is **0** (unregistered) are masked out of every metric;
    - MSE over the unmasked pixels of all frames, PSNR = 10·log10(1/MSE) (peak 1 = code 255),
      SSIM (Gaussian σ = 1.5, K1 = 0.01, K2 = 0.03, data range 1) as the mean of each frame's
      SSIM map over its unmasked pixels outside the border, averaged over frames;
    - HDR-VDP 3 Q (with ``hdrvdp``, keyword arguments of :func:`hdrvdp_q`): task
      ``side-by-side``, ``luminance`` encoding, the pixels per degree of a 21-inch 640×480
      display at 1 m (:func:`pixels_per_degree`, 26.4), frame units × 255 as cd/m² (the values
      as the files store them); masked pixels of the reconstruction are set to the reference's
      (0) so they add no difference.

    Parameters
    ----------
    test_frames : (K, H, W) reconstruction, frame-linear units
    reference_frames : (K, H, W, 3) or (K, H, W) references as stored (``HDR_mat``)
    per_frame : bool
        Also return ``frames``: per frame ``index``, ``n_nonfinite``, ``n_valid``, ``mse`` (over
        that frame's unmasked pixels), ``psnr_db``, ``ssim`` and, with HDR-VDP, ``q``.
    """
    a = np.asarray(test_frames, np.float64)
    r = np.asarray(reference_frames, np.float64)
    if r.ndim == 4:
        r = r.mean(axis=3)
    a, r = _pair(a, r, "akf2021")
    check_shape(a, "K H W", "score_akf2021: sequences")
    r = r / AKF2021["frame_unit"]
    mask = r != 0
    n_bad = int(np.count_nonzero(~np.isfinite(a)))
    out = {"protocol": "akf2021", "normalise": "none", "n_frames": int(a.shape[0]), "n_nonfinite": n_bad,
           "n_masked": int(np.count_nonzero(~mask)), "n_valid": int(np.count_nonzero(mask)),
           "reference_units": "HDR_mat channel mean / 255 (frame-linear)"}
    if not mask.any():
        raise ValueError("akf2021: every reference pixel is 0 (unregistered); nothing to score")
    m = float(np.mean((a[mask] - r[mask]) ** 2))
    out["mse"] = m
    out["psnr_db"] = float("inf") if m == 0 else (10.0 * math.log10(1.0 / m) if math.isfinite(m) else float("nan"))
    smap, rad = ssim_map(a, r, 1.0)
    inner = np.zeros_like(mask)
    inner[:, rad:mask.shape[1] - rad, rad:mask.shape[2] - rad] = True
    per = [float(smap[k][mask[k] & inner[k]].mean()) for k in range(a.shape[0]) if (mask[k] & inner[k]).any()]
    out["ssim"] = float(np.mean(per)) if per else float("nan")
    hdrvdp_res = None
    if hdrvdp is not None:
        kw = dict(hdrvdp)
        kw.update(task=AKF2021["hdrvdp_task"], color_encoding=AKF2021["hdrvdp_color_encoding"],
                  pixels_per_degree=pixels_per_degree(AKF2021["display_diagonal_in"], AKF2021["display_resolution"],
                                                      AKF2021["viewing_distance_m"]),
                  luminance_scale_cd_m2=AKF2021["luminance_scale_cd_m2"])
        if n_bad:
            out["q"] = float("nan")
        else:
            res = hdrvdp_res = hdrvdp_q(np.where(mask, a, r), r, **kw)
            out["q"] = res.q
            out.update({f"q_{k}": v for k, v in asdict(res).items() if k not in ("q", "q_frames")})
    if per_frame:
        frames = []
        for k in range(a.shape[0]):
            mk = mask[k]
            mf = float(np.mean((a[k][mk] - r[k][mk]) ** 2)) if mk.any() else float("nan")
            sel = mk & inner[k]
            f = {"index": k, "n_nonfinite": int(np.count_nonzero(~np.isfinite(a[k]))),
                 "n_valid": int(np.count_nonzero(mk)), "mse": mf,
                 "psnr_db": (float("inf") if mf == 0 else
                             10.0 * math.log10(1.0 / mf) if math.isfinite(mf) else float("nan")),
                 "ssim": float(smap[k][sel].mean()) if sel.any() else float("nan")}
            if hdrvdp is not None:
                f["q"] = _frame_q(hdrvdp_res, k)
            frames.append(f)
        out["frames"] = frames
    return out


# -- HDR-VDP 3 bridge ---------------------------------------------------------------------------

class HDRVDPNotFound(ImportError):
    """No HDR-VDP 3 installation or no Octave/MATLAB to run it."""


def pixels_per_degree(diagonal_in: float = 21.0, resolution_wh=(640, 480), distance_m: float = 1.0) -> float:
    """Pixels per visual degree of a display, from its vertical extent (a flat screen seen head on).

    ``height = diagonal / sqrt(1 + (w/h)²)``, ``ppd = h_px / (2·atan(height / (2·distance)))`` in
    degrees. The defaults are the AKF follow-up's setting (21-inch 640×480 display at 1 m,
    Wang et al. 2021, §6): about 26.4 ppd.
    """
    w, h = resolution_wh
    if not (diagonal_in > 0 and distance_m > 0 and w > 0 and h > 0):
        raise ValueError("diagonal_in, distance_m and the resolution must be > 0")
    height_m = diagonal_in * 0.0254 / math.sqrt(1.0 + (w / h) ** 2)
    return float(h / math.degrees(2.0 * math.atan(height_m / (2.0 * distance_m))))


_default_ppd = pixels_per_degree


@dataclass(frozen=True)
class HDRVDPResult:
    """HDR-VDP Q (mean over frames) with the settings it depends on (never compare Q across versions)."""

    q: float
    version: str
    task: str
    color_encoding: str
    pixels_per_degree: float
    luminance_scale_cd_m2: float
    engine: str
    q_frames: tuple = ()


def find_hdrvdp(hdrvdp_dir=None) -> Path:
    """The HDR-VDP folder (containing ``hdrvdp3.m``) from the argument or ``HYBRIDHDR_HDRVDP_DIR``."""
    d = hdrvdp_dir if hdrvdp_dir is not None else os.environ.get("HYBRIDHDR_HDRVDP_DIR")
    if not d:
        raise HDRVDPNotFound("HDR-VDP 3 not configured: pass hdrvdp_dir / --hdrvdp-dir or set HYBRIDHDR_HDRVDP_DIR "
                             "to the folder holding hdrvdp3.m (download HDR-VDP 3 from "
                             "https://sourceforge.net/projects/hdrvdp/); Q is reported as n/a")
    p = Path(d).expanduser()
    if not (p / "hdrvdp3.m").is_file():
        raise HDRVDPNotFound(f"HDR-VDP 3 not found: expected {p / 'hdrvdp3.m'}, but it does not exist")
    return p


def _engine(engine: str) -> tuple[str, str]:
    if engine not in ("auto", "octave", "matlab"):
        raise ValueError(f"engine must be 'auto', 'octave' or 'matlab', got {engine!r}")
    order = ("octave", "matlab") if engine == "auto" else (engine,)
    for e in order:
        exe = shutil.which(e)
        if exe:
            return e, exe
    raise HDRVDPNotFound(f"no {' or '.join(order)} executable on PATH to run HDR-VDP 3 "
                         f"(install GNU Octave: apt-get install octave)")


_Q_RE = re.compile(r"HYBRIDHDR_Q=([-+0-9.eEinfaINFA]+)")
_V_RE = re.compile(r"HYBRIDHDR_VERSION=(.*)")


def hdrvdp_q(test, reference, *, hdrvdp_dir=None, engine: str = "auto", task: str = "side-by-side",
             color_encoding: str = "luminance", pixels_per_degree: float | None = None,
             luminance_scale_cd_m2: float = 4000.0, timeout_s: float = 600.0) -> HDRVDPResult:
    """HDR-VDP 3 quality Q of ``test`` against ``reference`` via the user's installation.

    Parameters
    ----------
    test, reference : ndarray of shape (H, W) or (K, H, W)
        Linear intensity in [0, 1] (after :func:`normalise_pair`); multiplied by
        ``luminance_scale_cd_m2`` to give absolute luminance (cd/m²) for ``color_encoding =
        "luminance"``. A stack is scored frame by frame in one Octave/MATLAB session.
    hdrvdp_dir : path, optional
        Folder holding ``hdrvdp3.m``; default ``$HYBRIDHDR_HDRVDP_DIR``.
    engine : {"auto", "octave", "matlab"}
        ``octave --no-gui --quiet --eval`` or ``matlab -batch``; auto prefers Octave.
    task, color_encoding : str
        Passed to ``hdrvdp3(task, test, reference, color_encoding, ppd)``.
    pixels_per_degree : float, optional
        Default :func:`pixels_per_degree` () (21-inch 640×480 at 1 m, as the AKF follow-up).

    Returns
    -------
    HDRVDPResult
        Q (3.x: 10 = indistinguishable; the mean over frames, each in ``q_frames``) with the
        version reported by ``hdrvdp_version`` when the installation has it (else "unknown"),
        task, encoding, ppd, luminance scale and engine.

    Raises
    ------
    HDRVDPNotFound
        No installation or no engine (a clear message; callers report Q as n/a).
    """
    from scipy.io import savemat
    a, b = _pair(test, reference, "hdrvdp_q")
    if a.ndim == 2:
        a, b = a[None], b[None]
    check_shape(a, "K H W", "hdrvdp_q: luminance images (or (H, W))")
    if not luminance_scale_cd_m2 > 0:
        raise ValueError(f"luminance_scale_cd_m2 must be > 0, got {luminance_scale_cd_m2}")
    d = find_hdrvdp(hdrvdp_dir)
    eng, exe = _engine(engine)
    ppd = _default_ppd() if pixels_per_degree is None else float(pixels_per_degree)
    for name, s in (("task", task), ("color_encoding", color_encoding)):
        if not re.fullmatch(r"[A-Za-z0-9_\-]+", s):
            raise ValueError(f"{name} must be a plain word, got {s!r}")
    with tempfile.TemporaryDirectory(prefix="hybridhdr_hdrvdp_") as tmp:
        mat = Path(tmp) / "images.mat"
        # frames along the last axis: MATLAB reads (H, W, K)
        savemat(mat, {"test": np.moveaxis(a, 0, -1) * luminance_scale_cd_m2,
                      "ref": np.moveaxis(b, 0, -1) * luminance_scale_cd_m2})
        q = lambda s: "'" + str(s).replace("'", "''") + "'"  # noqa: E731  MATLAB string literal
        script = (f"addpath(genpath({q(d)})); S = load({q(mat)}); "
                  "for k = 1:size(S.test, 3), "
                  f"res = hdrvdp3({q(task)}, S.test(:, :, k), S.ref(:, :, k), {q(color_encoding)}, {ppd!r}); "
                  "fprintf('HYBRIDHDR_Q=%.17g\\n', res.Q); end; "
                  "v = 'unknown'; if exist('hdrvdp_version') == 2, v = hdrvdp_version(); end; "
                  "fprintf('HYBRIDHDR_VERSION=%s\\n', v);")
        cmd = ([exe, "--no-gui", "--quiet", "--no-window-system", "--eval", script] if eng == "octave"
               else [exe, "-batch", script])
        try:
            pr = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired as e:
            raise RuntimeError(f"HDR-VDP via {eng} did not finish within {timeout_s} s") from e
    qs, mv = [float(x) for x in _Q_RE.findall(pr.stdout)], _V_RE.search(pr.stdout)
    if pr.returncode != 0 or len(qs) != a.shape[0]:
        tail = (pr.stderr or pr.stdout).strip().splitlines()[-5:]
        raise RuntimeError(f"HDR-VDP via {eng} failed (exit {pr.returncode}, {len(qs)} of {a.shape[0]} Q values): "
                           + " | ".join(tail))
    return HDRVDPResult(float(np.mean(qs)), mv.group(1).strip() if mv else "unknown", task, color_encoding, ppd,
                        float(luminance_scale_cd_m2), eng, tuple(qs))
