"""Analytic blinking-checkerboard rig for the calibrate tests: exact, known geometry at every pixel.

The simulator's physically based board (``builtin:blinking_checkerboard``, Mitsuba) is used by
``test_simulated_board.py``; this one stays analytic so that the rig tests know the true
intrinsics, distortion and extrinsics exactly and run without a renderer.

A chessboard on a monitor (white squares and a one-square white margin; the monitor is black when
the board is off) is placed at known poses and rendered, 4x4 supersampled, on the pixel grid of
each camera: for every sub-pixel sample the distorted pixel is undistorted (OpenCV's iterative
``undistortPoints``), the ray is intersected with the board plane and the square colour looked up.
The board's inner corners project, by construction, where ``cv2.projectPoints`` puts them.

Events: each event-camera pixel is a log-intensity change detector with a per-pixel contrast
threshold (nominal ``c`` with 5 % mismatch) and a random reference level; at each blink transition
it fires ``floor(|ΔL| / c_pixel)`` events of the change's sign (plus a Gaussian read noise on L),
spread over a few hundred µs after the transition. Uniform background-noise events and "hot"
pixels that fire ON events only (single polarity, to exercise the rejection) are added.
"""

from __future__ import annotations

import cv2
import numpy as np

from hybridhdr.events import EVENT_DTYPE, SensorSize
from hybridhdr.calibrate.rig import Board

BOARD = Board(9, 6, 30.0)

# event camera 320x240 and frame camera 480x360; X_event = R X_frame + T
K_EVENT = np.array([[310.0, 0, 158.3], [0, 309.2, 121.7], [0, 0, 1]])
D_EVENT = np.array([-0.12, 0.05, 0.0005, -0.0003, 0.0])
SIZE_EVENT = SensorSize(240, 320)
K_FRAME = np.array([[452.0, 0, 242.4], [0, 451.5, 178.9], [0, 0, 1]])
D_FRAME = np.array([-0.08, 0.03, 0.0, 0.0, 0.0])
SIZE_FRAME = SensorSize(360, 480)
RVEC_FE = np.array([0.01, -0.025, 0.005])        # frame -> event rotation (~1.6 degrees)
R_FE = cv2.Rodrigues(RVEC_FE)[0]
T_FE = np.array([-0.060, 0.004, 0.002])          # metres, baseline ~60 mm
ZMIN, ZMAX = 0.38, 0.6                           # board distance range, metres


def board_colour(X, Y, board=BOARD):
    """1 on white squares and the one-square white margin, 0 on black squares and off the board."""
    s = board.square_mm / 1000.0
    i = np.floor(X / s)
    j = np.floor(Y / s)
    inside = (i >= -2) & (i <= board.cols) & (j >= -2) & (j <= board.rows)
    squares = (i >= -1) & (i <= board.cols - 1) & (j >= -1) & (j <= board.rows - 1)
    white = ((i + j) % 2 == 0)
    return np.where(inside, np.where(squares, white, True), False).astype(np.float64)


_RAYS: dict = {}


def render_board(K, dist, size: SensorSize, rvec, tvec, ss: int = 4, board=BOARD):
    """Fraction of each pixel covered by white board (H, W) float64, ``ss`` x ``ss`` supersampled."""
    h, w = size.shape
    key = (K.tobytes(), np.asarray(dist).tobytes(), size, ss)
    xn = _RAYS.get(key)
    if xn is None:
        off = (np.arange(ss) + 0.5) / ss - 0.5
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
        u = np.broadcast_to(uu[..., None, None] + off[None, None, None, :], (h, w, ss, ss)).ravel()
        v = np.broadcast_to(vv[..., None, None] + off[None, None, :, None], (h, w, ss, ss)).ravel()
        from hybridhdr.calibrate.rig import undistort_normalized
        xn = _RAYS[key] = undistort_normalized(np.stack([u, v], 1), K, dist)
    R = cv2.Rodrigues(np.asarray(rvec, float))[0]
    t = np.asarray(tvec, float).ravel()
    # board plane: X_cam = R [X, Y, 0] + t; ray X_cam = lam [xn, yn, 1]
    # solve lam d = R[:, 0] X + R[:, 1] Y + t for (X, Y, lam)
    n = R[:, 2]
    x, y = xn[:, 0], xn[:, 1]
    lam = (n @ t) / (x * n[0] + y * n[1] + n[2])
    P = [x * lam - t[0], y * lam - t[1], lam - t[2]]
    X = P[0] * R[0, 0] + P[1] * R[1, 0] + P[2] * R[2, 0]
    Y = P[0] * R[0, 1] + P[1] * R[1, 1] + P[2] * R[2, 1]
    c = board_colour(X, Y, board) * (lam > 0)
    return c.reshape(h, w, ss * ss).mean(axis=2)


