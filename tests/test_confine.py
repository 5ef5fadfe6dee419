"""Scene and bench files touch only their own folder unless the user allows more (docs/security.md)."""

from __future__ import annotations

import os

import pytest

from hybridhdr._util.confine import OutsideFolderError, confine


def test_confine_resolves_relative_dotdot_and_symlinks(tmp_path):
    base = tmp_path / "bench"
    (base / "data").mkdir(parents=True)
    (tmp_path / "secret").write_text("x")
    assert confine("data/r.h5", base, what="k") == (base / "data" / "r.h5").resolve()
    assert confine(str(base / "data"), base, what="k") == (base / "data").resolve()
    with pytest.raises(OutsideFolderError, match=r"k = '\.\./secret' resolves to .*secret.*outside the file's folder"):
        confine("../secret", base, what="k")
    os.symlink(tmp_path / "secret", base / "link")  # a link inside pointing out is outside
    with pytest.raises(OutsideFolderError, match="--allow-outside"):
        confine("link", base, what="k", source="b.toml")
    assert confine("link", base, [tmp_path], what="k") == (tmp_path / "secret").resolve()
    with pytest.raises(OutsideFolderError):  # an allowed folder that does not hold it
        confine("../secret", base, [base / "data"], what="k")
    with pytest.raises(ValueError, match="expected a file or folder path"):
        confine(3, base, what="k")


def _scene_toml(extra: str) -> str:
    return ('name = "s"\nduration_us = 100000\n[camera]\nwidth = 8\nheight = 6\nfov_deg = 60\n'
            '[[emitters]]\ntype = "point"\nposition = [0, 1, 0]\nintensity = 1.0\n' + extra)


def test_scene_files_outside_the_scene_folder_need_allow_outside(tmp_path):
    pytest.importorskip("trimesh")
    from hybridhdr.simulate.scene import load_scene
    d = tmp_path / "scene"
    d.mkdir()
    (tmp_path / "tex.png").write_bytes(b"not read at load time")
    obj = ('[[objects]]\nname = "p"\nmesh = { type = "plane", size = [1, 1] }\n'
           'material = { reflectance = { texture = "../tex.png" } }\n')
    (d / "a.toml").write_text(_scene_toml(obj))
    with pytest.raises(OutsideFolderError, match=r"objects\[0\]\.material texture = '\.\./tex\.png'"):
        load_scene(d / "a.toml")
    assert load_scene(d / "a.toml", allow_outside=[tmp_path]).objects[0].material.reflectance.texture == "../tex.png"
    mesh = tmp_path / "m.ply"  # an absolute path outside the scene's folder
    (d / "b.toml").write_text(_scene_toml(f'[[objects]]\nname = "m"\nmesh = {{ type = "file", path = "{mesh}" }}\n'))
    with pytest.raises(OutsideFolderError, match=r"objects\[0\]\.mesh\.path"):
        load_scene(d / "b.toml")
    # the calibration is read while the scene is built: refused before it is opened
    cal = tmp_path / "cal.json"
    (d / "c.toml").write_text(_scene_toml("").replace("fov_deg = 60\n", f'calibration = "{cal}"\n'))
    with pytest.raises(OutsideFolderError, match=r"camera\.calibration = '.*cal\.json'"):
        load_scene(d / "c.toml")


def test_simulate_cli_refuses_and_allows(tmp_path, capsys):
    pytest.importorskip("trimesh")
    from hybridhdr.cli import main
    d = tmp_path / "scene"
    d.mkdir()
    (tmp_path / "m.foo").write_text("a mesh in a format trimesh does not know\n")
    (d / "b.toml").write_text(_scene_toml('[[objects]]\nname = "m"\nmesh = { type = "file", path = "../m.foo" }\n'))
    assert main(["simulate", str(d / "b.toml"), "--out", str(tmp_path / "o.h5")]) == 1
    err = capsys.readouterr().err
    assert "outside the file's folder" in err and "--allow-outside" in err and "Traceback" not in err
    assert not (tmp_path / "o.h5").exists()
    # allowed: the next check (an unknown mesh format) is what stops it, as a clean error
    assert main(["simulate", str(d / "b.toml"), "--out", str(tmp_path / "o.h5"), "--allow-outside",
                 str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "not one trimesh reads" in err and "outside" not in err


def _bench_toml(ds_extra: str = "", bench_extra: str = "", method_extra: str = "") -> str:
    return (f'[bench]\nname = "t"\nwarmup = false\nstrips = 0\njod = false\n{bench_extra}'
            f'[[datasets]]\nname = "d"\nkind = "file"\npath = "rec.h5"\n{ds_extra}'
            f'[[methods]]\nmethod = "akf"\n{method_extra}')


def test_bench_files_are_confined_and_never_name_code(tmp_path):
    from hybridhdr.evaluate import bench as B
    d = tmp_path / "b"
    d.mkdir()
    f = d / "b.toml"
    f.write_text(_bench_toml())
    b = B.load_bench(f)
    assert b.datasets[0]["path"] == str((d / "rec.h5").resolve())  # relative to the bench file, not the cwd
    f.write_text(_bench_toml().replace('"rec.h5"', '"../rec.h5"'))
    with pytest.raises(OutsideFolderError, match=r"datasets\[0\]\.path = '\.\./rec\.h5'"):
        B.load_bench(f)
    assert B.load_bench(f, allow_outside=[tmp_path]).datasets[0]["path"] == str((tmp_path / "rec.h5").resolve())
    f.write_text(_bench_toml(ds_extra=f'profile = "{tmp_path / "x.json"}"\n'))
    with pytest.raises(OutsideFolderError, match=r"datasets\[0\]\.profile"):
        B.load_bench(f)
    # the cache may be written in the bench's folder or under --out, nowhere else
    f.write_text(_bench_toml(bench_extra=f'cache_dir = "{tmp_path / "elsewhere"}"\n'))
    with pytest.raises(OutsideFolderError, match=r"\[bench\]\.cache_dir"):
        B.load_bench(f)
    out = tmp_path / "out"
    f.write_text(_bench_toml(bench_extra=f'cache_dir = "{out / "cache"}"\n'))
    assert B.load_bench(f, out_dir=out).cache_dir == str((out / "cache").resolve())
    f.write_text(_bench_toml(bench_extra='hdrvdp_dir = "."\n'))
    with pytest.raises(ValueError, match=r"hdrvdp_dir is not accepted in a bench file.*--hdrvdp-dir"):
        B.load_bench(f)
    f.write_text(_bench_toml(method_extra='params = { allow_pickle = true }\n'))
    with pytest.raises(ValueError, match="allow_pickle is not accepted in a bench file"):
        B.load_bench(f)
    # a dict from Python is trusted code: not confined
    hv = str(tmp_path / "hdrvdp")
    assert B.parse_bench({"bench": {"hdrvdp_dir": hv}, "datasets": [{"kind": "file", "path": str(tmp_path / "r.h5")}],
                          "methods": [{"method": "akf"}]}).hdrvdp_dir == hv


def test_bench_cli_allow_outside(tmp_path, capsys):
    from hybridhdr.cli import main
    d = tmp_path / "b"
    d.mkdir()
    (d / "b.toml").write_text(_bench_toml().replace('"rec.h5"', '"../rec.h5"'))
    assert main(["evaluate", "bench", str(d / "b.toml"), "--out", str(tmp_path / "o"), "--workers", "0"]) == 1
    err = capsys.readouterr().err
    assert "outside the file's folder" in err and "Traceback" not in err
