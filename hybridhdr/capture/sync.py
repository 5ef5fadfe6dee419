"""Frame/event synchronisation from trigger edges: exposures on the event clock, offset and drift.

A frame camera wired to the event camera's trigger input produces, for every exposure, a rising
edge when the exposure starts and a falling edge when it ends (``TRIGGER_DTYPE`` edge +1 / −1,
``docs/conventions.md``). :func:`sync_frames`

1. pairs the edges of one channel into pulses (a rising edge followed by a falling edge); edges
   without a partner are reported;
2. numbers the pulses and the frames by their slot in the frame period (each time relative to the
   last good one, so drift never accumulates into the numbering), flags duplicates and off-grid
   pulses as *extra*, and pairs slots — the alignment of the two numberings is the shift that pairs
   most slots, ties broken by how well pulse widths match the frames' exposure times;
3. fits ``t_event = a + (1 + d) · t_frame`` to the paired start (and end) times by iteratively
   reweighted least squares with Huber weights (scale from the MAD, 1.345 σ threshold — Huber
   1964, doi:10.1214/aoms/1177703732), drops residuals beyond ``outlier_sigma`` σ and refits by least
   squares; the residual RMS and maximum are the synchronisation jitter;
4. returns the frames with exposure intervals on the event clock: the measured edges for frames
   with an intact pulse (``use="measured"``) or the fitted mapping (``use="fit"``, and always for
   frames whose trigger is missing), plus a :class:`SyncReport`.

Frames whose slot has no pulse are reported as *missing triggers* (by frame index); pulses whose
slot has no frame, duplicates and off-grid pulses as *extra triggers* (by index in the input
trigger array). The frame period must be constant (a triggered or free-running fixed-rate camera).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ..events import TRIGGER_DTYPE, validate_triggers
from ..model import Frames
from ..model import Metadata, Recording

__all__ = ["SyncReport", "sync_frames", "robust_line_fit", "trigger_pulses", "sync_recording", "EDGE_MODES"]

#: ``both``: rising = exposure start, falling = exposure end; ``rising``: starts only.
EDGE_MODES = ("both", "rising")


@dataclass
class SyncReport:
    """Result of :func:`sync_frames` (times in µs; JSON-able through :meth:`to_dict`)."""

    channel: int
    edge_mode: str
    offset_us: float          # a: event-clock time of frame-clock 0
    drift_ppm: float          # d × 1e6
    rms_us: float             # residual RMS of the inliers
    max_abs_us: float         # largest inlier residual
    n_frames: int
    n_pulses: int
    n_pairs: int
    frame_period_us: float
    missing_trigger_frames: list = field(default_factory=list)   # frame indices without a pulse
    extra_triggers: list = field(default_factory=list)           # trigger indices (rising edges)
    unpaired_edges: list = field(default_factory=list)           # trigger indices
    outlier_frames: list = field(default_factory=list)           # paired frames rejected by the fit
    shift_slots: int = 0
    use: str = "measured"

    def to_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        def lst(v):
            return "none" if not v else (", ".join(map(str, v[:20])) + (" ..." if len(v) > 20 else ""))
        return "\n".join([
            f"channel {self.channel} ({self.edge_mode} edges): {self.n_pulses} pulses, {self.n_frames} frames, "
            f"{self.n_pairs} paired (frame period {self.frame_period_us:.1f} µs)",
            f"t_event = {self.offset_us:.3f} µs + (1 + {self.drift_ppm:.3f} ppm) · t_frame",
            f"residual jitter: RMS {self.rms_us:.3f} µs, max {self.max_abs_us:.3f} µs",
            f"missing triggers (frame indices): {lst(self.missing_trigger_frames)}",
            f"extra triggers (trigger indices): {lst(self.extra_triggers)}",
            f"unpaired edges (trigger indices): {lst(self.unpaired_edges)}",
            f"fit outliers (frame indices): {lst(self.outlier_frames)}"])


def robust_line_fit(x, y, *, iterations: int = 30, huber_k: float = 1.345, outlier_sigma: float = 5.0,
                    min_scale: float = 0.05):
    """Fit ``y = a + b x`` robustly: Huber IRLS, then least squares on the inliers.

    Parameters
    ----------
    x, y : ndarray of shape (N,)
        Abscissae and ordinates (any unit; µs here). Centred internally for conditioning.
    huber_k : float
        Huber threshold in units of the robust scale (1.345 gives 95 % efficiency under Gaussian noise).
    outlier_sigma : float
        Residuals beyond this many robust σ are outliers and excluded from the final fit.
    min_scale : float
        Floor of the robust scale (same unit as y), so exact data do not divide by zero.

    Returns
    -------
    a, b : float
    inliers : ndarray of bool (N,)
    residuals : ndarray (N,)  y − (a + b x)
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"x and y must be 1-D of one length, got {x.shape} and {y.shape}")
    if len(x) < 2 or np.ptp(x) == 0:
        raise ValueError(f"a line fit needs at least 2 distinct abscissae, got {len(np.unique(x))}")
    x0, y0 = float(np.median(x)), float(np.median(y))
    xc, yc = x - x0, y - y0
    A = np.stack([np.ones_like(xc), xc], axis=1)
    w = np.ones_like(xc)
    beta = np.zeros(2)
    for _ in range(iterations):
        sw = np.sqrt(w)
        beta_new = np.linalg.lstsq(A * sw[:, None], yc * sw, rcond=None)[0]
        r = yc - A @ beta_new
        s = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), min_scale)
        c = huber_k * s
        ar = np.abs(r)
        w = np.where(ar <= c, 1.0, c / np.maximum(ar, 1e-300))
        done = np.allclose(beta_new, beta, rtol=0, atol=1e-12 * (1 + np.abs(beta)).max())
        beta = beta_new
        if done:
            break
    r = yc - A @ beta
    s = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), min_scale)
    inl = np.abs(r) <= outlier_sigma * s
    if inl.sum() >= 2 and np.ptp(xc[inl]) > 0:
        beta = np.linalg.lstsq(A[inl], yc[inl], rcond=None)[0]
    b = float(beta[1])
    a = float(y0 + beta[0] - b * x0)
    return a, b, inl, y - (a + b * x)


