"""The CUDA AKF/CF path (``hybridhdr.reconstruct.cuda``) agrees with the CPU path.

The kernels run in Numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``), which has to be set
before Numba is imported: ``cuda_checks.py`` runs in one child process (so the simulator never
leaks into this process's Numba), each check printing one JSON line. Set
``HYBRIDHDR_TEST_CUDA_REAL=1`` to run the same checks on a real GPU instead
(``benchmarks/device_run.sh``). Tolerances and what is compared: ``cuda_checks.py``'s docstring
(float64 L̂ and P within 1e-9 relative; float32 images within 2e-6).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
CHECKS = ["akf_paper_linear", "akf_reference_hold", "akf_discrete_thresholds", "akf_la_step_generic",
          "akf_windows_split", "akf_resident", "akf_resident_chunks", "cf", "cf_adaptive", "cf_generic",
          "cf_resident_chunks", "highpass", "direct", "reconstruct_forward", "reconstruct_causal",
          "reconstruct_two_sided", "reconstruct_two_sided_chunks", "reconstruct_two_sided_per_window",
          "reconstruct_two_sided_spill_stream", "reconstruct_two_sided_augmented", "reconstruct_two_sided_clipped"]
REAL = os.environ.get("HYBRIDHDR_TEST_CUDA_REAL") == "1"


@pytest.fixture(scope="module")
def results():
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    env["PYTHONPATH"] = str(HERE.parents[1]) + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [sys.executable, str(HERE / "cuda_checks.py")] + (["--real"] if REAL else [])
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    lines = [json.loads(s) for s in r.stdout.splitlines() if s.startswith("{")]
    if r.returncode != 0 or not lines:
        pytest.fail(f"cuda_checks.py failed (exit {r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    if "skip" in lines[0]:
        pytest.skip(f"numba.cuda cannot run here: {lines[0]['skip']}")
    return {d["check"]: d for d in lines}


@pytest.mark.slow
@pytest.mark.parametrize("name", CHECKS)
def test_cuda_agrees_with_cpu(results, name):
    d = results.get(name)
    assert d is not None, f"check {name} did not report"
    assert "error" not in d, d.get("trace", d.get("error"))
    assert d["ok"], d
    assert d["max_rel"] <= d["tol"], d


def test_device_resolution():
    """"cpu" never touches numba.cuda; "cuda" without a GPU is a clear error; unknown names are refused."""
    from hybridhdr.reconstruct.cuda import cuda_unavailable_reason
    from hybridhdr.reconstruct.request import Device
    assert Device.resolve("cpu") == Device("cpu", "device: cpu (requested)")
    with pytest.raises(ValueError, match="device must be one of"):
        Device.resolve("gpu")
    d = Device.resolve("auto", "edi")
    assert d.kind == "cpu" and "no CUDA path" in d.line
    why = cuda_unavailable_reason()
    d = Device.resolve("auto")
    assert d.line.startswith(f"device: {d.kind}")
    if why is not None:
        assert d.kind == "cpu" and why in d.line
        with pytest.raises(ValueError, match="device 'cuda' requested but"):
            Device.resolve("cuda")
