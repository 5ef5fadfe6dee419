"""Built-in scenes for the situations of the AKF paper (Wang et al., ICCV 2021, §5).

Every scene uses the DAVIS346 grid (346 × 260) by default with a pinhole of fx = fy = 280 px
(≈ 63° horizontal field of view, a 4.5 mm lens on 18.5 µm pixels), delta lights and the
``direct`` integrator with a few samples per pixel, so it renders in milliseconds per frame with
``llvm_ad_mono``. Worlds are y-up, in metres; radiance is linear in arbitrary units (the shadowed
parts of a scene sit near 0.01-0.1, bright parts near 10²-10³).

>>> from hybridhdr.simulate.builtin import BUILTIN_SCENES, builtin_scene
>>> sorted(BUILTIN_SCENES)[:2]
['blinking_checkerboard', 'dark_room_window']
>>> builtin_scene("slow_static", width=64, height=48).camera.width
64
"""

from __future__ import annotations

import math

import numpy as np

from .scene import (Blink, CameraSpec, Emission, Emitter, Keyframe, Material, MeshSpec, Pattern, RenderSettings,
                    Scene, SceneObject, Trajectory, look_at_rotation, quat_from_matrix)

__all__ = ["BUILTIN_SCENES", "builtin_scene", "HDR_V2_SCENES", "REALISTIC_SENSOR", "TYPICAL_DAVIS_SENSOR", "SCENE_TIERS", "scene_sensor"]

#: name -> one-line description
BUILTIN_SCENES = {
    "dark_room_window": "camera pans from a dark room to a bright window (~10^4 dynamic range)",
    "night_drive_sign": "night drive with headlights past a bright illuminated road sign",
    "fast_object_bright_background": "a fast dark ball in front of a static, sunlit, over-exposed wall "
                                     "(the complementary filter's shadowing case)",
    "slow_static": "slow, nearly static table-top scene: few events, the frames carry it",
    "window_scenery": "hand-held view of a dim room's six-pane window onto daylit scenery (10^2-10^3x the wall)",
    "lamp_shade": "hand-held view of two lit, textured lamp shades in an evening room (10^2-10^3x the shadows)",
    "sunlit_facade": "hand-held view from a shaded arcade of a sunlit brick facade between its pillars "
                     "(10^2-10^3x the shade)",
    "blinking_checkerboard": "a checkerboard on a monitor blinking on/off at a known period, static camera "
                             "(rig calibration; board geometry and intrinsics in describe())",
}

_DEFAULT_DURATION_S = {"dark_room_window": 1.0, "night_drive_sign": 1.0, "fast_object_bright_background": 0.5,
                       "slow_static": 1.0, "blinking_checkerboard": 1.0, "window_scenery": 1.0, "lamp_shade": 1.0,
                       "sunlit_facade": 1.0}

#: HDR set v2: scenes modelled on the AKF paper's real HDR dataset (hand-held camera, bright
#: textured regions the camera sweeps over while the frames clip them).
HDR_V2_SCENES = ("window_scenery", "lamp_shade", "sunlit_facade")

#: Typical figures of a DAVIS346 / DAVIS240 (HDR set v2's sensor before a measured profile existed;
#: kept as the fallback of the tiers a profile cannot identify): contrast threshold 0.25 (DAVIS346
#: ON/OFF thresholds are set by bias to about 0.2-0.3 ln units; v2e's default 0.2), per-pixel
#: mismatch sigma 0.03 (v2e's default, Hu, Liu & Delbruck, CVPRW 2021,
#: doi:10.1109/CVPRW53098.2021.00144), refractory period 0.5 ms (v2e's default; the refractory
#: bias sets 0.1-1 ms: Graça, McReynolds & Delbruck, "Shining light on the DVS pixel", 2023,
#: arXiv:2304.04706), shot noise 0.5 Hz per pixel (background activity of DAVIS pixels is
#: 0.1-1 Hz indoors; v2e), leak 0.1 Hz (v2e's noisy preset, IEBCS's ON leak rate).
TYPICAL_DAVIS_SENSOR = {"contrast_threshold_on": 0.25, "contrast_threshold_off": 0.25, "threshold_mismatch_sigma": 0.03,
                        "refractory_period_us": 500, "shot_noise_rate_hz": 0.5, "leak_rate_hz": 0.1}


