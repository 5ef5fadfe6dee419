"""Mitsuba radiance source: intrinsics, determinism, radiance ratios, motion bound."""

from __future__ import annotations

import glob
import math
import os

import numpy as np
import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("trimesh")

from hybridhdr.simulate import render as R  # noqa: E402
from hybridhdr.simulate.render import MitsubaSource, llvm_available, mitsuba_camera_params, select_variant  # noqa: E402
from hybridhdr.simulate.scene import (CameraSpec, Emission, Emitter, Keyframe, Material, MeshSpec, Pattern,  # noqa: E402
                                      RenderSettings, Scene, SceneObject, Trajectory, look_at_rotation,
                                      quat_from_matrix)
from hybridhdr.simulate.source import RadianceSource  # noqa: E402


def _centroid(img):
    ys, xs = np.mgrid[: img.shape[0], : img.shape[1]]
    s = img.sum()
    return float((img * xs).sum() / s), float((img * ys).sum() / s)


def _ball_scene(cam, ball_traj, duration_us=100_000, radius=0.2, spp=16):
    ball = SceneObject("ball", MeshSpec("sphere", radius=radius, subdivisions=3), Material(Pattern(0.0)),
                       Emission(Pattern(1.0)), trajectory=ball_traj)
    return Scene("ball", duration_us, cam, (ball,), render=RenderSettings(spp=spp))


def test_variant_selection():
    v = select_variant()
    assert v in ("llvm_ad_mono", "scalar_rgb")
    assert v == (os.environ.get("HYBRIDHDR_MITSUBA_VARIANT") or ("llvm_ad_mono" if llvm_available() else "scalar_rgb"))
    with pytest.raises(ValueError, match="variant"):
        select_variant("cuda_ad_rgb")


def test_selection_decision_on_fake_llvm_versions():
    def no_probe():
        raise AssertionError("an LLVM below the minimum must not even be probed")

    v, why = R._decide((15, 0, 6), no_probe)
    assert v == "scalar_rgb" and "LLVM 15.0.6" in why and ">= 17" in why
    v, why = R._decide((16, 0, 0), no_probe)
    assert v == "scalar_rgb" and "16.0.0" in why
    v, why = R._decide((-1, -1, -1), no_probe)  # Dr.Jit found none it can use (e.g. only LLVM 14)
    assert v == "scalar_rgb" and "no usable libLLVM" in why
    assert R._decide((19, 1, 7), lambda: (True, "")) == ("llvm_ad_mono", "")
    v, why = R._decide((17, 0, 0), lambda: (False, "the LLVM test render failed (signal 6: LLVM ERROR: x)"))
    assert v == "scalar_rgb" and "LLVM 17.0.0" in why and "signal 6" in why


@pytest.fixture
def fresh_choice(monkeypatch, tmp_path):
    """The automatic choice reset (restored afterwards), with its disk cache under tmp_path."""
    monkeypatch.setattr(R, "_DECISION", None)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("HYBRIDHDR_MITSUBA_VARIANT", raising=False)
    monkeypatch.delenv("_HYBRIDHDR_VARIANT_NOTED", raising=False)
    monkeypatch.delenv("HYBRIDHDR_VARIANT_CACHE", raising=False)
    monkeypatch.setenv("HYBRIDHDR_MITSUBA_CUDA", "0")  # the LLVM/scalar choice, whether or not a GPU is here
    return monkeypatch


@pytest.mark.parametrize("fake", [(15, 0, 6), (-1, -1, -1)])
def test_old_llvm_selects_scalar_with_one_line(fresh_choice, capsys, fake):
    fresh_choice.setattr(R, "_drjit_llvm_version", lambda: fake)
    fresh_choice.setattr(R, "_probe_llvm", lambda: pytest.fail("probed"))
    assert select_variant() == "scalar_rgb" and not llvm_available()
    assert select_variant() == "scalar_rgb"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scalar_rgb" in err[0] and "apt-get install libllvm19" in err[0]
    with pytest.raises(ImportError, match="apt-get install libllvm19"):
        select_variant("llvm_ad_mono")
    # forcing a variant: the environment variable and the argument
    fresh_choice.setenv("HYBRIDHDR_MITSUBA_VARIANT", "scalar_rgb")
    assert select_variant() == "scalar_rgb"
    fresh_choice.setenv("HYBRIDHDR_MITSUBA_VARIANT", "llvm_ad_mono")
    with pytest.raises(ImportError, match="LLVM"):
        select_variant()
    fresh_choice.setenv("HYBRIDHDR_MITSUBA_VARIANT", "cuda_ad_rgb")
    with pytest.raises(ValueError, match="variant"):
        select_variant()


