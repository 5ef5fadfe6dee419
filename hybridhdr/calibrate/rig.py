"""Stereo calibration of a hybrid event/frame rig with a checkerboard.

Pipeline (``docs/calibrate.md`` gives the sources of the choices):

1. **Corners** (:func:`find_corners`): ``cv2.findChessboardCornersSB`` with ``CALIB_CB_EXHAUSTIVE
   | CALIB_CB_ACCURACY`` (``CALIB_CB_NORMALIZE_IMAGE`` optional, see there; already sub-pixel; views whose
   ``estimateChessboardSharpness`` exceeds ``max_sharpness_px`` are dropped), or the classic
   ``findChessboardCorners`` + ``cornerSubPix`` (``detector="classic"``).
2. **Intrinsics** per camera at its own size (:func:`calibrate_camera`):
   ``cv2.calibrateCameraExtended`` with a distortion model from :data:`DISTORTION_MODELS`.
   Outlier views are pruned iteratively: after each calibration every view whose RMS error
   exceeds ``prune_factor`` times the median per-view error is dropped and the camera is
   re-calibrated, until no view is dropped, ``max_prune_rounds`` rounds have run, or dropping
   would leave fewer than ``min_views`` views.
3. **Extrinsics** (:func:`calibrate_stereo`): ``cv2.stereoCalibrate`` with ``CALIB_FIX_INTRINSIC``
   on the views seen by both cameras (its ``imageSize`` only seeds intrinsics, so cameras of
   different resolution are handled correctly). Convention: ``X_2 = R X_1 + T`` with camera 1 the
   frame camera and camera 2 the event camera; ``T`` in metres.
4. **Frame → event mapping**: the homography induced by the fronto-parallel plane ``Z_1 = d`` in
   frame-camera coordinates, ``H = K_e (R + T nᵀ/d) K_f⁻¹`` with ``n = (0, 0, 1)`` (derivation:
   ``X_e = R X_f + T = (R + T nᵀX_f/d) X_f`` for ``nᵀX_f = d``), or ``H = K_e R K_f⁻¹`` at
   infinity (the paper's far-scene case: Wang et al. 2021 align the frames to the event camera by
   a homography). A point at depth ``z ≠ d`` lands off by the residual parallax, about
   ``f_e |T_⊥| |1/z − 1/d|`` pixels; :func:`parallax_error` computes it exactly on a pixel grid.
   Stereo rectification (:func:`stereo_rectify`) is the alternative when depth varies.

The result is a :class:`RigCalibration`, saved as ``calibration.json`` (schema in
``docs/calibrate.md``), accepted as ``Metadata.calibration`` (:meth:`RigCalibration.to_metadata`)
and readable by the simulator (top-level ``K``/``image_size`` of camera 2).

References
----------
Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000,
doi:10.1109/34.888718. Z. Wang, Y. Ng, C. Scheerlinck, R. Mahony, "An Asynchronous Kalman Filter
for Hybrid Event Cameras", ICCV 2021, doi:10.1109/ICCV48922.2021.00050. R. Hartley, A. Zisserman,
"Multiple View Geometry", 2nd ed., §13.1 (homography induced by a plane).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._util.atomic import write_json_atomic
from .._util.checks import check_shape
from .._version import __version__
from ..events import SensorSize

__all__ = ["Board", "DISTORTION_MODELS", "CameraCalibration", "StereoCalibration", "RigCalibration",
           "find_corners", "calibrate_camera", "calibrate_stereo", "plane_homography",
           "parallax_error", "stereo_rectify", "frame_to_event_maps", "warp_frame_to_event",
           "undistort_normalized", "calibrate_rig", "load_calibration", "save_calibration",
           "plot_corners", "plot_per_view_errors", "plot_parallax",
           "CALIBRATION_FORMAT", "CALIBRATION_VERSION"]

CALIBRATION_FORMAT = "hybridhdr-rig-calibration"
CALIBRATION_VERSION = 1

#: distortion model name -> (OpenCV flags builder, number of coefficients, description)
DISTORTION_MODELS = {
    "none": "no distortion (k1..k3, p1, p2 fixed at 0)",
    "k1": "one radial coefficient k1",
    "fixed_k3": "k1, k2, p1, p2 (k3 fixed at 0)",
    "plumb_bob": "Brown-Conrady k1, k2, p1, p2, k3 (OpenCV default, 5 coefficients)",
    "rational": "rational radial k1..k6 with p1, p2 (8 coefficients)",
}


def _cv2():
    try:
        import cv2
    except ImportError as e:  # pragma: no cover - cv2 is a calibrate dependency
        raise ImportError("hybridhdr.calibrate needs OpenCV: pip install opencv-contrib-python-headless") from e
    return cv2


def _model_flags(model: str) -> int:
    cv2 = _cv2()
    if model == "none":
        return (cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST)
    if model == "k1":
        return cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    if model == "fixed_k3":
        return cv2.CALIB_FIX_K3
    if model == "plumb_bob":
        return 0
    if model == "rational":
        return cv2.CALIB_RATIONAL_MODEL
    raise ValueError(f"distortion model must be one of {sorted(DISTORTION_MODELS)}, got {model!r}")


def _n_params(model: str) -> int:
    return {"none": 0, "k1": 1, "fixed_k3": 4, "plumb_bob": 5, "rational": 8}[model] + 4


@dataclass(frozen=True)
class Board:
    """A chessboard: ``cols`` x ``rows`` *inner* corners, squares of ``square_mm`` millimetres."""

    cols: int
    rows: int
    square_mm: float

    def __post_init__(self):
        for n in ("cols", "rows"):
            v = getattr(self, n)
            if not isinstance(v, (int, np.integer)) or v < 2:
                raise ValueError(f"Board.{n} (inner corners) must be an int >= 2, got {v!r}")
        if not (isinstance(self.square_mm, (int, float, np.floating)) and self.square_mm > 0
                and math.isfinite(self.square_mm)):
            raise ValueError(f"Board.square_mm must be a positive number, got {self.square_mm!r}")

    @classmethod
    def parse(cls, spec: str, square_mm: float) -> "Board":
        """``"9x6"`` (inner corners, columns x rows) and a square size in mm."""
        try:
            c, r = (int(v) for v in spec.lower().split("x"))
        except ValueError:
            raise ValueError(f"board must be COLSxROWS inner corners like '9x6', got {spec!r}") from None
        return cls(c, r, float(square_mm))

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV's ``patternSize`` (columns, rows)."""
        return (self.cols, self.rows)

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    def object_points(self) -> np.ndarray:
        """Corner positions on the board plane, shape (cols*rows, 3), float32, metres, row-major
        (x along the columns), z = 0."""
        g = np.zeros((self.rows, self.cols, 3), np.float32)
        g[..., 0] = np.arange(self.cols)[None, :]
        g[..., 1] = np.arange(self.rows)[:, None]
        return (g.reshape(-1, 3) * np.float32(self.square_mm / 1000.0)).astype(np.float32)

    def to_dict(self) -> dict:
        return {"type": "chessboard", "cols": int(self.cols), "rows": int(self.rows),
                "square_mm": float(self.square_mm)}

    @classmethod
    def from_dict(cls, d: dict) -> "Board":
        return cls(int(d["cols"]), int(d["rows"]), float(d["square_mm"]))


