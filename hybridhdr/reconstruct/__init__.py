"""Reconstruct: the Asynchronous Kalman Filter (Wang et al., ICCV 2021) and its baselines.

>>> from hybridhdr.reconstruct import reconstruct, AKFParams
>>> AKFParams().process_noise_per_s
0.0005

See ``docs/reconstruct.md``.
"""

from .api import METHOD_ALIASES, METHODS, Video, make_params, reconstruct, reconstruct_iter, resolve_method
from .measurement import FrameMeasurements, Segment
from .params import AKFParams, CFParams, DirectParams, FramesParams, HighPassParams

__all__ = [
    "reconstruct", "reconstruct_iter", "Video", "METHODS", "METHOD_ALIASES", "resolve_method", "make_params",
    "AKFParams", "CFParams", "HighPassParams", "DirectParams", "FramesParams",
    "FrameMeasurements", "Segment",
]
