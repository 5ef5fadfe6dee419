"""cvvdp's torchvision: the real one wherever it loads, else cvvdp_metric's pure-PyTorch stand-in.

Both paths run: the stand-in is forced in a child process (torchvision made unimportable there), and
the real path is checked wherever torchvision loads (torchvision built for this PyTorch: the CPU
index gives matched +cpu builds; PyPI's CUDA-linked torchvision cannot load beside a CPU torch)."""

from __future__ import annotations

import functools
import json
import subprocess
import sys

import pytest

cv = pytest.importorskip("hybridhdr.evaluate.cvvdp_metric")
if not cv.cvvdp_available():
    pytest.skip("cvvdp (ColorVideoVDP) or PyTorch not installed: pip install 'hybridhdr[evaluate]'",
                allow_module_level=True)

_PROBE = """
import json, sys
import numpy as np
if sys.argv[1] == "block":
    sys.modules["torchvision"] = None      # `import torchvision` now fails, as a broken build does
from hybridhdr.evaluate import cvvdp_metric as cv
pycvvdp = cv._import_pycvvdp()
import pycvvdp.cvvdp_metric as m
yy, xx = np.mgrid[0:48, 0:64]
ref = (0.01 + np.exp(3 * np.sin(xx / 9.0) * np.cos(yy / 13.0)) / 20.0)[None].repeat(2, 0)
noisy = ref * np.exp(0.2 * np.random.default_rng(0).standard_normal(ref.shape))
print(json.dumps({"blur": m.GaussianBlur.__module__ + "." + m.GaussianBlur.__qualname__,
                  "same": cv.cvvdp_jod(ref, ref).jod, "noisy": cv.cvvdp_jod(noisy, ref).jod,
                  "left": sorted(k for k in sys.modules if k.startswith("torchvision") and sys.modules[k])}))
"""


def _probe(mode: str) -> dict:
    r = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@functools.lru_cache(maxsize=None)
def _torchvision_loads() -> tuple[bool, str]:
    r = subprocess.run([sys.executable, "-c", "from torchvision.transforms import GaussianBlur"],
                       capture_output=True, text=True, timeout=300)
    return r.returncode == 0, (r.stderr.strip().splitlines() or [""])[-1]


@pytest.mark.slow  # a child process imports PyTorch and cvvdp (about 10 s)
def test_stand_in_path_when_torchvision_cannot_load():
    out = _probe("block")
    assert out["blur"] == "hybridhdr.evaluate.cvvdp_metric._gaussian_blur_class.<locals>.GaussianBlur"
    assert out["same"] == pytest.approx(10.0, abs=1e-4)   # identical inputs: 10 JOD (float32 rounding)
    assert out["noisy"] < 9.9
    assert out["left"] == []   # the stand-in is not left in sys.modules for others to find


@pytest.mark.slow  # a child process imports PyTorch and cvvdp (about 10 s)
def test_real_torchvision_path_wherever_it_loads():
    ok, why = _torchvision_loads()
    if not ok:
        pytest.skip(f"torchvision does not load beside this PyTorch ({why}); the stand-in path serves")
    out = _probe("real")
    assert out["blur"] == "torchvision.transforms.transforms.GaussianBlur"
    assert out["same"] == pytest.approx(10.0, abs=1e-4)
    blocked = _probe("block")   # both paths give the same scores: the stand-in is the same blur
    assert out["noisy"] == pytest.approx(blocked["noisy"], abs=1e-4)


@pytest.mark.slow  # a child process imports PyTorch and cvvdp (about 10 s)
def test_stand_in_blur_equals_torchvision_blur():
    ok, why = _torchvision_loads()
    if not ok:
        pytest.skip(f"torchvision does not load beside this PyTorch ({why})")
    code = """
import numpy as np, torch
from torchvision.transforms import GaussianBlur
from hybridhdr.evaluate.cvvdp_metric import _gaussian_blur_class
x = torch.from_numpy(np.random.default_rng(2).random((2, 3, 40, 52)).astype(np.float32))
err = 0.0
for k, s in ((5, 1.0), (13, 3.0), (9, 2.25)):   # cvvdp's calls: GaussianBlur(int(4*s)+1, s)
    err = max(err, float((GaussianBlur(k, s)(x) - _gaussian_blur_class(torch)(k, s)(x)).abs().max()))
print(err)
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert float(r.stdout.strip().splitlines()[-1]) < 1e-6   # float32 summation order only