# ----------------------------------------------------------------------------------------------
# corners


def _as_gray8(image) -> np.ndarray:
    im = np.asarray(image)
    check_shape(im, "H W | H W 3 | H W 4", "image")
    if im.ndim == 3:
        im = im[..., :3].astype(np.float64) @ np.array([0.114, 0.587, 0.299])  # BGR order as cv2 reads
    if im.dtype == np.uint8:
        return np.ascontiguousarray(im)
    im = im.astype(np.float64)
    lo, hi = np.nanmin(im), np.nanmax(im)
    if not hi > lo:
        return np.zeros(im.shape, np.uint8)
    return np.round((im - lo) / (hi - lo) * 255).astype(np.uint8)


def find_corners(image, board: Board, *, detector: str = "sb", max_sharpness_px: float | None = 4.0,
                 normalize: bool = False, subpix_window: int = 11):
    """Chessboard inner corners of one image, or None when the board is not found (or too blurry).

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, 3)
        Any dtype; non-uint8 images are scaled to 0-255.
    board : Board
    detector : {"sb", "sb+subpix", "classic"}
        ``"sb"``: ``findChessboardCornersSB`` with EXHAUSTIVE | ACCURACY (| NORMALIZE_IMAGE when
        ``normalize``). ``"sb+subpix"``: the SB corners refined by ``cornerSubPix`` with a
        half-window of 0.25 x the median square side in pixels, clamped to 2..7 px (larger windows
        reach the board's outer edge from the border corners: up to 11 px shifts on the OpenCV
        stereo sample). ``"classic"``:
        ``findChessboardCorners`` then ``cornerSubPix`` with a ``(2*subpix_window+1)``-pixel
        search window (11 as in OpenCV's calibration sample).

        Measured on the rendered rig of ``tests/calibrate/_sim.py`` (16 views, 480x360, 1 DN
        noise; OpenCV 5.0.0): plain SB corners carry a systematic error on sharp grey-level
        frames (corner RMS 0.105 px, focal length off by 0.61 %), which ``sb+subpix`` removes
        (0.089 px, 0.03 %); on blinking-board event images (blocky, quantised counts) plain SB is
        best (0.118 px, focal 0.07 %) and ``cornerSubPix`` makes it worse (0.22-0.27 px). Hence
        the defaults of :func:`calibrate_rig`: ``sb+subpix`` for frames, ``sb`` for event images.
    max_sharpness_px : float or None
        SB only: drop the view when ``estimateChessboardSharpness`` reports an edge width above
        this; None keeps every view. calibration.md step 4 advises about 3 px, but the 13 left
        views of OpenCV's stereo sample measure 2.5-3.3 px and all calibrate well (0.19 px RMS),
        so the default is 4 px.
    normalize : bool
        SB only: add ``CALIB_CB_NORMALIZE_IMAGE`` (histogram equalisation before detection). Off by
        default, and tried only when the board is not found without it: on rendered boards with 0.5-2 DN of noise it raised the corner RMS error from
        0.03-0.09 px to 0.31-0.47 px (measured with OpenCV 5.0.0 on the test rig of
        ``tests/calibrate/_sim.py``); use it only for very dark or low-contrast images.
    Returns
    -------
    corners : ndarray of shape (cols*rows, 2), float32, pixel (x=column, y=row), or None
    """
    cv2 = _cv2()
    g = _as_gray8(image)
    if detector in ("sb", "sb+subpix"):
        flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        if normalize:
            flags |= cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, c = cv2.findChessboardCornersSB(g, board.pattern_size, flags=flags)
        if not ok and not normalize:  # second chance: equalised image (finds dim/low-contrast boards)
            ok, c = cv2.findChessboardCornersSB(g, board.pattern_size, flags=flags | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok or c is None:
            return None
        c = c.reshape(-1, 2).astype(np.float32)
        if max_sharpness_px is not None:
            r = cv2.estimateChessboardSharpness(g, board.pattern_size, c.reshape(-1, 1, 2))
            if float(r[0][0]) > max_sharpness_px:
                return None
        if detector == "sb+subpix":
            g2 = c.reshape(board.rows, board.cols, 2)
            sq = np.median(np.concatenate([np.linalg.norm(np.diff(g2, axis=1), axis=2).ravel(),
                                           np.linalg.norm(np.diff(g2, axis=0), axis=2).ravel()]))
            w = int(min(max(2, 0.25 * sq), 7))
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
            c = cv2.cornerSubPix(g, c.reshape(-1, 1, 2).copy(), (w, w), (-1, -1), crit).reshape(-1, 2)
        return c
    if detector == "classic":
        ok, c = cv2.findChessboardCorners(g, board.pattern_size,
                                          flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok or c is None:
            return None
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
        c = cv2.cornerSubPix(g, c.astype(np.float32), (subpix_window, subpix_window), (-1, -1), crit)
        return c.reshape(-1, 2).astype(np.float32)
    raise ValueError(f"detector must be 'sb', 'sb+subpix' or 'classic', got {detector!r}")


# ----------------------------------------------------------------------------------------------
# intrinsics


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """One camera's intrinsics (OpenCV pinhole + distortion) and the views that made them.

    ``K`` (3, 3) pixels; ``dist`` OpenCV coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]);
    ``image_size`` the sensor size; ``rms_px`` the overall RMS reprojection error;
    ``per_view_errors_px`` and ``views`` the RMS error and name of each view kept;
    ``rejected_views`` (name, reason) pairs; ``rvecs``/``tvecs`` (board → camera, metres) per view.
    """

    K: np.ndarray
    dist: np.ndarray
    image_size: SensorSize
    model: str
    rms_px: float
    per_view_errors_px: np.ndarray
    views: tuple[str, ...]
    rejected_views: tuple[tuple[str, str], ...] = ()
    std_intrinsics: np.ndarray | None = None
    rvecs: np.ndarray | None = None
    tvecs: np.ndarray | None = None

    @property
    def focal_px(self) -> tuple[float, float]:
        return float(self.K[0, 0]), float(self.K[1, 1])

    def to_dict(self) -> dict:
        h, w = self.image_size.shape
        d = {"K": np.asarray(self.K, float).tolist(), "dist": np.asarray(self.dist, float).ravel().tolist(),
             "distortion_model": self.model, "image_size": [w, h], "width": w, "height": h,
             "rms_px": float(self.rms_px),
             "per_view_errors_px": np.asarray(self.per_view_errors_px, float).ravel().tolist(),
             "views": list(self.views), "rejected_views": [list(r) for r in self.rejected_views]}
        if self.std_intrinsics is not None:
            d["std_intrinsics"] = np.asarray(self.std_intrinsics, float).ravel().tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict, name: str = "camera") -> "CameraCalibration":
        try:
            K = np.asarray(d["K"], np.float64)
            dist = np.asarray(d.get("dist", [0, 0, 0, 0, 0]), np.float64).ravel()
            if "width" in d and "height" in d:
                size = SensorSize(int(d["height"]), int(d["width"]))
            else:
                w, h = d["image_size"]
                size = SensorSize(int(h), int(w))
        except KeyError as e:
            raise ValueError(f"calibration of {name}: missing key {e.args[0]!r}") from None
        check_shape(K, "3 3", f"calibration of {name}: K")
        if dist.size not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"calibration of {name}: dist must have 4, 5, 8, 12 or 14 coefficients, "
                             f"got {dist.size}")
        return cls(K, dist, size, str(d.get("distortion_model", "plumb_bob")), float(d.get("rms_px", float("nan"))),
                   np.asarray(d.get("per_view_errors_px", []), np.float64), tuple(d.get("views", [])),
                   tuple(tuple(r) for r in d.get("rejected_views", [])),
                   None if d.get("std_intrinsics") is None else np.asarray(d["std_intrinsics"], np.float64))


