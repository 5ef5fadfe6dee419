"""The one atomic writer: files and folders appear complete or not at all, with the umask's mode."""

from __future__ import annotations

import json
import os
import stat

import pytest

from hybridhdr._util.atomic import AtomicFolder, atomic_folder, atomic_path, write_json_atomic, write_text_atomic


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    yield
    os.umask(old)


def _mode(p) -> int:
    return stat.S_IMODE(os.stat(p).st_mode)


def test_atomic_path_renames_on_success_with_the_umask_mode(tmp_path, umask_027):
    target = tmp_path / "sub" / "a.png"
    with atomic_path(target, ".png") as tmp:
        assert tmp.parent == target.parent and tmp.name.endswith(".partial.png") and not target.exists()
        tmp.write_bytes(b"x")
    assert target.read_bytes() == b"x"
    assert _mode(target) == 0o640  # 0o666 & ~0o027, not mkstemp's 0o600
    assert os.listdir(target.parent) == ["a.png"]


def test_atomic_path_keeps_the_old_file_and_leaves_nothing_on_error(tmp_path):
    target = tmp_path / "r.json"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert target.read_text() == "old" and os.listdir(tmp_path) == ["r.json"]


def test_text_and_json(tmp_path):
    assert write_text_atomic(tmp_path / "t.md", "é\n").read_text(encoding="utf-8") == "é\n"
    p = write_json_atomic(tmp_path / "j.json", {"a": [1, 2]})
    assert p.read_text(encoding="utf-8") == '{\n "a": [\n  1,\n  2\n ]\n}\n' and json.loads(p.read_text()) == {"a": [1, 2]}


def test_atomic_folder(tmp_path, umask_027):
    out = tmp_path / "set"
    (tmp_path / "set.partial").mkdir()  # not made by hybridhdr (no marker): refused, never deleted
    (tmp_path / "set.partial" / "junk").write_text("x")
    with pytest.raises(FileExistsError, match="never deleted"):
        with atomic_folder(out):
            pass
    assert (tmp_path / "set.partial" / "junk").read_text() == "x"
    (tmp_path / "set.partial" / ".hybridhdr-partial").write_text("pid 1 host h\n")  # ours, no live writer: stale
    with atomic_folder(out) as tmp:
        assert tmp == tmp_path / "set.partial" and [p.name for p in tmp.iterdir()] == [".hybridhdr-partial"]
        (tmp / "a.txt").write_text("a")
    assert sorted(os.listdir(tmp_path)) == ["set"] and (out / "a.txt").read_text() == "a"
    assert _mode(out) == 0o750
    with pytest.raises(ValueError):
        with atomic_folder(tmp_path / "bad") as tmp:
            (tmp / "b").write_text("b")
            raise ValueError("bad image")
    assert sorted(os.listdir(tmp_path)) == ["set"]


def test_atomic_folder_replaces_an_empty_folder_only(tmp_path):
    (tmp_path / "e").mkdir()
    with atomic_folder(tmp_path / "e") as tmp:
        (tmp / "f").write_text("1")
    assert os.listdir(tmp_path / "e") == ["f"]
    with pytest.raises(OSError):  # not empty: nothing is overwritten, the partial folder is removed
        with atomic_folder(tmp_path / "e") as tmp:
            (tmp / "g").write_text("2")
    assert os.listdir(tmp_path / "e") == ["f"] and sorted(os.listdir(tmp_path)) == ["e"]


def test_atomic_folder_object_overwrites_only_its_outputs(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "frame_000000.exr").write_text("old")
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty"):
        AtomicFolder(out, outputs=("frame_*.exr",), command="reconstruct")
    f = AtomicFolder(out, outputs=("frame_*.exr", "run.json"), command="reconstruct", overwrite=True)
    assert f.path == tmp_path / "o.partial"
    (f.path / "frame_000001.exr").write_text("new")
    (f.path / "run.json").write_text("{}")
    f.commit()
    assert sorted(os.listdir(out)) == ["frame_000001.exr", "notes.txt", "run.json"]
    assert not (tmp_path / "o.partial").exists()
    g = AtomicFolder(tmp_path / "p", outputs=(), command="x")
    g.abort()
    assert not (tmp_path / "p.partial").exists() and not (tmp_path / "p").exists()