def _measured_sensor() -> dict:
    """The built-in profile measured on a real DAVIS240C (``builtin:davis240c``, estimated from
    ``ecd_slider_depth`` by ``hybridhdr calibrate sensor``): the parameters that recording
    identifies (ON 0.47, OFF 0.39, shot noise 0.68 Hz, leak ~0), and :data:`TYPICAL_DAVIS_SENSOR`'s
    for the tiers it cannot (mismatch sigma, refractory period: docs/simulate-sensor.md)."""
    from .sensor import load_profile_spec
    measured = load_profile_spec("builtin:davis240c").simulator_params
    return {**TYPICAL_DAVIS_SENSOR, **{k: float(v) for k, v in measured.items() if k in TYPICAL_DAVIS_SENSOR}}


#: The event sensor of HDR set v2, in the simulator's own parameter names: the measured DAVIS240C
#: profile where it identifies a parameter, typical figures elsewhere (the one place to swap in
#: another measured profile). With the typical figures alone (0.25, sigma 0.03) one pixel of
#: ``sunlit_facade`` drew an ON threshold of 0.104 and its 3.7 ln rise became 6.5 ln: 89 % of the
#: AKF's set-v2 MSE (docs/simulate.md).
REALISTIC_SENSOR = _measured_sensor()

#: Sensor tiers (``hybridhdr.simulate.sensor.SENSOR_TIERS``) each HDR-v2 scene needs, and why;
#: the others are switched off (:func:`scene_sensor`). No scene needs tier 4 (photoreceptor
#: bandwidth): its shadows are lit, and the profile states no measured cutoff.
SCENE_TIERS = {
    "window_scenery": ((1, 2, 3), "mismatch and refractory decide how much of the panes' rise the events "
                                  "report; shot and leak noise matter in the dim room"),
    "lamp_shade": ((1, 2, 3), "as window_scenery: an evening room, dim corners"),
    "sunlit_facade": ((1, 2), "mismatch and refractory; the arcade's shade is daylit, where background "
                              "activity is far below the texture's event rate"),
}

_W0, _H0, _F0 = 346, 260, 280.0
_UP = (0.0, 1.0, 0.0)


def _cam(keyframes, interpolation="linear") -> CameraSpec:
    return CameraSpec(_W0, _H0, _F0, _F0, (_W0 - 1) / 2, (_H0 - 1) / 2, Trajectory(tuple(keyframes), interpolation))


def _kf(t_us, position, target, up=_UP) -> Keyframe:
    return Keyframe(int(t_us), tuple(float(v) for v in position),
                    quat_from_matrix(look_at_rotation(position, target, up)))


def _facing(position, normal_out, up=_UP) -> Trajectory:
    """Static pose of a plane at ``position`` whose visible side faces along ``normal_out``
    (the plane's local +z points the other way, its texture's top towards ``up``)."""
    p = np.asarray(position, float)
    target = p - np.asarray(normal_out, float)
    return Trajectory.static(tuple(p), quat_from_matrix(look_at_rotation(p, target, up)))


def _plane(name, size, position, normal_out, reflectance=0.5, emission=None, up=_UP) -> SceneObject:
    return SceneObject(name, MeshSpec("plane", size=tuple(size)),
                       Material(reflectance if isinstance(reflectance, Pattern) else Pattern(reflectance)),
                       emission, trajectory=_facing(position, normal_out, up))