def test_new_llvm_is_probed_once_and_remembered(fresh_choice, capsys, tmp_path):
    calls = []
    fresh_choice.setattr(R, "_drjit_llvm_version", lambda: (19, 1, 7))
    fresh_choice.setattr(R, "_probe_llvm", lambda: calls.append(1) or (True, ""))
    assert select_variant() == "llvm_ad_mono" and llvm_available() and len(calls) == 1
    assert select_variant("llvm_ad_mono") == "llvm_ad_mono"
    fresh_choice.setenv("HYBRIDHDR_MITSUBA_VARIANT", "scalar_rgb")
    assert select_variant() == "scalar_rgb"  # forced
    fresh_choice.delenv("HYBRIDHDR_MITSUBA_VARIANT")
    assert capsys.readouterr().err == ""  # quiet when nothing is missing
    assert (tmp_path / "hybridhdr" / "mitsuba-variant.json").exists()
    # a new process (same interpreter and libraries) reads the decision from disk
    fresh_choice.setattr(R, "_DECISION", None)
    assert select_variant() == "llvm_ad_mono" and len(calls) == 1
    # a probe that fails (the child aborted): scalar_rgb, with the reason
    fresh_choice.setattr(R, "_DECISION", None)
    fresh_choice.setenv("HYBRIDHDR_VARIANT_CACHE", "0")
    fresh_choice.setattr(R, "_probe_llvm", lambda: (False, "the LLVM test render failed (signal 6: LLVM ERROR: Cannot "
                                                           "select: fminimum)"))
    assert select_variant() == "scalar_rgb"
    err = capsys.readouterr().err
    assert "fminimum" in err and "apt-get install libllvm19" in err


@pytest.mark.slow
def test_probe_survives_an_aborting_llvm(monkeypatch):
    # the real child-process probe, past the version gate: with an LLVM that aborts (15/16) only
    # the child dies and the answer is "no", with the reason; with a working one it says yes
    ok, why = R._probe_llvm(check_version=False)
    ver = R._drjit_llvm_version()
    if ver >= R.MIN_LLVM_VERSION:
        assert ok == llvm_available(), why
    old = sorted(p for d in R._LIB_DIRS for p in glob.glob(os.path.join(d, "libLLVM-1[56].so.1")))
    if not old:
        pytest.skip("no system libLLVM 15/16 to abort with")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", old[0])  # the child loads the aborting LLVM
    ok, why = R._probe_llvm(check_version=False)
    assert not ok and "failed" in why, why


def test_intrinsics_projection_with_off_centre_principal_point():
    # camera rotated and translated, principal point 8 px right and 3.5 px above the centre
    pos = (0.3, -0.2, -1.0)
    q = quat_from_matrix(look_at_rotation(pos, (0.6, 0.1, 4.0), (0.05, -1.0, 0.0)))
    cam = CameraSpec(64, 48, 52.0, 52.0, 39.5, 20.0, Trajectory.static(pos, q))
    for P in ([0.6, 0.1, 4.0], [-0.3, 0.5, 3.0], [1.2, -0.4, 5.0]):
        src = MitsubaSource(_ball_scene(cam, Trajectory.static(P)))
        img = src.render(0)
        u, v = cam.project(P)[0]
        cu, cv = _centroid(img)
        # a 0.2 m sphere is ~3-4 px wide: its pixel-integrated centroid is the projected centre
        # to well below 0.1 px (sphere-projection asymmetry ~ (r/Z)^2 * offset); 0.5 px per the spec
        assert abs(cu - u) < 0.5 and abs(cv - v) < 0.5, (P, (u, v), (cu, cv))


def test_camera_params_formula():
    d = mitsuba_camera_params(50.0, 31.5, 23.5, 64, 48)
    assert d["principal_point_offset_x"] == 0 and d["principal_point_offset_y"] == 0
    assert d["fov"] == pytest.approx(math.degrees(2 * math.atan(64 / 100)))


