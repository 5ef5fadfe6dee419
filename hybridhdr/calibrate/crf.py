"""Camera response function (CRF) from exposure brackets: Debevec-Malik and Robertson.

A camera maps the exposure ``X = E * t`` (irradiance times exposure time) to a code
``z = f(X)``. Both methods recover the **log inverse response** ``g(z) = ln f^-1(z) = ln E + ln t``
per code (and per colour channel) up to an additive constant, fixed here by ``g(z_mid) = 0``
with ``z_mid = (max_code + 1) // 2``.

* **Debevec & Malik** (SIGGRAPH 1997, doi:10.1145/258734.258884), eq. 3: the linear least-squares
  problem over sampled pixels ``i`` and exposures ``j``::

      min  sum_ij [w(z_ij) (g(z_ij) - ln E_i - ln t_j)]^2 + lambda sum_z [w(z) g''(z)]^2

  with the hat weight ``w(z) = min(z, max_code - z)`` (0 at both ends: clipped codes carry no
  information). Solved here as one sparse system (scipy). The smoothness weight is
  ``smoothness * sqrt(n_samples * n_images / n_codes)`` so that ``smoothness`` keeps its meaning
  whatever the number of samples. Pixels are sampled individually (never from a downsampled
  image, the fault of opencv/opencv#26613), stratified over the brightness range and taken from
  flat regions (low local contrast), so that a small misregistration does not bias the fit.

* **Robertson, Borman & Stevenson** (ICIP 1999 / JEI 2003, doi:10.1117/1.1557695): the
  maximum-likelihood alternation ``E_i = sum_j w t_j I(z_ij) / sum_j w t_j^2`` and
  ``I(m) = mean_{z_ij = m} E_i t_j``, normalised to ``I(z_mid) = 1``, with the Gaussian-like
  weight ``exp(-4 (z - z_mid)^2 / z_mid^2)`` (0 at both ends). Our own implementation, not
  OpenCV's ``createCalibrateRobertson`` (8-bit 3-channel only, NaN for unseen codes
  (opencv/opencv#18180) and an interpreter abort on single-channel input; calibration.md).
  Unseen codes are interpolated in the log domain and counted in ``CRF.info``.

The end codes 0 and max_code are clipped (weight 0), so their ``g`` is not determined by the
data: it is extrapolated linearly from the two neighbouring codes. Both results are then made
non-decreasing (a response is monotonic) by a weighted isotonic (pool-adjacent-violators) fit;
the number of codes it changed is reported in ``info["monotonic_fixes"]``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._util.atomic import write_json_atomic
from .._util.checks import check_shape

__all__ = ["CRF", "DebevecParams", "RobertsonParams", "estimate_crf", "debevec", "robertson",
           "hat_weight", "check_brackets", "gamma_crf", "CRF_FORMAT", "METHODS"]

CRF_FORMAT = "hybridhdr-crf"
CRF_VERSION = 1
METHODS = ("debevec", "robertson")
#: Largest code count the Debevec solver accepts (12-bit); higher depths are linear RAW anyway.
MAX_CODES = 4096


@dataclass(frozen=True, kw_only=True)
class DebevecParams:
    """Parameters of Debevec & Malik 1997 (doi:10.1145/258734.258884).

    n_samples : pixels sampled per channel (the paper needs N (P - 1) > Z_max - Z_min; 70 in
        OpenCV; more samples average noise).
    smoothness : lambda of eq. 3, scaled by ``sqrt(n_samples * n_images / n_codes)``.
    seed : seeds the pixel sampling (numpy Generator); same seed, same curve.
    """

    n_samples: int = 400
    smoothness: float = 10.0
    seed: int | None = 0

    def __post_init__(self):
        if isinstance(self.n_samples, bool) or not isinstance(self.n_samples, (int, np.integer)) or self.n_samples < 2:
            raise ValueError(f"n_samples must be an int >= 2, got {self.n_samples!r}")
        if not (np.isfinite(self.smoothness) and self.smoothness >= 0):
            raise ValueError(f"smoothness must be a finite number >= 0, got {self.smoothness!r}")


@dataclass(frozen=True, kw_only=True)
class RobertsonParams:
    """Parameters of Robertson et al. 2003 (doi:10.1117/1.1557695).

    max_iter, tol : stop after ``max_iter`` alternations or when the mean absolute change of
        ``g`` is below ``tol`` (natural-log units); OpenCV's defaults are 30 and 0.01.
    max_pixels : pixels used (random subset, ``seed``) to bound memory and time.
    """

    max_iter: int = 50
    tol: float = 1e-4
    max_pixels: int = 200_000
    seed: int | None = 0

    def __post_init__(self):
        if self.max_iter < 1 or self.max_pixels < 2 or not self.tol > 0:
            raise ValueError(f"need max_iter >= 1, max_pixels >= 2, tol > 0; got {self.max_iter}, "
                             f"{self.max_pixels}, {self.tol}")


def hat_weight(n_codes: int) -> np.ndarray:
    """Debevec's hat ``w(z) = min(z, n - 1 - z)``, scaled to a maximum of 1 (0 at both ends)."""
    z = np.arange(n_codes, dtype=np.float64)
    w = np.minimum(z, n_codes - 1 - z)
    return w / max(w.max(), 1.0)


