"""Synthetic data for the photometric calibration tests and benchmarks: a textured HDR scene,
random homographies and LDR frames rendered through a gamma response (all seeded)."""

from __future__ import annotations

import numpy as np

__all__ = ["hdr_scene", "random_homography", "render_frame"]


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