def test_deterministic_renders_and_protocol():
    cam = CameraSpec(48, 36, 40.0, 40.0, 23.5, 17.5, Trajectory((Keyframe(0, (0.0, 0.0, 0.0)),
                                                                 Keyframe(100_000, (0.2, 0.0, 0.0)))))
    sc = _ball_scene(cam, Trajectory.static((0.0, 0.0, 3.0)), spp=2)
    floor = SceneObject("wall", MeshSpec("plane", size=(6.0, 6.0)), Material(Pattern(checkerboard=(6, 6), low=0.2, high=0.7)),
                        trajectory=Trajectory.static((0.0, 0.0, 5.0)))
    sc = Scene(sc.name, sc.duration_us, cam, sc.objects + (floor,), (Emitter("point", position=(0.0, -1.0, 0.0), intensity=5.0),),
               RenderSettings(spp=2))
    a = MitsubaSource(sc)
    assert isinstance(a, RadianceSource)
    r1 = a.render(50_000)
    a.render(10_000)
    r2 = a.render(50_000)
    b = MitsubaSource(sc)
    r3 = b.render(50_000)
    assert r1.dtype == np.float32 and r1.shape == (36, 48)
    assert np.isfinite(r1).all() and r1.min() >= 0 and r1.max() > 0
    assert np.array_equal(r1, r2) and np.array_equal(r1, r3)  # same bits
    assert a.renders == 3
    d = a.describe()
    assert d["variant"] == a.variant and d["spp"] == 2 and d["K"][0][2] == 23.5
    with pytest.raises(ValueError, match="render time"):
        a.render(100_001)


def test_sun_to_shadow_ratio():
    # wall at z = 5 facing the camera; fill light straight along +z (irradiance E_f = 1) and a sun
    # at 45 deg whose light an occluder outside the view blocks on the right part of the wall.
    # Lambertian radiance: lit = rho/pi (E_s cos45 + E_f), shadow = rho/pi E_f.
    ratio = 1e4
    e_s = (ratio - 1) / math.cos(math.pi / 4)
    cam = CameraSpec(64, 48, 52.0, 52.0, 31.5, 23.5)
    wall = SceneObject("wall", MeshSpec("plane", size=(20.0, 20.0)), Material(Pattern(0.5)),
                       trajectory=Trajectory.static((0.0, 0.0, 5.0)))
    occ = SceneObject("occluder", MeshSpec("plane", size=(10.0, 20.0)), Material(Pattern(0.5)),
                      trajectory=Trajectory.static((8.5, 0.0, 3.0)))  # x in [3.5, 13.5] at z = 3
    ems = (Emitter("directional", direction=(-1.0, 0.0, 1.0), irradiance=e_s),
           Emitter("directional", direction=(0.0, 0.0, 1.0), irradiance=1.0))
    src = MitsubaSource(Scene("sun", 1000, cam, (wall, occ), ems, RenderSettings(spp=4)))
    img = src.render(0)
    # shadow edge on the wall at x = 3.5 - 2 = 1.5 m -> u = 52 * 1.5 / 5 + 31.5 = 47.1
    lit, shadow = img[:, 5:40], img[:, 52:]
    assert np.allclose(lit, 0.5 / math.pi * ratio, rtol=1e-4)
    assert np.allclose(shadow, 0.5 / math.pi, rtol=1e-4)
    assert np.median(lit) / np.median(shadow) == pytest.approx(ratio, rel=1e-4)


def _track(src, ts):
    return np.array([_centroid(src.render(int(t))) for t in ts])


