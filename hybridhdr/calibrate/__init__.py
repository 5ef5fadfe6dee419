"""Calibrate: measure a hybrid rig from its own data — stereo geometry (event images of a blinking
checkerboard), camera response and the AKF noise profile, HDR references, contrast thresholds.

See ``docs/calibrate.md``. The camera model these produce is :mod:`hybridhdr.camera`.
"""

from .crf import CRF, estimate_crf, gamma_crf
from .event_images import BlinkParams, event_images
from .hdr_reference import RegistrationParams, align_brackets, merge_brackets, register, register_recording
from .noise_profile import noise_profile
from .rig import Board, RigCalibration, calibrate_rig, load_calibration, save_calibration
from .thresholds import estimate_thresholds

__all__ = [
    "Board", "RigCalibration", "calibrate_rig", "load_calibration", "save_calibration", "BlinkParams",
    "event_images", "CRF", "estimate_crf", "gamma_crf", "noise_profile", "merge_brackets", "align_brackets",
    "register", "RegistrationParams", "register_recording", "estimate_thresholds",
]
