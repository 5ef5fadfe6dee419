"""Analytic radiance sources for the simulate tests (implement the RadianceSource protocol)."""

from __future__ import annotations

import math

import numpy as np

from hybridhdr.events import SensorSize


class BlobSource:
    """A Gaussian blob (peak ``contrast`` x background) moving at ``speed_px_s`` along x,
    optionally with the whole image's brightness modulated sinusoidally."""

    def __init__(self, height=24, width=32, duration_us=200_000, speed_px_s=40.0, sigma_px=3.0,
                 contrast=20.0, background=0.2, flicker_hz=0.0, flicker_depth=0.0):
        self.sensor_size = SensorSize(height, width)
        self.duration_us = int(duration_us)
        self.renders = 0
        self.speed = float(speed_px_s)
        self.sigma = float(sigma_px)
        self.contrast = float(contrast)
        self.background = float(background)
        self.flicker_hz = float(flicker_hz)
        self.flicker_depth = float(flicker_depth)
        self._yy, self._xx = np.mgrid[0:height, 0:width].astype(np.float64)

    def render(self, t_us):
        self.renders += 1
        s = t_us * 1e-6
        cx = 5.0 + self.speed * s
        cy = self.sensor_size.height / 2.0
        g = np.exp(-((self._xx - cx) ** 2 + (self._yy - cy) ** 2) / (2 * self.sigma ** 2))
        img = self.background * (1.0 + self.contrast * g)
        if self.flicker_hz:
            img = img * (1.0 + self.flicker_depth * math.sin(2 * math.pi * self.flicker_hz * s))
        return img.astype(np.float32)

    def max_image_speed_px_per_s(self, t0_us, t1_us):
        return abs(self.speed)

    def describe(self):
        return {"name": "blob", "speed_px_s": self.speed, "flicker_hz": self.flicker_hz}


class SwitchSource:
    """A static random texture whose right half brightens by ``factor`` over ``ramp_us``
    starting at ``t_switch_us`` (a light switching on: no motion, a sudden brightness change)."""

    def __init__(self, height=16, width=20, duration_us=100_000, t_switch_us=40_000, ramp_us=500,
                 factor=8.0, seed=0):
        self.sensor_size = SensorSize(height, width)
        self.duration_us = int(duration_us)
        self.renders = 0
        self.times = []
        self.t_switch, self.ramp, self.factor = int(t_switch_us), int(ramp_us), float(factor)
        self.base = np.random.default_rng(seed).uniform(0.1, 1.0, (height, width))
        self.mask = np.zeros((height, width))
        self.mask[:, width // 2:] = 1.0

    def render(self, t_us):
        self.renders += 1
        self.times.append(int(t_us))
        f = np.clip((t_us - self.t_switch) / self.ramp, 0.0, 1.0)
        gain = 1.0 + (self.factor - 1.0) * f * self.mask
        return (self.base * gain).astype(np.float32)

    def max_image_speed_px_per_s(self, t0_us, t1_us):
        return 0.0

    def describe(self):
        return {"name": "switch"}
