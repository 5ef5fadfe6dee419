"""Camera noise profile for the AKF: certainty/weighting function f_w, σ²_im and R(code).

AKF (Wang et al., ICCV 2021, doi:10.1109/ICCV48922.2021.00050), eqs. 4-6: the certainty is the
slope of the camera response, renormalised to a maximum of 1; the weighting function
``f_w = f_c o CRF^-1`` is that slope as a function of the code; the frame covariance is
``R̄(code) = σ²_im / f_w(code)``, saturated where f_w falls below a floor.

**Which slope.** We use the slope with respect to **log** exposure (Mann & Picard's certainty,
the form the AKF filters in, since its state is log intensity)::

    f_w(z) = (d z / d ln X) / max = (1 / g'(z)) / max,   g(z) = ln CRF^-1(z)

(from the log inverse response of :mod:`hybridhdr.calibrate.crf`; ``g'`` by central
differences of ``g`` smoothed with a Gaussian of ``smooth_codes`` codes, default 2 for 8 bits). The linear-irradiance
form of eq. 4, ``dz/dX = 1 / (X g'(z))``, differs by a factor ``X``; it is available as
``domain="linear"`` (:func:`hybridhdr.camera.profile.weighting_from_inverse_crf`). ``f_w`` is
forced to 0 at the end codes (0 and max_code: clipped) and at codes that never occurred in the
brackets below the first / above the last observed code (the curve is extrapolated there).

**σ²_im estimator** (:func:`estimate_sigma2_im`), in intensity² with the intensity
``I = CRF^-1(z)`` normalised to 1 at the top code (the unit of ``CameraProfile.intensity``):

* *temporal*, when the bracket set holds two or more images with the same exposure: half the
  variance of the difference of each such pair, over pixels whose mean code lies within ±10 % of
  the code range around mid-grey, converted to intensity with the local slope ``dI/dz``;
* *spatial* otherwise: Immerkær's fast noise estimator (CVIU 64(2), 1996,
  doi:10.1006/cviu.1996.0060), ``σ = sqrt(π/2) / 6 · mean |I * N|`` with the 3x3 Laplacian
  difference mask ``N = [[1,-2,1],[-2,4,-2],[1,-2,1]]``, on the image whose codes are closest to
  mid-grey, restricted to pixels with mid-grey codes and with a low local gradient (below its
  median, so that edges do not count as noise).

The precision stored in the profile is ``frame_precision_scale = 1 / σ²_im`` (camera-profile.md;
the paper's 7e5 for the DAVIS240C). ``--sigma2-im`` overrides the estimate.
"""

from __future__ import annotations

import numpy as np

from .._util.atomic import atomic_path
from ..camera.profile import CameraProfile, weighting_from_inverse_crf
from .crf import CRF

__all__ = ["certainty", "estimate_sigma2_im", "noise_profile", "plot_profile", "DOMAINS"]

DOMAINS = ("log", "linear")


def certainty(crf: CRF, *, domain: str = "log", smooth_codes: float | None = None,
              channel: int | None = None) -> np.ndarray:
    """Certainty/weighting function ``f_w(z)`` per code, in [0, 1] with maximum 1.

    Parameters
    ----------
    crf : CRF
    domain : {"log", "linear"}
        Slope with respect to log exposure (default) or linear exposure (eq. 4 literally).
    smooth_codes : float, optional
        Gaussian smoothing of ``g`` before differencing, in codes (default ``n_codes / 128``).
    channel : int, optional
        Channel of a colour CRF; None returns shape (C, n_codes) for all channels.

    Returns
    -------
    ndarray of shape (n_codes,) or (C, n_codes), float64
    """
    if domain not in DOMAINS:
        raise ValueError(f"domain must be one of {DOMAINS}, got {domain!r}")
    n = crf.max_code + 1
    s = float(n / 128.0 if smooth_codes is None else smooth_codes)
    if not s >= 0:
        raise ValueError(f"smooth_codes must be >= 0, got {smooth_codes}")
    out = []
    chans = range(crf.n_channels) if channel is None else [channel]
    for c in chans:
        g = crf.log_inverse[c]
        if domain == "linear":
            inv = np.exp(g - g[-1])
            if s > 0:
                inv = np.maximum.accumulate(_smooth_linear_ends(inv, s))
            fw = weighting_from_inverse_crf(inv, np.ones(n))
        else:
            slope = np.gradient(_smooth_linear_ends(g, s) if s > 0 else g)
            fw = np.where(slope > 0, 1.0 / np.where(slope > 0, slope, 1.0), 0.0)
        fw = fw.copy()
        fw[0] = fw[-1] = 0.0
        if crf.observed is not None:
            seen = np.flatnonzero(crf.observed[c])
            if seen.size:
                fw[:seen[0]] = 0.0
                fw[seen[-1] + 1:] = 0.0
        top = fw.max()
        if not top > 0:
            raise ValueError("the response curve is flat everywhere: no certainty (eq. 4)")
        out.append(np.clip(fw / top, 0.0, 1.0))
    out = np.array(out)
    return out[0] if channel is not None else out