def _check_views(object_points, image_points, names, n_corners_min=4):
    if len(object_points) != len(image_points):
        raise ValueError(f"need one object-point array per view: {len(object_points)} object vs "
                         f"{len(image_points)} image point arrays")
    if names is None:
        names = [f"view{i}" for i in range(len(image_points))]
    if len(names) != len(image_points):
        raise ValueError(f"need one name per view, got {len(names)} names for {len(image_points)} views")
    O, I = [], []
    for n, o, i in zip(names, object_points, image_points):
        o = np.ascontiguousarray(o, np.float32).reshape(-1, 3)
        i = np.ascontiguousarray(i, np.float32).reshape(-1, 2)
        if o.shape[0] != i.shape[0]:
            raise ValueError(f"view {n}: {o.shape[0]} object points but {i.shape[0]} image points")
        if i.shape[0] < n_corners_min:
            raise ValueError(f"view {n}: too few corners ({i.shape[0]}); need at least {n_corners_min}")
        O.append(o)
        I.append(i)
    return O, I, list(names)


def calibrate_camera(object_points, image_points, image_size, *, model: str = "plumb_bob", names=None,
                     prune_factor: float | None = 2.0, max_prune_rounds: int = 3,
                     min_views: int = 4) -> CameraCalibration:
    """Intrinsics of one camera with ``cv2.calibrateCameraExtended`` and outlier-view pruning.

    Parameters
    ----------
    object_points : list of ndarray (n_i, 3)
        Board points per view (metres, z = 0).
    image_points : list of ndarray (n_i, 2)
        Detected corners per view (pixels).
    image_size : SensorSize or (height, width)
    model : str
        Distortion model, one of :data:`DISTORTION_MODELS`.
    names : list of str, optional
        View names used in the report.
    prune_factor : float or None
        Drop views whose RMS error exceeds ``prune_factor`` x the median per-view error
        (calibration.md step 5: 2x), then re-calibrate; None disables pruning.
    max_prune_rounds : int
    min_views : int
        Fewest views accepted (also the floor for pruning).

    Raises
    ------
    ValueError
        Too few views (found vs needed), point-count mismatches, too few corners in a view.
    """
    cv2 = _cv2()
    flags = _model_flags(model)
    size = SensorSize.from_any(image_size)
    if size is None:
        raise ValueError("image_size (height, width) is required")
    O, I, names = _check_views(object_points, image_points, names)
    min_views = max(int(min_views), 1)
    if len(I) < min_views:
        raise ValueError(f"too few views with a detected board: found {len(I)}, need at least {min_views}")
    for n, i in zip(names, I):
        if (i[:, 0].min() < -0.5 or i[:, 1].min() < -0.5 or i[:, 0].max() > size.width - 0.5
                or i[:, 1].max() > size.height - 0.5):
            raise ValueError(f"view {n}: corners lie outside the {size} image (x {i[:, 0].min():.1f}.."
                             f"{i[:, 0].max():.1f}, y {i[:, 1].min():.1f}..{i[:, 1].max():.1f}); "
                             f"mismatched image sizes?")
    n_params = _n_params(model)
    n_obs = 2 * sum(i.shape[0] for i in I)
    if n_obs <= n_params + 6 * len(I):
        raise ValueError(f"too few corners: {n_obs // 2} corners in {len(I)} views cannot constrain "
                         f"{n_params} intrinsics and {6 * len(I)} pose parameters")
    keep = list(range(len(I)))
    rejected: list[tuple[str, str]] = []
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rounds = 0
    while True:
        res = cv2.calibrateCameraExtended([O[k] for k in keep], [I[k] for k in keep], (size.width, size.height),
                                          None, None, flags=flags, criteria=crit)
        rms, K, dist, rvecs, tvecs, std_in, _, pve = res
        pve = np.asarray(pve, np.float64).ravel()
        if prune_factor is None or rounds >= max_prune_rounds:
            break
        med = float(np.median(pve))
        bad = [j for j in range(len(keep)) if pve[j] > prune_factor * med]
        if not bad or len(keep) - len(bad) < min_views:
            break
        for j in bad:
            rejected.append((names[keep[j]], f"per-view RMS {pve[j]:.3f} px > {prune_factor} x median "
                                             f"{med:.3f} px (round {rounds + 1})"))
        keep = [k for j, k in enumerate(keep) if j not in bad]
        rounds += 1
    return CameraCalibration(np.asarray(K, np.float64), np.asarray(dist, np.float64).ravel(), size, model,
                             float(rms), pve, tuple(names[k] for k in keep), tuple(rejected),
                             np.asarray(std_in, np.float64).ravel(),
                             np.asarray(rvecs, np.float64).reshape(-1, 3),
                             np.asarray(tvecs, np.float64).reshape(-1, 3))


