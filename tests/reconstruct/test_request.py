"""The request the reconstruct driver takes: public signatures kept, one frozen validated request,
no keyword bag between the public functions and the drivers, short driver functions."""

from __future__ import annotations

import ast
import dataclasses
import inspect
from pathlib import Path

import numpy as np
import pytest

from hybridhdr.reconstruct import api
from hybridhdr.reconstruct.methods import METHODS, MethodSpec, method_spec, methods_with
from hybridhdr.reconstruct.request import Device, ReconstructRequest

API_FILE = Path(api.__file__)

#: The public signatures as they were before the request existed (users' code calls them).
RECONSTRUCT_SIGNATURE = (
    "(source, method: 'str' = 'akf', params=None, *, times_us=None, fps: 'float | None' = None, mode: 'str' = "
    "'offline', profile=None, t_start_us: 'int | None' = None, t_end_us: 'int | None' = None, n_workers: 'int' = "
    "1, chunk_events: 'int' = 1048576, measurements=None, progress: 'Callable[[int], None] | None' = None, "
    "augment=None, thresholds=None, cfa=None, demosaic: 'str' = 'log_cubic', frame_time_offset_us: 'int' = 0, "
    "device: 'str' = 'cpu') -> 'Video'")
RECONSTRUCT_ITER_SIGNATURE = (
    "(source, method: 'str' = 'akf', params=None, *, times_us=None, fps: 'float | None' = None, mode: 'str' = "
    "'offline', profile=None, t_start_us: 'int | None' = None, t_end_us: 'int | None' = None, n_workers: 'int' = "
    "1, chunk_events: 'int' = 1048576, measurements=None, progress: 'Callable[[int], None] | None' = None, "
    "info: 'dict | None' = None, augment=None, thresholds=None, cfa=None, demosaic: 'str' = 'log_cubic', "
    "frame_time_offset_us: 'int' = 0, device: 'str' = 'cpu') -> 'Iterator[tuple[int, np.ndarray]]'")

PUBLIC = {"reconstruct", "reconstruct_iter"}


def test_public_signatures_are_unchanged():
    assert str(inspect.signature(api.reconstruct)) == RECONSTRUCT_SIGNATURE
    assert str(inspect.signature(api.reconstruct_iter)) == RECONSTRUCT_ITER_SIGNATURE


def test_the_request_takes_every_public_argument():
    """ReconstructRequest.build takes exactly reconstruct()'s arguments but the source."""
    got = set(inspect.signature(ReconstructRequest.build).parameters)
    want = set(inspect.signature(api.reconstruct).parameters) - {"source"}
    assert got == want


def _functions(tree):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node


def _n_params(fn) -> int:
    a = fn.args
    n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)
    return n - (1 if a.args and a.args[0].arg in ("self", "cls") else 0)


def test_api_functions_are_short_and_take_few_parameters():
    """Every function in reconstruct/api.py but the two public ones: <= 6 parameters, <= 80 lines."""
    tree = ast.parse(API_FILE.read_text(encoding="utf-8"))
    bad = []
    for fn in _functions(tree):
        if fn.name in PUBLIC:
            continue
        lines = fn.end_lineno - fn.lineno + 1
        if _n_params(fn) > 6 or lines > 80:
            bad.append(f"{fn.name}: {_n_params(fn)} parameters, {lines} lines")
    assert not bad, bad


def test_the_checker_counts_what_it_should():
    """The counting above on literals: a 7-parameter function and a long one are caught."""
    src = "def f(a, b, c, d, e, f, g):\n    pass\n\ndef g(self, *args, **kw):\n" + "    x = 1\n" * 90
    fns = {fn.name: fn for fn in _functions(ast.parse(src))}
    assert _n_params(fns["f"]) == 7
    assert _n_params(fns["g"]) == 2 and fns["g"].end_lineno - fns["g"].lineno + 1 == 91


def test_no_keyword_bag_between_public_functions_and_drivers():
    """No ``**kw`` parameter or ``**name`` call argument in api.py's functions (the request
    carries the arguments)."""
    tree = ast.parse(API_FILE.read_text(encoding="utf-8"))
    bags = [fn.name for fn in _functions(tree) if fn.args.kwarg is not None]
    splats = [f"line {n.lineno}" for n in ast.walk(tree) if isinstance(n, ast.Call)
              for k in n.keywords if k.arg is None and not _is_overrides_call(k.value)]
    assert not bags and not splats, (bags, splats)


def _is_overrides_call(node) -> bool:
    """``p.replace(**got.overrides())`` (or a comprehension over them that keeps the fields ``p``
    has): the resolver's field overrides, not an argument bag."""
    if isinstance(node, ast.DictComp):
        return any(isinstance(n, ast.Call) and getattr(n.func, "attr", "") == "overrides" for n in ast.walk(node))
    return isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "overrides"


