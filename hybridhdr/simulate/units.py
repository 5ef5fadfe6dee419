"""Ground truth in the reconstruction's **frame-linear units** (the contract with ``reconstruct``).

A reconstruction is in frame-linear units: 1.0 is the frame camera's clip level, the intensity
that maps to the highest unclipped code, at the frame's exposure (a camera profile's inverse CRF
is normalised so that its clip code is 1.0). Simulated references are scene radiance; the
simulated frame camera (:mod:`hybridhdr.simulate.camera`) maps radiance ``R`` over an exposure
``T`` to the normalised signal ``v = R · T · electrons_per_radiance_s · gain / full_well_e``
(before the full-well clip), then the CRF and quantisation, then the optional ``code_clip``. So

    reference in frame-linear units = v / v_clip = R · T · k / v_clip,
    k = electrons_per_radiance_s · gain / full_well_e,
    v_clip = inverse CRF at the highest unclipped code (``code_clip[1]`` when set, else the
             maximum code) = ``crf_inverse_table(camera)[-1]``.

``T`` is the exposure of the frame nearest in time (mid-exposure) to each reference, so that a
camera with auto-exposure converts each reference with its own frame's exposure (the
reconstruction's unit changes with the exposure too); the result says whether it varied.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .camera import FrameCameraParams, crf_inverse_table

__all__ = ["reference_to_frame_units", "frame_units_scale", "camera_from_provenance"]


def camera_from_provenance(prov):
    """The :class:`~hybridhdr.simulate.camera.FrameCameraParams` recorded in a simulated
    recording's provenance (``provenance["camera"]``), or None."""
    cam = prov.get("camera") if isinstance(prov, dict) else None
    if not isinstance(cam, dict):
        return None
    names = {f.name for f in dataclasses.fields(FrameCameraParams)}
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in cam.items() if k in names}
    return FrameCameraParams(**kw)


def frame_units_scale(camera, exposure_us) -> np.ndarray:
    """Frame-linear units per unit radiance at exposure(s) ``exposure_us`` (µs) for ``camera``
    (a ``FrameCameraParams``): ``T · electrons_per_radiance_s · gain / full_well_e / v_clip``."""
    v_clip = float(np.asarray(crf_inverse_table(camera), dtype=np.float64)[-1])
    if not v_clip > 0:
        raise ValueError(f"the camera's clip level must be > 0, got v_clip = {v_clip}")
    k = camera.electrons_per_radiance_s * camera.gain / camera.full_well_e
    return np.asarray(exposure_us, dtype=np.float64) * 1e-6 * k / v_clip


def reference_to_frame_units(images, t_us, camera, frames) -> tuple[np.ndarray, dict]:
    """Convert radiance references to frame-linear units (see the module docstring).

    Parameters
    ----------
    images : ndarray (K, H, W) or (K, H, W, C)
        Reference radiance (the simulator's HDR references).
    t_us : array_like (K,)
        Reference times in µs.
    camera : FrameCameraParams or dict
        The simulated frame camera (or a recording's provenance holding ``"camera"``).
    frames : Frames
        The recording's frames; each reference uses the exposure of the frame whose
        mid-exposure is nearest to it.

    Returns
    -------
    images : ndarray float32, same shape
    info : dict
        ``scale`` (per reference), ``exposure_us`` (per reference), ``exposure_varies`` (bool),
        ``v_clip`` and ``units`` = "frame_linear".
    """
    if isinstance(camera, dict):
        cam = camera_from_provenance(camera if "camera" in camera else {"camera": camera})
    else:
        cam = camera
    if cam is None:
        raise ValueError("reference_to_frame_units needs the simulated frame camera's parameters")
    if frames is None or len(frames) == 0:
        raise ValueError("reference_to_frame_units needs the frames (their exposures set the unit)")
    t = np.asarray(t_us, dtype=np.int64)
    mid = np.asarray(frames.t_mid_us, dtype=np.int64)
    exp_all = np.asarray(frames.t_end_us, dtype=np.int64) - np.asarray(frames.t_start_us, dtype=np.int64)
    j = np.clip(np.searchsorted(mid, t), 0, len(mid) - 1)
    jm = np.clip(j - 1, 0, len(mid) - 1)
    near = np.where(np.abs(mid[jm] - t) <= np.abs(mid[j] - t), jm, j)
    exp = exp_all[near]
    scale = frame_units_scale(cam, exp)
    im = np.asarray(images, dtype=np.float64)
    shape = (len(t),) + (1,) * (im.ndim - 1)
    out = (im * scale.reshape(shape)).astype(np.float32)
    info = {"units": "frame_linear", "scale": scale.tolist(), "exposure_us": exp.tolist(),
            "exposure_varies": bool(np.unique(exp_all).size > 1),
            "v_clip": float(np.asarray(crf_inverse_table(cam))[-1])}
    return out, info