def corners_visible(K, dist, size: SensorSize, rvec, tvec, margin_px=8.0, board=BOARD):
    """True when the whole board (with its white margin) projects inside the image."""
    s = board.square_mm / 1000.0
    xs = np.array([-2 * s, (board.cols + 1) * s])
    ys = np.array([-2 * s, (board.rows + 1) * s])
    pts = np.array([[x, y, 0.0] for x in xs for y in ys])
    p, _ = cv2.projectPoints(pts, np.asarray(rvec, float), np.asarray(tvec, float), K, dist)
    p = p.reshape(-1, 2)
    return bool(np.all(p[:, 0] > margin_px) and np.all(p[:, 0] < size.width - margin_px)
                and np.all(p[:, 1] > margin_px) and np.all(p[:, 1] < size.height - margin_px))


def make_poses(n, seed=0, board=BOARD):
    """``n`` board poses (rvec, tvec) in *frame*-camera coordinates, visible in both cameras."""
    rng = np.random.default_rng(seed)
    s = board.square_mm / 1000.0
    centre = np.array([(board.cols - 1) * s / 2, (board.rows - 1) * s / 2, 0.0])
    poses = []
    while len(poses) < n:
        ax = np.radians(rng.uniform(-35, 35))
        ay = np.radians(rng.uniform(-35, 35))
        az = np.radians(rng.uniform(-15, 15))
        R = (cv2.Rodrigues(np.array([ax, 0, 0]))[0] @ cv2.Rodrigues(np.array([0, ay, 0]))[0]
             @ cv2.Rodrigues(np.array([0, 0, az]))[0])
        z = rng.uniform(ZMIN, ZMAX)
        c = np.array([rng.uniform(-0.08, 0.05), rng.uniform(-0.05, 0.05), z])
        t = c - R @ centre
        rvec = cv2.Rodrigues(R)[0].ravel()
        re, te = frame_to_event_pose(rvec, t)
        if (corners_visible(K_FRAME, D_FRAME, SIZE_FRAME, rvec, t)
                and corners_visible(K_EVENT, D_EVENT, SIZE_EVENT, re, te)):
            poses.append((rvec, t))
    return poses


def frame_to_event_pose(rvec, tvec):
    R = cv2.Rodrigues(np.asarray(rvec, float))[0]
    Re = R_FE @ R
    te = R_FE @ np.asarray(tvec, float) + T_FE
    return cv2.Rodrigues(Re)[0].ravel(), te


