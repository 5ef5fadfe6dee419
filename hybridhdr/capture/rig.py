"""A two-SDK rig without trigger wiring: frames put on the event clock through the host clock.

The paper's rig pairs an event camera with a machine-vision frame camera. With a trigger wire
(frame strobe into the event camera's trigger input) :mod:`hybridhdr.capture.sync` maps the frames
onto the event clock from the trigger edges, to the microsecond. Without one, both sources are tied
to the host's monotonic clock:

* the event source records ``(event timestamp, host time of arrival)`` samples, thinned to the
  lowest latency per bin (:class:`~hybridhdr.capture.dv_backend.HostClockSamples`);
* the frame source stamps frames on the host clock (:mod:`hybridhdr.capture.pylon_backend`: the
  camera clock mapped by latch samples, else the software trigger time, else the arrival time).

:func:`host_clock_sync` fits ``host = a + b · t_event`` to the event samples with the robust line
fit of :mod:`hybridhdr.capture.sync` (Huber IRLS, then least squares on the inliers) and maps every
frame's exposure interval through the inverse. The report gives the fit (offset, drift in ppm), the
residual RMS and maximum of the samples (the variation of the transport latency: the uncertainty
of this synchronisation, typically hundreds of µs to ms, against µs for trigger wiring), and the
samples' span. The latency's constant part cannot be observed from the host: it biases the
offset by the minimum transport latency of the event stream.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..model import Frames, Metadata, Recording
from .sync import robust_line_fit

__all__ = ["HostSyncReport", "host_clock_sync", "host_clock_sync_recording"]


@dataclass
class HostSyncReport:
    """Result of :func:`host_clock_sync` (µs)."""

    method: str
    offset_us: float        # a in host = a + (1 + d) · t_event
    drift_ppm: float        # d × 1e6
    rms_us: float           # residual RMS of the inlier samples (latency variation)
    max_abs_us: float
    n_samples: int
    n_inliers: int
    span_s: float           # host time covered by the samples
    n_frames: int
    frame_timestamp_source: str | None = None
    drift_stderr_ppm: float = float("nan")  # standard error of the drift: rms / (sqrt(n) · std(t_event))

    def to_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        return "\n".join([
            f"host clock = {self.offset_us:.1f} µs + (1 + {self.drift_ppm:.2f} ± {self.drift_stderr_ppm:.2f} ppm) "
            f"· event clock "
            f"({self.n_inliers} of {self.n_samples} samples over {self.span_s:.2f} s)",
            f"latency variation: RMS {self.rms_us:.1f} µs, max {self.max_abs_us:.1f} µs",
            f"{self.n_frames} frames put on the event clock (frame times from: {self.frame_timestamp_source})"])


def host_clock_sync(frames: Frames, event_data_us, event_host_us, *, frame_timestamp_source=None):
    """Frames stamped on the host clock -> frames on the event clock, and a :class:`HostSyncReport`."""
    x = np.asarray(event_data_us, np.int64)
    y = np.asarray(event_host_us, np.int64)
    if len(x) < 2 or len(np.unique(x)) < 2:
        raise ValueError(f"the event source left {len(x)} host-clock samples; at least 2 at distinct times are "
                         f"needed (record longer than a fraction of a second)")
    x0, y0 = int(x[0]), int(y[0])
    a, b, inl, r = robust_line_fit((x - x0).astype(np.float64), (y - y0).astype(np.float64))
    if not b > 0:
        raise ValueError(f"the host-clock fit has slope {b}; the event timestamps do not advance with the host clock")

    def to_event(h):
        return np.round((np.asarray(h, np.float64) - y0 - a) / b + x0).astype(np.int64)

    ts, te = to_event(frames.t_start_us), to_event(frames.t_end_us)
    te = np.maximum(te, ts)
    out = Frames(frames.images, ts, te, encoding=frames.encoding, iso=frames.iso, gain=frames.gain)
    ri = r[inl]
    xi = (x[inl] - x0).astype(np.float64)
    se = (float(np.sqrt(np.mean(ri ** 2))) / (np.sqrt(len(xi)) * float(np.std(xi))) * 1e6
          if len(xi) > 2 and np.std(xi) > 0 else float("nan"))
    rep = HostSyncReport("host-clock", float(y0 + a - b * x0), float((b - 1) * 1e6),
                         float(np.sqrt(np.mean(ri ** 2))) if len(ri) else float("nan"),
                         float(np.max(np.abs(ri))) if len(ri) else float("nan"), int(len(x)), int(inl.sum()),
                         float((y[-1] - y[0]) / 1e6), int(len(frames)), frame_timestamp_source, se)
    return out, rep


def host_clock_sync_recording(rec: Recording) -> tuple[Recording, HostSyncReport]:
    """Apply :func:`host_clock_sync` to a recording made by the recorder (samples from its provenance)."""
    prov = rec.metadata.provenance or {}
    st = prov.get("recorder") or {}
    clocks = st.get("source_clocks") or {}
    ev = clocks.get("events")
    if not ev:
        raise ValueError("the recording holds no host-clock samples of its event source (recorded by a source "
                         "that keeps none, or recovered after a crash, when the final statistics are lost)")
    if rec.frames is None or not len(rec.frames):
        raise ValueError("the recording holds no frames to synchronise")
    fsrc = ((prov.get("sources") or {}).get("frames") or {}).get("timestamp_source")
    frames, rep = host_clock_sync(rec.frames, ev["data_us"], ev["host_us"], frame_timestamp_source=fsrc)
    md = Metadata(rec.metadata.event_camera, rec.metadata.frame_camera, rec.metadata.calibration,
                  {**prov, "host_clock_sync": rep.to_dict()})
    return Recording(rec.events, rec.sensor_size, frames=frames, triggers=rec.triggers, metadata=md, imu=rec.imu), rep
