"""Cross-part check: the simulator's built-in blinking checkerboard calibrates.

The event image of ``builtin:blinking_checkerboard`` (Mitsuba render -> ideal event sensor ->
blink-period detection -> both-polarity accumulation) must show the full 9x6 inner-corner board
at the corners' projected positions. Only the white squares blink, like a monitor; if the black
squares blinked too the event image would be a uniform rectangle with no corners.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mitsuba")


def test_builtin_blinking_checkerboard_event_image_has_the_board():
    from hybridhdr.calibrate.event_images import event_images
    from hybridhdr.calibrate.rig import Board, find_corners
    from hybridhdr.simulate import builtin_scene, simulate
    from hybridhdr.simulate.render import MitsubaSource

    scene = builtin_scene("blinking_checkerboard", width=240, height=180, duration_s=0.32)
    info = scene.info
    src = MitsubaSource(scene)
    res = simulate(src, sensor="ideal", camera=None, seed=0, progress=False)
    ev = res.recording.events
    blink = event_images(ev, res.recording.sensor_size)
    assert blink.period.period_us == pytest.approx(info["blink_period_us"], rel=1e-3)
    assert len(blink.poses) == 1
    cols, rows = info["board_inner_corners"]
    corners = find_corners(blink.poses[0].image, Board(cols, rows, info["square_size_m"] * 1e3))
    assert corners is not None and corners.shape == (cols * rows, 2)
    # the detected grid spans the board's projected extent (not a fragment): its corners lie
    # inside the image and are spread over a region about (cols-1) x (rows-1) squares wide
    span = corners.max(0) - corners.min(0)
    assert np.all(corners > 0) and np.all(corners < [240, 180])
    assert span[0] / span[1] == pytest.approx((cols - 1) / (rows - 1), rel=0.15)
