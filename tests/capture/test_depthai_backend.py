"""depthai backend against test doubles of the depthai device, queues, controls and frames.

``FakeDepthaiDevice`` and friends are TEST DOUBLES: they model an OAK camera whose exposure
changes take effect ``latency_frames`` frames after the control is sent and whose sensor
quantises exposure to whole 18 µs lines, so the reported exposure differs from the requested one.
"""

from __future__ import annotations

from datetime import timedelta

import numpy as np
import pytest

from hybridhdr.formats.brackets import read_bracket_set
from hybridhdr.capture.depthai_backend import DepthaiFrameSource
from hybridhdr.capture.recorder import Recorder
from hybridhdr.capture.sources import SyntheticEventSource
from hybridhdr.formats.container import read_recording

LINE_US = 18
PERIOD_US = 33_333


class FakeControl:
    """Test double of dai.CameraControl: records the calls."""

    def __init__(self):
        self.calls = []

    def setManualExposure(self, exposure_us, iso):
        self.calls.append(("setManualExposure", exposure_us, iso))
        return self

    def setFrameSyncMode(self, mode):
        self.calls.append(("setFrameSyncMode", mode))
        return self

    def setExternalTrigger(self, burst, discard):
        self.calls.append(("setExternalTrigger", burst, discard))
        return self

    def setStrobeSensor(self, level):
        self.calls.append(("setStrobeSensor", level))
        return self


class FakeImgFrame:
    """Test double of dai.ImgFrame."""

    def __init__(self, seq, exposure_us, iso, t_start_us, image):
        self.seq, self.exposure_us, self.iso, self.t0, self.image = seq, exposure_us, iso, t_start_us, image

    def getExposureTime(self):
        return timedelta(microseconds=self.exposure_us)

    def getSensitivity(self):
        return self.iso

    def getSequenceNum(self):
        return self.seq

    def getTimestampDevice(self, offset):
        return timedelta(microseconds=self.t0 + (self.exposure_us if offset == "END" else 0))


class FakeControlQueue:
    def __init__(self, device):
        self.device, self.sent = device, []

    def send(self, ctrl):
        self.sent.append(ctrl)
        self.device._control(ctrl)


class FakeFrameQueue:
    def __init__(self, device):
        self.device = device

    def tryGet(self):
        return self.device._next_frame()

    def get(self):
        return self.device._next_frame()