def _smooth_linear_ends(v: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of a curve padded by linear extrapolation of its end slopes, so the
    ends are not flattened (a flat end would give a spurious certainty peak)."""
    from scipy.ndimage import gaussian_filter1d
    k = int(np.ceil(4 * sigma)) + 1
    m = min(4, v.size - 1)
    lo = v[0] - (v[m] - v[0]) / m * np.arange(k, 0, -1)
    hi = v[-1] + (v[-1] - v[-1 - m]) / m * np.arange(1, k + 1)
    return gaussian_filter1d(np.concatenate([lo, v, hi]), sigma, mode="nearest")[k:k + v.size]


def _immerkaer_sigma(img: np.ndarray, sel: np.ndarray) -> float:
    from scipy.ndimage import convolve, sobel
    m = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64)
    f = img.astype(np.float64)
    r = np.abs(convolve(f, m, mode="reflect"))
    grad = np.hypot(sobel(f, 0), sobel(f, 1))
    sel = sel.copy()
    sel[[0, -1], :] = False
    sel[:, [0, -1]] = False
    if sel.sum() < 16:
        raise ValueError("too few mid-grey pixels to estimate the noise; pass sigma2_im explicitly")
    flat = sel & (grad <= np.median(grad[sel]))
    return float(np.sqrt(np.pi / 2.0) / 6.0 * r[flat].mean())


def estimate_sigma2_im(images, exposures_s, crf: CRF) -> tuple[float, dict]:
    """σ²_im in normalised intensity² (see the module docstring); returns ``(sigma2, details)``.

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, C) integer arrays
    exposures_s : (K,) seconds
    crf : CRF
        Converts code noise to intensity noise through ``dI/dz`` at the measured codes.
    """
    imgs = [np.asarray(im) for im in images]
    ex = np.asarray(exposures_s, np.float64)
    stack = np.stack(imgs)
    if stack.ndim == 3:
        stack = stack[..., None]
    mx = crf.max_code
    lo, hi = 0.4 * mx, 0.6 * mx
    inv = np.stack([crf.inverse(c) for c in range(crf.n_channels)])  # (C, n), top code -> 1
    slope = np.gradient(inv, axis=1)  # dI/dz per code
    uniq, counts = np.unique(ex, return_counts=True)
    dup = uniq[counts >= 2]
    if dup.size:
        vals, wsum = 0.0, 0
        for t in dup:
            idx = np.flatnonzero(ex == t)
            for a, b in zip(idx[:-1], idx[1:]):
                for c in range(stack.shape[3]):
                    za, zb = stack[a, ..., c].astype(np.float64), stack[b, ..., c].astype(np.float64)
                    zm = 0.5 * (za + zb)
                    sel = (zm >= lo) & (zm <= hi)
                    if sel.sum() < 16:
                        continue
                    dz = (za - zb)[sel]
                    k = np.clip(np.round(zm[sel]).astype(np.int64), 0, mx)
                    dI = dz * slope[min(c, slope.shape[0] - 1)][k]
                    vals += float(np.sum(dI ** 2) / 2.0)
                    wsum += dz.size
        if wsum:
            s2 = vals / wsum
            return s2, {"estimator": "temporal (pairs of equal exposures)", "n_pixels": int(wsum),
                        "sigma_code_mid": float(np.sqrt(s2) / slope.mean(axis=0)[int(mx // 2)])}
    # spatial: the image closest to mid-grey
    med = np.array([np.median(stack[k]) for k in range(stack.shape[0])])
    k = int(np.argmin(np.abs(med - mx / 2.0)))
    sig_codes, s2s = [], []
    for c in range(stack.shape[3]):
        z = stack[k, ..., c]
        sel = (z >= lo) & (z <= hi)
        sz = _immerkaer_sigma(z, sel)
        sl = float(np.median(slope[min(c, slope.shape[0] - 1)][z[sel].astype(np.int64)]))
        sig_codes.append(sz)
        s2s.append((sz * sl) ** 2)
    return float(np.mean(s2s)), {"estimator": "spatial (Immerkaer 1996) on mid-grey flat pixels",
                                  "image": k, "sigma_code_mid": float(np.mean(sig_codes))}


def noise_profile(crf: CRF, *, sigma2_im: float, floor: float = 0.09, domain: str = "log",
                  name: str = "", source: str = "", extra: dict | None = None) -> CameraProfile:
    """The :class:`CameraProfile` (camera-profile.md) of a measured CRF and noise level.

    ``weighting`` = :func:`certainty` (channel-averaged for colour CRFs), ``inverse_crf`` =
    :meth:`CRF.inverse` (top code -> 1), ``frame_precision_scale = 1 / sigma2_im``,
    ``min_weighting = floor``; so ``profile.variance(z) = σ²_im / max(f_w(z), floor)`` is the
    R(code) of eq. 6.
    """
    if not (np.isfinite(sigma2_im) and sigma2_im > 0):
        raise ValueError(f"sigma2_im must be > 0 (intensity², I in [0, 1]), got {sigma2_im}")
    if not 0 < floor <= 1:
        raise ValueError(f"floor must be in (0, 1], got {floor}")
    fw = certainty(crf, domain=domain)
    fw = fw.mean(axis=0)
    fw = fw / fw.max()
    ex = {"crf_method": crf.method, "certainty_domain": domain, "sigma2_im": float(sigma2_im),
          "bit_depth": int(np.ceil(np.log2(crf.max_code + 1)))}
    ex.update(extra or {})
    return CameraProfile(weighting=fw, inverse_crf=np.maximum.accumulate(crf.inverse()),
                         frame_precision_scale=1.0 / float(sigma2_im), min_weighting=float(floor),
                         name=name, source=source or f"hybridhdr calibrate crf ({crf.method})", extra=ex)


def plot_profile(crf: CRF, profile: CameraProfile, path) -> None:
    """PNG with three panels: log inverse CRF per channel, f_w, and R(code) (log scale)."""
    from pathlib import Path

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    z = np.arange(crf.max_code + 1)
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    cols = ["k"] if crf.n_channels == 1 else ["r", "g", "b"]
    for c in range(crf.n_channels):
        ax[0].plot(z, crf.log_inverse[c], cols[c], lw=1)
    ax[0].set(xlabel="code z", ylabel="g(z) = ln CRF⁻¹(z)")
    ax[0].set_title(f"inverse response ({crf.method})", fontsize=10)
    ax[1].plot(z, profile.weighting, "k", lw=1)
    # the floor is named in the title, not in a legend that would sit on the curve
    ax[1].axhline(profile.min_weighting, color="0.5", ls="--", lw=0.8)
    ax[1].set(xlabel="code z", ylabel="f_w", ylim=(0, 1.05))
    ax[1].set_title(f"weighting f_w (eq. 5)\ndashed: floor {profile.min_weighting:g}", fontsize=10)
    ax[2].semilogy(z, profile.variance(z), "k", lw=1)
    ax[2].margins(y=0.08)
    ax[2].set(xlabel="code z", ylabel="R̄ (intensity²)")
    # two short lines: one line ran off the figure's right edge
    ax[2].set_title(f"R(z) = σ²_im / max(f_w, floor)\nσ²_im = {1 / profile.frame_precision_scale:.3g}",
                    fontsize=10)
    fig.tight_layout()
    try:
        with atomic_path(path, ".png") as tmp:
            fig.savefig(tmp, dpi=110)
    finally:
        plt.close(fig)
