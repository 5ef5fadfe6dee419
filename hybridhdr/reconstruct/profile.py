"""Moved to :mod:`hybridhdr.camera.profile` (the camera model is a part of its own); kept as an alias."""

from ..camera.profile import *  # noqa: F401,F403
from ..camera.profile import (DEFAULT_GAMMA, CameraProfile, default_profile, load_profile,  # noqa: F401
                              profile_for_frames, weighting_from_inverse_crf)