def gamma_crf(n_codes: int = 256, gamma: float = 2.2) -> np.ndarray:
    """Log inverse response of the gamma curve ``z = max (X)^(1/gamma)``: ``g(z) = gamma ln(z/max)``
    (``-inf`` at 0 replaced by the value at code 0.5). For tests and as a reference."""
    z = np.maximum(np.arange(n_codes, dtype=np.float64), 0.5) / (n_codes - 1)
    g = gamma * np.log(z)
    return g - g[n_codes // 2]


@dataclass(frozen=True, eq=False)
class CRF:
    """Inverse camera response per code and channel, in the log domain.

    Parameters
    ----------
    log_inverse : ndarray of shape (C, n_codes), float64
        ``g(z) = ln f^-1(z)``: log relative exposure (irradiance x time) of code ``z``, with
        ``g(z_mid) = 0``; non-decreasing in ``z``. ``C`` is 1 (grey) or 3 (RGB).
    method : str
        "debevec", "robertson" or a free label.
    observed : ndarray of shape (C, n_codes), bool, optional
        Codes seen in the brackets (unseen ones were interpolated).
    info : dict
        Estimation details (samples, residuals, fixes).
    """

    log_inverse: np.ndarray
    method: str = ""
    observed: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        g = np.asarray(self.log_inverse, dtype=np.float64)
        if g.ndim == 1:
            g = g[None]
        if g.ndim != 2 or g.shape[0] not in (1, 3) or g.shape[1] < 2:
            raise ValueError(f"CRF.log_inverse must have shape (1 or 3, n_codes >= 2), got {g.shape}")
        if not np.all(np.isfinite(g)):
            raise ValueError("CRF.log_inverse must be finite")
        if np.any(np.diff(g, axis=1) < -1e-12):
            raise ValueError("CRF.log_inverse must be non-decreasing in the code")
        g = g.copy()
        g.setflags(write=False)
        object.__setattr__(self, "log_inverse", g)
        if self.observed is not None:
            o = np.asarray(self.observed, dtype=bool)
            if o.shape != g.shape:
                raise ValueError(f"CRF.observed must have shape {g.shape}, got {o.shape}")
            object.__setattr__(self, "observed", o)

    @property
    def n_channels(self) -> int:
        return int(self.log_inverse.shape[0])

    @property
    def max_code(self) -> int:
        return int(self.log_inverse.shape[1] - 1)

    def log_exposure(self, codes, channel: int | None = None) -> np.ndarray:
        """``g(z)`` for an array of integer codes: (..., C) arrays use each channel's curve, (...)
        arrays use ``channel`` (default 0, or the only channel)."""
        z = np.asarray(codes)
        if z.dtype.kind not in "ui":
            raise TypeError(f"codes must be integers (uint8/uint16), got dtype {z.dtype}")
        if z.size and (z.min() < 0 or z.max() > self.max_code):
            raise ValueError(f"codes must lie in 0..{self.max_code}, got {z.min()}..{z.max()}")
        if channel is None and self.n_channels > 1 and z.ndim >= 1 and z.shape[-1] == self.n_channels:
            out = np.empty(z.shape, np.float64)
            for c in range(self.n_channels):
                out[..., c] = self.log_inverse[c][z[..., c]]
            return out
        return self.log_inverse[0 if channel is None else channel][z]

    def inverse(self, channel: int | None = None) -> np.ndarray:
        """Relative linear inverse response ``f^-1(z) = exp(g(z))`` normalised to 1 at the top code.

        ``channel=None`` averages the channels' normalised curves (one curve for a camera
        profile); else that channel's curve. Shape (n_codes,)."""
        inv = np.exp(self.log_inverse - self.log_inverse[:, -1:])
        return inv.mean(axis=0) if channel is None else inv[channel]

    def forward(self, log_exposure, channel: int = 0) -> np.ndarray:
        """Codes (float, not rounded) of log exposures ``ln X``: the response ``f`` by
        interpolation of ``g``; below/above the table it clips to 0 / max_code."""
        g = self.log_inverse[channel]
        z = np.arange(g.shape[0], dtype=np.float64)
        # g can be flat where codes were fixed for monotonicity: keep the first of equal values
        keep = np.concatenate([[True], np.diff(g) > 0])
        return np.interp(np.asarray(log_exposure, np.float64), g[keep], z[keep])

    # -- file format -------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"format": CRF_FORMAT, "version": CRF_VERSION, "method": self.method,
                "max_code": self.max_code, "n_channels": self.n_channels,
                "log_inverse": [[float(v) for v in row] for row in self.log_inverse],
                "observed": None if self.observed is None else [[bool(v) for v in row] for row in self.observed],
                "info": self.info}

    @classmethod
    def from_dict(cls, d) -> "CRF":
        if not isinstance(d, dict) or d.get("format") != CRF_FORMAT:
            raise ValueError(f"CRF file 'format' must be {CRF_FORMAT!r}, got "
                             f"{d.get('format') if isinstance(d, dict) else type(d).__name__!r}")
        if d.get("version") != CRF_VERSION:
            raise ValueError(f"CRF file 'version' must be {CRF_VERSION}, got {d.get('version')!r}")
        if "log_inverse" not in d:
            raise ValueError("CRF file is missing 'log_inverse'")
        return cls(np.asarray(d["log_inverse"], np.float64), str(d.get("method", "")),
                   None if d.get("observed") is None else np.asarray(d["observed"], bool), dict(d.get("info") or {}))

    def save(self, path) -> Path:
        """Write JSON atomically (temporary file in the same folder, then rename)."""
        return write_json_atomic(path, self.to_dict(), default=_json_default)

    @classmethod
    def load(cls, path) -> "CRF":
        path = Path(path)
        try:
            from .._util.limits import read_text_bounded
            d = json.loads(read_text_bounded(path, "CRF file"))
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not a JSON CRF file ({e})") from None
        return cls.from_dict(d)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# -- input checks ----------------------------------------------------------------------------
