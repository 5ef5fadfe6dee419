"""Colour event cameras (issue 16 item 2): the mosaic path of the reconstruction."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hybridhdr.reconstruct import reconstruct
from tests.reconstruct.data.make_mono_reference import RUNS, recordings

REFERENCE = Path(__file__).parent / "data" / "mono_reference.npz"


@pytest.fixture(scope="module")
def mono_recordings():
    return recordings()


@pytest.mark.parametrize("frames_kind", ["grey", "rgb"])
@pytest.mark.parametrize("method,mode,kw", RUNS, ids=[f"{m}-{mo}{'-aug' if kw else ''}" for m, mo, kw in RUNS])
def test_monochrome_outputs_unchanged(mono_recordings, frames_kind, method, mode, kw):
    """No CFA: every method gives, bit for bit, the outputs committed before the colour path
    existed (grey frames, and colour frames reduced to luminance)."""
    rec = mono_recordings[0 if frames_kind == "grey" else 1]
    key = f"{frames_kind}_{method}_{mode}" + ("_aug" if kw else "")
    with np.load(REFERENCE) as ref:
        want, want_t = ref[key], ref[key + "_t"]
    v = reconstruct(rec, method, mode=mode, fps=100, **kw)
    assert v.frames.dtype == np.float32 and v.frames.shape == want.shape
    np.testing.assert_array_equal(v.t_us, want_t)
    assert v.frames.tobytes() == want.tobytes()
