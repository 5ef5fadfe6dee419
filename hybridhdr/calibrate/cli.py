"""``hybridhdr calibrate``: ``rig`` (stereo event/frame rig), ``crf`` (response and noise profile),
``hdr-reference`` (merged, registered HDR references), ``thresholds`` (per-pixel ON/OFF contrast
thresholds), ``sensor`` (the event-sensor profile the simulator reads).

Each step lives in its own module with ``register(subparsers)``.
"""

from __future__ import annotations

from .._util.cliargs import HelpFormatter
from . import _cli_photometric, _cli_rig, _cli_sensor, _cli_thresholds

_STEP_MODULES = (_cli_rig, _cli_photometric, _cli_thresholds, _cli_sensor)


def add_parser(sub) -> None:
    p = sub.add_parser("calibrate", help="stereo rig, camera response and noise profile, HDR references",
                       description="Calibrate a hybrid event/frame rig: geometry (rig), photometry (crf), "
                                   "HDR references (hdr-reference), contrast thresholds (thresholds) and the event-sensor "
                                   "profile (sensor). Each step "
                                   "writes a JSON report and PNG plots.",
                       formatter_class=HelpFormatter)
    steps = p.add_subparsers(dest="calibrate_step", metavar="STEP")
    for mod in _STEP_MODULES:
        mod.register(steps)

    def _no_step(args) -> int:
        p.print_help()
        return 2

    p.set_defaults(func=_no_step)
