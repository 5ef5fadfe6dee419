"""The README's short tour runs verbatim on the sample data (../shared/data; skipped when absent).

The first ``sh`` block under "## A short tour" is run line by line through ``hybridhdr.cli.main``
(the words as a shell would split them, comments dropped) from a folder whose ``../shared/data``
is the sample data, as it is from the repository root. The "Longer runs" block is only parsed.

It needs nothing beyond what ``make demo`` installs (``hybridhdr[demo]``) and pytest: ``make tour``
runs it in such an environment (``.venv-demo``), so a tour line that needs a test-only extra fails
there instead of being hidden by ``make test``'s extras.
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


def test_readme_python_examples_return_events(tmp_path, monkeypatch):
    """The README's Python block runs on the sparklers sample (its file names mapped to the sample)
    and every window it takes returns events: the sample starts at 913,716,224 µs sensor time, so
    a window counted from 0 used to return nothing, silently."""
    import ast

    import numpy as np

    from .conftest import shared_file
    raw = shared_file("prophesee/sparklers_gen3_evt2.raw")
    text = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
    block = re.findall(r"```python\n(.*?)```", text, flags=re.S)[0]
    src = block.replace('"sparklers.raw"', repr(str(raw))).replace('"big.raw"', repr(str(raw)))
    assert src != block, "the README's Python block no longer reads sparklers.raw"
    monkeypatch.chdir(tmp_path)
    tree = ast.parse(src)
    ns: dict = {}
    windows = 0
    for node in tree.body:  # statement by statement: each window expression is checked
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Call) and \
                getattr(node.value.func, "attr", "") == "slice_time":
            got = eval(compile(ast.Expression(node.value), "README", "eval"), ns)
            assert got.n_events > 0, ast.unparse(node)
            windows += 1
        else:
            exec(compile(ast.Module([node], []), "README", "exec"), ns)
    assert windows >= 2
    assert len(ns["ev"]) > 0 and np.all(np.diff(ns["ev"]["t"]) >= 0)
    a = ns["rec"].slice_time(10_000, 20_000, absolute=False)
    b = ns["rec"].slice_time(913_726_224, 913_736_224)
    assert a.n_events == b.n_events > 0  # the two time bases name the same window


def test_api_window_outside_the_data_names_the_span(tmp_path):
    """A window outside the data raises, naming the span, in every API entry point."""
    import hybridhdr as hh
    from hybridhdr.container import RecordingFile, write_recording
    from hybridhdr.errors import WindowOutsideDataError
    from hybridhdr.events import make_events
    rec = hh.Recording(make_events([1_000_000, 1_000_500, 1_002_000], [0, 1, 2], [0, 0, 0], [1, -1, 1]),
                       hh.SensorSize(4, 4))
    assert rec.data_span_us() == (1_000_000, 1_002_000)
    with pytest.raises(WindowOutsideDataError, match=r"1,000,000\.\.1,002,000 µs.*absolute=False"):
        rec.slice_time(0, 50_000)
    with pytest.raises(WindowOutsideDataError, match="outside the data"):
        rec.slice_time(10_000, None, absolute=False)  # starts after the last event
    assert rec.slice_time(0, 600, absolute=False).n_events == 2
    assert rec.slice_time(1_000_400, 1_000_450).n_events == 0  # inside the data, empty: no error
    p = write_recording(rec, tmp_path / "r.h5")
    with RecordingFile(p) as f:
        assert f.events(500, None, absolute=False)["t"].tolist() == [1_000_500, 1_002_000]
        with pytest.raises(WindowOutsideDataError, match="RecordingFile.events"):
            f.events(0, 50_000)
        with pytest.raises(WindowOutsideDataError):
            list(f.iter_event_columns(2, 3_000_000, None))
        assert f.read(0, 1, absolute=False).n_events == 1
    assert hh.read(p, t_start_us=1_000, absolute=False).n_events == 1
    with pytest.raises(WindowOutsideDataError, match="1,000,000"):
        hh.read(p, t_start_us=0, t_end_us=10)