# ----------------------------------------------------------------------------------------------
# extrinsics


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """``X_2 = R X_1 + T`` (T in metres), essential and fundamental matrices, RMS and per-view
    errors (n_views, 2) of the views in ``views``."""

    R: np.ndarray
    T_m: np.ndarray
    E: np.ndarray
    F: np.ndarray
    rms_px: float
    per_view_errors_px: np.ndarray
    views: tuple[str, ...]
    rejected_views: tuple[tuple[str, str], ...] = ()

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.T_m))

    @property
    def rotation_deg(self) -> float:
        cv2 = _cv2()
        return float(np.degrees(np.linalg.norm(cv2.Rodrigues(self.R)[0])))

    def to_dict(self) -> dict:
        return {"R": self.R.tolist(), "T_m": self.T_m.ravel().tolist(), "E": self.E.tolist(),
                "F": self.F.tolist(), "baseline_m": self.baseline_m, "rotation_deg": self.rotation_deg,
                "rms_px": float(self.rms_px), "per_view_errors_px": np.asarray(self.per_view_errors_px).tolist(),
                "views": list(self.views), "rejected_views": [list(r) for r in self.rejected_views]}

    @classmethod
    def from_dict(cls, d: dict) -> "StereoCalibration":
        R = np.asarray(d["R"], np.float64)
        T = np.asarray(d["T_m"], np.float64).ravel()
        check_shape(R, "3 3", "stereo: R")
        check_shape(T, "3", "stereo: T_m")
        return cls(R, T, np.asarray(d.get("E", np.zeros((3, 3))), np.float64),
                   np.asarray(d.get("F", np.zeros((3, 3))), np.float64), float(d.get("rms_px", float("nan"))),
                   np.asarray(d.get("per_view_errors_px", []), np.float64), tuple(d.get("views", [])),
                   tuple(tuple(r) for r in d.get("rejected_views", [])))