def trigger_pulses(triggers: np.ndarray, channel: int, edge_mode: str = "both"):
    """Pulses of one channel: ``(starts, ends, rising_index, unpaired)``.

    ``starts``/``ends`` are µs (ends = -1 for ``edge_mode="rising"``), ``rising_index`` the index of
    each pulse's rising edge in ``triggers`` and ``unpaired`` the indices of edges without partner.
    """
    if edge_mode not in EDGE_MODES:
        raise ValueError(f"edge_mode must be one of {EDGE_MODES}, got {edge_mode!r}")
    validate_triggers(triggers)
    idx = np.flatnonzero(triggers["channel"] == channel)
    if idx.size == 0:
        chans = sorted(set(int(c) for c in np.unique(triggers["channel"])))
        raise ValueError(f"no trigger edges on channel {channel}; channels present: {chans or 'none'}")
    e = triggers["edge"][idx]
    t = triggers["t"][idx]
    if edge_mode == "rising":
        r = e == 1
        return t[r], np.full(int(r.sum()), -1, np.int64), idx[r], []
    rising = np.flatnonzero(e == 1)
    ok = rising[(rising + 1 < len(e))]
    ok = ok[e[ok + 1] == -1]
    paired = np.zeros(len(e), bool)
    paired[ok] = True
    paired[ok + 1] = True
    return t[ok], t[ok + 1], idx[ok], [int(i) for i in idx[~paired]]


def _slots(t, period, tol_frac):
    from ._kernels import assign_slots
    t = np.ascontiguousarray(t, np.int64)
    slot = np.empty(len(t), np.int64)
    status = np.empty(len(t), np.int8)
    assign_slots(t, float(period), float(tol_frac), slot, status)
    return slot, status


def _median_period(t, name):
    d = np.diff(t)
    d = d[d > 0]
    if d.size == 0:
        raise ValueError(f"cannot estimate the frame period: {name} needs at least 2 distinct times")
    p = float(np.median(d))
    # refine on the diffs within 25 % of one period (skips gaps and doubles)
    near = d[np.abs(d - p) < 0.25 * p]
    return float(near.mean()) if near.size else p


