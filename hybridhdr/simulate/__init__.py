"""Simulate: scenes (Mitsuba 3, analytic, AHDR images) to events, LDR frames and HDR ground truth,
through event-sensor and frame-camera models with adaptive time sampling; simulated datasets.

See ``docs/simulate.md`` and ``docs/simulate-sensor.md``; the analytic generator every test and
the demo use is :mod:`.procedural`.
"""

# sensor models, time sampling, pipeline and AHDR builder (docs/simulate-sensor.md)
from .ahdr import ImageMotionSource, ImageSequenceSource, MotionParams, build_ahdr
from .camera import FrameCamera, FrameCameraParams
from .pipeline import SimulationResult, simulate, simulate_to_file
from .sampling import SamplingParams, TimeSampler, event_fidelity
from .sensor import PRESETS, EventSensor, EventSensorParams, sensor_preset
from .source import RadianceSource

# scenes, Mitsuba rendering and built-in scenes (docs/simulate.md)
from .builtin import BUILTIN_SCENES, builtin_scene
from .render import MitsubaSource, preview_strip, select_variant
from .scene import Scene, SceneError, load_scene, save_scene

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
]
