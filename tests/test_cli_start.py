"""``hybridhdr --help`` starts without numpy: the package's top-level names and every verb's heavy
modules load on first use (``benchmarks/cli_start.py`` measures the time)."""

import subprocess
import sys


def _run(code):
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


def test_import_hybridhdr_and_building_the_parser_import_no_numpy():
    assert _run("import sys, hybridhdr; print('numpy' in sys.modules)") == "False"
    assert _run("import sys, hybridhdr.cli as c; c.build_parser(); print('numpy' in sys.modules)") == "False"


def test_help_imports_no_numpy():
    code = ("import sys, contextlib, io\nfrom hybridhdr.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    try: main(['--help'])\n    except SystemExit: pass\n"
            "print('numpy' in sys.modules)")
    assert _run(code) == "False"


def test_top_level_names_still_work_lazily():
    import numpy as np

    import hybridhdr as hh
    for name in hh.__all__:
        assert getattr(hh, name) is not None, name
        assert name in dir(hh)
    ev = hh.make_events(t=[0, 5], x=[1, 2], y=[0, 1], p=[1, -1])
    assert ev.dtype == hh.EVENT_DTYPE and np.array_equal(ev["t"], [0, 5])
    from hybridhdr import Recording, read, write  # noqa: F401  (the README's imports)
    try:
        hh.no_such_name
    except AttributeError as e:
        assert "no_such_name" in str(e)
    else:
        raise AssertionError("an unknown top-level name must raise AttributeError")


def test_exr_compression_names_in_help_match_the_writer():
    """reconstruct's --help lists the EXR compressions without importing OpenEXR; the list is the
    writer's own."""
    from hybridhdr.formats.images import _EXR_COMPRESSION_NAMES
    from hybridhdr.reconstruct.cli import EXR_COMPRESSION_NAMES
    assert tuple(_EXR_COMPRESSION_NAMES) == EXR_COMPRESSION_NAMES


def test_frame_encoding_choices_are_the_camera_models():
    from hybridhdr._util.cliargs import FRAME_ENCODING_CHOICES
    from hybridhdr.camera.encoding import ENCODING_CHOICES, parse_frame_encoding
    assert ENCODING_CHOICES == FRAME_ENCODING_CHOICES
    for name in FRAME_ENCODING_CHOICES:
        parse_frame_encoding(name)