def frame_image(cov, rng, noise_dn=1.0):
    """8-bit frame of the board 'on': black squares 12 DN, white 230 DN, Gaussian noise."""
    img = 12.0 + 218.0 * cov + rng.normal(0.0, noise_dn, cov.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


class EventPixels:
    """Per-pixel state of a simple DVS model (contrast threshold ``c`` in log units)."""

    def __init__(self, size: SensorSize, rng, c=0.4, mismatch=0.05, noise_log=0.02):
        self.size = size
        self.rng = rng
        self.c = c * (1.0 + mismatch * rng.standard_normal(size.shape)).clip(0.5, 1.5)
        self.noise = noise_log
        self.ref = None

    def step(self, L, t_us):
        """Events for a change to log image ``L`` at ``t_us``; returns (t, x, y, p) arrays."""
        Ln = L + self.noise * self.rng.standard_normal(L.shape)
        if self.ref is None:
            self.ref = Ln - self.rng.uniform(0, 1, L.shape) * self.c
            return [np.zeros(0, np.int64)] * 2 + [np.zeros(0, np.int64)] * 2
        d = Ln - self.ref
        n = np.trunc(d / self.c).astype(np.int64)
        self.ref = self.ref + n * self.c
        yy, xx = np.nonzero(n)
        cnt = np.abs(n[yy, xx])
        pol = np.sign(n[yy, xx])
        lat = self.rng.uniform(50, 300, yy.size)
        rep = np.repeat(np.arange(yy.size), cnt)
        k = np.arange(rep.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        t = t_us + (lat[rep] + 40.0 * k + self.rng.uniform(0, 30, rep.size)).astype(np.int64)
        return t, xx[rep], yy[rep], pol[rep]


def log_image(cov, on: bool, dark=0.03, white=1.0):
    return np.log(dark + (white - dark) * cov if on else np.full(cov.shape, dark))


def blink_events(cov_list, period_us=100_000, periods=3, seed=0, c=0.4, noise_rate_hz=0.05,
                 n_hot=150, hot_rate_hz=200.0, t0_us=1_000_000, motion_us=0, motion_steps=40,
                 triggers=False):
    """Events of a board blinking at ``1e6/period_us`` Hz for ``periods`` periods per pose.

    ``cov_list`` holds one white-coverage image per pose, or for motion (``motion_us > 0``) a
    pair ``(cov_a, cov_b)`` list: between poses the coverage is interpolated linearly over
    ``motion_steps`` steps of ``motion_us`` in total while the board keeps blinking (the monitor
    is assumed on during motion). Returns ``(events, triggers_or_None, pose_spans)``.
    """
    rng = np.random.default_rng(seed)
    size = SensorSize(*cov_list[0].shape)
    pix = EventPixels(size, rng, c=c)
    chunks = []
    spans = []
    trig = []
    t = t0_us
    pix.step(log_image(cov_list[0], False), t)
    # warm-up: the monitor has been blinking before the recording starts, so the pixels' reference
    # levels are in their steady on/off cycle (these events are not recorded)
    for _ in range(2):
        pix.step(log_image(cov_list[0], True), t)
        pix.step(log_image(cov_list[0], False), t)
    for k, cov in enumerate(cov_list):
        if k > 0 and motion_us > 0:
            prev = cov_list[k - 1]
            for s in range(1, motion_steps + 1):
                a = s / motion_steps
                chunks.append(pix.step(log_image((1 - a) * prev + a * cov, True), t))
                t += motion_us // motion_steps
            chunks.append(pix.step(log_image(cov, False), t))
            # the monitor keeps its blink phase: the next pose starts on a period boundary
            t = t0_us + period_us * (-(-(t - t0_us + period_us // 4) // period_us))
        t_start = t
        for _ in range(periods):
            trig.append((t, 1))
            chunks.append(pix.step(log_image(cov, True), t))
            trig.append((t + period_us // 2, -1))
            chunks.append(pix.step(log_image(cov, False), t + period_us // 2))
            t += period_us
        spans.append((t_start, t))
    t_end = t
    # background noise (random polarity) and hot pixels (ON only)
    n_noise = rng.poisson(noise_rate_hz * size.n_pixels * (t_end - t0_us) * 1e-6)
    chunks.append((rng.integers(t0_us, t_end, n_noise), rng.integers(0, size.width, n_noise),
                   rng.integers(0, size.height, n_noise), rng.choice([-1, 1], n_noise)))
    hx = rng.integers(0, size.width, n_hot)
    hy = rng.integers(0, size.height, n_hot)
    n_h = rng.poisson(hot_rate_hz * (t_end - t0_us) * 1e-6, n_hot)
    chunks.append((rng.integers(t0_us, t_end, n_h.sum()), np.repeat(hx, n_h), np.repeat(hy, n_h),
                   np.ones(n_h.sum(), np.int64)))
    t = np.concatenate([c[0] for c in chunks]).astype(np.int64)
    order = np.argsort(t, kind="stable")
    ev = np.empty(t.size, EVENT_DTYPE)
    ev["t"] = t[order]
    ev["x"] = np.concatenate([c[1] for c in chunks])[order]
    ev["y"] = np.concatenate([c[2] for c in chunks])[order]
    ev["p"] = np.concatenate([c[3] for c in chunks])[order]
    tr = None
    if triggers:
        from hybridhdr.events import make_triggers
        tt = np.array([a for a, _ in trig], np.int64)
        tr = make_triggers(tt, np.zeros(tt.size, np.uint16), np.array([e for _, e in trig]))
    return ev, tr, spans