def calibrate_stereo(object_points, points1, points2, cam1: CameraCalibration, cam2: CameraCalibration, *,
                     names=None, prune_factor: float | None = 2.0, max_prune_rounds: int = 3,
                     min_views: int = 3) -> StereoCalibration:
    """Extrinsics ``X_2 = R X_1 + T`` with ``cv2.stereoCalibrate(..., CALIB_FIX_INTRINSIC)``.

    ``points1[i]`` and ``points2[i]`` are the same board corners seen by both cameras in view
    ``i``. Views whose stereo RMS (mean of both cameras) exceeds ``prune_factor`` x the median are
    dropped and the extrinsics re-estimated, as in :func:`calibrate_camera`.
    """
    cv2 = _cv2()
    O, P1, names = _check_views(object_points, points1, names)
    _, P2, _ = _check_views(object_points, points2, names)
    if len(O) < min_views:
        raise ValueError(f"too few views seen by both cameras: found {len(O)}, need at least {min_views}")
    keep = list(range(len(O)))
    rejected = []
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rounds = 0
    while True:
        r = cv2.stereoCalibrate([O[k] for k in keep], [P1[k] for k in keep], [P2[k] for k in keep],
                                cam1.K, cam1.dist, cam2.K, cam2.dist,
                                (cam1.image_size.width, cam1.image_size.height), np.eye(3),
                                np.zeros((3, 1)), np.eye(3), np.eye(3), np.zeros((len(keep), 2)),
                                flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
        rms, _, _, _, _, R, T, E, F, pve = r
        pve = np.asarray(pve, np.float64).reshape(len(keep), 2)
        if prune_factor is None or rounds >= max_prune_rounds:
            break
        m = pve.mean(axis=1)
        med = float(np.median(m))
        bad = [j for j in range(len(keep)) if m[j] > prune_factor * med]
        if not bad or len(keep) - len(bad) < min_views:
            break
        for j in bad:
            rejected.append((names[keep[j]], f"stereo RMS {m[j]:.3f} px > {prune_factor} x median {med:.3f} px"))
        keep = [k for j, k in enumerate(keep) if j not in bad]
        rounds += 1
    return StereoCalibration(np.asarray(R, np.float64), np.asarray(T, np.float64).ravel(),
                             np.asarray(E, np.float64), np.asarray(F, np.float64), float(rms), pve,
                             tuple(names[k] for k in keep), tuple(rejected))


# ----------------------------------------------------------------------------------------------
# frame -> event mapping


def plane_homography(K1, K2, R, T_m, depth_m: float | None) -> np.ndarray:
    """Homography from camera-1 to camera-2 (undistorted) pixels induced by the plane ``Z_1 = depth_m``.

    ``H = K2 (R + T nᵀ/d) K1⁻¹`` with ``n = (0, 0, 1)``; ``depth_m=None`` (or inf) gives the
    infinite homography ``K2 R K1⁻¹``. Normalised so that ``H[2, 2] = 1``.
    """
    A = np.asarray(R, np.float64).copy()
    if depth_m is not None and math.isfinite(depth_m):
        if not depth_m > 0:
            raise ValueError(f"depth_m must be > 0 (metres) or None for infinity, got {depth_m}")
        A = A + np.outer(np.asarray(T_m, np.float64).ravel(), [0.0, 0.0, 1.0]) / depth_m
    H = np.asarray(K2, np.float64) @ A @ np.linalg.inv(np.asarray(K1, np.float64))
    return H / H[2, 2]


def parallax_error(K1, size1: SensorSize, K2, R, T_m, depth_m: float | None, depths_m, grid: int = 9):
    """Residual parallax (pixels in camera 2) of the plane homography for points at other depths.

    For a ``grid`` x ``grid`` lattice of camera-1 pixels, the point at depth ``z`` (each value of
    ``depths_m``) is projected exactly into camera 2 (pinhole, ``X_2 = R X_1 + T``) and compared with
    the homography's prediction. Returns ``(median_px, max_px)`` arrays, one value per depth.
    """
    H = plane_homography(K1, K2, R, T_m, depth_m)
    us = np.linspace(0, size1.width - 1, grid)
    vs = np.linspace(0, size1.height - 1, grid)
    uu, vv = np.meshgrid(us, vs)
    pix = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])
    rays = np.linalg.inv(K1) @ pix
    ph = H @ pix
    ph = ph[:2] / ph[2]
    med, mx = [], []
    for z in np.asarray(depths_m, np.float64).ravel():
        X2 = R @ (rays * z) + np.asarray(T_m, np.float64).reshape(3, 1)
        x2 = K2 @ X2
        x2 = x2[:2] / x2[2]
        e = np.linalg.norm(x2 - ph, axis=0)
        med.append(float(np.median(e)))
        mx.append(float(np.max(e)))
    return np.asarray(med), np.asarray(mx)


def undistort_normalized(points_px, K, dist) -> np.ndarray:
    """Normalised (z = 1) coordinates of distorted pixels, shape (N, 2); iterated to 1e-12."""
    cv2 = _cv2()
    pts = np.ascontiguousarray(points_px, np.float64).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    K = np.asarray(K, np.float64)
    dist = np.asarray(dist, np.float64)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x: the criteria overload has this name
        return cv2.undistortPointsIter(pts, K, dist, None, None, crit).reshape(-1, 2)
    return cv2.undistortPoints(pts, K, dist, None, None, criteria=crit).reshape(-1, 2)  # OpenCV 5