def check_brackets(images, exposures_s, *, max_codes: int | None = MAX_CODES):
    """Validate brackets; return ``(stack (K, H, W, C) integer, exposures (K,), n_codes)``.

    Errors (ValueError/TypeError) for: fewer than 2 images, fewer than 2 distinct exposure
    times, images of different shapes, non-integer codes, non-positive exposures.
    """
    if hasattr(images, "images") and hasattr(images, "exposures_s") and exposures_s is None:
        bs = images
        images, exposures_s = bs.images, bs.exposures_s
        max_code = bs.max_code
    else:
        max_code = None
    imgs = [np.asarray(im) for im in images]
    k = len(imgs)
    if k < 2:
        raise ValueError(f"a response curve needs at least 2 exposures, got {k}")
    shapes = [im.shape for im in imgs]
    if len(set(shapes)) != 1:
        raise ValueError(f"all bracket images must have the same shape; found {shapes}")
    check_shape(imgs[0], "H W | H W 3 | H W 1", "bracket images")
    if any(im.dtype.kind not in "ui" for im in imgs):
        raise TypeError(f"the response is estimated from integer codes (uint8/uint16), got "
                        f"{sorted({str(im.dtype) for im in imgs})}; float/linear data need no CRF")
    ex = np.asarray(exposures_s, dtype=np.float64)
    check_shape(ex, "K", "exposures_s (one exposure time per image)", sizes={"K": k})
    if not np.all(np.isfinite(ex) & (ex > 0)):
        raise ValueError(f"exposure times must be finite and > 0 s, got {ex.tolist()}")
    distinct = np.unique(ex)
    if distinct.size < 2:
        raise ValueError(f"bracket exposures must differ: all {k} images have exposure {ex[0]} s, so the "
                         "response cannot be separated from the scene radiance")
    stack = np.stack(imgs)
    if stack.ndim == 3:
        stack = stack[..., None]
    if max_code is None:
        max_code = 255 if stack.dtype == np.uint8 else int(stack.max())
        if stack.dtype != np.uint8:
            max_code = (1 << int(np.ceil(np.log2(max_code + 1)))) - 1 if max_code > 0 else 1
    n = int(max_code) + 1
    if int(stack.min()) < 0 or int(stack.max()) > max_code:
        raise ValueError(f"codes must lie in 0..{max_code}, found {stack.min()}..{stack.max()}")
    if max_codes is not None and n > max_codes:
        raise ValueError(f"{n} codes (bit depth > 12) are beyond the Debevec/Robertson solvers (max "
                         f"{max_codes}); RAW data are linear: use BracketSet.linear_stack() instead")
    return stack, ex, n


