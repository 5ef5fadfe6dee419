"""DV network streams through dv-processing: a NetworkWriter serves the DAVIS346 recording on UNIX
sockets (the stand-in for a live DAVIS behind iniVation's DV software), and the recorder stores it.

The servers run as separate processes (``hybridhdr capture serve-dv``), as the DV software does, so
killing one is a real dropped stream. The source of truth is hybridhdr's own AEDAT4 reader (an
independent decoder of the same file), not dv-processing.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dv_processing", reason="dv-processing (the [dv] extra) is not installed")

from hybridhdr.capture.dv_backend import (DvCapture, HostClockSamples, events_from_dv, imu_from_dv,  # noqa: E402
                                          parse_dv_source, triggers_from_dv)
from hybridhdr.capture.recorder import Recorder  # noqa: E402
from hybridhdr.cli import main  # noqa: E402
from hybridhdr.formats import open_reader  # noqa: E402
from hybridhdr.formats.container import read_recording  # noqa: E402

from ..conftest import SHARED_DATA  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
DAVIS = SHARED_DATA / "aedat4" / "davis346_street.aedat4"
needs_davis = pytest.mark.skipif(not DAVIS.exists(), reason=f"the DAVIS346 recording is absent ({DAVIS})")
#: the DV streams a DAVIS346 serves, one network stream per kind
KINDS = ("events", "frames", "triggers", "imu")


@pytest.fixture(scope="module")
def source():
    if not DAVIS.exists():
        pytest.skip(f"the DAVIS346 recording is absent ({DAVIS})")
    with open_reader(DAVIS) as r:
        return r.read()


def _urls(d: Path, transport: str = "unix"):
    if transport == "unix":
        return {k: f"dv-unix://{d / (k + '.sock')}" for k in KINDS}
    import socket
    ports = []
    socks = []
    for _ in KINDS:  # free loopback ports (held together so that they differ)
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        socks.append(s)
        ports.append(s.getsockname()[1])
    for s in socks:
        s.close()
    return {k: f"dv-tcp://127.0.0.1:{p}" for k, p in zip(KINDS, ports)}


def _serve(urls: dict, *extra) -> subprocess.Popen:
    args = [sys.executable, "-m", "hybridhdr", "capture", "serve-dv", str(DAVIS), "--wait-clients-s", "120"]
    for k, v in urls.items():
        args += [f"--{k}", v]
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.Popen(args + list(extra), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _wait_sockets(urls: dict, proc: subprocess.Popen, timeout_s: float = 120.0):
    """Wait for the server's line saying its sockets listen (a probe connection would count as a client)."""
    import selectors
    sel = selectors.DefaultSelector()
    sel.register(proc.stderr, selectors.EVENT_READ)
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if sel.select(timeout=0.5):
            line = proc.stderr.readline()
            if "waiting for clients" in line:
                return
            if not line and proc.poll() is not None:
                break
    raise AssertionError(f"the server did not open its sockets (exit {proc.poll()})")


def _end(proc: subprocess.Popen):
    if proc.poll() is None:
        proc.kill()
    proc.communicate(timeout=30)  # reads and closes the pipes


def test_url_parsing(tmp_path):
    assert parse_dv_source("dv-tcp://127.0.0.1:7777") == ("tcp", ("127.0.0.1", 7777))
    sock = tmp_path / "a.sock"
    assert parse_dv_source(f"dv-unix://{sock}") == ("unix", str(sock))
    for bad in ("dv-tcp://host", "tcp://h:1", "dv-unix://", "davis"):
        with pytest.raises(ValueError, match="expected"):
            parse_dv_source(bad)