def _dark_room_window(T: int) -> Scene:
    # room 6 m wide, 3 m high, back wall at z = 4; window in the back wall; dim ceiling lamp
    objs = (
        _plane("floor", (6, 8), (0, 0, 0), (0, 1, 0), 0.3, up=(0, 0, 1)),
        _plane("back_wall", (6, 3), (0, 1.5, 4), (0, 0, -1), 0.6),
        _plane("left_wall", (8, 3), (3, 1.5, 0), (-1, 0, 0), Pattern(checkerboard=(8, 3), low=0.2, high=0.7)),
        _plane("window", (1.4, 1.1), (-0.6, 1.7, 3.98), (0, 0, -1), 0.0,
               emission=Emission(Pattern(checkerboard=(2, 2), low=150.0, high=250.0))),
        SceneObject("cabinet", MeshSpec("box", extents=(0.8, 1.2, 0.5)), Material(Pattern(0.4)),
                    trajectory=Trajectory.static((2.2, 0.6, 2.5))),
    )
    ems = (Emitter("point", position=(0.5, 2.8, 1.5), intensity=1.0),)
    # pan (yaw) from the dark left wall (+x) to the window over the first 80 % of the time
    pos = (0.0, 1.5, -0.5)
    cam = _cam([_kf(0, pos, (3.0, 1.4, 1.0)), _kf(int(0.8 * T), pos, (-0.6, 1.6, 4.0)),
                _kf(T, pos, (-0.6, 1.6, 4.0))])
    return Scene("dark_room_window", T, cam, objs, ems, RenderSettings(spp=4),
                 info={"dynamic_range": "window radiance 150-250 vs room 0.005-0.03 (~10^4)"})


def _night_drive_sign(T: int) -> Scene:
    objs = [
        _plane("road", (8, 80), (0, 0, 30), (0, 1, 0), Pattern(checkerboard=(2, 40), low=0.04, high=0.08), up=(0, 0, 1)),
        _plane("sign", (1.6, 1.0), (-3.0, 2.6, 20.0), (0.3, 0, -1),
               0.0, emission=Emission(Pattern(checkerboard=(4, 1), low=20.0, high=400.0))),
        SceneObject("pole", MeshSpec("cylinder", radius=0.05, height=2.1, sections=12), Material(Pattern(0.3)),
                    trajectory=Trajectory.static((-3.0, 1.05, 20.05),
                                                 quat_from_matrix(look_at_rotation((0, 0, 0), (0, 1, 0), (0, 0, 1))))),
    ]
    for i, z in enumerate((8.0, 16.0, 24.0, 32.0)):
        objs.append(SceneObject(f"post{i}", MeshSpec("box", extents=(0.1, 0.8, 0.1)), Material(Pattern(0.6)),
                                trajectory=Trajectory.static((3.2, 0.4, z))))
    ems = (Emitter("spot", position=(0.6, 0.6, 0.5), look_at=(0.6, 0.9, 20.0), intensity=400.0, cutoff_deg=30,
                   beam_width_deg=20, attached_to_camera=True),
           Emitter("spot", position=(-0.6, 0.6, 0.5), look_at=(-0.6, 0.9, 20.0), intensity=400.0, cutoff_deg=30,
                   beam_width_deg=20, attached_to_camera=True),
           Emitter("point", position=(4.0, 6.0, 40.0), intensity=2.0))
    # 12 m/s along the road, camera at 1.2 m looking slightly down the road
    cam = _cam([_kf(0, (0.5, 1.2, 0.0), (0.5, 1.0, 30.0)), _kf(T, (0.5, 1.2, 12.0 * T * 1e-6), (0.5, 1.0, 30.0 + 12.0 * T * 1e-6))])
    return Scene("night_drive_sign", T, cam, tuple(objs), ems, RenderSettings(spp=4),
                 info={"speed_m_per_s": 12.0, "sign_radiance": [20.0, 400.0]})


