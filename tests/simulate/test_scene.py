"""Scene description: TOML round trip, validation errors, trajectories, intrinsics."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hybridhdr.simulate.builtin import BUILTIN_SCENES, builtin_scene
from hybridhdr.simulate.scene import (Blink, CameraSpec, Keyframe, Scene, SceneError, Trajectory, dumps_toml,
                                      load_calibration, load_scene, look_at_rotation, matrix_from_quat,
                                      quat_from_matrix, save_scene)

EXAMPLE = """
name = "example"
duration_us = 200000

[render]
spp = 2
integrator = "direct"
seed = 3

[camera]
width = 64
height = 48
fx = 50.0
cx = 31.5
cy = 23.5
interpolation = "catmull_rom"
[[camera.keyframes]]
t_us = 0
position = [0.0, 1.0, -3.0]
look_at = [0.0, 1.0, 0.0]
[[camera.keyframes]]
t_us = 100000
position = [0.5, 1.0, -3.0]
look_at = [0.0, 1.0, 0.0]
[[camera.keyframes]]
t_us = 200000
position = [1.0, 1.2, -3.0]
quaternion = [1.0, 0.0, 0.0, 0.0]

[[emitters]]
type = "point"
position = [0.0, 3.0, -1.0]
intensity = 10.0

[[emitters]]
type = "directional"
direction = [0.0, -1.0, 1.0]
irradiance = 1000.0
blink = { period_us = 50000, duty = 0.5, off_scale = 0.1 }

[[objects]]
name = "floor"
mesh = { type = "plane", size = [10.0, 10.0] }
material = { reflectance = { checkerboard = [10, 10], low = 0.1, high = 0.8 } }
position = [0.0, 0.0, 0.0]
look_at = [0.0, -1.0, 0.0]
up = [0.0, 0.0, 1.0]

[[objects]]
name = "ball"
mesh = { type = "sphere", radius = 0.3, subdivisions = 2 }
material = { reflectance = 0.5 }
scale = 1.5
[[objects.keyframes]]
t_us = 0
position = [-1.0, 0.5, 0.0]
[[objects.keyframes]]
t_us = 200000
position = [1.0, 0.5, 0.0]

[[objects]]
name = "lamp"
mesh = { type = "box", extents = [0.2, 0.2, 0.2] }
emission = { radiance = 500.0 }
position = [2.0, 2.0, 2.0]