def test_the_public_functions_build_the_request_once():
    tree = ast.parse(API_FILE.read_text(encoding="utf-8"))
    for fn in _functions(tree):
        if fn.name in PUBLIC:
            calls = [n for n in ast.walk(fn) if isinstance(n, ast.Call) and getattr(n.func, "attr", "") == "build"]
            assert len(calls) == 1, fn.name


def test_request_is_frozen_and_grouped():
    req = ReconstructRequest.build("hpf", {"cutoff_hz": 2.0}, fps=50.0, t_start_us=10, mode="causal",
                                   frame_time_offset_us=-3)
    assert req.run.method == "highpass" and req.run.mode == "causal" and req.run.params.cutoff_hz == 2.0
    assert req.run.device == Device("cpu", "device: cpu (requested)")
    assert req.output.fps == 50.0 and req.output.t_start_us == 10 and req.output.times_us is None
    assert req.reading.frame_time_offset_us == -3 and req.reading.thresholds is None
    assert not req.reading.thresholds_stated
    for obj, name in ((req, "run"), (req.run, "mode"), (req.output, "fps"), (req.reading, "cfa")):
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, name, None)


@pytest.mark.parametrize("kw, exc, msg", [
    ({"mode": "sideways"}, ValueError, "mode must be one of"),
    ({"n_workers": 0}, ValueError, "n_workers must be an int >= 1"),
    ({"chunk_events": True}, ValueError, "chunk_events must be an int >= 1"),
    ({"t_start_us": 1.5}, TypeError, "t_start_us must be an int"),
    ({"frame_time_offset_us": 2.0}, TypeError, "frame_time_offset_us must be an int"),
    ({"device": "gpu"}, ValueError, "device must be one of"),
    ({"thresholds": object()}, TypeError, "thresholds must be a threshold map"),
    ({"augment": 3}, TypeError, "augment must be AugmentParams"),
])
def test_build_raises_the_messages_reconstruct_raises(kw, exc, msg):
    with pytest.raises(exc, match=msg):
        ReconstructRequest.build("akf", **kw)
    rec = _tiny()
    with pytest.raises(exc, match=msg):
        api.reconstruct(rec, "akf", **kw)


def test_thresholds_stated_follows_the_params():
    assert ReconstructRequest.build("akf", {"contrast_threshold_on": 0.2}).reading.thresholds_stated
    assert not ReconstructRequest.build("akf", {"process_noise_per_s": 1e-3}).reading.thresholds_stated
    assert ReconstructRequest.build("akf", api.make_params("akf")).reading.thresholds_stated
    req = ReconstructRequest.build("cf", thresholds=(np.full((2, 3), 0.2), np.full((2, 3), 0.3)))
    assert req.reading.thresholds.source == "map" and req.reading.thresholds.maps[1][0, 0] == 0.3


def test_method_registry_names_its_capabilities():
    assert all(isinstance(s, MethodSpec) and s.name == n for n, s in METHODS.items())
    assert methods_with(cuda_engine=True) == ("akf", "cf", "highpass", "direct")
    assert methods_with(takes_thresholds=True) == ("akf", "cf", "highpass", "direct")
    assert methods_with(uses_events=False) == ("frames_zoh", "frames_linear")
    assert set(methods_with(needs_frames=False)) == {"highpass", "e2vid", "firenet"}
    assert method_spec("hpf") is METHODS["highpass"] and METHODS["highpass"].events_only
    # the scalar thresholds a method takes are exactly the fields of its parameters
    for s in METHODS.values():
        assert s.takes_thresholds == hasattr(s.params_class(), "contrast_threshold_on"), s.name


def _tiny():
    from hybridhdr.simulate.procedural import edge_sweep_recording
    from hybridhdr.events import SensorSize
    return edge_sweep_recording(0, sensor_size=SensorSize(8, 12), duration_us=150_000)[0]


def test_frames_shifted_is_the_one_frame_time_shift():
    """The API's frame time offset and self-calibration's apply_time_offset shift the frames the
    same way (Frames.shifted), events untouched."""
    from hybridhdr.calibrate.selfcal import apply_time_offset
    rec = _tiny()
    fr = rec.frames.shifted(1234)
    assert np.array_equal(fr.t_start_us, rec.frames.t_start_us + 1234)
    assert np.array_equal(fr.t_end_us, rec.frames.t_end_us + 1234) and fr.images is rec.frames.images
    assert rec.frames.shifted(0) is rec.frames
    sh = apply_time_offset(rec, 1234)
    assert np.array_equal(sh.frames.t_start_us, fr.t_start_us) and sh.events is rec.events
    with pytest.raises(TypeError, match="dt_us must be an int"):
        rec.frames.shifted(1.5)
    a = api.reconstruct(rec, "akf", mode="causal", frame_time_offset_us=1234)
    b = api.reconstruct(sh, "akf", mode="causal", times_us=a.t_us)
    assert a.info["frame_time_offset_us"] == 1234
    assert np.array_equal(a.frames, b.frames)
