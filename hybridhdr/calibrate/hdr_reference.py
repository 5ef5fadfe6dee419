"""HDR references: merge exposure brackets into radiance, write OpenEXR, register to LDR frames.

**Merge** (:func:`merge_brackets`).

* Coded brackets (8/16-bit with a CRF): Debevec & Malik's weighted average **in the log
  domain** (SIGGRAPH 1997, doi:10.1145/258734.258884, eq. 6)::

      ln E = sum_j w(z_j) (g(z_j) - ln t_j) / sum_j w(z_j)

  with ``w`` the certainty function f_w of the CRF (:func:`~hybridhdr.calibrate.noise_profile.certainty`,
  0 at clipped codes), or Debevec's hat (``weighting="hat"``).
* Linear/RAW brackets (no CRF): the maximum-likelihood estimate under Poisson (shot) noise,
  **in the linear domain**: ``E = sum_j x_j / sum_j t_j`` over the exposures where the pixel is
  not saturated (calibration.md, "HDR merge": zero weight at saturation).
* A pixel with no usable exposure takes the shortest exposure if it is clipped white in every
  image (a lower bound) and the longest if it is black in every image (an upper bound); the
  count of such pixels is reported.

The radiance is relative (``E`` in units of the CRF's ``g(z_mid) = 0`` per second), float32.

**Registration** (:func:`register`): both images are mapped to a common photometric space --
the reference's log radiance is histogram-matched to the frame's codes (a monotonic map, as a
CRF is; no exposure or response needs to be known) -- then keypoints are detected (SURF from
mahotas, or OpenCV's when a non-free build is present; SIFT with ``features="sift"``),
matched with Lowe's ratio test (IJCV 2004, doi:10.1023/B:VISI.0000029664.99615.94), a
homography is fitted with ``cv2.findHomography(..., cv2.USAC_MAGSAC)`` and optionally refined
by ECC (Evangelidis & Psarakis, PAMI 2008, doi:10.1109/TPAMI.2008.113;
``cv2.findTransformECC`` with ``MOTION_HOMOGRAPHY``, which is invariant to gain and offset).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._util.atomic import atomic_path
from ..formats.brackets import BracketSet
from ..formats.container import read_recording, write_recording
from ..model import HDRReferences
from .crf import CRF, check_brackets, hat_weight

__all__ = ["merge_brackets", "write_exr", "read_exr_rgb", "corner_error", "register", "Registration", "RegistrationParams",
           "warp_reference", "refine_ecc", "to_grey", "photometric_match", "surf_backend", "FEATURES",
           "register_recording", "RegistrationError", "align_brackets"]

FEATURES = ("surf", "sift")


# -- merge -----------------------------------------------------------------------------------
def merge_brackets(images, exposures_s=None, crf: CRF | None = None, *, weighting: str = "certainty",
                   encoding: str | None = None, camera: dict | None = None, info: dict | None = None) -> np.ndarray:
    """Merge brackets into float32 relative radiance of shape (H, W) or (H, W, 3).

    Parameters
    ----------
    images : sequence of arrays or a BracketSet (then ``exposures_s=None``)
    exposures_s : (K,) seconds
    crf : CRF, optional
        Required for coded (gamma/unknown) brackets; omitted for "raw"/"linear" BracketSets,
        which are merged linearly.
    weighting : {"certainty", "hat"}
        Weight per code for the log-domain merge.
    info : dict, optional
        Filled with ``n_clipped_white``, ``n_clipped_black`` (pixels without a usable exposure).
    """
    bs = None
    if hasattr(images, "images") and hasattr(images, "exposures_s") and exposures_s is None:
        bs = images
        encoding = bs.encoding if encoding is None else encoding
    info = {} if info is None else info
    if crf is None:
        if bs is None or bs.encoding not in ("raw", "linear"):
            raise ValueError("merging coded brackets needs a CRF (hybridhdr calibrate crf); only 'raw'/'linear' "
                             f"BracketSets merge without one, got encoding {encoding!r}")
        return _merge_linear(bs.linear_stack(), bs.exposures_s, bs.saturated(), info)
    stack, ex, n = check_brackets(bs if bs is not None else images, None if bs is not None else exposures_s)
    if n != crf.max_code + 1:
        raise ValueError(f"the CRF has {crf.max_code + 1} codes but the brackets use {n}")
    C = stack.shape[3]
    if crf.n_channels not in (1, C):
        raise ValueError(f"the CRF has {crf.n_channels} channels, the brackets {C}")
    if weighting == "certainty":
        from .noise_profile import certainty
        W = certainty(crf)
    elif weighting == "hat":
        W = np.tile(hat_weight(n), (crf.n_channels, 1))
    else:
        raise ValueError(f"weighting must be 'certainty' or 'hat', got {weighting!r}")
    ln_t = np.log(ex)
    out = np.empty(stack.shape[1:], np.float32)
    i_long, i_short = int(np.argmax(ex)), int(np.argmin(ex))
    nw = nb = 0
    for c in range(C):
        cc = c if crf.n_channels > 1 else 0
        g, w = crf.log_inverse[cc], W[cc]
        num = np.zeros(stack.shape[1:3])
        den = np.zeros(stack.shape[1:3])
        for k in range(stack.shape[0]):
            z = stack[k, ..., c]
            wk = w[z]
            num += wk * (g[z] - ln_t[k])
            den += wk
        lnE = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
        bad = den <= 0
        if bad.any():
            white = bad & (stack[i_short, ..., c] >= n // 2)
            black = bad & ~white
            zs, zl = stack[i_short, ..., c], stack[i_long, ..., c]
            lnE[white] = g[zs[white]] - ln_t[i_short]
            lnE[black] = g[zl[black]] - ln_t[i_long]
            nw += int(white.sum())
            nb += int(black.sum())
        out[..., c] = np.exp(lnE)
    info.update(domain="log", weighting=weighting, n_clipped_white=nw, n_clipped_black=nb)
    return out[..., 0] if C == 1 and np.asarray(stack).shape[-1] == 1 and _is_grey(images) else out


def _is_grey(images) -> bool:
    im = images.images[0] if hasattr(images, "images") else np.asarray(images[0])
    return np.asarray(im).ndim == 2


def _merge_linear(lin: np.ndarray, ex: np.ndarray, sat: np.ndarray, info: dict) -> np.ndarray:
    t = ex.reshape((-1,) + (1,) * (lin.ndim - 1))
    ok = ~sat
    num = (lin * ok).sum(axis=0, dtype=np.float64)
    den = (t * ok).sum(axis=0, dtype=np.float64)
    E = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    none = den <= 0
    i_short = int(np.argmin(ex))
    E[none] = lin[i_short][none] / ex[i_short]
    info.update(domain="linear", weighting="poisson-ml", n_clipped_white=int(none.sum()), n_clipped_black=0)
    return E.astype(np.float32)


# -- EXR -------------------------------------------------------------------------------------
def write_exr(path, image) -> Path:
    """Write float32 (H, W) as channel "Y" or (H, W, 3) as "RGB" to OpenEXR (ZIP), atomically."""
    try:
        import OpenEXR
    except ImportError as e:  # pragma: no cover
        raise ImportError("writing EXR needs the OpenEXR package (pip install OpenEXR)") from e
    im = np.ascontiguousarray(image, dtype=np.float32)
    if im.ndim == 2:
        ch = {"Y": im}
    elif im.ndim == 3 and im.shape[2] == 3:
        ch = {"RGB": im}
    else:
        raise ValueError(f"EXR image must be (H, W) or (H, W, 3), got {im.shape}")
    path = Path(path)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path, ".exr") as tmp:
        OpenEXR.File(header, ch).write(str(tmp))
    return path


def read_exr_rgb(path) -> np.ndarray:
    """Read an EXR written by :func:`write_exr` (RGB or Y) as float32."""
    import OpenEXR
    with OpenEXR.File(str(path)) as f:
        chans = f.channels()
        if "RGB" in chans:
            return np.asarray(chans["RGB"].pixels, np.float32)
        if "Y" in chans:
            return np.asarray(chans["Y"].pixels, np.float32)
        if all(k in chans for k in "RGB"):
            return np.stack([np.asarray(chans[k].pixels, np.float32) for k in "RGB"], axis=-1)
    raise ValueError(f"{path}: no 'RGB' or 'Y' channel, found {sorted(chans)}")


# -- registration ----------------------------------------------------------------------------
def to_grey(img) -> np.ndarray:
    """Rec. 709 luminance of (H, W, 3), float64; (H, W) passes through as float64."""
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 3:
        return a @ np.array([0.2126, 0.7152, 0.0722])
    return a


def photometric_match(reference: np.ndarray, frame: np.ndarray, valid=None) -> np.ndarray:
    """The reference's log radiance mapped monotonically onto the frame's value distribution.

    Quantile (histogram) matching: the k-th percentile of ``log reference`` goes to the k-th
    percentile of ``frame``. A camera response is monotonic, so for a small misalignment this
    reproduces the frame's rendition of the reference, clipping included. Returns float64
    (H, W) in the frame's units.
    """
    r = np.log(np.maximum(to_grey(reference), 1e-12))
    f = to_grey(frame)
    rv = r if valid is None else r[valid]
    q = np.linspace(0, 100, 1025)
    rq = np.percentile(rv[np.isfinite(rv)], q)
    fq = np.percentile(f, q)
    rq, idx = np.unique(rq, return_index=True)
    return np.interp(r, rq, fq[idx])


def _u8(img: np.ndarray, lo: float, hi: float) -> np.ndarray:
    a = np.asarray(img, np.float64)
    if hi <= lo:
        hi = lo + 1.0
    return np.clip(np.round(255.0 * (a - lo) / (hi - lo)), 0, 255).astype(np.uint8)


def surf_backend() -> str:
    """"opencv" when ``cv2.xfeatures2d.SURF_create`` works (non-free build), else "mahotas"."""
    try:
        import cv2
        cv2.xfeatures2d.SURF_create(400)
        return "opencv"
    except Exception:
        pass
    try:
        import mahotas.features.surf  # noqa: F401
        return "mahotas"
    except ImportError:
        return "none"


@dataclass(frozen=True, kw_only=True)
class RegistrationParams:
    """Keypoint registration and ECC refinement settings.

    features : "surf" (Bay et al., CVIU 2008, doi:10.1016/j.cviu.2007.09.014) or "sift".
    ratio : Lowe's ratio test threshold (0.75 in calibration.md's comparison; Lowe used 0.8).
    ransac_px : MAGSAC/RANSAC reprojection threshold in pixels (3 in calibration.md).
    ecc : refine with ECC; ecc_iterations / ecc_eps its stopping criteria; ecc_blur_px the
        Gaussian pre-filter size in px (odd, 1 = none).
    surf_threshold, max_points : mahotas SURF detector threshold and point budget.
    """

    features: str = "surf"
    ratio: float = 0.75
    ransac_px: float = 3.0
    ecc: bool = True
    ecc_iterations: int = 100
    ecc_eps: float = 1e-6
    ecc_blur_px: int = 3
    surf_threshold: float = 0.05
    max_points: int = 4000
    min_inliers: int = 12

    def __post_init__(self):
        if self.features not in FEATURES:
            raise ValueError(f"features must be one of {FEATURES}, got {self.features!r}")
        if not 0 < self.ratio < 1:
            raise ValueError(f"ratio must be in (0, 1), got {self.ratio}")
        if not self.ransac_px > 0:
            raise ValueError(f"ransac_px must be > 0, got {self.ransac_px}")
        if self.ecc_blur_px < 1 or self.ecc_blur_px % 2 == 0:
            raise ValueError(f"ecc_blur_px must be odd and >= 1 (1 = no blur), got {self.ecc_blur_px}")


@dataclass(frozen=True)
class Registration:
    """Result of :func:`register`: ``homography`` maps reference pixel (x, y, 1) to frame pixels."""

    homography: np.ndarray
    n_keypoints: tuple
    n_matches: int
    n_inliers: int
    reprojection_px: float
    ecc_correlation: float | None
    time_s: float
    backend: str
    info: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"homography": self.homography.tolist(), "n_keypoints": list(self.n_keypoints),
                "n_matches": self.n_matches, "n_inliers": self.n_inliers,
                "reprojection_px": self.reprojection_px, "ecc_correlation": self.ecc_correlation,
                "time_s": self.time_s, "backend": self.backend, **self.info}


def _detect(img_u8: np.ndarray, p: RegistrationParams, backend: str):
    """Keypoints (N, 2) as (x, y) and float32 descriptors (N, D)."""
    import cv2
    if p.features == "sift":
        det = cv2.SIFT_create(nfeatures=p.max_points)
        kps, des = det.detectAndCompute(img_u8, None)
        pts = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        return pts, (des if des is not None else np.zeros((0, 128), np.float32)).astype(np.float32), None
    if backend == "opencv":  # pragma: no cover - needs a non-free OpenCV build
        det = cv2.xfeatures2d.SURF_create(400)
        kps, des = det.detectAndCompute(img_u8, None)
        pts = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        return pts, des.astype(np.float32), None
    if backend != "mahotas":
        raise ImportError("SURF needs mahotas (pip install mahotas) or a non-free OpenCV build; use features='sift'")
    from mahotas.features import surf
    r = surf.surf(img_u8.astype(np.float64), threshold=p.surf_threshold, max_points=p.max_points,
                  descriptor_only=False)
    # columns: y, x, scale, score, laplacian, angle, descriptor[64]
    pts = np.ascontiguousarray(r[:, [1, 0]], np.float32)
    return pts, np.ascontiguousarray(r[:, 6:], np.float32), r[:, 4]


def _match(d1, d2, ratio, lap1=None, lap2=None):
    import cv2
    if len(d1) < 2 or len(d2) < 2:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    knn = bf.knnMatch(d1, d2, k=2)
    pairs = []
    for m in knn:
        if len(m) == 2 and m[0].distance < ratio * m[1].distance:
            if lap1 is not None and lap1[m[0].queryIdx] != lap2[m[0].trainIdx]:
                continue
            pairs.append((m[0].queryIdx, m[0].trainIdx))
    return np.array(pairs, np.int64).reshape(-1, 2)


class RegistrationError(ValueError):
    """Registration cannot succeed (too few matches, a degenerate homography, unrelated images)."""


def _check_homography(H, what: str = "homography") -> np.ndarray:
    """A finite, invertible, well-conditioned 3x3 homography normalised to ``H[2, 2] = 1``."""
    H = None if H is None else np.asarray(H, np.float64)
    if H is None or H.shape != (3, 3) or not np.all(np.isfinite(H)) or abs(H[2, 2]) < 1e-12:
        raise RegistrationError(f"registration failed: the {what} is degenerate (not finite or H[2,2] = 0)")
    H = H / H[2, 2]
    c = np.linalg.cond(H)
    if not np.isfinite(c) or c > 1e10:
        raise RegistrationError(f"registration failed: the {what} is singular (condition number {c:.3g})")
    return H


def _tone_fit(x: np.ndarray, y: np.ndarray, n_bins: int = 64):
    """Monotone map ``x -> y`` from co-located samples: means of ``y`` in quantile bins of ``x``,
    made non-decreasing, linearly interpolated. Returns a callable; None with < 100 samples."""
    x = np.asarray(x, np.float64).ravel()
    y = np.asarray(y, np.float64).ravel()
    if x.size < 100:
        return None
    edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, n_bins + 1)))
    if edges.size < 3:
        return None
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(idx, minlength=edges.size - 1)
    ok = cnt > 0
    cx = np.bincount(idx, x, minlength=edges.size - 1)[ok] / cnt[ok]
    cy = np.maximum.accumulate(np.bincount(idx, y, minlength=edges.size - 1)[ok] / cnt[ok])
    return lambda v: np.interp(v, cx, cy)


def _grid_residual(fixed: np.ndarray, moving: np.ndarray, H: np.ndarray, fixed_ok: np.ndarray,
                   moving_ok: np.ndarray | None = None):
    """RMS of ``fixed - m(moving warped by H)`` over the pixels both see well, with ``m`` the
    monotone tone map fitted on those pixels. Returns (rms, warped-and-mapped moving, mask)."""
    import cv2
    h, w = fixed.shape
    mv = cv2.warpPerspective(moving.astype(np.float32), H, (w, h), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE)
    src_ok = np.ones(moving.shape, np.float32) if moving_ok is None else moving_ok.astype(np.float32)
    cov = cv2.warpPerspective(src_ok, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=0) > 0.999
    m = cov & fixed_ok
    tm = _tone_fit(mv[m], fixed[m])
    if tm is None:
        return np.inf, None, m
    mapped = tm(mv)
    return float(np.sqrt(np.mean((fixed[m] - mapped[m]) ** 2))), mapped, m


def register(reference: np.ndarray, frame: np.ndarray, params: RegistrationParams | None = None, *,
             valid=None) -> Registration:
    """Homography from the HDR ``reference`` (radiance, any scale) to an LDR ``frame`` (codes).

    Keypoints give ``H``; with ``params.ecc`` the reference is then **resampled into the frame's
    grid** by ``H`` (so ECC works on two images of one size, whatever the sizes of reference
    and frame), tone-mapped onto the frame by a monotone map fitted on co-located pixels, and
    ECC estimates the remaining homography. The ECC result is kept only if it lowers the
    photometric residual (RMS of frame minus tone-mapped warped reference, re-fitted for each
    homography, over the frame pixels the reference covers); otherwise, or when ECC fails, the keypoint
    ``H`` is kept and ``info["warnings"]`` says why (``info["ecc"]`` has the details).

    ``valid``: optional (H, W) bool mask of usable reference pixels.

    Raises :class:`RegistrationError` (a ValueError) when fewer than ``min_inliers`` matches
    survive or the homography is degenerate (e.g. unrelated images).
    """
    import cv2
    p = params or RegistrationParams()
    t0 = time.perf_counter()
    ref = np.asarray(reference)
    frm = np.asarray(frame)
    if min(ref.shape[:2] + frm.shape[:2]) < 16:
        raise RegistrationError(f"images too small to register: reference {ref.shape}, frame {frm.shape}")
    fgrey = to_grey(frm)
    rmatch = photometric_match(ref, fgrey, valid)
    lo, hi = (float(v) for v in np.percentile(fgrey, [0.1, 99.9]))
    a, b = _u8(rmatch, lo, hi), _u8(fgrey, lo, hi)  # one 8-bit scale for both
    backend = "sift" if p.features == "sift" else surf_backend()
    pa, da, la = _detect(a, p, backend)
    pb, db, lb = _detect(b, p, backend)
    pairs = _match(da, db, p.ratio, la, lb)
    if len(pairs) < max(4, p.min_inliers):
        raise RegistrationError(f"registration failed: {len(pairs)} keypoint matches after the ratio test "
                                f"(need >= {max(4, p.min_inliers)}); keypoints {len(pa)} / {len(pb)}")
    src, dst = pa[pairs[:, 0]], pb[pairs[:, 1]]
    method = getattr(cv2, "USAC_MAGSAC", cv2.RANSAC)
    H, inl = cv2.findHomography(src, dst, method, p.ransac_px, maxIters=10000, confidence=0.9999)
    if H is None or inl is None or int(inl.sum()) < p.min_inliers:
        raise RegistrationError(f"registration failed: {0 if inl is None else int(inl.sum())} homography inliers "
                                f"of {len(pairs)} matches (need >= {p.min_inliers})")
    inl = inl.ravel().astype(bool)
    # least-squares polish on the inliers (MAGSAC's model is fitted on a minimal/weighted set)
    H2, _ = cv2.findHomography(src[inl], dst[inl], 0)
    if H2 is not None and np.all(np.isfinite(H2)):
        H = H2
    H = _check_homography(H)
    proj = cv2.perspectiveTransform(src[inl].reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
    rep = float(np.sqrt(np.mean(np.sum((proj - dst[inl]) ** 2, axis=1))))
    corr = None
    info: dict = {"warnings": []}
    if p.ecc:
        t1 = time.perf_counter()
        info["homography_keypoints"] = H.tolist()
        H, corr, ecc = _ecc_in_frame(ref, fgrey, H, p, valid)
        info["ecc"] = ecc
        info["ecc_converged"] = ecc["status"] != "failed"
        info["ecc_time_s"] = time.perf_counter() - t1
        if ecc["status"] == "failed":
            info["warnings"].append(f"ECC refinement failed ({ecc['reason']}); the keypoint homography is kept")
        elif ecc["status"] == "rejected":
            info["warnings"].append(f"ECC refinement did not lower the residual ({ecc['residual_before']:.4g} -> "
                                    f"{ecc['residual_after']:.4g}); the keypoint homography is kept")
    return Registration(H, (len(pa), len(pb)), int(len(pairs)), int(inl.sum()), rep, corr,
                        time.perf_counter() - t0, backend, info)


def refine_ecc(reference: np.ndarray, frame: np.ndarray, H: np.ndarray, params: RegistrationParams | None = None,
               *, valid=None) -> tuple[np.ndarray, float | None]:
    """ECC refinement of a reference -> frame homography ``H`` (see :func:`register`); returns
    ``(H, correlation)``: the refined ``H`` when it lowers the residual, else ``H`` unchanged;
    ``correlation`` is None when ECC failed."""
    p = params or RegistrationParams()
    H2, corr, _ = _ecc_in_frame(np.asarray(reference), to_grey(frame), _check_homography(H), p, valid)
    return H2, corr


def _ecc_in_frame(reference: np.ndarray, fgrey: np.ndarray, H: np.ndarray, p: RegistrationParams, valid=None):
    """ECC between the frame and the reference resampled into the frame's grid by ``H``.

    Returns ``(H_kept, correlation or None, report)`` with ``report["status"]`` "kept",
    "rejected" (did not lower the residual) or "failed" (with ``reason``)."""
    import cv2
    lr = np.log(np.maximum(to_grey(reference), 1e-12)).astype(np.float32)
    ref_ok = np.isfinite(lr) & (to_grey(reference) > 0)
    if valid is not None:
        ref_ok &= np.asarray(valid, bool)
    lr = np.where(ref_ok, lr, np.float32(np.nanmedian(lr[ref_ok]) if ref_ok.any() else 0.0)).astype(np.float32)
    # all covered pixels, clipped ones included: the fitted monotone map reproduces the clipping
    # (a mask of well-exposed pixels, full of holes, made OpenCV 5's ECC diverge on bright frames)
    f_ok = np.isfinite(fgrey)
    res0, mapped, m = _grid_residual(fgrey, lr, H, f_ok, ref_ok)
    rep = {"status": "failed", "residual_before": res0, "residual_after": None, "correlation": None}
    if mapped is None or m.sum() < 1000:
        rep["reason"] = f"only {int(m.sum())} frame pixels covered by the reference (need 1000)"
        return H, None, rep
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, p.ecc_iterations, p.ecc_eps)
    try:
        # template(x) ~ input(W x): frame(x) ~ mapped(W x) = reference(H^-1 W x), so H_new = W^-1 H
        corr, W = cv2.findTransformECC(fgrey.astype(np.float32), mapped.astype(np.float32),
                                       np.eye(3, dtype=np.float32), cv2.MOTION_HOMOGRAPHY, crit,
                                       m.astype(np.uint8), p.ecc_blur_px)
        Hn = _check_homography(np.linalg.inv(_check_homography(W, "ECC warp")) @ H)
    except (cv2.error, np.linalg.LinAlgError, ValueError) as e:
        rep["reason"] = str(e).strip().splitlines()[-1][:200]
        return H, None, rep
    res1, _, _ = _grid_residual(fgrey, lr, Hn, f_ok, ref_ok)
    rep.update(residual_after=res1, correlation=float(corr))
    if res1 < res0:
        rep["status"] = "kept"
        return Hn, float(corr), rep
    rep["status"] = "rejected"
    return H, float(corr), rep


def warp_reference(reference: np.ndarray, H: np.ndarray, shape: tuple) -> np.ndarray:
    """Warp a float32 reference into a frame grid of ``shape`` (H, W); pixels that fall outside
    the reference are NaN (no data)."""
    import cv2
    ref = np.asarray(reference, np.float32)
    h, w = int(shape[0]), int(shape[1])
    out = cv2.warpPerspective(ref, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    cover = cv2.warpPerspective(np.ones(ref.shape[:2], np.float32), H, (w, h), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    out[cover < 0.999] = np.nan
    return out


def corner_error(H_est: np.ndarray, H_true: np.ndarray, shape: tuple) -> float:
    """Mean distance in px between the image corners mapped by two homographies."""
    import cv2
    h, w = shape[:2]
    c = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64).reshape(-1, 1, 2)
    a = cv2.perspectiveTransform(c, np.asarray(H_est, np.float64))
    b = cv2.perspectiveTransform(c, np.asarray(H_true, np.float64))
    return float(np.mean(np.linalg.norm((a - b).reshape(-1, 2), axis=1)))


def register_recording(reference: np.ndarray, recording_path, out_path, params: RegistrationParams | None = None,
                       *, progress: bool = True, frame_indices=None, valid=None) -> tuple[Path, list[dict]]:
    """Register ``reference`` to every frame of a recording and write a NEW recording with the
    warped references (``HDRReferences`` at the frames' mid-exposure times).

    The input file is never modified; the output is written atomically (``.partial`` then rename).
    The references keep RGB when the frames are RGB, else are converted to luminance. Pixels
    outside the reference are NaN.

    Every frame is registered before anything is written: a frame that cannot be registered
    raises :class:`RegistrationError` naming it, and no output file is left. ``valid``: usable
    reference pixels (e.g. not the blue border of Debevec's scans).
    """
    import dataclasses

    from tqdm import tqdm

    src, dst = Path(recording_path), Path(out_path)
    if src.resolve() == dst.resolve():
        raise ValueError(f"--out-recording must differ from the input recording {src}; it is never modified in place")
    rec = read_recording(src)
    if rec.frames is None or len(rec.frames) == 0:
        raise ValueError(f"{src}: the recording has no frames to register the reference to")
    fr = rec.frames
    idx = range(len(fr)) if frame_indices is None else list(frame_indices)
    ref = np.asarray(reference, np.float32)
    if fr.images.ndim == 3 and ref.ndim == 3:
        ref_store = to_grey(ref).astype(np.float32)
    else:
        ref_store = ref
    imgs, ts, reports = [], [], []
    for k in tqdm(idx, desc="register", unit="frame", disable=not progress):
        try:
            r = register(ref, fr.images[k], params, valid=valid)
        except RegistrationError as e:
            raise RegistrationError(f"{src}: frame {k}: {e}") from None
        imgs.append(warp_reference(ref_store, r.homography, fr.shape))
        ts.append(int(fr.t_mid_us[k]))
        reports.append({"frame": int(k), "t_us": int(fr.t_mid_us[k]), **r.to_dict()})
    hdr = HDRReferences(np.stack(imgs), np.asarray(ts, np.int64))
    out = dataclasses.replace(rec, hdr=hdr)
    write_recording(out, dst)
    return dst, reports


# -- bracket-to-bracket alignment --------------------------------------------------------------
def _pair_homography(fixed: np.ndarray, moving: np.ndarray, fixed_ok, moving_ok, features: str,
                     max_shift_bits: int):
    """Candidates for the homography moving -> fixed grid between two exposures of one scene:
    identity, ``cv2.AlignMTB`` (median threshold bitmaps: exposure-invariant, integer shift) and
    a keypoint homography on the tone-matched images (larger or non-translational motion). The
    one with the lowest photometric residual (:func:`_grid_residual`) wins; identity unless
    another lowers the residual by more than 1 %. Returns (H, method, residuals dict)."""
    import cv2
    cands = {"identity": np.eye(3)}
    try:
        mtb = cv2.createAlignMTB(max_shift_bits)
        dx, dy = mtb.calculateShift(_u8(fixed, *np.percentile(fixed, [0, 100])),
                                    _u8(moving, *np.percentile(moving, [0, 100])))
        if (dx, dy) != (0, 0):
            cands["mtb"] = np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])
    except cv2.error:
        pass
    try:
        # quantile matching (needs no co-located pixels, unlike the residual's tone fit)
        q = np.linspace(0, 100, 257)
        mq, idx = np.unique(np.percentile(moving, q), return_index=True)
        if mq.size >= 3:
            matched = np.interp(moving, mq, np.percentile(fixed, q)[idx])
            lo, hi = (float(v) for v in np.percentile(fixed, [0.1, 99.9]))
            p = RegistrationParams(features=features, ecc=False)
            backend = "sift" if features == "sift" else surf_backend()
            pa, da, la = _detect(_u8(matched, lo, hi), p, backend)
            pb, db, lb = _detect(_u8(fixed, lo, hi), p, backend)
            pairs = _match(da, db, p.ratio, la, lb)
            if len(pairs) >= p.min_inliers:
                src, dst = pa[pairs[:, 0]], pb[pairs[:, 1]]
                H, inl = cv2.findHomography(src, dst, getattr(cv2, "USAC_MAGSAC", cv2.RANSAC), p.ransac_px,
                                            maxIters=10000, confidence=0.9999)
                if H is not None and inl is not None and int(inl.sum()) >= p.min_inliers:
                    inl = inl.ravel().astype(bool)
                    H2, _ = cv2.findHomography(src[inl], dst[inl], 0)
                    cands["features"] = _check_homography(H2 if H2 is not None else H)
    except (cv2.error, ValueError, ImportError):
        pass
    res = {k: _grid_residual(fixed, moving, H, fixed_ok, moving_ok)[0] for k, H in cands.items()}
    best = min(res, key=res.get)
    if best != "identity" and not res[best] < 0.99 * res["identity"]:
        best = "identity"
    return cands[best], best, res


def align_brackets(images, exposures_s=None, *, anchor: int | None = None, features: str = "sift",
                   max_shift_bits: int = 6, info: dict | None = None):
    """Align hand-held brackets to one anchor exposure before merging.

    Exposures are sorted; each image is aligned to its neighbour towards the anchor (default:
    the median exposure) by :func:`_pair_homography` (AlignMTB, then a keypoint homography for
    larger motion, each kept only if it lowers the photometric residual), the pair homographies
    are chained, and every image is resampled (bilinear) into the anchor's grid. Pixels that
    no longer see the image take code 0 for coded brackets (weight 0 in the certainty and hat
    merges) and the white level for RAW/linear ones (excluded as saturated).

    Returns a BracketSet when given one, else a list of images. ``info`` gets per image the
    method, the homography to the anchor and the residuals (``info["pairs"]``).
    """
    import cv2

    bs = images if isinstance(images, BracketSet) else None
    imgs = [np.asarray(im) for im in (bs.images if bs is not None else images)]
    ex = np.asarray(bs.exposures_s if bs is not None else exposures_s, np.float64)
    if len(imgs) != len(ex):
        raise ValueError(f"{len(imgs)} images but {len(ex)} exposure times")
    info = {} if info is None else info
    n = len(imgs)
    if n < 2:
        info.update(anchor=0, pairs=[])
        return images
    order = np.argsort(ex, kind="stable")
    a_pos = len(order) // 2 if anchor is None else int(np.flatnonzero(order == anchor)[0])
    greys = [to_grey(im).astype(np.float32) for im in imgs]
    linear = bs is not None and bs.encoding in ("raw", "linear")
    top = [float(np.iinfo(im.dtype).max) if np.issubdtype(im.dtype, np.integer) else 1.0 for im in imgs]
    oks = [(g > 0.02 * t) & (g < 0.98 * t) for g, t in zip(greys, top)]
    to_anchor = {int(order[a_pos]): np.eye(3)}
    pairs = []
    for step, rng_ in ((-1, range(a_pos - 1, -1, -1)), (1, range(a_pos + 1, n))):
        for pos in rng_:
            i, j = int(order[pos]), int(order[pos - step])  # align i to its neighbour j (nearer the anchor)
            H, how, res = _pair_homography(greys[j], greys[i], oks[j], oks[i], features, max_shift_bits)
            to_anchor[i] = to_anchor[j] @ H
            pairs.append({"image": i, "to": j, "method": how, "residuals": res,
                          "homography_to_anchor": (to_anchor[i] / to_anchor[i][2, 2]).tolist()})
    out = []
    for k, im in enumerate(imgs):
        H = to_anchor[k]
        if np.allclose(H, np.eye(3)):
            out.append(im)
            continue
        h, w = im.shape[:2]
        fill = top[k] if linear else 0.0
        warped = cv2.warpPerspective(im.astype(np.float32), H, (w, h), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=(fill, fill, fill, fill))
        cover = cv2.warpPerspective(np.ones((h, w), np.float32), H, (w, h), flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0.999
        warped[~cover] = fill
        if np.issubdtype(im.dtype, np.integer):
            warped = np.clip(np.round(warped), 0, top[k])
        out.append(warped.astype(im.dtype))
    info.update(anchor=int(order[a_pos]), pairs=sorted(pairs, key=lambda d: d["image"]),
                n_moved=int(sum(d["method"] != "identity" for d in pairs)))
    if bs is None:
        return out
    import dataclasses
    return dataclasses.replace(bs, images=out)
