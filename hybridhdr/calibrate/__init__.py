"""Calibrate: measure a hybrid rig from its own data — stereo geometry (event images of a blinking
checkerboard), camera response and the AKF noise profile, HDR references, contrast thresholds.

See ``docs/calibrate.md``. The camera model these produce is :mod:`hybridhdr.camera`.
"""

from .._util.lazy import lazy_exports

# Lazy (PEP 562): the names below load their module on first use, so that building the command
# line's parser (hybridhdr --help) does not import numba and the kernels (a slow start).
_LAZY = {
    'BlinkParams': '.event_images',
    'event_images': '.event_images',
    'noise_profile': '.noise_profile',
    'CRF': '.crf',
    'estimate_crf': '.crf',
    'gamma_crf': '.crf',
    'RegistrationParams': '.hdr_reference',
    'align_brackets': '.hdr_reference',
    'merge_brackets': '.hdr_reference',
    'register': '.hdr_reference',
    'register_recording': '.hdr_reference',
    'Board': '.rig',
    'RigCalibration': '.rig',
    'calibrate_rig': '.rig',
    'load_calibration': '.rig',
    'save_calibration': '.rig',
    'estimate_thresholds': '.thresholds',
}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)


__all__ = [
    "Board", "RigCalibration", "calibrate_rig", "load_calibration", "save_calibration", "BlinkParams",
    "event_images", "CRF", "estimate_crf", "gamma_crf", "noise_profile", "merge_brackets", "align_brackets",
    "register", "RegistrationParams", "register_recording", "estimate_thresholds",
]
