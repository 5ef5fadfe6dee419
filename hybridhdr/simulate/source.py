"""The radiance-source protocol that joins scene rendering to the sensor models.

A *radiance source* renders linear HDR radiance on the event sensor's pixel grid at any time
and states an upper bound on image motion, which the adaptive sampler uses.
Mitsuba scenes (:mod:`hybridhdr.simulate.render`) and image-motion sources such as the AHDR
builder (:mod:`hybridhdr.simulate.ahdr`) implement it; the simulation pipeline
(:mod:`hybridhdr.simulate.pipeline`) consumes it.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from ..events import SensorSize


@runtime_checkable
class RadianceSource(Protocol):
    """What the pipeline needs from a scene.

    Attributes
    ----------
    sensor_size : SensorSize
        Pixel grid of the rendered images (height, width).
    duration_us : int
        Length of the scene; times run from 0 to ``duration_us`` inclusive.
    renders : int
        Number of calls to :meth:`render` so far (reported by the pipeline).
    """

    sensor_size: SensorSize
    duration_us: int
    renders: int

    def render(self, t_us: int) -> np.ndarray:
        """Linear radiance at time ``t_us`` as float32 (height, width), finite and >= 0.

        Deterministic: the same ``t_us`` gives the same bits (render noise uses a fixed seed).
        """
        ...

    def max_image_speed_px_per_s(self, t0_us: int, t1_us: int) -> float:
        """Upper bound of image-plane speed (pixels per second) of any scene point over
        ``[t0_us, t1_us]``, from the known camera and object motion. ``math.inf`` if unknown
        (the sampler then relies on brightness change alone, within its rate limits)."""
        ...

    def describe(self) -> dict:
        """JSON-serialisable description for the recording's provenance (scene name, variant, spp...)."""
        ...


class AnalyticSceneSource:
    """An analytic scene (an object with ``sensor_size`` and ``intensity(t_us)``) as a
    :class:`RadianceSource`: renders are exact evaluations, counted. Subclasses state the motion
    bound and the description."""

    def __init__(self, scene, duration_us: int):
        self.scene = scene
        self.sensor_size = scene.sensor_size
        self.duration_us = int(duration_us)
        self.renders = 0

    def render(self, t_us: int) -> np.ndarray:
        self.renders += 1
        return self.scene.intensity(int(t_us)).astype(np.float32)