def _fast_object_bright_background(T: int) -> Scene:
    sun_irr = 1000.0
    objs = (
        _plane("wall", (8, 5), (0, 2.0, 6.0), (0, 0, -1), Pattern(checkerboard=(8, 5), low=0.5, high=0.8)),
        _plane("ground", (8, 8), (0, 0, 3.0), (0, 1, 0), 0.4, up=(0, 0, 1)),
        SceneObject("ball", MeshSpec("sphere", radius=0.25, subdivisions=3), Material(Pattern(0.15)),
                    trajectory=Trajectory((Keyframe(0, (3.0, 1.0, 2.5)), Keyframe(T, (-3.0, 1.0, 2.5))))),
    )
    ems = (Emitter("directional", direction=(0.0, -0.4, 1.0), irradiance=sun_irr),  # sun from behind the camera
           Emitter("point", position=(0.0, 3.0, 0.0), intensity=0.1))              # dim fill (shadow level)
    cam = _cam([_kf(0, (0.0, 1.2, -1.0), (0.0, 1.2, 6.0))])
    return Scene("fast_object_bright_background", T, cam, objs, ems, RenderSettings(spp=4),
                 info={"ball_speed_m_per_s": 6.0 / (T * 1e-6), "sun_irradiance": sun_irr})


def _slow_static(T: int) -> Scene:
    objs = (
        _plane("table", (2.0, 1.5), (0, 0.75, 1.5), (0, 1, 0), Pattern(checkerboard=(6, 4), low=0.35, high=0.55),
               up=(0, 0, 1)),
        _plane("wall", (4, 3), (0, 1.5, 2.4), (0, 0, -1), 0.6),
        SceneObject("cup", MeshSpec("cylinder", radius=0.05, height=0.12, sections=20), Material(Pattern(0.8)),
                    trajectory=Trajectory.static((0.2, 0.81, 1.4),
                                                 quat_from_matrix(look_at_rotation((0, 0, 0), (0, 1, 0), (0, 0, 1))))),
        SceneObject("book", MeshSpec("box", extents=(0.25, 0.04, 0.18)), Material(Pattern(0.2)),
                    trajectory=Trajectory.static((-0.25, 0.77, 1.5))),
        SceneObject("ball", MeshSpec("sphere", radius=0.06, subdivisions=2), Material(Pattern(0.7)),
                    trajectory=Trajectory.static((0.0, 0.81, 1.7))),
    )
    ems = (Emitter("point", position=(0.8, 2.0, 0.8), intensity=3.0),)
    # 1 cm/s drift
    d = 0.01 * T * 1e-6
    cam = _cam([_kf(0, (0.0, 1.2, 0.6), (0.0, 0.8, 1.6)), _kf(T, (d, 1.2, 0.6), (d, 0.8, 1.6))])
    return Scene("slow_static", T, cam, objs, ems, RenderSettings(spp=4), info={"camera_speed_m_per_s": 0.01})


