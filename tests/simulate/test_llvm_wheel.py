"""The libLLVM for Dr.Jit: the user's DRJIT_LIBLLVM_PATH, else a system libLLVM 17-19, else the
karellen-llvm-core wheel (its libc++ made resolvable when the wheel's symlinks are missing); the
variant line says which and why, or why it fell back to scalar_rgb."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from hybridhdr.simulate import render as R

ROOT = Path(__file__).resolve().parents[2]


def _child(code: str, env_extra=None, drop=("DRJIT_LIBLLVM_PATH",)) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env.update(env_extra or {}, PYTHONPATH=str(ROOT), HYBRIDHDR_VARIANT_CACHE="0")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)


def test_order_user_path_then_system_then_wheel():
    code = """
import os
from hybridhdr.simulate import render as R
R._find_libllvm = lambda: {system!r}
R._wheel_libllvm = lambda: ('/w/lib/libLLVM.so.23.1', '23.1.4')
R._preload_libcxx = lambda p: []
R._prepare_llvm_env()
print(os.environ.get('DRJIT_LIBLLVM_PATH'), '|', R._LLVM_SOURCE)
"""
    r = _child(code.format(system="/usr/lib/x86_64-linux-gnu/libLLVM-19.so.1"))
    assert r.stdout.strip() == ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so.1 | the system's "
                                "/usr/lib/x86_64-linux-gnu/libLLVM-19.so.1"), r.stderr  # apt's libllvm19 first
    r = _child(code.format(system=None))
    assert r.stdout.strip() == "/w/lib/libLLVM.so.23.1 | the karellen-llvm-core 23.1.4 wheel's libLLVM.so.23.1", r.stderr
    r = _child(code.format(system="/x/libLLVM-19.so.1"), {"DRJIT_LIBLLVM_PATH": "/mine/libLLVM.so"}, drop=())
    assert r.stdout.strip() == "/mine/libLLVM.so | DRJIT_LIBLLVM_PATH=/mine/libLLVM.so", r.stderr


def test_scalar_fallback_says_why(monkeypatch):
    monkeypatch.setattr(R, "_DECISION", ("scalar_rgb", "Dr.Jit found no usable libLLVM"))
    monkeypatch.delenv("HYBRIDHDR_MITSUBA_VARIANT", raising=False)
    line = R.variant_reason("scalar_rgb")
    assert line.startswith("scalar_rgb, the slow fallback: Dr.Jit found no usable libLLVM")
    assert "karellen-llvm-core" in line and "libllvm19" in line
    assert R.variant_reason("scalar_rgb", asked="scalar_rgb") == "scalar_rgb, as asked (--variant)"


@pytest.mark.slow
def test_wheel_without_symlinks_loads(tmp_path):
    """The wheel's files copied without their symlinks (as a plain wheel install leaves them): the
    libc++ preload lets Dr.Jit load its libLLVM and a test render pass."""
    w = R._wheel_libllvm()
    if w is None:
        pytest.skip("karellen-llvm-core is not installed (pip install 'hybridhdr[simulate]')")
    path = Path(w[0])
    lib = tmp_path / "lib"
    (lib / "x86_64-unknown-linux-gnu").mkdir(parents=True)
    shutil.copy2(path, lib / path.name)
    arch = next(path.parent.glob("*-linux-gnu"))
    for f in arch.iterdir():
        if f.is_file() and not f.is_symlink() and ".so." in f.name:
            shutil.copy2(f, lib / "x86_64-unknown-linux-gnu" / f.name)
    assert not (lib / "x86_64-unknown-linux-gnu" / "libc++.so.1").exists()
    code = f"""
from hybridhdr.simulate import render as R
loaded = R._preload_libcxx({str(lib / path.name)!r})
import os
os.environ['DRJIT_LIBLLVM_PATH'] = {str(lib / path.name)!r}
print('loaded', len(loaded))
print('LLVM', *R._drjit_llvm_version())
"""
    r = _child(code)
    assert "loaded 3" in r.stdout and f"LLVM {w[1].split('.')[0]}" in r.stdout, (r.stdout, r.stderr)
    # without the preload the same copy cannot be loaded (libc++.so.1 unresolved)
    r = _child(f"""
import os
os.environ['DRJIT_LIBLLVM_PATH'] = {str(lib / path.name)!r}
from hybridhdr.simulate import render as R
print('LLVM', *R._drjit_llvm_version())
""")
    assert "LLVM -1 -1 -1" in r.stdout and "libc++.so.1" in r.stderr, (r.stdout, r.stderr)


@pytest.mark.slow
def test_wheel_gives_llvm_variant():
    if R._wheel_libllvm() is None:
        pytest.skip("karellen-llvm-core is not installed")
    if R._find_libllvm() is not None:
        pytest.skip("a system libLLVM 17-19 is preferred here")
    r = _child("""
from hybridhdr.simulate import render as R
print(R.variant_reason(R.select_variant()))
""")
    assert r.stdout.startswith("llvm_ad_mono: LLVM 23") and "karellen-llvm-core" in r.stdout, (r.stdout, r.stderr)