def test_conversions_match_the_aedat4_reader():
    import dv_processing as dv
    s = dv.EventStore()
    s.push_back(5, 1, 2, True)
    s.push_back(6, 3, 4, False)
    ev = events_from_dv(s)
    assert ev["t"].tolist() == [5, 6] and ev["x"].tolist() == [1, 3] and ev["p"].tolist() == [1, -1]
    tv = dv.TriggerPacket.TriggersVector()
    for t, ty in ((10, dv.TriggerType.APS_EXPOSURE_START), (11, dv.TriggerType.TIMESTAMP_RESET),
                  (12, dv.TriggerType.EXTERNAL_SIGNAL_FALLING_EDGE)):
        tv.append(dv.Trigger(t, ty))
    tr, resets = triggers_from_dv(tv)
    assert resets == 1
    assert tr["t"].tolist() == [10, 12] and tr["channel"].tolist() == [3, 0] and tr["edge"].tolist() == [1, -1]
    iv = dv.IMUPacket.ImuVector()
    vals = np.float32([[25.5, 0.1, -0.98, 0.2, 1.5, -2.25, 0.03, 40.0, -12.5, 3.0],
                       [25.6, 0.2, -0.97, 0.1, 1.0, -2.00, 0.01, 41.0, -12.0, 2.5]])
    for t, v in zip((20, 21), vals):  # dv.IMU(timestamp, temperature, accelerometer xyz, gyroscope xyz, magnetometer xyz)
        iv.append(dv.IMU(t, *[float(x) for x in v]))
    imu = imu_from_dv(iv)
    assert imu["t"].tolist() == [20, 21]
    for j, name in enumerate(("temperature_c", "accel_x_g", "accel_y_g", "accel_z_g", "gyro_x_deg_s", "gyro_y_deg_s",
                              "gyro_z_deg_s", "mag_x_ut", "mag_y_ut", "mag_z_ut")):
        np.testing.assert_array_equal(imu[name], vals[:, j], err_msg=name)


def test_host_clock_samples_keep_the_lower_envelope_and_stay_bounded():
    h = HostClockSamples(bin_us=100, max_bins=8)
    for k in range(1000):  # latency 10 + (k % 7) µs: the envelope keeps latency 10
        h.add(k * 10, k * 10 + 10 + (k % 7))
    d, host = h.arrays()
    assert len(d) <= 8 and np.all(host - d == 10)


@needs_davis
@pytest.mark.parametrize("transport", ["unix", "tcp"])
def test_record_dv_streams_equals_source(source, tmp_path, capsys, transport):
    """Every event, every frame with its exposure, every trigger and every IMU sample of the file,
    through four UNIX sockets (and four loopback TCP ports)."""
    urls = _urls(tmp_path, transport)
    proc = _serve(urls)
    try:
        _wait_sockets(urls, proc)
        out = tmp_path / "rec.h5"
        argv = ["capture", "record", "--out", str(out), "--reconnect-s", "1", "--no-progress"]
        for u in urls.values():
            argv += ["--source", u]
        assert main(argv) == 0
        served = proc.communicate(timeout=60)[0]
    finally:
        _end(proc)
    assert (f"served {len(source.events):,} events, {len(source.frames)} frames, {len(source.triggers):,} "
            f"triggers, {len(source.imu):,} imu") in served
    back = read_recording(out)
    np.testing.assert_array_equal(back.events, source.events)
    np.testing.assert_array_equal(back.triggers, source.triggers)
    np.testing.assert_array_equal(back.frames.images, source.frames.images)
    np.testing.assert_array_equal(back.frames.t_start_us, source.frames.t_start_us)
    np.testing.assert_array_equal(back.frames.t_end_us, source.frames.t_end_us)
    # every IMU sample, every field (t, accelerometer, gyroscope, temperature, magnetometer), bit for bit
    assert len(source.imu) == 2363 and back.imu.dtype == source.imu.dtype
    assert back.imu.tobytes() == source.imu.tobytes()
    st = back.metadata.provenance["recorder"]
    assert st["imu_written"] == len(source.imu) and not st["imu_dropped"]
    c = st["source_counters"]["events"]
    assert c["imu_samples"] == len(source.imu) and c["imu_out_of_order"] == 0 and c["imu_dropped_in_buffer"] == 0
    assert c["restarts"] == 0 and c["ended"] == 4  # the server exited after serving: every input ended
    capsys.readouterr()
    assert main(["info", str(out), "--json"]) == 0  # the summary counts the stored IMU samples
    assert json.loads(capsys.readouterr().out)["imu"] == len(source.imu)
    assert main(["info", str(out)]) == 0
    assert f"IMU samples   {len(source.imu):,}" in capsys.readouterr().out
    assert not st["events_dropped"] and not st["source_dropped"]
    assert back.sensor_size.shape == (260, 346)