def _blinking_checkerboard(T: int, *, period_us: int = 100_000, squares=(10, 7), square_size_m: float = 0.04,
                           poses: int = 1) -> Scene:
    # Like a monitor: only the white squares blink (emission 50 <-> 0); the black squares show the
    # screen's constant reflection of the room light (reflectance 0.3), so they fire no events and
    # the event image shows the board. 10x7 squares = 9x6 inner corners (odd x even: the board
    # does not look the same rotated by 180 degrees, so corner order cannot flip between cameras).
    nu, nv = squares
    bw, bh = nu * square_size_m, nv * square_size_m
    board_pos = (0.0, 1.2, 1.0)
    blink = Blink(period_us=int(period_us), duty=0.5, off_scale=0.0)
    board = _plane("board", (bw, bh), board_pos, (0, 0, -1), 0.3,
                   emission=Emission(Pattern(checkerboard=(nu, nv), low=0.0, high=50.0), blink=blink))
    bezel = SceneObject("monitor", MeshSpec("box", extents=(bw + 0.06, bh + 0.06, 0.03)), Material(Pattern(0.05)),
                        trajectory=Trajectory.static((board_pos[0], board_pos[1], board_pos[2] + 0.016)))
    objs = (board, bezel, _plane("wall", (4, 3), (0, 1.5, 1.6), (0, 0, -1), 0.5),
            _plane("desk", (2, 1.5), (0, 0.75, 1.0), (0, 1, 0), 0.3, up=(0, 0, 1)))
    ems = (Emitter("point", position=(0.5, 2.5, 0.0), intensity=0.3),)
    # static camera, or `poses` static views with 2 ms moves between them
    views = [(0.0, 1.2, 0.45), (0.12, 1.25, 0.5), (-0.12, 1.15, 0.5), (0.05, 1.3, 0.42), (-0.05, 1.1, 0.42)]
    from .._util.cliargs import BLINKING_BOARD_MAX_POSES
    assert len(views) == BLINKING_BOARD_MAX_POSES
    if not 1 <= poses <= len(views):
        raise ValueError(f"poses: expected 1..{len(views)}, found {poses}")
    kfs = []
    seg = T // poses
    for k in range(poses):
        t_in = 0 if k == 0 else k * seg
        kfs.append(_kf(t_in, views[k], board_pos))
        if k < poses - 1:
            kfs.append(_kf((k + 1) * seg - 2000, views[k], board_pos))
    if kfs[-1].t_us < T:
        kfs.append(Keyframe(T, kfs[-1].position, kfs[-1].quaternion))
    R = look_at_rotation(board_pos, np.asarray(board_pos) - (0, 0, -1), _UP)
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = board_pos
    info = {"board_squares": [nu, nv], "board_inner_corners": [nu - 1, nv - 1], "square_size_m": square_size_m,
            "board_to_world": M.tolist(),
            "board_frame": "origin at the board centre; x along the rows (square column index), y down the "
                           "columns, z into the monitor; square (0, 0) at the top-left corner (-w/2, -h/2) is white",
            "blink_period_us": int(period_us), "blink_duty": 0.5, "white_radiance_on": 50.0,
            "black_emission": 0.0, "screen_reflectance": 0.3,
            "camera_pose_change_times_us": [kf.t_us for kf in kfs[1:-1]]}
    return Scene("blinking_checkerboard", T, _cam(kfs), objs, ems, RenderSettings(spp=4), info=info)


def _handheld(T: int, position, look_at, *, sweep_rad: float, seed: int, shake_rad: float = 0.0008,
              step_us: int = 20_000) -> CameraSpec:
    """A hand-held camera at ``position``: a steady horizontal pan of ``sweep_rad`` (centred on
    ``look_at``) over the duration, plus shake (three sinusoids per axis, 1.5-4 Hz, random
    phases, ``shake_rad`` each; pure rotation). Keyframes every ``step_us``, slerped."""
    rng = np.random.default_rng([int(seed), 29])
    p = np.asarray(position, float)
    d0 = np.asarray(look_at, float) - p
    yaw0 = math.atan2(d0[0], d0[2])
    pitch0 = math.atan2(d0[1], math.hypot(d0[0], d0[2]))
    f = rng.uniform(1.5, 4.0, (2, 3))
    ph = rng.uniform(0, 2 * math.pi, (2, 3))
    kfs = []
    ts = list(range(0, T, step_us)) + [T]
    for t in ts:
        s = t * 1e-6
        shake = shake_rad * np.sin(2 * math.pi * f * s + ph).sum(axis=1)
        yaw = yaw0 + sweep_rad * (t / T - 0.5) + shake[0]
        pitch = pitch0 + shake[1]
        d = np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)])
        k = _kf(t, tuple(p), tuple(p + d))
        kfs.append(Keyframe(k.t_us, k.position, _unit(k.quaternion)))
    return _cam(kfs)


