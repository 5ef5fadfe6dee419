"""Prophesee event cameras through the Metavision SDK / OpenEB Python bindings (when installed).

The bindings (``metavision_hal``, ``metavision_core``) come with OpenEB or the Metavision SDK and
are not on PyPI, so they are optional: without them :class:`PropheseeEventSource` raises
:class:`~hybridhdr.capture.devices.NoDeviceFound` with installation instructions.

Live data: ``metavision_hal.DeviceDiscovery.open(serial)`` opens the camera (``""`` = the first
one), ``metavision_core.event_io.EventsIterator.from_device(device, delta_t=...)`` yields
structured arrays ``{x, y, p (0/1), t (µs)}`` every ``delta_t`` µs, and external triggers (after
``device.get_i_trigger_in().enable(channel)``) come from ``iterator.reader.get_ext_trigger_events()``
as ``{p (1 rising / 0 falling), t, id}``. They are converted to ``EVENT_DTYPE`` / ``TRIGGER_DTYPE``
(polarity ±1, ``docs/conventions.md``). The open and iterate functions are injectable for tests.
"""

from __future__ import annotations

import numpy as np

from ..events import EVENT_DTYPE, SensorSize, empty_triggers, make_triggers
from ..formats import EventChunk
from .devices import NoDeviceFound
from .sources import EventSource

__all__ = ["PropheseeEventSource", "metavision_available", "METAVISION_HINT"]

METAVISION_HINT = ("the Prophesee backend needs the Metavision HAL Python bindings (metavision_hal and "
                   "metavision_core from OpenEB >= 4 or the Metavision SDK; not on PyPI: build OpenEB, "
                   "https://github.com/prophesee-ai/openeb, and add its python packages to PYTHONPATH)")


def metavision_available() -> bool:
    try:
        import metavision_core.event_io  # noqa: F401
        import metavision_hal  # noqa: F401
    except ImportError:
        return False
    return True


def _default_open(serial: str):
    try:
        from metavision_hal import DeviceDiscovery
    except ImportError:
        raise NoDeviceFound(f"no device found: {METAVISION_HINT}") from None
    try:
        dev = DeviceDiscovery.open(serial)
    except Exception as e:  # the HAL raises its own exception type
        raise NoDeviceFound(f"no device found: no Prophesee camera could be opened ({e})") from None
    if dev is None:
        raise NoDeviceFound("no device found: no Prophesee camera attached (metavision_hal found none)")
    return dev


def _default_iterator(device, delta_t_us: int):
    from metavision_core.event_io import EventsIterator
    return EventsIterator.from_device(device=device, delta_t=delta_t_us)


def convert_cd(ev) -> np.ndarray:
    """Metavision CD events ``{x, y, p 0/1, t}`` -> ``EVENT_DTYPE`` (p ±1)."""
    out = np.empty(len(ev), EVENT_DTYPE)
    out["t"] = ev["t"]
    out["x"] = ev["x"]
    out["y"] = ev["y"]
    out["p"] = np.where(np.asarray(ev["p"]) > 0, 1, -1)
    return out


def convert_triggers(tr) -> np.ndarray:
    """Metavision external triggers ``{p 0/1, t, id}`` -> ``TRIGGER_DTYPE``."""
    if tr is None or len(tr) == 0:
        return empty_triggers()
    return make_triggers(np.asarray(tr["t"]), np.asarray(tr["id"]), np.asarray(tr["p"]) > 0)


class PropheseeEventSource(EventSource):
    """Live Prophesee camera as an :class:`~hybridhdr.capture.sources.EventSource`.

    Parameters
    ----------
    serial : str
        Camera serial ("" = first camera).
    delta_t_us : int
        Length of each delivered chunk in µs.
    trigger_channels : sequence of int
        External-trigger input channels to enable (``I_TriggerIn.enable``).
    open_device, make_iterator : callables, optional
        Injection points (tests): ``open_device(serial) -> device`` and
        ``make_iterator(device, delta_t_us) -> iterable of CD arrays`` with ``.reader``.
    """

    can_backpressure = False

    def __init__(self, serial: str = "", delta_t_us: int = 10_000, trigger_channels=(), *,
                 open_device=None, make_iterator=None):
        super().__init__()
        if int(delta_t_us) < 1:
            raise ValueError(f"delta_t_us must be >= 1 µs, got {delta_t_us}")
        self.serial, self.delta_t_us = serial, int(delta_t_us)
        self.trigger_channels = [int(c) for c in trigger_channels]
        self._open_device = open_device or _default_open
        self._make_iterator = make_iterator or _default_iterator
        self._device = self._it = None

    def open(self):
        if self._device is None:
            self._device = self._open_device(self.serial)
            geo = self._device.get_i_geometry()
            self.sensor_size = SensorSize(int(geo.get_height()), int(geo.get_width()))
            if self.trigger_channels:
                tin = self._device.get_i_trigger_in()
                if tin is None:
                    raise ValueError("this Prophesee camera has no external trigger input")
                for c in self.trigger_channels:
                    tin.enable(c)
            self._it = self._make_iterator(self._device, self.delta_t_us)
        return super().open()

    def close(self) -> None:
        self._it = None
        self._device = None
        super().close()

    def device_info(self) -> dict:
        info = {"kind": "prophesee", "serial": self.serial,
                "sensor": None if self.sensor_size is None else str(self.sensor_size)}
        try:
            hw = self._device.get_i_hw_identification()
            info["serial"] = hw.get_serial()
            info["model"] = str(hw.get_sensor_info())
        except Exception:
            pass
        return info

    def _iter(self):
        reader = getattr(self._it, "reader", None)
        for ev in self._it:
            tr = convert_triggers(reader.get_ext_trigger_events()) if (reader is not None and self.trigger_channels) \
                else empty_triggers()
            if reader is not None and self.trigger_channels and hasattr(reader, "clear_ext_trigger_events"):
                reader.clear_ext_trigger_events()
            yield EventChunk(convert_cd(ev), tr)
            if self.stopped:
                return