def test_motion_bound_covers_measured_motion():
    # 1) a ball moving 1 m in 0.1 s at 3 m depth, static camera
    cam = CameraSpec(64, 48, 52.0, 52.0, 31.5, 23.5)
    src = MitsubaSource(_ball_scene(cam, Trajectory((Keyframe(0, (-0.5, 0.0, 3.0)), Keyframe(100_000, (0.5, 0.0, 3.0)))),
                                    spp=4))
    ts = np.linspace(0, 100_000, 11)
    c = _track(src, ts)
    measured = np.linalg.norm(np.diff(c, axis=0), axis=1) / (np.diff(ts) * 1e-6)
    for i in range(len(ts) - 1):
        bound = src.max_image_speed_px_per_s(int(ts[i]), int(ts[i + 1]))
        assert measured[i] <= bound, (i, measured[i], bound)
        assert bound < 4 * measured[i]  # not vacuous: within a small factor
    # 2) a static ball seen by a panning camera (yaw 0.2 rad in 0.1 s)
    q1 = quat_from_matrix(look_at_rotation((0, 0, 0), (math.sin(0.2), 0, math.cos(0.2)), (0, -1, 0)))
    cam2 = CameraSpec(64, 48, 52.0, 52.0, 31.5, 23.5, Trajectory((Keyframe(0, (0.0, 0.0, 0.0)),
                                                                  Keyframe(100_000, (0.0, 0.0, 0.0), q1))))
    src2 = MitsubaSource(_ball_scene(cam2, Trajectory.static((0.2, 0.0, 3.0)), spp=4))
    c2 = _track(src2, ts)
    measured2 = np.linalg.norm(np.diff(c2, axis=0), axis=1) / (np.diff(ts) * 1e-6)
    for i in range(len(ts) - 1):
        bound = src2.max_image_speed_px_per_s(int(ts[i]), int(ts[i + 1]))
        assert measured2[i] <= bound and bound < 4 * measured2[i], (i, measured2[i], bound)
    # 3) nothing moves: bound 0
    src3 = MitsubaSource(_ball_scene(cam, Trajectory.static((0.0, 0.0, 3.0)), spp=1))
    assert src3.max_image_speed_px_per_s(0, 100_000) == 0.0


def test_texture_needs_uvs():
    cam = CameraSpec(16, 12, 13.0, 13.0, 7.5, 5.5)
    obj = SceneObject("b", MeshSpec("box", extents=(1.0, 1.0, 1.0)), Material(Pattern(checkerboard=(2, 2))),
                      trajectory=Trajectory.static((0.0, 0.0, 3.0)))
    with pytest.raises(ValueError, match="UV"):
        MitsubaSource(Scene("t", 10, cam, (obj,), (Emitter("point", position=(0.0, 0.0, 0.0)),)))


def test_checkerboard_texture_orientation():
    # square (0, 0) (top-left as the camera sees the plane) is 'high'
    cam = CameraSpec(40, 40, 40.0, 40.0, 19.5, 19.5)
    board = SceneObject("b", MeshSpec("plane", size=(2.0, 2.0)), Material(Pattern(0.0)),
                        Emission(Pattern(checkerboard=(2, 2), low=1.0, high=9.0)),
                        trajectory=Trajectory.static((0.0, 0.0, 2.0)))
    img = MitsubaSource(Scene("t", 10, cam, (board,), render=RenderSettings(spp=1))).render(0)
    # the board spans pixels 0..39; quadrant centres at 10 and 30
    assert img[10, 10] == pytest.approx(9.0) and img[30, 30] == pytest.approx(9.0)
    assert img[10, 30] == pytest.approx(1.0) and img[30, 10] == pytest.approx(1.0)


@pytest.mark.parametrize("kind", ["point", "spot", "directional"])
def test_blinking_light_leaves_the_others_alone(kind):
    # regression: equal nested dicts in one mi.load_dict call share one spectrum object, so
    # blinking one light also scaled an equally bright other light
    from hybridhdr.simulate.scene import Blink
    cam = CameraSpec(32, 24, 26.0, 26.0, 15.5, 11.5)
    wall = SceneObject("w", MeshSpec("plane", size=(10.0, 10.0)), trajectory=Trajectory.static((0.0, 0.0, 3.0)))
    steady = Emitter("directional", direction=(0.0, 0.0, 1.0), irradiance=1.0)
    blink = Blink(period_us=400, duty=0.5, off_scale=0.0)
    blinker = {"point": Emitter("point", position=(0.0, 0.0, 0.0), intensity=1.0, blink=blink),
               "spot": Emitter("spot", position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, 1.0), intensity=1.0, blink=blink),
               "directional": Emitter("directional", direction=(0.0, 0.3, 1.0), irradiance=1.0, blink=blink)}[kind]
    src = MitsubaSource(Scene("t", 1000, cam, (wall,), (blinker, steady), RenderSettings(spp=1)))
    on, off = src.render(0), src.render(250)
    # off: only the steady sun, Lambertian rho/pi * E = 0.5/pi everywhere
    assert np.allclose(off, 0.5 / math.pi, rtol=1e-5)
    assert on[12, 16] > off[12, 16] * 1.01 and np.all(on >= off)  # the centre is inside a spot's cone


