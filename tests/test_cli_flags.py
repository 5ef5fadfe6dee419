"""One flag vocabulary across verbs (issue 31, item 4), checked by introspecting the parsers.

The table below is the contract: for each shared flag, the verbs that take it. Each verb's
argparse parser is found in ``build_parser()`` and its action for the flag is checked (same
spellings, same type, same meaning), so a verb that drifts (a new ``--from`` only, a
``--thresholds`` with other choices) fails here.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from hybridhdr.calibrate.resolve import DEFAULT_THRESHOLDS, THRESHOLD_WORDS, thresholds_arg
from hybridhdr.cli import build_parser, main

#: verbs x shared flags: which verb takes which flag (every verb that reads a recording file takes
#: --format; --thresholds where a method's contrast thresholds are chosen).
VERBS_FLAGS = {
    ("info",): {"--format"},
    ("convert",): {"--format"},
    ("view",): {"--format"},
    ("reconstruct",): {"--format", "--thresholds"},
    ("evaluate", "holdout"): {"--format", "--thresholds"},
    ("calibrate", "thresholds"): {"--format"},
}

#: A flag's spellings: the first is the name, the others deprecated aliases or v2e's spellings.
SPELLINGS = {"--format": ("--format", "--from"), "--thresholds": ("--thresholds",)}

#: v2e's underscore spellings accepted by simulate, with the hybridhdr name they alias.
V2E_ALIASES = {"--pos_thres": "--pos-thres", "--neg_thres": "--neg-thres", "--sigma_thres": "--sigma-thres",
               "--cutoff_hz": "--cutoff-hz", "--leak_rate_hz": "--leak-rate-hz",
               "--shot_noise_rate_hz": "--shot-noise-rate-hz"}


def _sub(parser, *names):
    for name in names:
        acts = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        assert acts, f"{parser.prog} has no subcommands"
        parser = acts[0].choices[name]
    return parser


def _action(parser, option):
    return parser._option_string_actions.get(option)


@pytest.mark.parametrize("verb", sorted(VERBS_FLAGS), ids=" ".join)
def test_shared_flags_have_one_spelling_and_meaning(verb):
    p = _sub(build_parser(), *verb)
    for flag in ("--format", "--thresholds"):
        a = _action(p, flag)
        if flag not in VERBS_FLAGS[verb]:
            continue
        assert a is not None, f"hybridhdr {' '.join(verb)} lacks {flag}"
        assert tuple(a.option_strings) == SPELLINGS[flag], (verb, a.option_strings)
        assert a.default is None
        if flag == "--format":
            assert a.dest in ("format", "from_format") and a.choices is None
        else:
            assert a.type is thresholds_arg and a.choices is None
            assert all(w in a.help for w in ("FILE", *THRESHOLD_WORDS)) and DEFAULT_THRESHOLDS in a.help
    # the deprecated spelling parses to the same value as the name
    pos = [a for a in p._actions if not a.option_strings and a.required and a.nargs is None]
    argv = [*verb, *(["x"] * len(pos))]
    if any(a.required for a in p._actions if a.option_strings):
        argv += ["--out", "o"]
    top = build_parser()
    a_new = top.parse_known_args([*argv, "--format", "evt3"])[0]
    a_old = top.parse_known_args([*argv, "--from", "evt3"])[0]
    dest = _action(p, "--format").dest
    assert getattr(a_new, dest) == getattr(a_old, dest) == "evt3"


def test_no_verb_has_a_format_flag_of_its_own():
    """Every --from / --format in the whole command tree is the shared one (both spellings)."""
    seen = []

    def walk(parser, path):
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sp in a.choices.items():
                    walk(sp, path + (name,))
            elif {"--from", "--format"} & set(a.option_strings):
                seen.append(path)
                assert tuple(a.option_strings) == ("--format", "--from"), (path, a.option_strings)
    walk(build_parser(), ())
    assert set(VERBS_FLAGS) <= set(seen)


def test_thresholds_words():
    assert thresholds_arg("AUTO") == "auto" and thresholds_arg("input") == "input"
    assert thresholds_arg("params") == "params" and thresholds_arg("t/thresholds.npz") == Path("t/thresholds.npz")


def test_v2e_underscore_spellings_and_seconds():
    p = _sub(build_parser(), "simulate")
    for alias, name in V2E_ALIASES.items():
        assert _action(p, alias) is _action(p, name), alias
    a = build_parser().parse_args(["simulate", "s.toml", "--out", "o.h5", "--pos_thres", "0.3",
                                   "--refractory_period", "0.0005"])
    from hybridhdr.simulate.cli import sensor_params
    sp = sensor_params(a)
    assert sp.contrast_threshold_on == 0.3
    assert sp.refractory_period_us == 500  # v2e's seconds -> µs


def test_format_detection_failure_exits_1_in_every_verb(tmp_path, capsys):
    """The same error, the same exit status: a file whose format cannot be detected exits 1."""
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"junk" * 50)
    cmds = {("info",): [], ("convert",): [str(tmp_path / "o.h5")], ("view",): ["--out", str(tmp_path / "o.mp4")],
            ("reconstruct",): ["--out", str(tmp_path / "r")], ("evaluate", "holdout"): [],
            ("calibrate", "thresholds"): ["--out", str(tmp_path / "t")]}
    assert set(cmds) == set(VERBS_FLAGS)
    for verb, extra in cmds.items():
        rc = main([*verb, str(junk), *extra, "--no-progress"])
        err = capsys.readouterr().err
        assert rc == 1, (verb, err)
        assert "could not detect the event format" in err and "--format NAME" in err, (verb, err)


def test_building_the_parser_imports_no_heavy_module():
    """``hybridhdr --help`` (every command's start) builds the parser without numba, the kernels,
    cv2, h5py or matplotlib: the parts' packages load their modules lazily (benchmarks/cli_start.py
    measures the time)."""
    import subprocess
    import sys
    code = ("import sys, hybridhdr.cli as c; c.build_parser(); "
            "print(','.join(m for m in ('numba', 'cv2', 'h5py', 'matplotlib', 'hybridhdr.reconstruct._kernels', "
            "'hybridhdr.reconstruct.api', 'hybridhdr.evaluate.bench') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