# -- sampling ---------------------------------------------------------------------------------
def _select_samples(ch: np.ndarray, n_samples: int, rng, valid: np.ndarray | None) -> np.ndarray:
    """Flat indices of ``n_samples`` pixels stratified over brightness, from flat regions.

    ``ch`` is (K, H, W) codes of one channel. Brightness rank = mean code over the exposures
    (monotonic in irradiance); local contrast = max - min of that mean over the 3x3
    neighbourhood; pixels above the median contrast are dropped.
    """
    from scipy import ndimage
    mean = ch.astype(np.float32).mean(axis=0)
    contrast = ndimage.maximum_filter(mean, 3) - ndimage.minimum_filter(mean, 3)
    ok = np.ones(mean.shape, bool) if valid is None else valid.copy()
    ok[[0, -1], :] = False
    ok[:, [0, -1]] = False
    if ok.sum() < n_samples:
        ok = np.ones(mean.shape, bool) if valid is None else valid.copy()
    thr = np.median(contrast[ok])
    flat = ok & (contrast <= thr)
    if flat.sum() >= n_samples:
        ok = flat
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        raise ValueError("no valid pixels to sample (mask excludes everything)")
    order = idx[np.argsort(mean.ravel()[idx], kind="stable")]
    # one random pixel per brightness stratum
    edges = np.linspace(0, order.size, min(n_samples, order.size) + 1).astype(np.int64)
    lo, hi = edges[:-1], np.maximum(edges[1:], edges[:-1] + 1)
    pick = lo + (rng.random(lo.size) * (hi - lo)).astype(np.int64)
    return order[np.minimum(pick, order.size - 1)]