def _needs_llvm():
    if os.environ.get("HYBRIDHDR_MITSUBA_VARIANT", "llvm").startswith("scalar") or not llvm_available():
        pytest.skip("llvm_ad_mono is not usable here (or scalar_rgb is forced): nothing to compare scalar_rgb with")


def _agreement_scene(spp, seed, area_light):
    cam = CameraSpec(48, 36, 40.0, 40.0, 23.5, 17.5)
    wall = SceneObject("wall", MeshSpec("plane", size=(8.0, 8.0)), Material(Pattern(checkerboard=(4, 4), low=0.2, high=0.8)),
                       trajectory=Trajectory.static((0.0, 0.0, 4.0)))
    ball = SceneObject("ball", MeshSpec("sphere", radius=0.4, subdivisions=3), Material(Pattern(0.6)),
                       Emission(Pattern(3.0), sampling_weight=1.0 if area_light else 0.0),
                       trajectory=Trajectory.static((-0.5, 0.2, 2.5)))
    ems = (Emitter("point", position=(0.5, -1.0, 1.0), intensity=4.0),
           Emitter("spot", position=(-0.5, 0.0, 0.0), look_at=(0.3, 0.0, 4.0), intensity=20.0, cutoff_deg=25),
           Emitter("directional", direction=(0.2, 0.3, 1.0), irradiance=0.5))
    return Scene("agree", 1000, cam, (wall, ball), ems, RenderSettings(spp=spp, seed=seed))


@pytest.mark.parametrize("area_light", [False, True])
def test_variants_agree_within_sampling_noise(area_light):
    # Both variants run the same estimator (one sample of every light per camera sample), with
    # different random streams. Agreement bound, from the Monte-Carlo noise: over K = 8 render
    # seeds per variant, the image means m_v (1728 px x 4 spp each) have seed-to-seed spreads s_v,
    # and |mean_K(m_llvm) - mean_K(m_scalar)| <= 5 sqrt((s_llvm^2 + s_scalar^2) / K) + 1e-5 |mean|
    # (5 sigma of the difference of two means; 1e-5 for float32 and the Rec. 709 RGB -> Y sum).
    # Per pixel, z = |mean difference| / its standard error from the seed spreads: |z| > 4 in at
    # most 0.5 % of the pixels (Student t with ~14 degrees of freedom: 0.13 %), and pixels that no
    # seed changes in either variant (no noise at all) agree to 1e-4.
    _needs_llvm()
    K = 8
    m = {}
    imgs = {}
    for v in ("llvm_ad_mono", "scalar_rgb"):
        runs = [MitsubaSource(_agreement_scene(4, s, area_light), variant=v).render(0) for s in range(K)]
        imgs[v] = (np.mean(runs, axis=0), np.var(runs, axis=0, ddof=1))
        m[v] = np.array([r.mean() for r in runs])
    d = abs(m["llvm_ad_mono"].mean() - m["scalar_rgb"].mean())
    bound = 5 * math.sqrt((m["llvm_ad_mono"].var(ddof=1) + m["scalar_rgb"].var(ddof=1)) / K) + 1e-5 * m["scalar_rgb"].mean()
    assert d <= bound, (d, bound, m)
    (a, va), (b, vb) = imgs["llvm_ad_mono"], imgs["scalar_rgb"]
    se = np.sqrt((va + vb) / K)
    noisy = se > 1e-6 * np.maximum(a, b)
    z = np.abs(a - b)[noisy] / se[noisy]
    assert np.mean(z > 4) <= 0.005, np.sort(z)[-10:]
    np.testing.assert_allclose(b[~noisy], a[~noisy], rtol=1e-4, atol=1e-7)