def frame_to_event_maps(rig: "RigCalibration", depth_m: float | None = "calibrated"):
    """``cv2.remap`` maps (map_x, map_y; float32, event-grid shape) sampling the frame image.

    For every event pixel: undistort (event intrinsics), back-project onto the plane ``Z_f = d``
    (through the inverse homography in normalised coordinates), and project with the frame
    camera's intrinsics and distortion. ``depth_m="calibrated"`` uses the calibration's depth.
    """
    cv2 = _cv2()
    if isinstance(depth_m, str):
        depth_m = rig.depth_m
    ev, fr = rig.camera2, rig.camera1
    h, w = ev.image_size.shape
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    xn = undistort_normalized(np.stack([uu.ravel(), vv.ravel()], 1), ev.K, ev.dist)
    Hn = plane_homography(np.eye(3), np.eye(3), rig.stereo.R, rig.stereo.T_m, depth_m)
    Xf = np.linalg.inv(Hn) @ np.vstack([xn.T, np.ones(xn.shape[0])])
    Xf = (Xf / Xf[2]).T.reshape(-1, 1, 3)
    proj, _ = cv2.projectPoints(Xf, np.zeros(3), np.zeros(3), fr.K, fr.dist)
    proj = proj.reshape(h, w, 2).astype(np.float32)
    return proj[..., 0], proj[..., 1]


