"""Simulate: scenes (Mitsuba 3, analytic, AHDR images) to events, LDR frames and HDR ground truth,
through event-sensor and frame-camera models with adaptive time sampling; simulated datasets.

See ``docs/simulate.md`` and ``docs/simulate-sensor.md``; the analytic generator every test and
the demo use is :mod:`.procedural`.
"""

# sensor models, time sampling, pipeline and AHDR builder (docs/simulate-sensor.md)

# scenes, Mitsuba rendering and built-in scenes (docs/simulate.md)

from .._util.lazy import lazy_exports

# Lazy (PEP 562): the names below load their module on first use, so that building the command
# line's parser (hybridhdr --help) does not import numba and the kernels (a fast --help).
_LAZY = {
    'ImageMotionSource': '.ahdr',
    'ImageSequenceSource': '.ahdr',
    'MotionParams': '.ahdr',
    'build_ahdr': '.ahdr',
    'FrameCamera': '.camera',
    'FrameCameraParams': '.camera',
    'SimulationResult': '.pipeline',
    'simulate': '.pipeline',
    'simulate_to_file': '.pipeline',
    'SamplingParams': '.sampling',
    'TimeSampler': '.sampling',
    'event_fidelity': '.sampling',
    'PRESETS': '.sensor',
    'EventSensor': '.sensor',
    'EventSensorParams': '.sensor',
    'sensor_preset': '.sensor',
    'RadianceSource': '.source',
    'BUILTIN_SCENES': '.builtin',
    'builtin_scene': '.builtin',
    'MitsubaSource': '.render',
    'preview_strip': '.render',
    'select_variant': '.render',
    'RenderCache': '.resume',
    'VideoSource': '.video',
    'load_video': '.video',
    'load_spec': '.dataset_run',
    'Scene': '.scene',
    'SceneError': '.scene',
    'load_scene': '.scene',
    'save_scene': '.scene',
}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)


__all__: list[str] = [
    "RadianceSource",
    # scenes, rendering, built-in scenes
    "Scene", "SceneError", "load_scene", "save_scene", "MitsubaSource", "select_variant", "preview_strip",
    "BUILTIN_SCENES", "builtin_scene",
    # sensor models, sampling, pipeline
    "EventSensorParams", "EventSensor", "PRESETS", "sensor_preset",
    "FrameCameraParams", "FrameCamera",
    "SamplingParams", "TimeSampler", "event_fidelity",
    "simulate", "simulate_to_file", "SimulationResult",
    "MotionParams", "ImageMotionSource", "ImageSequenceSource", "build_ahdr",
    # resumable runs, footage, datasets
    "RenderCache", "VideoSource", "load_video", "load_spec",
]