@pytest.mark.slow
def test_table1_scores_agree_between_variants(monkeypatch):
    # The Table-1 score (AKF linear MSE on the quick paper's two multi-light HDR scenes, 0.15 s)
    # with each variant for render seeds 0, 1, 2. Bound: the two variants' mean scores differ by
    # at most 5 sqrt((s_llvm^2 + s_scalar^2) / 3) + 1 % of the score, s_v the seed-to-seed spread
    # (the renderer's Monte-Carlo noise as seen by the score; 1 %: with delta lights the noise is
    # anti-aliasing only and three seeds can underestimate its spread).
    _needs_llvm()
    import hybridhdr.simulate.builtin as B
    from hybridhdr.evaluate.bench import parse_bench, run_bench
    real = B.builtin_scene
    render_seed = {"s": 0}
    monkeypatch.setattr(B, "builtin_scene", lambda *a, **k: real(*a, **k).with_changes(seed=render_seed["s"]))
    common = {"width": 48, "height": 36, "duration_us": 150_000, "hdr_rate_hz": 50.0, "sensor": "clean",
              "sampling": {"mode": "fixed", "fixed_rate_hz": 500.0}, "camera": {"exposure_us": 10_000}}
    # no JOD: the score compared is the MSE (JOD was most of the bench's time, on 12 runs x 8 frames)
    spec = {"bench": {"name": "agree", "seed": 0, "jod": False},
            "datasets": [{"name": f"HDR:{s}", "kind": "builtin", "scene": s, **common}
                         for s in ("night_drive_sign", "fast_object_bright_background")],
            "methods": [{"name": "akf", "method": "akf"}]}
    score = {}
    for v in ("llvm_ad_mono", "scalar_rgb"):
        monkeypatch.setenv("HYBRIDHDR_MITSUBA_VARIANT", v)
        score[v] = []
        for s in range(3):
            render_seed["s"] = s
            rows = run_bench(parse_bench(spec), workers=0, progress=False)
            assert all(r["status"] == "ok" for r in rows), rows
            score[v].append(float(np.mean([float(r["mse"]) for r in rows])))
    a, b = np.array(score["llvm_ad_mono"]), np.array(score["scalar_rgb"])
    bound = 5 * math.sqrt((a.var(ddof=1) + b.var(ddof=1)) / 3) + 0.01 * a.mean()
    assert abs(a.mean() - b.mean()) <= bound, (score, bound)


def test_cuda_variant_chosen_when_a_gpu_renders(fresh_choice, capsys):
    """With an NVIDIA driver and a passing CUDA test render, cuda_ad_mono is chosen (before LLVM is
    even asked), remembered on disk; a failing CUDA probe falls back to the LLVM/scalar choice with
    one line saying why."""
    fresh_choice.delenv("HYBRIDHDR_MITSUBA_CUDA")
    fresh_choice.setattr(R, "_cuda_driver_present", lambda: True)
    calls = []
    fresh_choice.setattr(R, "_probe_cuda", lambda: calls.append(1) or (True, ""))
    fresh_choice.setattr(R, "_drjit_llvm_version", lambda: pytest.fail("LLVM asked"))
    assert select_variant() == "cuda_ad_mono" and R.cuda_available() and len(calls) == 1
    assert select_variant("cuda_ad_mono") == "cuda_ad_mono"
    fresh_choice.setattr(R, "_DECISION", None)  # a new process: read from disk
    assert select_variant() == "cuda_ad_mono" and len(calls) == 1
    assert capsys.readouterr().err == ""
    # the probe fails: the LLVM choice, and one line naming the CUDA failure
    fresh_choice.setattr(R, "_DECISION", None)
    fresh_choice.setenv("HYBRIDHDR_VARIANT_CACHE", "0")
    fresh_choice.setattr(R, "_probe_cuda", lambda: (False, "the CUDA test render failed (exit code 1: jit_cuda_init)"))
    fresh_choice.setattr(R, "_drjit_llvm_version", lambda: (19, 1, 7))
    fresh_choice.setattr(R, "_probe_llvm", lambda: (True, ""))
    assert select_variant() == "llvm_ad_mono" and not R.cuda_available()
    assert "jit_cuda_init" in capsys.readouterr().err
    with pytest.raises(ImportError, match="cuda_ad_mono"):
        select_variant("cuda_ad_mono")
    # no driver: no CUDA probe at all
    fresh_choice.setattr(R, "_DECISION", None)
    fresh_choice.setattr(R, "_cuda_driver_present", lambda: False)
    fresh_choice.setattr(R, "_probe_cuda", lambda: pytest.fail("probed CUDA"))
    assert select_variant() == "llvm_ad_mono"