[info]
note = "free-form"
"""


def test_example_loads(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text(EXAMPLE)
    sc = load_scene(p)
    assert sc.name == "example" and sc.duration_us == 200000
    assert sc.render.spp == 2 and sc.render.seed == 3
    assert (sc.camera.fx, sc.camera.fy, sc.camera.cx) == (50.0, 50.0, 31.5)
    assert sc.camera.trajectory.interpolation == "catmull_rom" and len(sc.camera.trajectory.keyframes) == 3
    assert [o.name for o in sc.objects] == ["floor", "ball", "lamp"]
    assert sc.objects[1].scale == (1.5, 1.5, 1.5)
    assert sc.objects[0].material.reflectance.checkerboard == (10, 10)
    assert sc.objects[2].emission.radiance.value == 500.0
    assert sc.emitters[1].blink == Blink(period_us=50000, duty=0.5, off_scale=0.1)
    assert sc.info == {"note": "free-form"}
    assert sc.base_dir == str(tmp_path.resolve())


@pytest.mark.parametrize("name", list(BUILTIN_SCENES))
def test_round_trip_builtin(tmp_path, name):
    sc = builtin_scene(name, width=80, height=60)
    p = save_scene(sc, tmp_path / f"{name}.toml")
    assert not (tmp_path / f"{name}.toml.partial").exists()
    back = load_scene(p)
    assert back == sc  # dataclass equality over every field (base_dir excluded)
    assert save_scene(back, tmp_path / "again.toml").read_text() == p.read_text()


def test_round_trip_example(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text(EXAMPLE)
    sc = load_scene(p)
    q = save_scene(sc, tmp_path / "out.toml")
    assert load_scene(q) == sc


def test_toml_writer_escapes():
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover
        import tomli as tomllib
    d = {"s": 'a "quoted" \\ str\nwith ünïcode', "f": 1e-300, "i": -3, "b": True, "arr": [1, 2.5],
         "t": {"x": 1}, "aot": [{"k": 1}, {"k": 2, "sub": {"z": [0.1]}}]}
    assert tomllib.loads(dumps_toml(d)) == d


def _load_str(tmp_path, text):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return load_scene(p)


@pytest.mark.parametrize("edit, needle", [
    (("duration_us = 200000", "duration_us = 200000\ncolour = 1"), "'colour'"),
    (("spp = 2", "spp = 'two'"), "render.spp"),
    (("fx = 50.0", "fx = -50.0"), "camera.fx"),
    (("radius = 0.3,", "radius = 'big',"), "objects[1].mesh.radius"),
    (('type = "sphere"', 'type = "teapot"'), "objects[1].mesh.type"),
    (("intensity = 10.0", "intensity = [1, 2]"), "emitters[0].intensity"),
    (("t_us = 100000", "t_us = 300000"), "keyframe times must increase"),
    (("quaternion = [1.0, 0.0, 0.0, 0.0]", "quaternion = [1.0, 1.0, 0.0, 0.0]"), "unit quaternion"),
    (("look_at = [0.0, 1.0, 0.0]\n[[camera.keyframes]]\nt_us = 100000",
      "look_at = [0.0, 1.0, 0.0]\nquaternion = [1.0, 0.0, 0.0, 0.0]\n[[camera.keyframes]]\nt_us = 100000"),
     "not both"),
    (('mesh = { type = "box", extents = [0.2, 0.2, 0.2] }', 'mesh = { type = "box", extent = [0.2, 0.2, 0.2] }'),
     "objects[2].mesh.extent"),
])
def test_bad_keys_name_the_key(tmp_path, edit, needle):
    old, new = edit
    assert old in EXAMPLE
    with pytest.raises(SceneError) as e:
        _load_str(tmp_path, EXAMPLE.replace(old, new, 1))
    assert needle in str(e.value)
    assert "bad.toml" in str(e.value)


def test_missing_and_invalid_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_scene(tmp_path / "nope.toml")
    p = tmp_path / "x.toml"
    p.write_text("name = [")
    with pytest.raises(SceneError, match="invalid TOML"):
        load_scene(p)
    with pytest.raises(SceneError, match="no light"):
        _load_str(tmp_path, EXAMPLE.split("[[emitters]]")[0])


def test_calibration_file(tmp_path):
    K = [[300.0, 0, 170.0], [0, 300.0, 128.0], [0, 0, 1]]
    (tmp_path / "calib.json").write_text(json.dumps({"K": K, "image_size": [346, 260], "dist": [0, 0, 0, 0]}))
    text = EXAMPLE.replace("width = 64\nheight = 48\nfx = 50.0\ncx = 31.5\ncy = 23.5", 'calibration = "calib.json"')
    sc = _load_str(tmp_path, text)
    assert (sc.camera.width, sc.camera.height, sc.camera.fx, sc.camera.cx, sc.camera.cy) == (346, 260, 300.0, 170.0, 128.0)
    assert load_calibration(tmp_path / "calib.json") == (300.0, 300.0, 170.0, 128.0, 346, 260)
    (tmp_path / "bad.json").write_text(json.dumps({"K": [[1, 2], [3, 4]], "image_size": [346, 260]}))
    with pytest.raises(SceneError, match="3x3"):
        load_calibration(tmp_path / "bad.json")
    (tmp_path / "bad2.json").write_text(json.dumps({"K": K, "image_size": [346]}))
    with pytest.raises(SceneError, match="image_size"):
        load_calibration(tmp_path / "bad2.json")


def test_non_square_pixels_rejected():
    with pytest.raises(SceneError, match="square pixels"):
        CameraSpec(64, 48, 50.0, 52.0, 31.5, 23.5)


def test_resized_keeps_the_field_of_view():
    cam = CameraSpec(346, 260, 280.0, 280.0, 172.5, 129.5)
    small = cam.resized(173, 130)
    # the image edges map to the same viewing angles: (edge - c) / f is preserved (pixel edges at -0.5, W-0.5)
    for c0, f0, n0, c1, f1, n1 in ((cam.cx, cam.fx, cam.width, small.cx, small.fx, small.width),
                                   (cam.cy, cam.fy, cam.height, small.cy, small.fy, small.height)):
        assert (-0.5 - c0) / f0 == pytest.approx((-0.5 - c1) / f1, rel=1e-12)
        assert (n0 - 0.5 - c0) / f0 == pytest.approx((n1 - 0.5 - c1) / f1, rel=1e-12)


def test_rotations():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q *= np.sign(q[0])
        R = matrix_from_quat(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.allclose(quat_from_matrix(R), q, atol=1e-12)
    R = look_at_rotation((0, 0, 0), (0, 0, 5), (0, 1, 0))
    # looking along +z with +y up: image down (camera y) is world -y, image right (x) is world -x
    assert np.allclose(R, np.diag([-1.0, -1.0, 1.0]))


def test_trajectory_linear_and_slerp():
    q1 = quat_from_matrix(look_at_rotation((0, 0, 0), (1, 0, 0), (0, 1, 0)))  # 90° yaw
    tr = Trajectory((Keyframe(0, (0.0, 0.0, 0.0)), Keyframe(1_000_000, (2.0, 0.0, 0.0), q1)))
    R0, _ = tr.pose(0)
    R, p = tr.pose(500_000)
    assert np.allclose(p, [1, 0, 0])
    # half of a 180° rotation (identity -> look_at(+x) with y down is a 180° turn about... ) : angle halves
    ang_full = math.acos((np.trace(matrix_from_quat(q1)) - 1) / 2)
    ang_half = math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    assert ang_half == pytest.approx(ang_full / 2, abs=1e-9)
    v, w = tr.speed_bounds(0, 1_000_000)
    assert v == pytest.approx(2.0) and w == pytest.approx(ang_full)
    assert tr.pose(-5)[1].tolist() == [0, 0, 0] and tr.pose(2_000_000)[1].tolist() == [2, 0, 0]  # held


def test_catmull_rom_passes_keys_and_speed_bound_is_the_max():
    kfs = tuple(Keyframe(t, p) for t, p in [(0, (0.0, 0.0, 0.0)), (100_000, (1.0, 0.5, 0.0)),
                                            (250_000, (1.5, -0.5, 0.2)), (400_000, (3.0, 0.0, 0.0))])
    tr = Trajectory(kfs, "catmull_rom")
    for k in kfs:
        assert np.allclose(tr.pose(k.t_us)[1], k.position, atol=1e-12)
    for t0, t1 in [(0, 400_000), (30_000, 170_000), (260_000, 300_000)]:
        ts = np.linspace(t0, t1, 4001)
        P = np.array([tr.pose(t)[1] for t in ts])
        fd = np.linalg.norm(np.diff(P, axis=0), axis=1) / (np.diff(ts) * 1e-6)
        vmax, _ = tr.speed_bounds(t0, t1)
        # finite differences on a 4000-step grid under-estimate the true max by < 0.5 %
        assert fd.max() <= vmax * (1 + 1e-9)
        assert fd.max() >= vmax * 0.995


def test_blink():
    b = Blink(period_us=100, duty=0.3, off_scale=0.25, phase_us=10)
    assert [b.scale(t) for t in (10, 39, 40, 109, 110)] == [1.0, 1.0, 0.25, 0.25, 1.0]
    assert b.edges_us(0, 250) == [10, 40, 110, 140, 210, 240]
    with pytest.raises(SceneError, match="duty"):
        Blink(period_us=10, duty=1.5)


def test_scene_validation():
    cam = CameraSpec(8, 6, 5.0, 5.0, 3.5, 2.5)
    with pytest.raises(SceneError, match="duration_us"):
        Scene("x", 0, cam)
    with pytest.raises(SceneError, match="no light"):
        Scene("x", 10, cam)


def test_docs_example_loads_and_renders(tmp_path):
    """The complete example in docs/simulate.md stays valid."""
    import re
    from pathlib import Path
    trimesh = pytest.importorskip("trimesh")
    pytest.importorskip("mitsuba")
    iio = pytest.importorskip("imageio.v3")
    doc = (Path(__file__).resolve().parents[2] / "docs" / "simulate.md").read_text()
    (tmp_path / "ex.toml").write_text(re.search(r"```toml\n(.*?)```", doc, re.S).group(1))
    trimesh.creation.icosphere(subdivisions=1, radius=0.3).export(tmp_path / "statue.ply")
    iio.imwrite(tmp_path / "poster.png", np.random.default_rng(0).integers(0, 255, (8, 8), dtype=np.uint8))
    sc = load_scene(tmp_path / "ex.toml")
    assert [o.name for o in sc.objects] == ["floor", "ball", "window", "statue", "poster"]
    assert load_scene(save_scene(sc, tmp_path / "back.toml")) == sc
    from hybridhdr.simulate.render import MitsubaSource
    img = MitsubaSource(sc.with_changes(width=32, height=24, spp=1)).render(250_000)
    assert img.shape == (24, 32) and np.isfinite(img).all() and img.max() > 0


def test_mesh_files_trimesh_cannot_read_are_scene_errors(tmp_path):
    """An unknown extension or a malformed file is a SceneError naming the file, never trimesh's own
    NotImplementedError / KeyError traceback."""
    pytest.importorskip("trimesh")
    from hybridhdr.simulate.scene import MeshSpec
    (tmp_path / "x.foo").write_text("garbage\n")
    with pytest.raises(SceneError, match=r"x\.foo.*format 'foo' is not one trimesh reads; expected one of .*ply"):
        MeshSpec("file", path="x.foo").build(tmp_path)
    (tmp_path / "z.ply").write_text("ply\nformat ascii 1.0\nelement vertex 99999999999\nend_header\n")
    with pytest.raises(SceneError, match=r"z\.ply.*not a readable PLY mesh"):
        MeshSpec("file", path="z.ply").build(tmp_path)
    (tmp_path / "e.stl").write_text("solid x\nendsolid\n")
    with pytest.raises(SceneError, match="expected a triangle mesh"):
        MeshSpec("file", path="e.stl").build(tmp_path)