class FakeDepthaiDevice:
    """Test double of the depthai device: a sensor with late-applied, line-quantised exposure."""

    exposure_offsets = ("START", "END")

    def __init__(self, latency_frames=3, ignore_controls=False, drop_sequences=(), radiance=50.0):
        self.latency, self.ignore, self.drop = latency_frames, ignore_controls, set(drop_sequences)
        self.exposure_us, self.iso = 10_000, 100  # auto-exposure state before any control
        self.pending = []  # (apply at sequence, exposure, iso)
        self.seq = 0
        self.started = self.stopped = False
        self.radiance = radiance
        self.control_queue = FakeControlQueue(self)
        self.frame_queue = FakeFrameQueue(self)

    def start(self):
        self.started = True

    def stop(self):
        self.stopped = True

    def info(self):
        return {"kind": "depthai", "name": "FakeOAK", "serial": "FAKE0001"}

    def new_control(self):
        return FakeControl()

    def frame_sync_mode(self, name):
        return f"FrameSyncMode.{name.upper()}"

    def image(self, msg):
        return msg.image

    def _control(self, ctrl):
        for c in ctrl.calls:
            if c[0] == "setManualExposure" and not self.ignore:
                self.pending.append((self.seq + self.latency, c[1], c[2]))

    def _next_frame(self):
        while True:
            s = self.seq
            self.seq += 1
            for p in list(self.pending):
                if p[0] <= s:
                    self.exposure_us = (p[1] // LINE_US) * LINE_US  # whole sensor lines
                    self.iso = p[2]
                    self.pending.remove(p)
            if s not in self.drop:
                break
        img = np.full((4, 6), min(255, int(self.radiance * self.exposure_us * self.iso / 1e5)), np.uint8)
        return FakeImgFrame(s, self.exposure_us, self.iso, 1_000_000 + s * PERIOD_US, img)


def test_bracket_sequencing_late_application_and_own_exposure_tags(tmp_path):
    dev = FakeDepthaiDevice(latency_frames=3)
    src = DepthaiFrameSource(dev)
    exps = [1_000, 4_000, 16_000]
    items, rep = src.capture_brackets(exps, 200, frames_per_step=2, folder=tmp_path / "br")
    # each step: the 3 frames already in the pipeline when the control is sent still show the
    # previous exposure and are discarded
    assert rep["frames_discarded"] == [3, 3, 3]
    # the frames carry the exposure the sensor reported (whole 18 µs lines), not the request
    assert rep["reported_us"] == [990, 990, 3996, 3996, 15984, 15984]
    assert rep["requested_us"] == [1_000, 1_000, 4_000, 4_000, 16_000, 16_000]
    assert all(it.iso == 200 for it in items)
    # consecutive sequence numbers within a step; stale frames never kept
    seq = rep["sequence"]
    assert seq[1] == seq[0] + 1 and seq[3] == seq[2] + 1
    # controls were sent in bracket order
    sent = [c.calls[0] for c in dev.control_queue.sent]
    assert sent == [("setManualExposure", e, 200) for e in exps]
    # the bracket set on disk: same layout as the calibrate reader expects, own exposures
    bs = read_bracket_set(tmp_path / "br")
    np.testing.assert_allclose(bs.exposures_s, np.array(rep["reported_us"]) * 1e-6, rtol=1e-12)
    assert bs.encoding == "gamma" and bs.camera["serial"] == "FAKE0001"
    assert [int(im[0, 0]) for im in bs.images] == [int(it.image[0, 0]) for it in items]
    np.testing.assert_array_equal(bs.t_us, [it.t_start_us for it in items])


def test_frame_times_from_metadata():
    dev = FakeDepthaiDevice()
    src = DepthaiFrameSource(dev, exposure_us=2_000, iso=400)
    src.open()
    it = next(iter(src))
    assert it.t_end_us - it.t_start_us == it.exposure_us == 10_000  # control not applied yet
    src.close()
    assert dev.stopped


def test_never_applied_exposure_times_out_with_clear_message():
    src = DepthaiFrameSource(FakeDepthaiDevice(ignore_controls=True))
    with pytest.raises(TimeoutError, match="requested exposure 1000 µs / ISO 100, but the camera still reports "
                                           "10000 µs"):
        src.capture_brackets([1_000], 100, max_wait_frames=5)


def test_trigger_and_frame_sync_settings_sent_at_open():
    dev = FakeDepthaiDevice()
    src = DepthaiFrameSource(dev, exposure_us=5_000, iso=800, frame_sync="output", external_trigger=(1, 0),
                             strobe=True)
    src.open()
    assert dev.started
    assert dev.control_queue.sent[0].calls == [("setManualExposure", 5_000, 800),
                                               ("setFrameSyncMode", "FrameSyncMode.OUTPUT"),
                                               ("setExternalTrigger", 1, 0), ("setStrobeSensor", 1)]
    info = src.device_info()
    assert info["frame_sync"] == "output" and info["name"] == "FakeOAK"
    src.close()


def test_argument_errors():
    dev = FakeDepthaiDevice()
    with pytest.raises(ValueError, match="together"):
        DepthaiFrameSource(dev, exposure_us=1000)
    with pytest.raises(ValueError, match="frame_sync"):
        DepthaiFrameSource(dev, frame_sync="both")
    with pytest.raises(ValueError, match="frames_per_burst"):
        DepthaiFrameSource(dev, external_trigger=(0, 0))
    with pytest.raises(ValueError, match="could not tell them apart"):
        DepthaiFrameSource(dev).capture_brackets([1000, 1020], 100)


def test_recorder_counts_frames_lost_before_the_host(tmp_path):
    dev = FakeDepthaiDevice(drop_sequences={3, 4, 9})
    fs = DepthaiFrameSource(dev, exposure_us=3_000, iso=100)

    ev = SyntheticEventSource(1e5, sensor_size=(4, 6), chunk_us=1_000, duration_s=0.02, pace="fast")
    n = {"k": 0}
    orig = fs._iter

    def limited():
        for it in orig():
            yield it
            n["k"] += 1
            if n["k"] >= 12:
                return
    fs._iter = limited
    stats = Recorder(tmp_path / "r.h5", ev, fs, flush_interval_s=0.05, compression=None).record()
    assert stats.frames_written == 12 and stats.frames_missing_by_sequence == 3
    rec = read_recording(tmp_path / "r.h5")
    assert len(rec.frames) == 12 and rec.frames.encoding == "gamma"
    assert rec.metadata.provenance["recorder"]["frames_missing_by_sequence"] == 3
    assert rec.metadata.provenance["sources"]["frames"]["serial"] == "FAKE0001"
