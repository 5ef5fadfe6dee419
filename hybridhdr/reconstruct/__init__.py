"""Reconstruct: the Asynchronous Kalman Filter (Wang et al., ICCV 2021) and its baselines.

>>> from hybridhdr.reconstruct import reconstruct, AKFParams
>>> AKFParams().process_noise_per_s
0.0005

See ``docs/reconstruct.md``.
"""

from .._util.lazy import lazy_exports

# Lazy (PEP 562): the names below load their module on first use, so that building the command
# line's parser (hybridhdr --help) does not import numba and the kernels (a slow start).
_LAZY = {
    'METHOD_ALIASES': '.api',
    'MethodSpec': '.methods',
    'ReconstructRequest': '.request',
    'METHODS': '.api',
    'Video': '.api',
    'make_params': '.api',
    'reconstruct': '.api',
    'reconstruct_iter': '.api',
    'resolve_method': '.api',
    'FrameMeasurements': '.measurement',
    'Segment': '.measurement',
    'AKFParams': '.params',
    'CFParams': '.params',
    'DirectParams': '.params',
    'FramesParams': '.params',
    'HighPassParams': '.params',
}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)


__all__ = [
    "reconstruct", "reconstruct_iter", "Video", "METHODS", "METHOD_ALIASES", "MethodSpec", "ReconstructRequest",
    "resolve_method", "make_params",
    "AKFParams", "CFParams", "HighPassParams", "DirectParams", "FramesParams",
    "FrameMeasurements", "Segment",
]