def _unit(q):
    """``q`` divided by its norm until that no longer changes it (a scene file's reader
    normalises every quaternion: this makes the TOML round trip exact)."""
    for _ in range(8):
        n = math.sqrt(sum(c * c for c in q))
        q2 = tuple(c / n for c in q)
        if q2 == q:
            break
        q = q2
    return q


def _window_scenery(T: int) -> Scene:
    # a dim room's back wall (painted plaster) with a six-pane window onto daylit scenery; one
    # ceiling lamp. Sky up to 40, trees 4-10 (radiance; the 10 ms frames clip at 2), mullions
    # ~1, wall 0.03-0.1: the panes 10^2-10^3x the wall.
    objs = (
        _plane("back_wall", (7, 3.5), (0, 1.75, 2.62), (0, 0, -1), Pattern(1.0, procedural="plaster", seed=1)),
        _plane("window", (1.7, 1.15), (0.0, 1.65, 2.6), (0, 0, -1), 0.0,
               emission=Emission(Pattern(40.0, procedural="scenery", seed=1))),
    )
    ems = (Emitter("point", position=(1.0, 2.6, 0.8), intensity=3.0),)
    cam = _handheld(T, (0.0, 1.5, 0.0), (0.0, 1.6, 2.6), sweep_rad=0.15, seed=1)
    return Scene("window_scenery", T, cam, objs, ems, RenderSettings(spp=4),
                 info={"dynamic_range": "panes 4-40 (sky 30-40, trees 4-10), mullions ~1, wall 0.03-0.1 (10^2-10^3)",
                       "sensor_tiers": list(SCENE_TIERS["window_scenery"][0]), "camera": "hand-held pan 0.15 rad/s with shake"})


def _lamp_shade(T: int) -> Scene:
    # an evening room: a floor lamp's textured fabric shade (4 panels between ribs) lit by its
    # bulb, which also lights the wallpapered wall behind (a glow falling off with distance); a
    # table lamp's smaller shade beside it (emission only). Shades up to 40 and 25, their ribs
    # ~1, wall 0.05-1.
    objs = (
        _plane("wall", (6, 3.2), (0, 1.6, 2.5), (0, 0, -1), Pattern(1.0, procedural="wallpaper", seed=2)),
        _plane("shade", (0.8, 0.55), (0.1, 1.25, 1.5), (0, 0, -1), 0.6,
               emission=Emission(Pattern(40.0, procedural="lampshade", seed=2))),
        _plane("table_shade", (0.4, 0.3), (-0.75, 0.95, 1.45), (0, 0, -1), 0.6,
               emission=Emission(Pattern(25.0, procedural="lampshade", seed=3))),
    )
    ems = (Emitter("point", position=(0.1, 1.25, 1.7), intensity=5.0),)
    cam = _handheld(T, (0.0, 1.2, 0.0), (-0.1, 1.15, 1.5), sweep_rad=0.15, seed=2)
    return Scene("lamp_shade", T, cam, objs, ems, RenderSettings(spp=4),
                 info={"dynamic_range": "shades 10-40, ribs ~1, wall 0.05-1 (10^2-10^3x the dark wall)",
                       "sensor_tiers": list(SCENE_TIERS["lamp_shade"][0]), "camera": "hand-held pan 0.15 rad/s with shake"})


