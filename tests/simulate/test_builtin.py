"""Built-in scenes: they build, render fast at tiny sizes, and show the situations they name."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from hybridhdr.simulate.builtin import BUILTIN_SCENES, builtin_scene  # noqa: E402
from hybridhdr.simulate.render import MitsubaSource  # noqa: E402


@pytest.mark.parametrize("name", list(BUILTIN_SCENES))
def test_builtin_renders(name):
    sc = builtin_scene(name, width=48, height=36, duration_s=0.2, spp=1)
    assert sc.duration_us == 200_000 and (sc.camera.width, sc.camera.height) == (48, 36)
    src = MitsubaSource(sc)
    for t in (0, 100_000, 200_000):
        img = src.render(t)
        assert img.shape == (36, 48) and img.dtype == np.float32
        assert np.isfinite(img).all() and img.min() >= 0 and img.max() > 0
    b = src.max_image_speed_px_per_s(0, 10_000)
    assert b >= 0
    d = src.describe()
    assert d["scene"] == name and d["width"] == 48


def test_builtin_prefix_and_errors():
    assert builtin_scene("builtin:slow_static", width=32, height=24).name == "slow_static"
    with pytest.raises(ValueError, match="unknown built-in scene"):
        builtin_scene("teapot")
    with pytest.raises(ValueError, match="duration_s"):
        builtin_scene("slow_static", duration_s=0)
    with pytest.raises(ValueError, match="options"):
        builtin_scene("slow_static", poses=2)


def test_default_resolution_is_davis346():
    sc = builtin_scene("dark_room_window")
    assert (sc.camera.width, sc.camera.height) == (346, 260)


def test_dark_room_window_dynamic_range():
    src = MitsubaSource(builtin_scene("dark_room_window", width=64, height=48, spp=1))
    start, end = src.render(0), src.render(src.duration_us)
    room = np.median(start[start > 0])
    window = end.max()
    # the window is ~10^4 brighter than the room (window 150-250, room walls ~0.005-0.03)
    assert 3e3 < window / room < 1e5
    assert start.max() < 1.0  # the pan starts on the dark wall, window out of view


def test_fast_object_over_exposed_background_and_motion():
    src = MitsubaSource(builtin_scene("fast_object_bright_background", width=64, height=48, spp=1))
    a, b = src.render(100_000), src.render(400_000)
    wall = np.median(a[5:20, 10:54])
    assert wall > 100  # sunlit wall (sun irradiance 1000, reflectance 0.5-0.8)
    changed = np.abs(np.log(a + 1e-3) - np.log(b + 1e-3)) > 0.5
    assert 5 < changed.sum() < 0.3 * a.size  # only the ball (and its shadow) moves
    assert src.max_image_speed_px_per_s(0, 500_000) > 100  # a fast object


def test_slow_static_has_little_motion():
    src = MitsubaSource(builtin_scene("slow_static", width=64, height=48, spp=1))
    assert src.max_image_speed_px_per_s(0, src.duration_us) < 10  # px/s at 64 px width
    a, b = src.render(0), src.render(100_000)
    assert np.mean(np.abs(np.log(a + 1e-3) - np.log(b + 1e-3)) > 0.2) < 0.01


def test_blinking_checkerboard_describes_geometry_and_blinks():
    sc = builtin_scene("blinking_checkerboard", width=64, height=48, spp=1, period_us=40_000, squares=(6, 4))
    src = MitsubaSource(sc)
    d = src.describe()
    info = d["info"]
    assert info["board_squares"] == [6, 4] and info["board_inner_corners"] == [5, 3]
    assert info["square_size_m"] == 0.04 and info["blink_period_us"] == 40_000
    K = np.array(d["K"])
    assert K.shape == (3, 3) and K[0, 0] == pytest.approx(280.0 * 64 / 346)
    # board centre projects through the true intrinsics onto the bright board
    M = np.array(info["board_to_world"])
    u, v = sc.camera.project(M[:3, 3])[0]
    on, off = src.render(10_000), src.render(30_000)
    assert 10 < u < 54 and 8 < v < 40
    # corner square (0, 0) is white: its centre at (-w/2 + s/2, -h/2 + s/2) in the board frame
    s = info["square_size_m"]
    c00 = M[:3, :3] @ np.array([-3 * s + s / 2, -2 * s + s / 2, 0.0]) + M[:3, 3]
    c10 = M[:3, :3] @ np.array([-3 * s + 1.5 * s, -2 * s + s / 2, 0.0]) + M[:3, 3]
    (u0, v0), (u1, v1) = sc.camera.project(np.stack([c00, c10]))
    white_on, black_on = on[int(round(v0)), int(round(u0))], on[int(round(v1)), int(round(u1))]
    white_off, black_off = off[int(round(v0)), int(round(u0))], off[int(round(v1)), int(round(u1))]
    # white = emission 50 plus the screen's reflection of the room light; black = reflection only
    assert white_on == pytest.approx(50.0 + black_on, rel=1e-3)
    assert 0 < black_on < 0.05
    # blinking off: the white square drops to the reflection, the black square does not change
    # (a monitor's black squares fire no events, so the event image shows the board)
    # (5 %: the point light's irradiance differs a little between the two squares' centres)
    assert white_off == pytest.approx(black_on, rel=0.05)
    assert black_off == black_on
    assert src.max_image_speed_px_per_s(0, sc.duration_us) == 0.0  # static camera


def test_blinking_checkerboard_poses():
    sc = builtin_scene("blinking_checkerboard", width=32, height=24, poses=3)
    kfs = sc.camera.trajectory.keyframes
    assert len({k.position for k in kfs}) == 3
    assert len(sc.info["camera_pose_change_times_us"]) == 4  # hold/move keyframes between 3 views


@pytest.mark.parametrize("name", ["window_scenery", "lamp_shade", "sunlit_facade"])
def test_hdr_v2_scene_carries_recoverable_hdr(name):
    # HDR set v2's design: bright textured panes 10^2-10^3x the shadows that the 10 ms frames
    # clip (radiance 2 = the clip level of the set's camera), and every bright pixel seen
    # unclipped at some time while the hand-held camera sweeps (renders every 50 ms at 87x65)
    from hybridhdr.simulate.builtin import REALISTIC_SENSOR, SCENE_TIERS, scene_sensor
    sc = builtin_scene(name, width=87, height=65, spp=1)
    assert sc.info["sensor_tiers"] == list(SCENE_TIERS[name][0])
    src = MitsubaSource(sc)
    imgs = np.stack([src.render(t) for t in range(0, 1_000_001, 50_000)])
    clip = 2.0
    bright = imgs > clip
    shadow = np.quantile(imgs[imgs > 0], 0.05)
    assert 0.1 < bright.mean() < 0.5  # a good part of the view clips
    assert np.quantile(imgs[bright], 0.9) / shadow > 100  # 10^2-10^3x the shadows
    # seen unclipped at another time: >= 90 % of the pixel-times that clip (the rest: the view's
    # edges, where panes enter and leave the frame)
    seen = (~bright).any(axis=0)
    assert np.mean(seen[None].repeat(len(imgs), 0)[bright]) > 0.9
    # the scene's event sensor: the realistic profile restricted to its tiers
    s = scene_sensor(name)
    assert s["threshold_mismatch_sigma"] == REALISTIC_SENSOR["threshold_mismatch_sigma"]
    if 3 not in SCENE_TIERS[name][0]:
        assert s["shot_noise_rate_hz"] == 0 and s["leak_rate_hz"] == 0
    with pytest.raises(ValueError, match="scene_sensor"):
        scene_sensor("dark_room_window")
