"""Basler pylon cameras through pypylon, against pylon's own camera emulator (``PYLON_CAMEMU``).

Each scenario runs in a child process (``pylon_emu_scenarios.py``): pylon reads ``PYLON_CAMEMU``
once, when it starts, and emulated cameras must not appear in the other tests' device listings.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

if importlib.util.find_spec("pypylon") is None:  # not imported here: pylon must start in the child
    pytest.skip("pypylon (the [pylon] extra) is not installed", allow_module_level=True)

from hybridhdr.cli import main  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path.insert(0, str(HERE))
import pylon_emu_scenarios as sc  # noqa: E402


def _scenario(name, folder, *args, timeout=300) -> dict:
    env = {**os.environ, "PYLON_CAMEMU": "1", "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    p = subprocess.run([sys.executable, str(HERE / "pylon_emu_scenarios.py"), name, str(folder), *args],
                       capture_output=True, text=True, env=env, timeout=timeout)
    assert p.returncode == 0, p.stderr[-4000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


def test_bracket_with_exposures_read_back_then_calibrate_crf(tmp_path, capsys):
    r = _scenario("brackets", tmp_path)
    assert r["requested_us"] == [float(e) for e in sc.EXPOSURES_US]
    assert r["reported_us"] == sc.EXPOSURES_US              # read back from the camera's ExposureTime
    assert r["timestamp_source"] == "host-trigger"
    assert r["sequence"] == sorted(r["sequence"]) and len(set(r["sequence"])) == 5
    assert all(r["match_scene"])                              # frame k is the scene at exposure k
    bs = json.loads((tmp_path / "brackets" / "brackets.json").read_text())
    assert json.dumps(bs).count("0.064") >= 1                 # the folder stores the read-back exposures (s)
    out = tmp_path / "crf"
    assert main(["calibrate", "crf", str(tmp_path / "brackets"), "--out", str(out)]) == 0
    crf = json.loads((out / "crf.json").read_text())
    g = np.asarray(crf["log_inverse"][0])
    seen = np.asarray(crf["observed"][0])
    assert crf["info"]["exposures_s"] == [e * 1e-6 for e in sc.EXPOSURES_US]
    # the inverse response is increasing over the codes the bracket shows (Debevec's monotonic fix aside)
    assert np.all(np.diff(g[seen][1:]) > 0)
    assert (out / "camera_profile.json").exists()


def test_brackets_command_on_the_emulator(tmp_path):
    r = _scenario("brackets_cli", tmp_path)
    assert r["rc"] == 0
    imgs = r["brackets"]["images"]
    assert [round(i["exposure_s"] * 1e6) for i in imgs] == [1000, 4000, 16000]
    assert r["brackets"]["camera"]["model"] == "Emulation" and (tmp_path / "b.png").exists()


def test_software_trigger_frames_on_the_host_clock(tmp_path):
    r = _scenario("software_trigger", tmp_path, "40", "1.5")
    t0 = np.asarray(r["t_start_us"])
    t1 = np.asarray(r["t_end_us"])
    assert r["frames"] >= 10                                   # 40 Hz for 1.5 s on a loaded machine
    assert np.all(np.diff(t0) > 0)                            # strictly increasing (monotonic clock)
    assert np.all(t1 - t0 == 2000)                            # the exposure read back, 2 ms
    # on the host clock: inside the host's window around the recording
    assert r["host_before_us"] <= t0[0] and t1[-1] <= r["host_after_us"]
    # the software trigger period is 25 ms; scheduling can stretch it on a busy machine, never shrink
    # it below the period minus the trigger jitter (5 ms allowed)
    assert np.median(np.diff(t0)) >= 20_000
    assert r["source"]["timestamp_source"] == "host-trigger" and r["source"]["model"] == "Emulation"
    assert r["frames_dropped"] == 0 and r["frames_missing_by_sequence"] == 0
    assert r["counters"]["frames_skipped_by_camera_or_driver"] == 0


def test_rig_dv_stream_and_pylon_emulator_with_sync_report(tmp_path):
    from .test_dv_backend import DAVIS, _end, _serve, _wait_sockets
    if not DAVIS.exists():
        pytest.skip(f"the DAVIS346 recording is absent ({DAVIS})")
    pytest.importorskip("dv_processing", reason="dv-processing (the [dv] extra) is not installed")
    urls = {k: f"dv-unix://{tmp_path / (k + '.sock')}" for k in ("events", "triggers")}
    proc = _serve(urls, "--speed", "0.5")  # half speed: the 2.4 s of DAVIS data last 4.8 s
    try:
        _wait_sockets(urls, proc)
        r = _scenario("rig", tmp_path, urls["events"], urls["triggers"], "9")
    finally:
        _end(proc)
    assert r["rc"] == 0
    assert r["events"] == 78_830 and r["triggers"] == 236
    rep = r["report"]
    assert rep["method"] == "host-clock" and rep["frame_timestamp_source"] == "host-trigger"
    assert rep["n_samples"] >= 10 and rep["n_frames"] == r["frames"] >= 10
    # served at half speed, the event clock advances 0.5 µs per host µs: host = a + 2 · t_event, a drift
    # of exactly +1,000,000 ppm (one machine: the server's perf_counter and the samples' monotonic clock
    # are both CLOCK_MONOTONIC); the fit may miss it by its own noise only: 4 standard errors
    assert abs(rep["drift_ppm"] - 1e6) <= 4 * rep["drift_stderr_ppm"], rep
    # the latency variation of a loaded 2-core machine: below 50 ms
    assert rep["rms_us"] < 50_000, rep
    # frames triggered while the stream ran lie within the events' time span once on the event clock
    t = np.asarray(r["t_start_us"])
    inside = (t >= r["event_t0"] - 100_000) & (t <= r["event_t1"] + 100_000)
    # 25 Hz over the 4.8 s of the stream is 120 frames; on a loaded machine the recorder and the camera
    # may start a second or two after the stream: at least 30 of them
    assert inside.sum() >= 30, (inside.sum(), len(t))
    assert r["host_sync"]["offset_us"] == rep["offset_us"]
