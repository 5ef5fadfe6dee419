"""The frame camera model shared by every part (calibrate produces it, simulate renders with it,
reconstruct and evaluate consume it): response (CRF and its inverse), encoding, bit depth, clip
levels, and the AKF's weighting function and frame noise profile (eqs. 3-9 of Wang et al. 2021).
"""

from .profile import (CameraProfile, default_profile, load_profile, profile_for_frames, profile_from_inverse_crf,
                      weighting_from_inverse_crf)

__all__ = ["CameraProfile", "default_profile", "load_profile", "profile_for_frames", "profile_from_inverse_crf",
           "weighting_from_inverse_crf"]