def _isotonic(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least-squares non-decreasing fit (pool adjacent violators)."""
    vals, wts, lens = [], [], []
    for yi, wi in zip(y.tolist(), w.tolist()):
        vals.append(yi)
        wts.append(wi)
        lens.append(1)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            wsum = wts[-2] + wts[-1]
            v = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / wsum
            n = lens[-2] + lens[-1]
            del vals[-1], wts[-1], lens[-1]
            vals[-1], wts[-1], lens[-1] = v, wsum, n
    return np.repeat(np.array(vals), lens)


def _monotone(g: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """End codes (0 and max: clipped, zero weight, so not determined by data) are extrapolated
    from their two neighbours with a non-negative slope; then ``g`` is made non-decreasing by a
    weighted isotonic fit (weights: how often each code occurred), so that one noisy, rarely seen
    code cannot flatten the curve (as a running maximum would). Returns (g, codes changed)."""
    g = g.copy()
    if g.size >= 4:
        g[0] = g[1] - max(g[2] - g[1], 0.0)
        g[-1] = g[-2] + max(g[-2] - g[-3], 0.0)
    if np.all(np.diff(g) >= 0):
        return g, 0
    w = np.ones_like(g) if weights is None else np.asarray(weights, np.float64) + 1e-3
    m = _isotonic(g, w)
    return m, int(np.count_nonzero(np.abs(m - g) > 1e-12))


# -- Debevec ----------------------------------------------------------------------------------
def _debevec_channel(Z: np.ndarray, ln_t: np.ndarray, n: int, lam: float) -> tuple[np.ndarray, dict]:
    """Solve eq. 3 of Debevec & Malik for one channel; Z is (N, P) codes."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve
    w = hat_weight(n)
    N, P = Z.shape
    wz = w[Z]
    keep = (wz > 0).any(axis=1)
    Z, wz = Z[keep], wz[keep]
    N = Z.shape[0]
    if N < 2:
        raise ValueError("fewer than 2 sampled pixels are unclipped in any exposure; the brackets are "
                         "all saturated or all black")
    ii, jj = np.nonzero(wz > 0)
    nd = ii.size
    rows_d = np.arange(nd)
    wd = wz[ii, jj]
    data_rows = np.concatenate([rows_d, rows_d])
    data_cols = np.concatenate([Z[ii, jj], n + ii])
    data_vals = np.concatenate([wd, -wd])
    b = np.zeros(nd + 1 + (n - 2))
    b[:nd] = wd * ln_t[jj]
    # g(z_mid) = 0
    mid = n // 2
    r_fix = nd
    lam_eff = lam * np.sqrt(nd / n)
    zs = np.arange(1, n - 1)
    r_s = nd + 1 + np.arange(n - 2)
    sw = lam_eff * np.maximum(w[zs], 1.0 / n)  # keep end codes tied to their neighbours
    rows = np.concatenate([data_rows, [r_fix], r_s, r_s, r_s])
    cols = np.concatenate([data_cols, [mid], zs - 1, zs, zs + 1])
    vals = np.concatenate([data_vals, [1.0], sw, -2 * sw, sw])
    A = sparse.csr_matrix((vals, (rows, cols)), shape=(b.size, n + N))
    AtA = (A.T @ A).tocsc() + sparse.identity(n + N, format="csc") * 1e-10
    x = spsolve(AtA, A.T @ b)
    g = x[:n] - x[mid]
    resid = A @ x - b
    return g, {"n_samples": int(N), "n_equations": int(nd), "rms_residual": float(np.sqrt(np.mean(resid[:nd] ** 2)))}


def debevec(images, exposures_s=None, params: DebevecParams | None = None, *, mask=None) -> CRF:
    """Debevec & Malik 1997 response per channel (see the module docstring).

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, 3) integer arrays, or a BracketSet (then exposures_s=None)
    exposures_s : array_like (K,), seconds
    params : DebevecParams
    mask : (H, W) bool, optional
        Pixels that may be sampled (e.g. excluding the Memorial scans' blue border).
    """
    p = params or DebevecParams()
    stack, ex, n = check_brackets(images, exposures_s)
    rng = np.random.default_rng(p.seed)
    ln_t = np.log(ex)
    gs, observed, infos = [], [], []
    for c in range(stack.shape[3]):
        ch = stack[..., c]
        idx = _select_samples(ch, p.n_samples, rng, mask)
        Z = ch.reshape(ch.shape[0], -1)[:, idx].T.astype(np.int64)
        g, inf = _debevec_channel(Z, ln_t, n, p.smoothness)
        g, fixes = _monotone(g)
        g -= g[n // 2]
        inf["monotonic_fixes"] = fixes
        hist = np.bincount(ch.ravel(), minlength=n)[:n]
        observed.append(hist > 0)
        inf["unseen_codes"] = int(np.count_nonzero(hist == 0))
        gs.append(g)
        infos.append(inf)
    return CRF(np.array(gs), "debevec", np.array(observed),
               {"params": {"n_samples": p.n_samples, "smoothness": p.smoothness, "seed": p.seed},
                "exposures_s": ex.tolist(), "channels": infos})


# -- Robertson --------------------------------------------------------------------------------
def robertson_weight(n_codes: int) -> np.ndarray:
    """``exp(-4 (z - m)^2 / m^2)`` with ``m = (n - 1) / 2``, and 0 at both end codes."""
    z = np.arange(n_codes, dtype=np.float64)
    m = (n_codes - 1) / 2.0
    w = np.exp(-4.0 * (z - m) ** 2 / m ** 2)
    w[0] = w[-1] = 0.0
    return w


def _fill_unseen(logI: np.ndarray, seen: np.ndarray) -> np.ndarray:
    z = np.arange(logI.size, dtype=np.float64)
    if seen.sum() < 2:
        raise ValueError("fewer than 2 distinct codes observed; cannot estimate a response")
    zs, gs = z[seen], logI[seen]
    out = np.interp(z, zs, gs)
    # linear extrapolation beyond the observed codes, slope of the outermost 4 observed codes
    k = min(4, zs.size - 1)
    lo_slope = (gs[k] - gs[0]) / (zs[k] - zs[0])
    hi_slope = (gs[-1] - gs[-1 - k]) / (zs[-1] - zs[-1 - k])
    # a response rises: a negative end slope (noise on rarely seen codes) is replaced by the
    # mean slope over the observed codes
    mean_slope = max((gs[-1] - gs[0]) / max(zs[-1] - zs[0], 1.0), 0.0)
    lo_slope = lo_slope if lo_slope > 0 else mean_slope
    hi_slope = hi_slope if hi_slope > 0 else mean_slope
    out[z < zs[0]] = gs[0] + lo_slope * (z[z < zs[0]] - zs[0])
    out[z > zs[-1]] = gs[-1] + hi_slope * (z[z > zs[-1]] - zs[-1])
    return out


def robertson(images, exposures_s=None, params: RobertsonParams | None = None, *, mask=None,
              progress: bool = False) -> CRF:
    """Robertson et al. 2003 maximum-likelihood response per channel (own implementation)."""
    p = params or RobertsonParams()
    stack, ex, n = check_brackets(images, exposures_s)
    rng = np.random.default_rng(p.seed)
    K = stack.shape[0]
    flat = np.flatnonzero(np.ones(stack.shape[1:3], bool) if mask is None else mask)
    if flat.size > p.max_pixels:
        flat = np.sort(rng.choice(flat, p.max_pixels, replace=False))
    w = robertson_weight(n)
    mid = n // 2
    gs, observed, infos = [], [], []
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=stack.shape[3] * p.max_iter, desc="robertson", unit="iter")
    for c in range(stack.shape[3]):
        Z = stack[..., c].reshape(K, -1)[:, flat].astype(np.int64)  # (K, N)
        hist = np.bincount(Z.ravel(), minlength=n)[:n]
        seen = hist > 0
        I = np.arange(n, dtype=np.float64) / mid
        I[0] = 0.5 / mid
        I /= I[mid]
        wz = w[Z]
        t = ex[:, None]
        it, change = 0, np.inf
        for it in range(1, p.max_iter + 1):
            num = (wz * t * I[Z]).sum(axis=0)
            den = (wz * t * t).sum(axis=0)
            ok = den > 0
            E = np.where(ok, num / np.where(ok, den, 1.0), 0.0)
            # pixels with no usable exposure do not inform I(m)
            Et = (E[None, :] * t)
            valid = np.broadcast_to(ok[None, :], Z.shape)
            s = np.bincount(Z[valid], weights=Et[valid], minlength=n)[:n]
            cnt = np.bincount(Z[valid], minlength=n)[:n]
            have = (cnt > 0) & (s > 0)
            newI = np.where(have, s / np.maximum(cnt, 1), np.nan)
            if not have[mid]:
                raise ValueError(f"channel {c}: the middle code {mid} never occurs; cannot normalise")
            newI /= newI[mid]
            logI = _fill_unseen(np.log(np.where(have, newI, 1.0)), have)
            newI = np.exp(logI)
            change = float(np.mean(np.abs(np.log(newI) - np.log(I))))
            I = newI
            if bar is not None:
                bar.update(1)
            if change < p.tol:
                break
        if bar is not None:
            bar.update(p.max_iter - it)
        g, fixes = _monotone(np.log(I), hist)
        g -= g[mid]
        gs.append(g)
        observed.append(seen)
        infos.append({"iterations": it, "last_change": change, "unseen_codes": int(np.count_nonzero(~seen)),
                      "unseen_filled": "log-linear interpolation/extrapolation", "monotonic_fixes": fixes,
                      "n_pixels": int(flat.size)})
    crf = CRF(np.array(gs), "robertson", np.array(observed),
              {"params": {"max_iter": p.max_iter, "tol": p.tol, "max_pixels": p.max_pixels, "seed": p.seed},
                "exposures_s": ex.tolist(), "channels": infos})
    if bar is not None:
        bar.close()
    return crf


def estimate_crf(images, exposures_s=None, method: str = "debevec", params=None, *, mask=None,
                 progress: bool = False) -> CRF:
    """Dispatch to :func:`debevec` or :func:`robertson` (``method``); ``progress`` shows a tqdm
    bar for Robertson's iterations."""
    if method == "debevec":
        return debevec(images, exposures_s, params, mask=mask)
    if method == "robertson":
        return robertson(images, exposures_s, params, mask=mask, progress=progress)
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")
