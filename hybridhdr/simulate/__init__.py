"""Simulate: Mitsuba 3 scenes to events, LDR frames and HDR ground truth (see issue 5)."""

# sensor models, time sampling, pipeline and AHDR builder (docs/simulate-sensor.md)
from .camera import FrameCamera, FrameCameraParams
from .pipeline import SimulationResult, simulate, simulate_to_file
from .sampling import SamplingParams, TimeSampler, event_fidelity
from .sensor import PRESETS, EventSensor, EventSensorParams, sensor_preset
from .source import RadianceSource

__all__: list[str] = [
    "RadianceSource",
    # sensor models, sampling, pipeline
    "EventSensorParams", "EventSensor", "PRESETS", "sensor_preset",
    "FrameCameraParams", "FrameCamera",
    "SamplingParams", "TimeSampler", "event_fidelity",
    "simulate", "simulate_to_file", "SimulationResult",
]
