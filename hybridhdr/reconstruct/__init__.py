"""Reconstruct: the Asynchronous Kalman Filter (Wang et al., ICCV 2021) and its baselines.

>>> from hybridhdr.reconstruct import reconstruct, AKFParams
>>> AKFParams().process_noise_per_s
0.0005

See ``docs/reconstruct.md``.
"""

# Lazy (PEP 562): the names below load their module on first use, so that building the command
# line's parser (hybridhdr --help) does not import numba and the kernels (issue 31).
_LAZY = {
    'METHOD_ALIASES': '.api',
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


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib
    value = getattr(importlib.import_module(mod, __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "reconstruct", "reconstruct_iter", "Video", "METHODS", "METHOD_ALIASES", "resolve_method", "make_params",
    "AKFParams", "CFParams", "HighPassParams", "DirectParams", "FramesParams",
    "FrameMeasurements", "Segment",
]