def sync_frames(frames: Frames, triggers: np.ndarray, *, channel: int = 0, edge_mode: str = "both",
                frame_period_us: float | None = None, max_shift_slots: int = 5, tol_frac: float = 0.25,
                outlier_sigma: float = 5.0, use: str = "measured"):
    """Map frame exposures onto the event clock using trigger edges (module docstring).

    Parameters
    ----------
    frames : Frames
        Frames with exposure intervals on the frame camera's clock (µs).
    triggers : ndarray of TRIGGER_DTYPE
        Trigger edges on the event camera's clock (µs).
    channel : int
        Trigger channel the frame camera's strobe is wired to.
    edge_mode : {"both", "rising"}
        ``both``: rising = exposure start, falling = exposure end; ``rising``: only starts are used.
    frame_period_us : float, optional
        Frame period on the frame clock (default: estimated from the frames).
    max_shift_slots : int
        Largest misalignment (in frames) searched between the first frame and the first pulse.
    tol_frac : float
        A pulse farther than this fraction of a period from the grid is an extra trigger.
    outlier_sigma : float
        Robust-σ threshold of the fit's outlier rejection.
    use : {"measured", "fit"}
        Exposure times from the measured edges (where intact) or from the fitted clock mapping.

    Returns
    -------
    frames_ev : Frames
        Same images, exposure intervals on the event clock.
    report : SyncReport
    """
    if not isinstance(frames, Frames):
        raise TypeError(f"frames must be Frames, got {type(frames).__name__}")
    if use not in ("measured", "fit"):
        raise ValueError(f"use must be 'measured' or 'fit', got {use!r}")
    if not isinstance(triggers, np.ndarray) or triggers.dtype != TRIGGER_DTYPE:
        raise TypeError("triggers must be an ndarray of dtype TRIGGER_DTYPE")
    if len(frames) < 2:
        raise ValueError(f"synchronisation needs at least 2 frames, got {len(frames)}")
    ps, pe, pidx, unpaired = trigger_pulses(triggers, channel, edge_mode)
    if len(ps) < 2:
        raise ValueError(f"channel {channel} has {len(ps)} complete trigger pulses; need at least 2 "
                         f"(edge_mode={edge_mode!r})")
    fs, fe = frames.t_start_us, frames.t_end_us
    p_fr = float(frame_period_us) if frame_period_us is not None else _median_period(fs, "frames")
    p_ev = _median_period(ps, "trigger pulses")
    fslot, fstat = _slots(fs, p_fr, tol_frac)
    pslot, pstat = _slots(ps, p_ev, tol_frac)
    extra = [int(pidx[k]) for k in np.flatnonzero(pstat != 0)]
    good_p = np.flatnonzero(pstat == 0)
    good_f = np.flatnonzero(fstat == 0)
    pmap = {int(pslot[k]): int(k) for k in good_p}
    # alignment: the shift that pairs the most slots; ties -> pulse widths closest to exposures
    best = None
    for s in range(-int(max_shift_slots), int(max_shift_slots) + 1):
        pairs = [(int(j), pmap[int(fslot[j]) + s]) for j in good_f if int(fslot[j]) + s in pmap]
        if len(pairs) < 2:
            continue
        if edge_mode == "both":
            jj = np.array([p[0] for p in pairs])
            kk = np.array([p[1] for p in pairs])
            width_err = float(np.median(np.abs((pe[kk] - ps[kk]) - (fe[jj] - fs[jj]))))
        else:
            width_err = 0.0
        key = (-len(pairs), width_err, abs(s))
        if best is None or key < best[0]:
            best = (key, s, pairs)
    if best is None:
        raise ValueError("could not pair any frames with trigger pulses (check the channel, the edge mode "
                         "and that frames and triggers overlap in time)")
    _, shift, pairs = best
    jj = np.array([p[0] for p in pairs])
    kk = np.array([p[1] for p in pairs])
    paired_p = set(kk.tolist())
    extra += [int(pidx[k]) for k in good_p if int(k) not in paired_p]
    missing = sorted(set(range(len(frames))) - set(jj.tolist()))
    if edge_mode == "both":
        x = np.concatenate([fs[jj], fe[jj]])
        y = np.concatenate([ps[kk], pe[kk]])
    else:
        x, y = fs[jj], ps[kk]
    a, b, inl, res = robust_line_fit(x, y, outlier_sigma=outlier_sigma)
    m = len(jj)
    pair_ok = inl[:m] & (inl[m:] if edge_mode == "both" else True)
    outliers = sorted(int(j) for j in jj[~pair_ok])
    r_in = res[inl]
    report = SyncReport(channel=int(channel), edge_mode=edge_mode, offset_us=a, drift_ppm=(b - 1.0) * 1e6,
                        rms_us=float(np.sqrt(np.mean(r_in ** 2))), max_abs_us=float(np.abs(r_in).max()),
                        n_frames=len(frames), n_pulses=len(ps), n_pairs=int(pair_ok.sum()),
                        frame_period_us=p_fr, missing_trigger_frames=missing, extra_triggers=sorted(extra),
                        unpaired_edges=unpaired, outlier_frames=outliers, shift_slots=int(shift), use=use)
    ts = np.rint(a + b * fs.astype(np.float64)).astype(np.int64)
    te = np.rint(a + b * fe.astype(np.float64)).astype(np.int64)
    if use == "measured":
        ok = jj[pair_ok]
        ts[ok] = ps[kk[pair_ok]]
        if edge_mode == "both":
            te[ok] = pe[kk[pair_ok]]
        else:
            te[ok] = ts[ok] + np.rint(b * (fe[ok] - fs[ok])).astype(np.int64)
    order = np.argsort(ts, kind="stable")
    if np.any(order != np.arange(len(order))):
        raise ValueError("frames are out of order on the event clock after synchronisation; the trigger "
                         "pairing is inconsistent (try use='fit' or check the channel)")
    return Frames(frames.images, ts, np.maximum(te, ts), frames.gain, frames.iso, frames.encoding), report


def sync_recording(recording, *, channel: int = 0, **kwargs):
    """:func:`sync_frames` on a :class:`~hybridhdr.model.Recording`; the report goes to provenance."""
    if recording.frames is None or not len(recording.frames):
        raise ValueError("the recording holds no frames to synchronise")
    frames, report = sync_frames(recording.frames, recording.triggers, channel=channel, **kwargs)
    md = recording.metadata
    prov = dict(md.provenance)
    prov["sync"] = report.to_dict()
    md = Metadata(md.event_camera, md.frame_camera, md.calibration, prov)
    return Recording(recording.events, recording.sensor_size, frames, recording.triggers, recording.hdr, md,
                     recording.imu), report
