"""Exit statuses over the verbs: usage errors exit 2 everywhere (the README's promise), whether
argparse finds them (an unknown choice) or the command does once it has read its input (a method
or verb that needs frames given a recording without them, an unknown method in a comma list);
errors of the data exit 1."""

import pytest

from hybridhdr.cli import main


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    import hybridhdr as hh
    from hybridhdr.formats.container import write_recording
    from hybridhdr.simulate.procedural import procedural_recording
    d = tmp_path_factory.mktemp("exit")
    rec, _ = procedural_recording((20, 30), 300_000, seed=0)
    write_recording(rec, d / "hybrid.h5")
    write_recording(hh.Recording(events=rec.events, sensor_size=rec.sensor_size), d / "events_only.h5")
    (d / "junk.bin").write_bytes(b"\x01\x02 not an event file " * 8)
    return d


NEEDS_FRAMES = [
    ("reconstruct", "{events_only}", "--method", "akf", "--out", "{out}"),
    ("evaluate", "holdout", "{events_only}"),
    ("evaluate", "overexpose", "{events_only}", "--out", "{out}"),
    ("calibrate", "thresholds", "{events_only}", "--out", "{out}.npz"),
    ("calibrate", "sensor", "{events_only}", "--out", "{out}.json"),
]

UNKNOWN_METHOD = [
    ("reconstruct", "{hybrid}", "--method", "bogus", "--out", "{out}"),
    ("evaluate", "holdout", "{hybrid}", "--method", "akf,bogus"),
    ("evaluate", "overexpose", "{hybrid}", "--method", "bogus", "--out", "{out}"),
    ("evaluate", "overexpose", "{hybrid}", "--method", "highpass", "--out", "{out}"),  # takes no frames
    ("calibrate", "crf", "{hybrid}", "--method", "bogus", "--out", "{out}"),
]


def _run(capsys, recordings, tmp_path, argv):
    fill = {"events_only": recordings / "events_only.h5", "hybrid": recordings / "hybrid.h5",
            "junk": recordings / "junk.bin", "out": tmp_path / "out"}
    rc = main([a.format(**fill) for a in argv] + ["--no-progress"])
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("argv", NEEDS_FRAMES, ids=lambda a: " ".join(a[:2]))
def test_needs_frames_is_a_usage_error(capsys, recordings, tmp_path, argv):
    rc, err = _run(capsys, recordings, tmp_path, argv)
    assert rc == 2, err
    assert "frame" in err and "error:" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", UNKNOWN_METHOD, ids=lambda a: " ".join(a[:2] + a[-3:-2]))
def test_unknown_or_unsuitable_method_is_a_usage_error(capsys, recordings, tmp_path, argv):
    rc, err = _run(capsys, recordings, tmp_path, argv)
    assert rc == 2, err
    assert "bogus" in err or "takes no frames" in err


@pytest.mark.parametrize("argv", [("info", "{junk}"), ("reconstruct", "{junk}", "--out", "{out}"),
                                  ("evaluate", "holdout", "{junk}")], ids=lambda a: a[0] + " " + a[1])
def test_bad_data_exits_1(capsys, recordings, tmp_path, argv):
    rc, err = _run(capsys, recordings, tmp_path, argv)
    assert rc == 1, err


@pytest.mark.parametrize("argv", [("reconstruct", "{hybrid}", "--out", "{out}"),
                                  ("evaluate", "overexpose", "{hybrid}", "--out", "{out}")],
                         ids=lambda a: " ".join(a[:2]))
def test_a_non_empty_out_is_a_usage_error(capsys, recordings, tmp_path, argv):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "mine.txt").write_text("keep")
    rc, err = _run(capsys, recordings, tmp_path, argv)
    assert rc == 2 and "not empty" in err and "--overwrite" in err, err
    assert (tmp_path / "out" / "mine.txt").read_text() == "keep"


def test_refuse_existing_output_is_a_usage_error(tmp_path):
    from hybridhdr._util.atomic import refuse_existing_output
    from hybridhdr.errors import UsageError
    f = tmp_path / "x.h5"
    f.write_bytes(b"mine")
    with pytest.raises(UsageError, match="--overwrite"):
        refuse_existing_output(f, overwrite=False, command="convert")
