"""One runnable example per command, printed at the end of its ``--help``.

Each runs from the repository root with the sample data beside it in ``../shared/data``, as the
README's tour does; where the README shows the command, the example is the README's line
(``tests/test_help_examples.py`` runs every example and checks those it shares with the README).
Outputs named here (``video/``, ``rec.h5``, ``crf/``, ``sim.h5``) are the tour's, so one example's
output is the next one's input.
"""

from __future__ import annotations

__all__ = ["EXAMPLES", "example_epilog"]

_DATA = "../shared/data"

#: command (without ``hybridhdr``) -> the example command line
EXAMPLES = {
    "info": f"hybridhdr info {_DATA}/prophesee/sparklers_gen3_evt2.raw",
    "convert": f"hybridhdr convert {_DATA}/prophesee/sparklers_gen3_evt2.raw sparklers.h5 --start 0 --end 1s",
    "demo": "hybridhdr demo",
    "view": f"hybridhdr view {_DATA}/ecd_slider_depth --recon video/ --fps 100 --out clip.mp4 --still clip.png",
    "reconstruct": f"hybridhdr reconstruct {_DATA}/ecd_slider_depth --method akf --fps 300 --out video/ --png --mp4",
    "simulate": "hybridhdr simulate --list",
    "capture devices": "hybridhdr capture devices --json",
    "capture record": f"hybridhdr capture record --events {_DATA}/prophesee/sparklers_gen3_evt2.raw --out rec.h5 "
                      "--pace fast",
    "capture recover": "hybridhdr capture recover rec.h5",
    "capture brackets": f"hybridhdr capture brackets {_DATA}/brackets/memorial --out memorial/ --plot memorial.png",
    "capture sync": "hybridhdr capture sync street.h5 --trigger-channel 3 --out street_synced.h5 "
                    "--report street_sync.json",
    "capture session": "hybridhdr capture session session/ --recording rec.h5 --profile crf/camera_profile.json "
                       "--brackets memorial/",
    "capture serve-dv": f"hybridhdr capture serve-dv {_DATA}/aedat4/davis346_street.aedat4 "
                        "--events dv-tcp://127.0.0.1:0 --frames dv-tcp://127.0.0.1:0 "
                        "--triggers dv-tcp://127.0.0.1:0 --imu dv-tcp://127.0.0.1:0 --fast",
    "calibrate rig": f"hybridhdr calibrate rig --left '{_DATA}/checkerboard/opencv_stereo/left*.jpg' "
                     f"--right '{_DATA}/checkerboard/opencv_stereo/right*.jpg' --board 9x6 --square-mm 25 "
                     "--out stereo/",
    "calibrate crf": f"hybridhdr calibrate crf {_DATA}/brackets/memorial --out crf/ --ignore-colour 0,0,255",
    "calibrate hdr-reference": f"hybridhdr calibrate hdr-reference {_DATA}/brackets/memorial --crf crf/crf.json "
                               "--out ref.exr --ignore-colour 0,0,255",
    "calibrate thresholds": f"hybridhdr calibrate thresholds {_DATA}/ecd_slider_depth --out thresholds.npz",
    "calibrate sensor": f"hybridhdr calibrate sensor {_DATA}/ecd_slider_depth --out ecd_sensor.json",
    "evaluate metrics": "hybridhdr evaluate metrics sim_video/ --reference sim.h5",
    "evaluate bench": "hybridhdr evaluate bench tiny --out bench/",
    "evaluate paper": "hybridhdr evaluate paper --quick --out paper/",
    "evaluate holdout": f"hybridhdr evaluate holdout {_DATA}/ecd_slider_depth --method akf,cf",
    "evaluate overexpose": f"hybridhdr evaluate overexpose {_DATA}/ecd_slider_depth --gain 4 --method akf --out oe/",
}


def example_epilog(command: str) -> str | None:
    """The ``--help`` epilog of ``command`` (e.g. ``"calibrate crf"``), or None when it has none."""
    line = EXAMPLES.get(command)
    return None if line is None else f"example (from the repository root, sample data in {_DATA}):\n  {line}"
