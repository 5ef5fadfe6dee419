"""The README's short tour runs verbatim on the sample data (../shared/data; skipped when absent).

The first ``sh`` block under "## A short tour" is run line by line through ``hybridhdr.cli.main``
(the words as a shell would split them, comments dropped) from a folder whose ``../shared/data``
is the sample data, as it is from the repository root. The "Longer runs" block is only parsed.
"""

from __future__ import annotations

import os
import re
import shlex

import pytest

from hybridhdr.cli import build_parser, main

from .conftest import REPO_ROOT, SHARED_DATA


def _blocks():
    text = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
    tour = text[text.index("## A short tour"):]
    return re.findall(r"```sh\n(.*?)```", tour, flags=re.S)


def _commands(block):
    for line in block.splitlines():
        for part in line.split("&&"):
            argv = shlex.split(part, comments=True)
            if argv:
                assert argv[0] == "hybridhdr", line
                yield part.strip(), argv[1:]


def test_readme_tour_runs_verbatim(tmp_path, capsys, monkeypatch):
    if not SHARED_DATA.is_dir():
        pytest.skip(f"the sample data folder {SHARED_DATA} is absent (../shared/data beside the repository)")
    (tmp_path / "shared").mkdir()
    os.symlink(SHARED_DATA, tmp_path / "shared" / "data")
    repo = tmp_path / "repo"
    repo.mkdir()
    monkeypatch.chdir(repo)
    cmds = list(_commands(_blocks()[0]))
    assert len(cmds) >= 10
    for line, argv in cmds:
        rc = main(argv)
        out = capsys.readouterr()
        assert rc == 0, f"{line}\n{out.err}"
        if argv[0] == "convert" and "--start" in argv:
            from hybridhdr.formats.container import RecordingFile
            with RecordingFile(repo / argv[2]) as r:
                assert len(r.events()) == 521_252, "convert --start 0 --end 1s keeps the whole 96 ms file"
            assert "521,252 events" in out.out
    assert (repo / "clip.mp4").stat().st_size > 0 and (repo / "clip.png").exists()
    assert (repo / "video" / "preview.mp4").exists() and (repo / "crf" / "camera_profile.json").exists()


def test_readme_longer_runs_parse():
    blocks = _blocks()
    assert len(blocks) >= 2
    p = build_parser()
    for line, argv in _commands(blocks[1]):
        args = p.parse_args(argv)
        assert getattr(args, "func", None) is not None, line
