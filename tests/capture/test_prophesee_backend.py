"""Prophesee backend against test doubles of the Metavision HAL device and EventsIterator."""

from __future__ import annotations

import numpy as np
import pytest

from hybridhdr.capture.devices import NoDeviceFound
from hybridhdr.capture.prophesee_backend import PropheseeEventSource, metavision_available

CD = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
TRIG = np.dtype([("p", "<i2"), ("t", "<i8"), ("id", "<i2")])


class FakeGeometry:
    def get_width(self):
        return 640

    def get_height(self):
        return 480


class FakeTriggerIn:
    def __init__(self):
        self.enabled = []

    def enable(self, c):
        self.enabled.append(c)


class FakeHalDevice:
    """Test double of a metavision_hal.Device."""

    def __init__(self):
        self.trigger_in = FakeTriggerIn()

    def get_i_geometry(self):
        return FakeGeometry()

    def get_i_trigger_in(self):
        return self.trigger_in


class FakeReader:
    def __init__(self, triggers):
        self.triggers = triggers

    def get_ext_trigger_events(self):
        return self.triggers

    def clear_ext_trigger_events(self):
        self.triggers = np.zeros(0, TRIG)


class FakeEventsIterator:
    """Test double of metavision_core.event_io.EventsIterator (two delta_t slices)."""

    def __init__(self):
        self.reader = FakeReader(np.array([(1, 150, 0), (0, 900, 0)], TRIG))
        self.slices = [np.array([(1, 2, 1, 100), (3, 4, 0, 200)], CD), np.array([(5, 6, 0, 10_100)], CD)]

    def __iter__(self):
        return iter(self.slices)


def test_conversion_of_polarity_and_triggers():
    dev = FakeHalDevice()
    src = PropheseeEventSource(trigger_channels=[0], open_device=lambda s: dev,
                               make_iterator=lambda d, dt: FakeEventsIterator())
    with src:
        chunks = list(src)
    assert src.sensor_size.width == 640 and dev.trigger_in.enabled == [0]
    assert chunks[0].events["p"].tolist() == [1, -1] and chunks[0].events["t"].tolist() == [100, 200]
    assert chunks[0].triggers["edge"].tolist() == [1, -1] and chunks[0].triggers["t"].tolist() == [150, 900]
    assert len(chunks[1].triggers) == 0  # cleared after the first slice
    assert chunks[1].events["x"].tolist() == [5]


@pytest.mark.skipif(metavision_available(), reason="Metavision SDK installed here")
def test_without_sdk_clear_message():
    with pytest.raises(NoDeviceFound, match="no device found: the Prophesee backend needs the Metavision HAL"):
        PropheseeEventSource().open()
