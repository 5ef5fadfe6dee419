"""Event/frame self-calibration: the camera model of a recording, estimated from the recording itself.

Self-calibration is :func:`hybridhdr.calibrate.camera_model.estimate_camera_model` run on the
input recording when no profile is given: the same estimator as ``calibrate sensor`` and
``calibrate thresholds``' pooled figure, so the three give one ON/OFF pair for one recording.
It returns the time a frame stands for (``time_offset_us``: the shift of the frames' times
under which the events predict the next frame best), the log offset I0 of ``ln(I + I0)`` and
the thresholds c_on, c_off (module docstring of :mod:`.camera_model`).

``exclude_frames`` removes frames before anything is estimated (leave-one-out scoring: the
scored frame never informs its own calibration).
"""

from __future__ import annotations

import dataclasses

from ..model import Recording
from .camera_model import DEFAULT_INTENSITY_OFFSETS, SCHEMA, CameraModel, estimate_camera_model

__all__ = ["EventFrameCalibration", "estimate_event_frame_calibration", "apply_time_offset",
           "DEFAULT_INTENSITY_OFFSETS", "SCHEMA", "self_calibration"]

#: The self-calibration's result is the camera model.
EventFrameCalibration = CameraModel


def estimate_event_frame_calibration(recording, *, profile=None, exclude_frames=(), offsets_us=None,
                                     intensity_offsets=DEFAULT_INTENSITY_OFFSETS, well_exposed=None,
                                     c_range=(0.01, 3.0)) -> CameraModel:
    """The camera model of ``recording`` (:func:`hybridhdr.calibrate.camera_model.estimate_camera_model`).

    Raises
    ------
    ValueError
        Fewer than two usable frame intervals, no events, or no usable pixel-interval.
    """
    return estimate_camera_model(recording, profile=profile, exclude_frames=exclude_frames, offsets_us=offsets_us,
                                 intensity_offsets=intensity_offsets, well_exposed=well_exposed, c_range=c_range)


def apply_time_offset(recording, time_offset_us: int) -> Recording:
    """The recording with every frame's exposure interval shifted by ``time_offset_us`` (events,
    triggers and HDR references unchanged); provenance records the shift."""
    fr = recording.frames
    if fr is None or int(time_offset_us) == 0:
        return recording
    dt = int(time_offset_us)
    shifted = dataclasses.replace(fr, t_start_us=fr.t_start_us + dt, t_end_us=fr.t_end_us + dt)
    md = recording.metadata
    if md is not None and isinstance(md.provenance, dict):
        prov = dict(md.provenance)
        prov["frame_time_offset_us"] = int(prov.get("frame_time_offset_us", 0)) + dt
        md = dataclasses.replace(md, provenance=prov)
    return dataclasses.replace(recording, frames=shifted, metadata=md)


def self_calibration(recording, *, profile=None, intensity_offset: float | None = None, exclude_frames=(),
                     model: CameraModel | None = None) -> dict:
    """What a method needs from the camera model, as one record.

    ``intensity_offset=None`` (the AKF): the model's own I0. A number (a method whose log model is
    fixed, e.g. CF's published ``ln(I + 1)``): the time offset is the recording's (estimated with
    I0 free) and the thresholds are re-estimated at that offset in the method's own model.
    ``model``: an estimate already made for this recording (and these excluded frames).
    Returns ``{"time_offset_us", "intensity_offset", "c_on", "c_off", "r2", "r2_nominal",
    "calibration"}`` (the last: the full record)."""
    cal = model if model is not None else estimate_camera_model(recording, profile=profile,
                                                               exclude_frames=exclude_frames)
    rec = cal.to_dict()
    if intensity_offset is not None and float(intensity_offset) != cal.intensity_offset:
        used = estimate_camera_model(recording, profile=profile, exclude_frames=exclude_frames,
                                     time_offset_us=cal.latency_us if cal.latency_us is not None else cal.time_offset_us,
                                     intensity_offset=float(intensity_offset))
    else:
        used = cal
    return {"time_offset_us": int(cal.time_offset_us), "intensity_offset": float(used.intensity_offset),
            "c_on": float(used.c_on), "c_off": float(used.c_off), "r2": float(used.r2),
            "r2_nominal": float(cal.r2_nominal), "calibration": rec}