def _sunlit_facade(T: int) -> Scene:
    # from a shaded arcade: a sunlit brick facade across the street, seen between three dark
    # pillars (part of the facade's texture: the camera only rotates, so they show no
    # parallax); the arcade's ceiling and floor and the shaded buildings beside the facade lit
    # by a dim fill. Bricks up to 60 (radiance = albedo x sun / pi), glass ~8, pillars ~1.2,
    # shade 0.05-0.5: 10^2-10^3.
    objs = (
        _plane("facade", (8, 4.4), (0, 1.7, 6.0), (0, 0, -1), 0.0,
               emission=Emission(Pattern(60.0, procedural="facade", seed=3))),
        _plane("street_side", (16, 6), (0, 2.0, 6.1), (0, 0, -1), Pattern(1.0, procedural="plaster", seed=5)),
        _plane("ceiling", (8, 6), (0, 3.0, 3.0), (0, -1, 0), Pattern(1.0, procedural="plaster", seed=4), up=(0, 0, 1)),
        _plane("floor", (8, 6), (0, 0.0, 3.0), (0, 1, 0), Pattern(1.0, procedural="wood", seed=4), up=(0, 0, 1)),
    )
    ems = (Emitter("point", position=(0.0, 1.8, 2.0), intensity=6.0),)
    cam = _handheld(T, (0.0, 1.6, 0.0), (0.0, 1.7, 6.0), sweep_rad=0.15, seed=3)
    return Scene("sunlit_facade", T, cam, objs, ems, RenderSettings(spp=4),
                 info={"dynamic_range": "facade 8-60, pillars ~1.2, arcade shade 0.05-0.5 (10^2-10^3)",
                       "sensor_tiers": list(SCENE_TIERS["sunlit_facade"][0]), "camera": "hand-held pan 0.15 rad/s with shake"})


def scene_sensor(name: str, profile: dict | None = None) -> dict:
    """The event-sensor fields for an HDR-v2 scene: ``profile`` (default
    :data:`REALISTIC_SENSOR`) with the tiers the scene does not need switched off."""
    from .sensor import restrict_to_tiers
    key = name[len("builtin:"):] if name.startswith("builtin:") else name
    if key not in SCENE_TIERS:
        raise ValueError(f"scene_sensor: expected one of {', '.join(SCENE_TIERS)}, found {name!r}")
    return restrict_to_tiers(REALISTIC_SENSOR if profile is None else profile, SCENE_TIERS[key][0])


_BUILDERS = {"window_scenery": _window_scenery, "lamp_shade": _lamp_shade, "sunlit_facade": _sunlit_facade,
             "dark_room_window": _dark_room_window, "night_drive_sign": _night_drive_sign,
             "fast_object_bright_background": _fast_object_bright_background, "slow_static": _slow_static,
             "blinking_checkerboard": _blinking_checkerboard}


def builtin_scene(name: str, *, width: int = 346, height: int = 260, duration_s: float | None = None,
                  spp: int | None = None, **options) -> Scene:
    """A built-in scene (see :data:`BUILTIN_SCENES`).

    Parameters
    ----------
    name : str
        Scene name, with or without a ``builtin:`` prefix.
    width, height : int
        Pixel grid; the intrinsics scale with it (same field of view as 346 × 260).
    duration_s : float or None
        Length in seconds (defaults: 0.5 s for the fast object, 1 s otherwise); trajectories are
        stretched to it, so speeds scale inversely except where ``info`` states a fixed speed.
    spp : int or None
        Samples per pixel (default 4).
    options
        ``blinking_checkerboard`` accepts ``period_us`` (100000), ``squares`` ((10, 7)),
        ``square_size_m`` (0.04) and ``poses`` (1..5 static camera views).
    """
    key = name[len("builtin:"):] if name.startswith("builtin:") else name
    if key not in _BUILDERS:
        raise ValueError(f"unknown built-in scene {name!r}; expected one of: {', '.join(BUILTIN_SCENES)}")
    if options and key != "blinking_checkerboard":
        raise ValueError(f"built-in scene {key!r} takes no options, got {sorted(options)}")
    dur = _DEFAULT_DURATION_S[key] if duration_s is None else float(duration_s)
    if not (dur > 0 and math.isfinite(dur)):
        raise ValueError(f"duration_s: expected > 0, found {duration_s}")
    T = max(1, int(round(dur * 1e6)))
    sc = _BUILDERS[key](T, **options)
    if width < 1 or height < 1:
        raise ValueError(f"size: expected positive width and height, found {width}x{height}")
    return sc.with_changes(width=width, height=height, spp=spp)
