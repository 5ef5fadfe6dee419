"""``--thresholds`` is one vocabulary: every verb that takes it accepts a map FILE and the same
words, its ``--help`` states the same default, the README and the docs list the same words and
default, and no message still points at the old ``--contrast-threshold auto`` route."""

from __future__ import annotations

import argparse
import re

import numpy as np
import pytest

from hybridhdr.calibrate.resolve import DEFAULT_THRESHOLDS, THRESHOLD_WORDS
from hybridhdr.cli import build_parser, main

from .conftest import REPO_ROOT

VERBS = ("reconstruct", "evaluate holdout", "evaluate overexpose")
WORDS = "FILE|" + "|".join(THRESHOLD_WORDS)


def _leaves(p, path=()):
    subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield " ".join(path), p
    for a in subs:
        for name, child in a.choices.items():
            yield from _leaves(child, path + (name,))


def test_every_verb_takes_the_same_thresholds():
    leaves = dict(_leaves(build_parser()))
    having = sorted(n for n, p in leaves.items() if "--thresholds" in p._option_string_actions)
    assert having == sorted(VERBS)
    helps = set()
    for name in VERBS:
        act = leaves[name]._option_string_actions["--thresholds"]
        assert act.metavar == WORDS, name
        for word in THRESHOLD_WORDS:
            assert act.type(word) == word
        assert str(act.type("map.npz")) == "map.npz", name  # a map file, as reconstruct's
        h = " ".join(act.help.split())
        helps.add(h[:h.index("[default:")] if "[default:" in h else h)
        assert f"[default: {DEFAULT_THRESHOLDS}" in h, name
    assert len(helps) == 1  # the same words, said the same way


def _docs():
    return {p.name: p.read_text(encoding="utf-8") for p in
            (REPO_ROOT / "README.md", REPO_ROOT / "docs" / "reconstruct.md", REPO_ROOT / "docs" / "evaluate.md")}


def test_docs_list_the_same_words_and_default():
    for name, text in _docs().items():
        lists = re.findall(r"--thresholds ((?:[A-Za-z]+\|)+[A-Za-z]+)", text)
        assert lists, name
        for found in lists:
            assert set(found.split("|")) == set(WORDS.split("|")), (name, found)
        flat = " ".join(text.split())
        assert not re.search(r"default\W+`?input`?[,)]", flat), name  # the old default
    assert f"default `{DEFAULT_THRESHOLDS}`" in " ".join(_docs()["README.md"].split())
    assert f"default `{DEFAULT_THRESHOLDS}`" in " ".join(_docs()["reconstruct.md"].split())


def test_default_note_points_at_todays_words(tmp_path, capsys):
    from hybridhdr.formats.container import write_recording
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording((20, 30), 200_000, seed=0)
    p = write_recording(rec, tmp_path / "r.h5")
    assert main(["reconstruct", str(p), "--out", str(tmp_path / "o"), "--thresholds", "input",
                 "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "declares no contrast thresholds" in err
    assert "--contrast-threshold auto" not in err and "--thresholds selfcal" in err


def test_overexpose_takes_a_map_and_uses_it(tmp_path, capsys):
    """A uniform map of the simulated sensor's threshold (0.2) recovers the clipped pixels better
    than one of 0.5: the map reaches the methods. The CLI accepts the map file."""
    import json

    from hybridhdr.evaluate.overexpose import default_specs, evaluate_overexpose
    from hybridhdr.formats.container import write_recording
    from hybridhdr.formats.thresholds import ThresholdMap
    from hybridhdr.simulate.procedural import procedural_recording
    rec, _ = procedural_recording((20, 30), 300_000, contrast_threshold=0.2, seed=0)
    specs, _ = default_specs(["akf"], ["offline"])
    err = {}
    for c in (0.2, 0.5):
        m = ThresholdMap(np.full((20, 30), c), np.full((20, 30), c), c, c)
        g = next(iter(evaluate_overexpose(rec, [1.5], specs, thresholds=m)["by_gain"].values()))
        assert g["counts"]["recoverable_offline"] > 0
        err[c] = g["methods"]["akf"]["log_rmse"]["recoverable_offline"]
    assert err[0.2] < 0.5 * err[0.5], err
    m = ThresholdMap(np.full((20, 30), 0.2), np.full((20, 30), 0.2), 0.2, 0.2)
    mp = m.save(tmp_path / "map.npz")
    src = write_recording(rec, tmp_path / "r.h5")
    rc = main(["evaluate", "overexpose", str(src), "--gain", "1.5", "--method", "akf", "--mode", "offline",
               "--thresholds", str(mp), "--out", str(tmp_path / "oe"), "--no-figures", "--no-progress", "--json"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert json.loads(cap.out)["thresholds"] == f"per-pixel map {mp}"