@needs_davis
def test_restarted_stream_is_counted_and_nothing_is_lost(source, tmp_path):
    """The server stops after the first second and a new one serves the rest: four inputs restart."""
    t_cut = int(source.events["t"][0]) + 1_000_000
    urls = _urls(tmp_path)
    cap = DvCapture(list(urls.values()), reconnect_timeout_s=60.0)
    # first server: [start, t_cut), as fast as the sockets take it; it exits when done
    a = subprocess.Popen([sys.executable, "-c", _SERVE_PART, str(DAVIS), json.dumps(urls), "", str(t_cut)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        _wait_sockets(urls, a)
        rec = Recorder(tmp_path / "rec.h5", cap.event_source(), cap.frame_source(), flush_interval_s=0.1)
        rec.start()
        assert a.wait(120) == 0
        b = subprocess.Popen([sys.executable, "-c", _SERVE_PART, str(DAVIS), json.dumps(urls), str(t_cut), ""],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "PYTHONPATH": str(REPO)})
        try:
            assert b.wait(120) == 0
        finally:
            _end(b)
        t_end = time.monotonic() + 60
        # until everything served has reached the writer (the IMU and trigger inputs are separate
        # streams: they may still be on their way when the last event arrives)
        while (rec.stats.events_received < len(source.events) or rec.stats.imu_written < len(source.imu)
               or rec.stats.triggers_written < len(source.triggers)) and time.monotonic() < t_end:
            time.sleep(0.05)
        st = rec.finish()
    finally:
        _end(a)
    c = st.source_counters["events"]
    assert c["restarts"] == 4, c            # every input came back once
    assert c["interruptions"] >= 4 and len(c["gaps_us"]) == 4 and min(c["gaps_us"]) > 0
    assert len(c["interruption_log"]) == c["interruptions"]
    back = read_recording(tmp_path / "rec.h5")
    np.testing.assert_array_equal(back.events, source.events)
    np.testing.assert_array_equal(back.triggers, source.triggers)
    np.testing.assert_array_equal(back.frames.t_start_us, source.frames.t_start_us)
    assert back.imu.tobytes() == source.imu.tobytes()  # the IMU stream restarted too, nothing lost


@needs_davis
def test_killed_stream_is_counted(source, tmp_path):
    """kill -9 of the server mid-stream: the recording keeps what arrived (an exact prefix) and says the
    inputs stopped and never came back."""
    urls = _urls(tmp_path)
    proc = _serve(urls)  # realtime pace: about 2.4 s of data
    try:
        _wait_sockets(urls, proc)
        cap = DvCapture(list(urls.values()), reconnect_timeout_s=0.5)
        rec = Recorder(tmp_path / "rec.h5", cap.event_source(), cap.frame_source(), flush_interval_s=0.1)
        rec.start()
        t_end = time.monotonic() + 60
        while rec.stats.events_received < 1000 and time.monotonic() < t_end:
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
        rec.wait(30)
        st = rec.finish()
    finally:
        _end(proc)
    c = st.source_counters["events"]
    assert c["interruptions"] == 4 and c["ended"] == 4 and c["restarts"] == 0
    back = read_recording(tmp_path / "rec.h5")
    n = len(back.events)
    assert 1000 <= n < len(source.events)
    np.testing.assert_array_equal(back.events, source.events[:n])
    assert back.imu.tobytes() == source.imu[:len(back.imu)].tobytes()  # an exact prefix of the IMU too
    assert back.metadata.provenance["recorder"]["stream_interruptions"] == 4


_SERVE_PART = """
import json, os, sys
from hybridhdr.capture.dv_backend import serve_recording
lo = int(sys.argv[3]) if sys.argv[3] else None
hi = int(sys.argv[4]) if sys.argv[4] else None
serve_recording(sys.argv[1], json.loads(sys.argv[2]), speed=None, t_from_us=lo, t_to_us=hi, wait_clients_s=120,
                on_ready=lambda: print("waiting for clients", file=sys.stderr, flush=True))
os._exit(0)
"""


@needs_davis
def test_frames_of_a_stream_not_recorded_are_counted_apart_from_drops(source, tmp_path):
    """A rig records another camera's frames: the DAVIS frame stream is read (so its reader never
    overflows) and counted as not recorded, which is not a loss."""
    urls = _urls(tmp_path)
    proc = _serve(urls, "--fast")
    try:
        _wait_sockets(urls, proc)
        cap = DvCapture(list(urls.values()), reconnect_timeout_s=0.5)
        st = Recorder(tmp_path / "rec.h5", cap.event_source()).record(60)
    finally:
        _end(proc)
    c = st.source_counters["events"]
    assert c["frames_not_recorded"] == len(source.frames)
    assert st.source_dropped == 0 and not st.dropped_anything
    back = read_recording(tmp_path / "rec.h5")
    np.testing.assert_array_equal(back.events, source.events)
    assert back.frames is None or not len(back.frames)


def test_imu_with_an_infinite_reading_is_dropped_and_counted(tmp_path):
    """A sample the container cannot hold (an infinite reading) is dropped and counted; the others
    are stored exactly. The reader is a stand-in with dv-processing's reader interface."""
    import types

    import dv_processing as dv
    from hybridhdr.capture.dv_backend import DvInput
    from hybridhdr.events import IMU_FIELDS

    def sample(t, v):
        return types.SimpleNamespace(timestamp=t, **{dv_name: v for _, _, dv_name in IMU_FIELDS})

    class Reader:
        def __init__(self):
            store = dv.EventStore()
            store.push_back(10, 1, 1, True)
            self.events = [store]
            self.imu = [[sample(5, 0.5), sample(6, float("inf")), sample(7, -1.25)]]

        def isEventStreamAvailable(self):
            return True

        def isImuStreamAvailable(self):
            return True

        def isRunning(self):
            return bool(self.events or self.imu)

        def getEventResolution(self):
            return (4, 3)

        def getNextEventBatch(self):
            return self.events.pop(0) if self.events else None

        def getNextImuBatch(self):
            return self.imu.pop(0) if self.imu else None

    cap = DvCapture([DvInput("dv-tcp://127.0.0.1:1", opener=Reader)], reconnect_timeout_s=0.0)
    st = Recorder(tmp_path / "r.h5", cap.event_source()).record(30)
    c = st.source_counters["events"]
    assert c["imu_samples"] == 3 and c["imu_not_finite"] == 1 and st.source_dropped == 1 and st.dropped_anything
    back = read_recording(tmp_path / "r.h5")
    assert back.imu["t"].tolist() == [5, 7] and back.imu["accel_x_g"].tolist() == [0.5, -1.25]
    assert len(back.events) == 1


def test_port_zero_gets_distinct_free_ports_and_a_taken_port_is_a_clear_error(tmp_path):
    import socket

    import dv_processing as dv
    from hybridhdr.capture.dv_backend import _writer, resolve_free_ports
    urls = {"events": "dv-tcp://127.0.0.1:0", "frames": "dv-tcp://127.0.0.1:0", "imu": f"dv-unix://{tmp_path / 'x.sock'}"}
    got = resolve_free_ports(urls)
    ports = [parse_dv_source(got[k])[1][1] for k in ("events", "frames")]
    assert got["imu"] == urls["imu"] and len(set(ports)) == 2 and all(p > 0 for p in ports)
    busy = socket.socket()
    try:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        url = f"dv-tcp://127.0.0.1:{busy.getsockname()[1]}"
        with pytest.raises(OSError, match=f"{url}: cannot serve .*in use.*port 0"):
            _writer(dv, url, dv.io.Stream.TriggerStream(0, "triggers", "x"))
    finally:
        busy.close()
