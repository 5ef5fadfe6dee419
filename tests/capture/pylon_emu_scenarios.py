"""Scenarios run against pylon's camera emulator in a child process (``PYLON_CAMEMU`` must be set
before pylon starts, and emulated cameras must not show up in the other tests' ``capture devices``).

``python tests/capture/pylon_emu_scenarios.py NAME FOLDER [ARGS...]`` prints one JSON object.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

#: the scene in front of the emulated camera: radiance ramps over 3 decades (columns) times a
#: 0.5..1 vertical ramp; the camera's response is a 1/2.2 gamma with 8-bit quantisation
EXPOSURES_US = [250, 1000, 4000, 16000, 64000]
GAMMA = 2.2
H, W = 96, 128


def scene_codes(exposure_us: float) -> np.ndarray:
    rad = np.exp(np.linspace(np.log(1e-3), 0.0, W))[None, :] * np.linspace(0.5, 1.0, H)[:, None]
    x = np.clip(rad * exposure_us / 16000.0, 0, 1)  # the 16 ms exposure saturates the brightest column
    return np.round(255 * x ** (1 / GAMMA)).astype(np.uint8)


def _emulated(src, folder: Path):
    """Feed the emulator the scene's images, one file per triggered frame in order (ImageFileMode)."""
    from PIL import Image
    imgs = folder / "emulator_images"
    imgs.mkdir()
    for i, e in enumerate(EXPOSURES_US):
        Image.fromarray(scene_codes(e)).save(imgs / f"img{i}.png")
    cam = src.cam
    cam.TestImageSelector.Value = "Off"
    cam.ImageFilename.Value = str(imgs)
    cam.ImageFileMode.Value = "On"
    cam.Width.Value, cam.Height.Value = W, H


def brackets(folder: Path) -> dict:
    from pypylon import pylon

    from hybridhdr.capture.pylon_backend import PylonFrameSource
    cam = pylon.InstantCamera(pylon.TlFactory.GetInstance().CreateFirstDevice())
    src = PylonFrameSource(camera=cam, trigger="software", pixel_format="Mono8")
    src.open()
    _emulated(src, folder)
    items, rep = src.capture_brackets(EXPOSURES_US, gain_db=0.0, folder=folder / "brackets")
    src.close()
    return {**rep, "means": [float(it.image.mean()) for it in items],
            "match_scene": [bool(np.array_equal(it.image, scene_codes(e))) for it, e in zip(items, EXPOSURES_US)]}


def software_trigger(folder: Path, rate_hz: str = "40", seconds: str = "1.5") -> dict:
    from hybridhdr.capture.pylon_backend import PylonFrameSource
    from hybridhdr.capture.recorder import Recorder
    from hybridhdr.capture.sources import SyntheticEventSource
    from hybridhdr.formats.container import read_recording
    src = PylonFrameSource(trigger="software", software_rate_hz=float(rate_hz), exposure_us=2000, pixel_format="Mono8")
    src.open()
    src.cam.Width.Value, src.cam.Height.Value = 64, 48
    ev = SyntheticEventSource(1000, sensor_size=(48, 64), pace="realtime")
    h0 = time.monotonic_ns() // 1000
    rec = Recorder(folder / "rec.h5", ev, src, flush_interval_s=0.2)
    st = rec.record(float(seconds))
    h1 = time.monotonic_ns() // 1000
    back = read_recording(folder / "rec.h5")
    fr = back.frames
    prov = back.metadata.provenance
    return {"frames": len(fr), "t_start_us": fr.t_start_us.tolist(), "t_end_us": fr.t_end_us.tolist(),
            "host_before_us": h0, "host_after_us": h1, "frames_missing_by_sequence": st.frames_missing_by_sequence,
            "frames_dropped": st.frames_dropped, "source": prov["sources"]["frames"],
            "counters": st.source_counters.get("frames")}


def rig(folder: Path, events_url: str, triggers_url: str, seconds: str = "4") -> dict:
    """DV stream (events + triggers) and the pylon emulator (software trigger at 25 Hz) in one
    recording; frames put on the event clock through the host clock."""
    from hybridhdr.cli import main
    out = folder / "rig.h5"
    rc = main(["capture", "record", "--source", events_url, "--source", triggers_url, "--frames", "pylon",
               "--trigger", "software", "--trigger-rate-hz", "25", "--exposure-us", "5000", "--pixel-format",
               "Mono8", "--sync", "host", "--out", str(out), "--duration-s", seconds, "--reconnect-s", "0.5",
               "--no-progress"])
    rep = json.loads((folder / "rig.h5.sync.json").read_text())
    from hybridhdr.formats.container import read_recording
    back = read_recording(out)
    return {"rc": rc, "report": rep, "events": len(back.events), "triggers": len(back.triggers),
            "frames": len(back.frames), "t_start_us": back.frames.t_start_us.tolist(),
            "event_t0": int(back.events["t"][0]), "event_t1": int(back.events["t"][-1]),
            "host_sync": back.metadata.provenance.get("host_clock_sync")}


def brackets_cli(folder: Path) -> dict:
    """``hybridhdr capture brackets --device pylon`` on the emulator's own test image."""
    from hybridhdr.cli import main
    rc = main(["capture", "brackets", "--device", "pylon", "--exposures-us", "1000", "4000", "16000", "--gain-db",
               "0", "--out", str(folder / "b"), "--plot", str(folder / "b.png")])
    return {"rc": rc, "brackets": json.loads((folder / "b" / "brackets.json").read_text())}


if __name__ == "__main__":
    name, folder, *rest = sys.argv[1:]
    res = {"brackets": brackets, "brackets_cli": brackets_cli, "software_trigger": software_trigger,
           "rig": rig}[name](Path(folder), *rest)
    print(json.dumps(res))