def warp_frame_to_event(image, rig: "RigCalibration", depth_m: float | None = "calibrated",
                        interpolation: str = "linear") -> np.ndarray:
    """Resample a frame-camera image onto the event grid (lens distortion of both cameras included)."""
    cv2 = _cv2()
    mx, my = frame_to_event_maps(rig, depth_m)
    interp = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST, "cubic": cv2.INTER_CUBIC}[interpolation]
    im = np.asarray(image)
    if im.shape[:2] != rig.camera1.image_size.shape:
        raise ValueError(f"frame image must be {rig.camera1.image_size} (HxW {rig.camera1.image_size.shape}), "
                         f"got shape {im.shape[:2]}")
    if im.dtype in (np.float64,):
        im = im.astype(np.float32)
    return cv2.remap(im, mx, my, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def stereo_rectify(rig: "RigCalibration", alpha: float = 0.0) -> dict:
    """Rectification of the pair at the camera-2 (event) resolution.

    ``cv2.stereoRectify`` assumes one image size for both cameras, so camera 1 is first rescaled
    to camera 2's size (equivalent to resizing the frame image with ``cv2.resize``, whose pixel
    centres map as ``x' = s (x + 0.5) - 0.5``). Returns ``R1, R2, P1, P2, Q`` and the scaled
    ``K1_scaled``; use them with ``cv2.initUndistortRectifyMap`` on the resized frame image.
    """
    cv2 = _cv2()
    c1, c2 = rig.camera1, rig.camera2
    sx = c2.image_size.width / c1.image_size.width
    sy = c2.image_size.height / c1.image_size.height
    K1 = c1.K.copy()
    K1[0, 0] *= sx
    K1[0, 1] *= sx
    K1[0, 2] = sx * (K1[0, 2] + 0.5) - 0.5
    K1[1, 1] *= sy
    K1[1, 2] = sy * (K1[1, 2] + 0.5) - 0.5
    size = (c2.image_size.width, c2.image_size.height)
    R1, R2, P1, P2, Q, roi1, roi2 = cv2.stereoRectify(K1, c1.dist, c2.K, c2.dist, size, rig.stereo.R,
                                                      rig.stereo.T_m.reshape(3, 1), alpha=alpha)
    return {"R1": R1, "R2": R2, "P1": P1, "P2": P2, "Q": Q, "K1_scaled": K1, "roi1": roi1, "roi2": roi2}


# ----------------------------------------------------------------------------------------------
# the rig


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """Calibration of a two-camera rig: ``X_2 = R X_1 + T``.

    ``camera1`` is the frame camera and ``camera2`` the event camera (``names`` says what they
    are; ``("left", "right")`` for two frame cameras). ``homography`` maps undistorted camera-1
    pixels to undistorted camera-2 pixels for a scene at ``depth_m`` (None = infinity).
    """

    camera1: CameraCalibration
    camera2: CameraCalibration
    stereo: StereoCalibration
    board: Board
    depth_m: float | None = None
    names: tuple[str, str] = ("frame", "event")
    provenance: dict = field(default_factory=dict)

    @property
    def homography(self) -> np.ndarray:
        return plane_homography(self.camera1.K, self.camera2.K, self.stereo.R, self.stereo.T_m, self.depth_m)

    def parallax_table(self, depths_m=None) -> dict:
        """Residual parallax of :attr:`homography` (camera-2 pixels) at other depths."""
        if depths_m is None:
            base = self.depth_m if self.depth_m is not None else 10.0
            depths_m = sorted({*np.round(np.geomspace(0.25, 100.0, 13), 3).tolist(), float(base)})
        med, mx = parallax_error(self.camera1.K, self.camera1.image_size, self.camera2.K, self.stereo.R,
                                 self.stereo.T_m, self.depth_m, depths_m)
        f2 = float(self.camera2.K[0, 0])
        approx = [f2 * self.stereo.baseline_m * abs(1.0 / z - (0.0 if self.depth_m is None else 1.0 / self.depth_m))
                  for z in depths_m]
        return {"depth_m": [float(z) for z in depths_m], "median_px": med.tolist(), "max_px": mx.tolist(),
                "approx_f_T_px": approx}

    def to_dict(self) -> dict:
        n1, n2 = self.names
        c2 = self.camera2.to_dict()
        return {
            "format": CALIBRATION_FORMAT, "version": CALIBRATION_VERSION,
            "convention": "X_{camera2} = R X_{camera1} + T (metres); pixels x = column, y = row; OpenCV "
                          "pinhole + distortion; image_size is [width, height]",
            "camera1": n1, "camera2": n2,
            # single-camera readers (the simulator) take the top-level K / image_size: camera 2
            "K": c2["K"], "dist": c2["dist"], "image_size": c2["image_size"],
            "width": c2["width"], "height": c2["height"],
            "cameras": {n1: self.camera1.to_dict(), n2: c2},
            "board": self.board.to_dict(),
            "stereo": self.stereo.to_dict(),
            "mapping": {"type": "homography", "from": n1, "to": n2,
                        "depth_m": None if self.depth_m is None else float(self.depth_m),
                        "plane_normal": [0.0, 0.0, 1.0],
                        "H": self.homography.tolist(),
                        "parallax": self.parallax_table()},
            "provenance": dict(self.provenance),
        }

    def to_metadata(self) -> dict:
        """The JSON-able dict stored as ``Metadata.calibration`` of a recording."""
        return json.loads(json.dumps(self.to_dict()))

    @classmethod
    def from_dict(cls, d: dict) -> "RigCalibration":
        if not isinstance(d, dict):
            raise ValueError(f"calibration must be a JSON object, got {type(d).__name__}")
        if d.get("format") != CALIBRATION_FORMAT:
            raise ValueError(f"not a rig calibration: format is {d.get('format')!r}, expected {CALIBRATION_FORMAT!r}")
        if int(d.get("version", -1)) > CALIBRATION_VERSION:
            raise ValueError(f"calibration version {d.get('version')} is newer than supported "
                             f"({CALIBRATION_VERSION})")
        try:
            n1, n2 = str(d["camera1"]), str(d["camera2"])
            cams = d["cameras"]
            c1 = CameraCalibration.from_dict(cams[n1], n1)
            c2 = CameraCalibration.from_dict(cams[n2], n2)
            st = StereoCalibration.from_dict(d["stereo"])
            board = Board.from_dict(d["board"])
            depth = d.get("mapping", {}).get("depth_m")
        except KeyError as e:
            raise ValueError(f"calibration: missing key {e.args[0]!r}") from None
        return cls(c1, c2, st, board, None if depth is None else float(depth), (n1, n2),
                   dict(d.get("provenance") or {}))

    def save(self, path) -> Path:
        return save_calibration(self, path)


def save_calibration(rig: RigCalibration, path) -> Path:
    """Write ``calibration.json`` atomically (a temporary name, then rename)."""
    return write_json_atomic(path, rig.to_dict())


def load_calibration(path_or_dict) -> RigCalibration:
    """Read a ``calibration.json`` (or the dict of ``Metadata.calibration``)."""
    if isinstance(path_or_dict, dict):
        return RigCalibration.from_dict(path_or_dict)
    path = Path(path_or_dict)
    try:
        from .._util.limits import read_text_bounded
        d = json.loads(read_text_bounded(path, "calibration file"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from None
    try:
        return RigCalibration.from_dict(d)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def calibrate_rig(images1, images2, board: Board, *, names=None, model: str = "plumb_bob",
                  model2: str | None = None, detector1: str = "sb+subpix", detector2: str = "sb",
                  depth_m: float | None = None,
                  prune_factor: float | None = 2.0, min_views: int = 4, camera_names=("frame", "event"),
                  max_sharpness_px: float | None = 4.0, progress: bool = False):
    """Full rig calibration from paired views: corners, intrinsics, extrinsics, mapping.

    Parameters
    ----------
    images1, images2 : sequence of ndarray
        View ``i`` of camera 1 (frame) and camera 2 (event image) show the same board pose. All
        images of one camera must have the same size.
    board : Board
    model, model2 : str
        Distortion model of camera 1 and camera 2 (``model2`` defaults to ``model``).
    detector1, detector2 : str
        Corner detector of each camera (see :func:`find_corners`): ``sb+subpix`` suits frames,
        ``sb`` blinking-board event images; use ``sb+subpix`` for both with two frame cameras.
    max_sharpness_px : see :func:`find_corners`.
    depth_m : float or None
        Scene depth of the mapping homography (None = infinity).

    Returns
    -------
    rig : RigCalibration
    detections : dict
        ``{"corners1": [...], "corners2": [...], "names": [...]}`` (None where not found).
    """
    if len(images1) != len(images2):
        raise ValueError(f"need one {camera_names[1]} view per {camera_names[0]} view: got {len(images1)} and "
                         f"{len(images2)}")
    if len(images1) == 0:
        raise ValueError("no views given")
    names = list(names) if names is not None else [f"view{i:02d}" for i in range(len(images1))]
    sizes = []
    for cam, ims in zip(camera_names, (images1, images2)):
        shapes = {tuple(np.asarray(im).shape[:2]) for im in ims}
        if len(shapes) != 1:
            raise ValueError(f"mismatched image sizes for the {cam} camera: {sorted(shapes)} (HxW); all its "
                             f"views must have one size")
        sizes.append(SensorSize(*shapes.pop()))
    obj = board.object_points()
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=2 * len(images1), desc="corners", unit="view")
    corners, cals = [], []
    try:
        for cam, ims, size, mdl, det in ((camera_names[0], images1, sizes[0], model, detector1),
                                         (camera_names[1], images2, sizes[1], model2 or model, detector2)):
            cs = []
            for im in ims:
                cs.append(find_corners(im, board, detector=det, max_sharpness_px=max_sharpness_px))
                if bar is not None:
                    bar.update(1)
            idx = [i for i, c in enumerate(cs) if c is not None]
            if len(idx) < min_views:
                raise ValueError(f"too few views with the {board.cols}x{board.rows} board found in the {cam} "
                                 f"camera: found {len(idx)} of {len(cs)}, need at least {min_views} (check "
                                 f"--board: inner corners, columns x rows)")
            corners.append(cs)
            cals.append(calibrate_camera([obj] * len(idx), [cs[i] for i in idx], size, model=mdl,
                                         names=[names[i] for i in idx], prune_factor=prune_factor,
                                         min_views=min_views))
    finally:
        if bar is not None:
            bar.close()
    c1, c2 = corners
    kept1, kept2 = set(cals[0].views), set(cals[1].views)
    both = [i for i in range(len(names)) if names[i] in kept1 and names[i] in kept2]
    if len(both) < 3:
        raise ValueError(f"too few views with the board found in both cameras: found {len(both)}, need at "
                         f"least 3 for the extrinsics")
    st = calibrate_stereo([obj] * len(both), [c1[i] for i in both], [c2[i] for i in both], cals[0], cals[1],
                          names=[names[i] for i in both], prune_factor=prune_factor)
    rig = RigCalibration(cals[0], cals[1], st, board, depth_m, tuple(camera_names),
                         {"hybridhdr_version": __version__, "detectors": [detector1, detector2]})
    return rig, {"corners1": c1, "corners2": c2, "names": names}


# ----------------------------------------------------------------------------------------------
# plots (matplotlib imported inside; each returns (fig, ax) and never calls plt.show())


def _plt():
    try:
        import matplotlib
        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover
        raise ImportError("plots need matplotlib: pip install matplotlib") from e
    return plt


def plot_corners(image, corners, board: Board, title: str = "", ax=None):
    """The image with its detected corners (first corner circled, row order drawn)."""
    plt = _plt()
    fig, ax = (ax.figure, ax) if ax is not None else plt.subplots(figsize=(5, 4))
    ax.imshow(np.asarray(image), cmap="gray", interpolation="nearest")
    if corners is not None:
        c = np.asarray(corners).reshape(-1, 2)
        ax.plot(c[:, 0], c[:, 1], "-", color="tab:orange", lw=0.6)
        ax.plot(c[:, 0], c[:, 1], "+", color="tab:red", ms=5)
        ax.plot(c[0, 0], c[0, 1], "o", mfc="none", color="tab:cyan", ms=9)
    else:
        ax.text(0.5, 0.5, "board not found", transform=ax.transAxes, ha="center", color="red")
    ax.set_title(title, fontsize=8)
    ax.set_axis_off()
    return fig, ax


def plot_per_view_errors(rig: RigCalibration, ax=None):
    """Per-view RMS reprojection errors of both cameras' intrinsics and of the stereo fit."""
    plt = _plt()
    fig, ax = (ax.figure, ax) if ax is not None else plt.subplots(figsize=(8, 3.5))
    names = sorted(set(rig.camera1.views) | set(rig.camera2.views) | {r[0] for r in rig.camera1.rejected_views}
                   | {r[0] for r in rig.camera2.rejected_views})
    x = np.arange(len(names))
    w = 0.4
    for off, cam, label in ((-w / 2, rig.camera1, rig.names[0]), (w / 2, rig.camera2, rig.names[1])):
        err = dict(zip(cam.views, cam.per_view_errors_px))
        ax.bar(x + off, [err.get(n, np.nan) for n in names], w, label=f"{label} (RMS {cam.rms_px:.3f} px)")
        for r in cam.rejected_views:
            if r[0] in names:
                ax.plot(names.index(r[0]) + off, 0, "x", color="red")
    ax.set_xticks(x, names, rotation=90, fontsize=7)
    ax.set_ylabel("RMS reprojection error (px)")
    ax.set_title(f"per-view errors; stereo RMS {rig.stereo.rms_px:.3f} px; x = pruned view", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig, ax


def plot_parallax(rig: RigCalibration, depths_m=None, ax=None):
    """Residual parallax of the frame→event homography versus scene depth."""
    plt = _plt()
    if ax is None:
        fig, ax = plt.subplots(figsize=(6.8, 3.5))
    else:
        fig = ax.figure
    if depths_m is None:
        depths_m = np.geomspace(0.2, 200.0, 60)
    tab = rig.parallax_table(depths_m)
    # a translation gives nearly the same parallax everywhere, so max and median often coincide: the
    # max is drawn wide and translucent underneath, the median thin and dashed on top, so both show
    ax.loglog(tab["depth_m"], np.maximum(tab["max_px"], 1e-3), color="tab:blue", lw=4.0, alpha=0.45,
              solid_capstyle="butt", label="max over the image", zorder=2)
    ax.loglog(tab["depth_m"], np.maximum(tab["median_px"], 1e-3), color="tab:orange", lw=1.2, ls="--",
              label="median", zorder=3)
    if rig.depth_m is not None:
        ax.axvline(rig.depth_m, color="gray", ls=":", label=f"homography depth {rig.depth_m:g} m")
    ax.axhline(0.5, color="red", lw=0.6, ls="--", label="0.5 px")
    ax.set_xlabel("scene depth (m)")
    ax.set_ylabel(f"parallax error ({rig.names[1]} px)")
    ax.set_title(f"baseline {1000 * rig.stereo.baseline_m:.1f} mm", fontsize=9)
    # outside the axes: the curves reach every corner for some rigs
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    return fig, ax
