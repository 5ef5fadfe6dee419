"""Mitsuba 3.9 rendering of a :class:`~hybridhdr.simulate.scene.Scene` as a radiance source.

:class:`MitsubaSource` implements :class:`hybridhdr.simulate.source.RadianceSource`: it loads the
scene into Mitsuba once, then for each render time moves the camera (``sensor.to_world``),
rewrites the vertex positions of moving objects, rescales blinking emitters through
``mi.traverse`` parameters, and renders with a fixed sampler seed, so a static pixel gets the same
bits in every render (no render-noise events). Output is linear float32 radiance (H, W).

Variants (``docs/simulate.md``, "Rendering"): ``cuda_ad_mono`` when an NVIDIA driver is present and a
test render with it passes in a child process (the GPU); else ``llvm_ad_mono`` when Dr.Jit
loaded libLLVM >= 17 (15/16 abort the process when compiling real scenes' kernels, 14 is refused)
and a test render of the operations real scenes use passes in a child process; otherwise
``scalar_rgb``, whose RGB output is converted to luminance Y = 0.2126 R + 0.7152 G + 0.0722 B
(Rec. ITU-R BT.709 primaries, the sRGB/Rec.709 luminance coefficients). Both render ``direct``
scenes with the same every-light estimator, so they agree within Monte-Carlo noise. The variant in
use is in :meth:`MitsubaSource.describe`.
"""

from __future__ import annotations

import glob
import math
import os
import re
import subprocess
import sys
import time

import numpy as np

from .._util.atomic import atomic_path
from ..events import SensorSize
from .scene import Scene, SceneError
from .scene import look_at_rotation

__all__ = ["MitsubaSource", "select_variant", "variant_reason", "llvm_source", "llvm_available", "LUMINANCE_RGB", "mitsuba_camera_params", "preview_strip"]

#: Rec. ITU-R BT.709 luminance weights used to convert ``scalar_rgb`` renders to radiance.
LUMINANCE_RGB = (0.2126, 0.7152, 0.0722)

_VARIANTS = ("llvm_ad_mono", "scalar_rgb", "llvm_ad_rgb", "cuda_ad_mono")

#: Oldest libLLVM whose code generation the pinned Mitsuba 3.9 / Dr.Jit 1.5 kernels survive: LLVM
#: 15 and 16 abort the process on real scenes ("LLVM ERROR: Cannot select: ... fminimum"), 14 is
#: refused by Dr.Jit itself. A newer LLVM still has to pass the child-process probe.
MIN_LLVM_VERSION = (17, 0, 0)
_FAST_PATH_HINT = ("pip install 'hybridhdr[simulate]' (the karellen-llvm-core LLVM wheel, no root) or apt-get install "
                   "libllvm19 (Debian/Ubuntu) gives the fast llvm_ad_mono variant")
_PROBE_VERSION = 2  # bump when the probe scene changes (invalidates the on-disk decisions)
_DECISION: tuple | None = None  # (variant, reason) of the automatic choice in this process
_IN_PROBE = False  # set in the probe's child process


def _find_libllvm() -> str | None:
    """Path of a libLLVM with major version 17-19 in the system library folders (newest first)."""
    cands = []
    for d in _LIB_DIRS:
        for p in glob.glob(os.path.join(d, "libLLVM*")):
            m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(p))
            if m and 17 <= int(m.group(1)) <= 19:
                cands.append((int(m.group(1)), p))
    return max(cands)[1] if cands else None


_LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
             "/usr/local/lib", "/opt/homebrew/opt/llvm/lib")


#: The pip wheel that ships a libLLVM Dr.Jit can load (Apache-2.0 with LLVM exceptions; the
#: ``simulate`` extra installs it). Its libLLVM needs the libc++ it ships beside it.
LLVM_WHEEL = "karellen-llvm-core"


def _wheel_libllvm() -> tuple[str, str] | None:
    """(path of the wheel's libLLVM.so.N[.M], its version) when :data:`LLVM_WHEEL` is installed,
    located through the distribution's file list (no guessed folders)."""
    try:
        from importlib.metadata import PackageNotFoundError, distribution
        dist = distribution(LLVM_WHEEL)
    except (ImportError, PackageNotFoundError):
        return None
    best = None
    for f in dist.files or ():
        name = f.name
        m = re.fullmatch(r"libLLVM(?:-\d+)?\.so\.(\d+)(?:\.\d+)*", name)
        if m:
            p = str(f.locate())
            if os.path.isfile(p) and not os.path.islink(p):
                best = max(best or (0, ""), (int(m.group(1)), p))
    return (best[1], dist.version) if best else None


def _preload_libcxx(libllvm: str) -> list[str]:
    """Make the wheel's libc++ resolvable for its libLLVM: wheels carry no symlinks, so the
    ``libc++.so.1`` its libLLVM names may be missing (only ``libc++.so.1.0`` installed). Loading the
    versioned files with RTLD_GLOBAL, dependencies first (libunwind, libc++abi, libc++), registers
    their sonames, and the dynamic loader then resolves libLLVM's ``libc++.so.1`` to them. Nothing is
    loaded when the soname file is already there. Returns the files loaded."""
    import ctypes
    dirs = [os.path.dirname(libllvm)] + sorted(glob.glob(os.path.join(os.path.dirname(libllvm), "*-linux-gnu")))
    if any(os.path.exists(os.path.join(d, "libc++.so.1")) for d in dirs):
        return []
    loaded = []
    for stem in ("libunwind.so.1", "libc++abi.so.1", "libc++.so.1"):
        files = sorted(p for d in dirs for p in glob.glob(os.path.join(d, stem + ".*")) if not os.path.islink(p))
        if not files:
            continue
        try:
            ctypes.CDLL(files[0], mode=ctypes.RTLD_GLOBAL)
            loaded.append(files[0])
        except OSError:
            break
    return loaded


#: Where the libLLVM given to Dr.Jit came from (one line; "" before :func:`_prepare_llvm_env`).
_LLVM_SOURCE = ""


def _prepare_llvm_env() -> None:
    """Point Dr.Jit at a libLLVM before drjit is first imported, in this order: the user's own
    ``DRJIT_LIBLLVM_PATH``; a system libLLVM 17-19 (``apt-get install libllvm19``: preferred, the
    version Mitsuba 3.9 is built and tested with); the :data:`LLVM_WHEEL` pip wheel. Without any,
    Dr.Jit picks the last libLLVM*.so.* of the system folder (LLVM 15/16 crash: uncatchable
    SIGABRT, hence the version check and the probe)."""
    global _LLVM_SOURCE
    if "drjit" in sys.modules:
        return
    if "DRJIT_LIBLLVM_PATH" in os.environ:
        if not _LLVM_SOURCE:
            _LLVM_SOURCE = f"DRJIT_LIBLLVM_PATH={os.environ['DRJIT_LIBLLVM_PATH']}"
        return
    p = _find_libllvm()
    if p is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = p
        _LLVM_SOURCE = f"the system's {p}"
        return
    w = _wheel_libllvm()
    if w is not None:
        path, ver = w
        _preload_libcxx(path)
        os.environ["DRJIT_LIBLLVM_PATH"] = path
        _LLVM_SOURCE = f"the {LLVM_WHEEL} {ver} wheel's {os.path.basename(path)}"
        return
    _LLVM_SOURCE = "no libLLVM 17+ (system) and no " + LLVM_WHEEL + " wheel: Dr.Jit searched the system folders"


def _drjit_llvm_version() -> tuple[int, int, int]:
    """Version of the libLLVM Dr.Jit loaded ((-1, -1, -1) when it found none it could use).

    Importing drjit only loads and initialises libLLVM; nothing is compiled, so this cannot
    abort (the LLVM 15/16 crash happens when a kernel is compiled)."""
    _prepare_llvm_env()
    try:
        import drjit
        v = tuple(int(x) for x in drjit.detail.llvm_version())
    except Exception:  # drjit missing, or a drjit without llvm_version()
        return (-1, -1, -1)
    return (v + (0, 0, 0))[:3]


def _fmt_version(v) -> str:
    return ".".join(str(x) for x in v)


# The probe: the operations real scenes use, through MitsubaSource itself (the every-light direct
# integrator and the path integrator, triangle meshes with UVs, bitmap textures, an area light,
# point/spot/directional/constant emitters, blinking, a moving camera and object, hdrfilm with a
# box filter), at 16x12 px, in a child process so that an LLVM abort kills only the child.
_PROBE_CODE = r"""
import sys
import numpy as np
from hybridhdr.simulate import render as R
R._IN_PROBE = True  # take the variant as given (no nested probe)
v = R._drjit_llvm_version()
print('LLVM', *v, flush=True)
if v < R.MIN_LLVM_VERSION and sys.argv[2:] != ['force']:
    sys.exit(3)
from hybridhdr.simulate.scene import (Blink, CameraSpec, Emission, Emitter, Keyframe, Material, MeshSpec, Pattern,
                                      RenderSettings, Scene, SceneObject, Trajectory)
cam = CameraSpec(16, 12, 13.0, 13.0, 7.5, 5.5, Trajectory((Keyframe(0, (0.0, 0.0, 0.0)), Keyframe(1000, (0.1, 0.0, 0.0)))))
blink = Blink(period_us=400, duty=0.5, off_scale=0.1)
objs = (SceneObject('wall', MeshSpec('plane', size=(6.0, 6.0)), Material(Pattern(checkerboard=(4, 4), low=0.2, high=0.8)),
                    trajectory=Trajectory.static((0.0, 0.0, 4.0))),
        SceneObject('ball', MeshSpec('sphere', radius=0.3, subdivisions=2), Material(Pattern(0.5)),
                    Emission(Pattern(2.0), sampling_weight=0.5, blink=blink),
                    trajectory=Trajectory((Keyframe(0, (-0.5, 0.0, 2.5)), Keyframe(1000, (0.5, 0.0, 2.5))))),
        SceneObject('box', MeshSpec('box', extents=(0.4, 0.4, 0.4)), Material(Pattern(0.7)),
                    trajectory=Trajectory.static((0.6, 0.5, 3.0))))
ems = (Emitter('point', position=(0.0, 1.0, 1.0), intensity=3.0, blink=blink),
       Emitter('spot', position=(0.5, 0.0, 0.0), look_at=(0.0, 0.0, 4.0), intensity=5.0),
       Emitter('directional', direction=(0.3, -0.2, 1.0), irradiance=1.0),
       Emitter('constant', radiance=0.01, sampling_weight=0.1))
for integ in ('direct', 'path'):
    sc = Scene('probe', 1000, cam, objs, ems, RenderSettings(spp=2, integrator=integ))
    src = R.MitsubaSource(sc, variant=sys.argv[1])
    for t in (0, 250, 1000):
        a = src.render(t)
        if not (a.shape == (12, 16) and np.isfinite(a).all() and a.max() > 0):
            print('BAD', integ, t, flush=True)
            sys.exit(4)
print('OK', flush=True)
"""


def _cuda_driver_present() -> bool:
    """Whether an NVIDIA driver is visible (device nodes or libcuda), without loading Dr.Jit: the
    CUDA probe's child process is started only then."""
    if os.environ.get("HYBRIDHDR_MITSUBA_CUDA", "1") in ("0", "off", "no"):
        return False
    if os.path.exists("/dev/nvidiactl") or os.path.exists("/dev/nvidia0"):
        return True
    import ctypes.util
    return ctypes.util.find_library("cuda") is not None


def _probe_cuda(timeout_s: float = 180.0) -> tuple[bool, str]:
    """:data:`_PROBE_CODE` with ``cuda_ad_mono`` in a child process: (works, why not)."""
    env = dict(os.environ)
    env.pop("HYBRIDHDR_MITSUBA_VARIANT", None)
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE_CODE, "cuda_ad_mono", "force"], capture_output=True,
                           text=True, timeout=timeout_s, env=env)
    except subprocess.TimeoutExpired:
        return False, f"the CUDA test render did not finish in {timeout_s:g} s"
    except OSError as e:
        return False, f"the CUDA test render could not start ({e})"
    if r.returncode == 0 and r.stdout.strip().endswith("OK"):
        return True, ""
    err = [ln.strip() for ln in (r.stderr or "").splitlines() if ln.strip()]
    return False, f"the CUDA test render failed (exit code {r.returncode}{': ' + err[-1][:160] if err else ''})"


def _probe_llvm(timeout_s: float = 180.0, check_version: bool = True) -> tuple[bool, str]:
    """Run :data:`_PROBE_CODE` with ``llvm_ad_mono`` in a child process: (works, why not).
    ``check_version=False`` renders even with an LLVM below :data:`MIN_LLVM_VERSION` (tests)."""
    env = dict(os.environ)
    env.pop("HYBRIDHDR_MITSUBA_VARIANT", None)
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE_CODE, "llvm_ad_mono"] + ([] if check_version else ["force"]),
                           capture_output=True, text=True,
                           timeout=timeout_s, env=env)
    except subprocess.TimeoutExpired:
        return False, f"the LLVM test render did not finish in {timeout_s:g} s"
    except OSError as e:
        return False, f"the LLVM test render could not start ({e})"
    if r.returncode == 0 and r.stdout.strip().endswith("OK"):
        return True, ""
    err = [ln.strip() for ln in (r.stderr or "").splitlines() if ln.strip()]
    hint = next((ln for ln in err if "LLVM ERROR" in ln), err[-1] if err else "")
    how = f"signal {-r.returncode}" if r.returncode < 0 else f"exit code {r.returncode}"
    return False, f"the LLVM test render failed ({how}{': ' + hint[:160] if hint else ''})"


def _decide(llvm_version, probe) -> tuple[str, str]:
    """The automatic variant and, for ``scalar_rgb``, why: from the LLVM version Dr.Jit loaded
    and, only if that is new enough, ``probe()`` -> (works, why not)."""
    v = tuple(llvm_version)
    if v[0] < 0:
        return "scalar_rgb", "Dr.Jit found no usable libLLVM"
    if v < MIN_LLVM_VERSION:
        return "scalar_rgb", (f"Dr.Jit loaded LLVM {_fmt_version(v)}, and Mitsuba's LLVM variants need "
                              f"LLVM >= {MIN_LLVM_VERSION[0]}")
    ok, why = probe()
    if ok:
        return "llvm_ad_mono", ""
    return "scalar_rgb", f"LLVM {_fmt_version(v)}: {why}"


def _cache_file() -> str | None:
    if os.environ.get("HYBRIDHDR_VARIANT_CACHE", "1") in ("0", "", "off", "no"):
        return None
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "hybridhdr", "mitsuba-variant.json")


def _cache_key(llvm_version) -> str:
    """What the decision depends on: interpreter, drjit/mitsuba versions, the libLLVM Dr.Jit was
    pointed at and every system libLLVM file (path, size, mtime), the probe's version."""
    import hashlib
    import json
    try:
        from importlib.metadata import version
        vers = [version("drjit"), version("mitsuba")]
    except Exception:
        vers = ["?", "?"]
    libs = []
    for d in _LIB_DIRS:
        for p in sorted(glob.glob(os.path.join(d, "libLLVM*"))):
            try:
                st = os.stat(p)
                libs.append([p, st.st_size, st.st_mtime_ns])
            except OSError:
                pass
    lib = os.environ.get("DRJIT_LIBLLVM_PATH", "")
    if lib:
        try:
            st = os.stat(lib)
            lib = [lib, st.st_size, st.st_mtime_ns]
        except OSError:
            pass
    raw = json.dumps([_PROBE_VERSION, sys.executable, sys.version, vers, list(llvm_version), lib, libs])
    return hashlib.sha256(raw.encode()).hexdigest()[:32]


def _cache_read(key: str):
    import json
    f = _cache_file()
    try:
        with open(f, encoding="utf-8") as fh:
            d = json.load(fh).get(key)
        if d and d[0] in ("llvm_ad_mono", "scalar_rgb", "cuda_ad_mono"):
            return d[0], str(d[1])
    except (OSError, ValueError, TypeError, AttributeError, IndexError):
        pass
    return None


def _cache_write(key: str, decision) -> None:
    import json
    f = _cache_file()
    if f is None:
        return
    try:
        os.makedirs(os.path.dirname(f), exist_ok=True)
        try:
            with open(f, encoding="utf-8") as fh:
                d = json.load(fh)
            d = d if isinstance(d, dict) else {}
        except (OSError, ValueError):
            d = {}
        d = dict(list(d.items())[-15:])  # a few interpreters/venvs at most
        d[key] = list(decision)
        with atomic_path(f) as tmp, open(tmp, "w", encoding="utf-8") as fh:
            json.dump(d, fh)
    except OSError:
        pass


def _auto_variant() -> tuple[str, str]:
    """The automatic (variant, reason), decided once per process (and remembered on disk, see
    :func:`_cache_key`); prints one line to stderr when it falls back to ``scalar_rgb``."""
    global _DECISION
    if _DECISION is None and _cuda_driver_present():  # the GPU first: cuda_ad_mono if its test render passes
        ckey = _cache_key(("cuda",))
        dec = _cache_read(ckey)
        if dec is None:
            ok, why = _probe_cuda()
            dec = ("cuda_ad_mono", "") if ok else ("", why)
            _cache_write(ckey, dec if ok else ("scalar_rgb", why))  # a failed probe is remembered too
        elif dec[0] != "cuda_ad_mono":
            dec = ("", dec[1])
        if dec[0] == "cuda_ad_mono":
            _DECISION = dec
        else:
            print(f"hybridhdr: an NVIDIA driver is present but Mitsuba's cuda_ad_mono variant does not work: {dec[1]}",
                  file=sys.stderr, flush=True)
    if _DECISION is None:
        ver = _drjit_llvm_version()
        key = _cache_key(ver) if ver >= MIN_LLVM_VERSION else None
        dec = _cache_read(key) if key else None
        if dec is None:
            dec = _decide(ver, _probe_llvm)
            if key:
                _cache_write(key, dec)
        _DECISION = dec
        if dec[0] == "scalar_rgb" and not os.environ.get("_HYBRIDHDR_VARIANT_NOTED"):
            os.environ["_HYBRIDHDR_VARIANT_NOTED"] = "1"  # inherited: child processes stay quiet
            print(f"hybridhdr: rendering with Mitsuba's slower scalar_rgb variant: {dec[1]}; {_FAST_PATH_HINT}",
                  file=sys.stderr, flush=True)
    return _DECISION


def variant_reason(variant: str, asked: str | None = None) -> str:
    """One line saying why ``variant`` renders: asked for, or the automatic choice and where its
    libLLVM came from (the user's ``DRJIT_LIBLLVM_PATH``, a system libLLVM 17-19, or the
    :data:`LLVM_WHEEL` wheel), or why the automatic choice fell back to ``scalar_rgb``."""
    asked = asked or os.environ.get("HYBRIDHDR_MITSUBA_VARIANT") or None
    if asked:
        return f"{variant}, as asked ({'--variant' if asked == variant else 'HYBRIDHDR_MITSUBA_VARIANT'})"
    v, why = _auto_variant()
    if v == "cuda_ad_mono":
        return "cuda_ad_mono: an NVIDIA GPU passed the test render"
    if v == "llvm_ad_mono":
        return (f"llvm_ad_mono: LLVM {_fmt_version(_drjit_llvm_version())} from {_LLVM_SOURCE or 'Dr.Jit'} "
                f"passed the test render")
    return f"scalar_rgb, the slow fallback: {why}; {_FAST_PATH_HINT}"


def llvm_source() -> str:
    """Where the libLLVM given to Dr.Jit comes from (see :func:`_prepare_llvm_env`)."""
    _prepare_llvm_env()
    return _LLVM_SOURCE


def cuda_available() -> bool:
    """Whether ``cuda_ad_mono`` is usable: an NVIDIA driver is present and a test render passed
    in a child process. Decided once per process (remembered on disk)."""
    return _auto_variant()[0] == "cuda_ad_mono"


def llvm_available() -> bool:
    """Whether ``llvm_ad_mono`` is usable: Dr.Jit loaded LLVM >= :data:`MIN_LLVM_VERSION` and a test
    render of the operations real scenes use passed in a child process (a failing LLVM aborts the
    process that compiles the kernel). Decided once per process."""
    return _auto_variant()[0] == "llvm_ad_mono"


def select_variant(variant: str | None = None) -> str:
    """The Mitsuba variant to use: ``variant`` if given, else ``$HYBRIDHDR_MITSUBA_VARIANT``, else
    ``cuda_ad_mono`` when :func:`cuda_available` (an NVIDIA GPU), else ``llvm_ad_mono`` when
    :func:`llvm_available`, else ``scalar_rgb``."""
    v = variant or os.environ.get("HYBRIDHDR_MITSUBA_VARIANT") or None
    if v is not None and v not in _VARIANTS:
        raise ValueError(f"Mitsuba variant: expected one of {', '.join(_VARIANTS)}, found {v!r}")
    if v is None:
        return _auto_variant()[0]
    if v.startswith("cuda") and not _IN_PROBE and not cuda_available():
        raise ImportError(f"Mitsuba variant {v!r} is not usable here (no NVIDIA driver, or its test render failed); "
                          f"use llvm_ad_mono or scalar_rgb")
    if v.startswith("llvm") and not _IN_PROBE and _auto_variant()[0] == "cuda_ad_mono":
        if _drjit_llvm_version() < MIN_LLVM_VERSION:
            raise ImportError(f"Mitsuba variant {v!r} is not usable here (Dr.Jit has no LLVM >= "
                              f"{MIN_LLVM_VERSION[0]}); use cuda_ad_mono or scalar_rgb")
        return v
    if v.startswith("llvm") and not _IN_PROBE and not llvm_available():
        raise ImportError(f"Mitsuba variant {v!r} is not usable here ({_auto_variant()[1]}); use scalar_rgb, "
                          f"or: {_FAST_PATH_HINT}")
    return v


def _import_mitsuba(variant: str):
    _prepare_llvm_env()
    try:
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - dependency missing
        raise ImportError("the simulator needs Mitsuba 3.9: pip install 'hybridhdr[simulate]'") from e
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


def mitsuba_camera_params(fx: float, cx: float, cy: float, width: int, height: int) -> dict:
    """Mitsuba ``perspective`` sensor parameters for a square-pixel pinhole camera.

    ``fov`` is the horizontal field of view 2·atan(W / (2 fx)) in degrees (``fov_axis='x'``). The
    principal point offsets are fractions of the film size and move the image the opposite way:
    offset_x = -(cx - (W-1)/2)/W, offset_y = -(cy - (H-1)/2)/H, with OpenCV pixel centres at integer
    coordinates (checked by ``tests/simulate/test_render.py`` projecting a known 3-D point).
    """
    return {"fov": math.degrees(2 * math.atan(width / (2 * fx))), "fov_axis": "x",
            "principal_point_offset_x": -(cx - (width - 1) / 2) / width,
            "principal_point_offset_y": -(cy - (height - 1) / 2) / height}


_DIRECT_ALL = "hybridhdr_direct"
_REGISTERED: set = set()


def _register_direct_all(mi) -> None:
    """Register a direct-lighting integrator that evaluates every light for every sample.

    Mitsuba's ``direct`` integrator picks one emitter per sample in proportion to its sampling
    weight, so a scene with a sun and a dim fill light shows salt-and-pepper noise (pixels whose
    samples all picked the other light) that moves with the camera and makes spurious events.
    This integrator adds, per camera sample, the emission of the surface hit plus, for every
    emitter with a positive sampling weight, one light sample with a shadow ray (exact for delta
    lights: point, spot, directional). Emissive surfaces with sampling weight 0 are seen but do
    not light the scene.
    """
    v = mi.variant()
    if v in _REGISTERED:
        return
    import drjit as dr
    scalar = v.startswith("scalar")

    class _DirectAll(mi.SamplingIntegrator):
        def __init__(self, props):
            super().__init__(props)

        def sample(self, scene, sampler, ray, medium=None, active=True):
            if scalar:
                return self._sample_scalar(scene, sampler, ray)
            si = scene.ray_intersect(ray, active)
            valid = si.is_valid()
            result = mi.Spectrum(0.0)
            result += si.emitter(scene).eval(si, active & valid)
            bsdf = si.bsdf(ray)
            ctx = mi.BSDFContext()
            for em in scene.emitters():
                if em.sampling_weight() <= 0:
                    continue
                ds, w = em.sample_direction(si, sampler.next_2d(), active & valid)
                ok = active & valid & (ds.pdf > 0)
                vis = ok & ~scene.ray_test(si.spawn_ray_to(ds.p), ok)
                f = bsdf.eval(ctx, si, si.to_local(ds.d), vis)
                result += dr.select(vis, f * w, 0.0)
            return result, valid, []

        def _sample_scalar(self, scene, sampler, ray):
            # the same estimator one sample at a time (scalar variants pass Python bools, and
            # si.emitter() is None on surfaces that do not emit)
            si = scene.ray_intersect(ray)
            if not si.is_valid():
                return mi.Spectrum(0.0), False, []
            result = mi.Spectrum(0.0)
            e = si.emitter(scene)
            if e is not None:
                result += e.eval(si)
            bsdf = si.bsdf(ray)
            ctx = mi.BSDFContext()
            for em in scene.emitters():
                if em.sampling_weight() <= 0:
                    continue
                ds, w = em.sample_direction(si, sampler.next_2d())
                if ds.pdf > 0 and not scene.ray_test(si.spawn_ray_to(ds.p)):
                    result += bsdf.eval(ctx, si, si.to_local(ds.d)) * w
            return result, True, []

        def aov_names(self):
            return []

    mi.register_integrator(_DIRECT_ALL, lambda props: _DirectAll(props))
    _REGISTERED.add(v)


_CV_TO_MI = np.diag([-1.0, -1.0, 1.0])  # OpenCV camera axes -> Mitsuba's (x left, y up, z forward)


def _rb_frobenius(x: float, y: float) -> float:
    """Frobenius norm of the rotational image-motion matrix at normalised coordinates (x, y):
    [[xy, -(1+x²), y], [1+y², -xy, -x]] (Longuet-Higgins & Prazdny 1980, doi:10.1098/rspb.1980.0057)."""
    return math.sqrt(2 * (x * y) ** 2 + (1 + x * x) ** 2 + (1 + y * y) ** 2 + x * x + y * y)


class MitsubaSource:
    """Render a :class:`~hybridhdr.simulate.scene.Scene` with Mitsuba 3 (a ``RadianceSource``).

    Parameters
    ----------
    scene : Scene
        The scene (camera, objects, emitters, duration).
    variant : str or None
        Mitsuba variant; None chooses with :func:`select_variant`.
    spp : int or None
        Samples per pixel (default: ``scene.render.spp``). Higher lowers anti-aliasing noise
        on moving edges; static pixels never flicker because the seed is fixed.
    seed : int or None
        Sampler seed used for every render (default: ``scene.render.seed``).

    Attributes
    ----------
    sensor_size : SensorSize
    duration_us : int
    renders : int
        Number of :meth:`render` calls so far.
    render_time_s : float
        Total wall time spent in :meth:`render`.
    variant : str
    """

    def __init__(self, scene: Scene, variant: str | None = None, spp: int | None = None, seed: int | None = None):
        if not isinstance(scene, Scene):
            raise TypeError(f"MitsubaSource needs a hybridhdr.simulate.Scene, got {type(scene).__name__}")
        self.scene = scene
        self.variant = select_variant(variant)
        self.spp = int(scene.render.spp if spp is None else spp)
        self.seed = int(scene.render.seed if seed is None else seed)
        if self.spp < 1:
            raise ValueError(f"spp: expected >= 1, found {self.spp}")
        if self.seed < 0:
            raise ValueError(f"seed: expected >= 0, found {self.seed}")
        cam = scene.camera
        self.sensor_size = SensorSize(cam.height, cam.width)
        self.duration_us = int(scene.duration_us)
        self.renders = 0
        self.render_time_s = 0.0
        self._mi = _import_mitsuba(self.variant)
        self._build()

    # ------------------------------------------------------------------------------------------
    def _build(self) -> None:
        mi = self._mi
        sc = self.scene
        base = None if sc.base_dir is None else sc.base_dir
        mono = "mono" in self.variant
        cam = sc.camera

        def tex(pattern, nearest):
            img = pattern.image(base)
            if img.shape == (1, 1):
                return {"type": "uniform", "value": float(img[0, 0])}, None
            arr = img[..., None] if mono else np.repeat(img[..., None], 3, axis=2)
            return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(arr, np.float32)),
                    "filter_type": "nearest" if nearest else "bilinear", "raw": True,
                    "wrap_mode": "clamp"}, arr

        d: dict = {"type": "scene"}
        any_env = any(e.kind == "constant" for e in sc.emitters)
        integ: dict
        self.integrator_name = sc.render.integrator
        # emitters Mitsuba samples (the dark light below included)
        n_lights = (sum(e.sampling_weight > 0 for e in sc.emitters) + sum(
            o.emission is not None and o.emission.sampling_weight > 0 for o in sc.objects)
            + (sum(e.sampling_weight for e in sc.emitters) == 0))
        if sc.render.integrator == "direct" and self.variant.startswith("scalar") and n_lights <= 1 and not any_env:
            # one light: Mitsuba's own direct integrator with one emitter sample and no BSDF
            # sample is the same estimator as the every-light one below, in C++ (the Python
            # integrator costs ~15 us a sample in scalar variants)
            integ = {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}
            self.integrator_name = "direct (every light per sample)"
        elif sc.render.integrator == "direct":
            # Mitsuba's own direct integrator would pick one light per sample: salt-and-pepper
            # noise with several lights (see _register_direct_all)
            _register_direct_all(mi)
            integ = {"type": _DIRECT_ALL}
            self.integrator_name = "direct (every light per sample)"
        else:
            integ = {"type": "path", "max_depth": int(sc.render.max_depth)}
        d["integrator"] = integ
        film = {"type": "hdrfilm", "width": cam.width, "height": cam.height,
                "pixel_format": "luminance" if mono else "rgb", "rfilter": {"type": "box"}}
        d["sensor"] = {"type": "perspective", **mitsuba_camera_params(cam.fx, cam.cx, cam.cy, cam.width, cam.height),
                       "near_clip": 1e-3, "far_clip": 1e5,
                       "to_world": mi.ScalarTransform4f(self._camera_matrix(0)),
                       "sampler": {"type": "independent", "sample_count": self.spp}, "film": film}

        self._objects = []  # (key, SceneObject, local vertices (V,3), faces, R_max)
        self._area = []     # (param key, base value or tensor, Blink)
        for i, o in enumerate(sc.objects):
            key = f"obj{i}"
            m, uv = o.mesh.build(None if base is None else base)
            V = np.asarray(m.vertices, float) * np.asarray(o.scale, float)
            F = np.asarray(m.faces, np.uint32)
            props = mi.Properties()
            refl, _ = tex(o.material.reflectance, nearest=o.material.reflectance.checkerboard is not None)
            props["bsdf"] = mi.load_dict({"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": refl}})
            if o.emission is not None:
                rad, arr = tex(o.emission.radiance, nearest=o.emission.radiance.checkerboard is not None)
                props["emitter"] = mi.load_dict({"type": "area", "radiance": rad,
                                                 "sampling_weight": float(o.emission.sampling_weight)})
                if o.emission.blink is not None:
                    if arr is None:
                        self._area.append((f"{key}.emitter.radiance.value", float(rad["value"]), o.emission.blink))
                    else:
                        self._area.append((f"{key}.emitter.radiance.data", arr, o.emission.blink))
            needs_uv = not (o.material.reflectance.is_constant and (o.emission is None or o.emission.radiance.is_constant))
            if needs_uv and uv is None:
                raise SceneError(f"object {o.name!r}: a texture or checkerboard needs UV coordinates, and a "
                                 f"{o.mesh.kind!r} mesh has none (use a 'plane' or a mesh file with UVs)")
            mesh = mi.Mesh(key, len(V), len(F), props, has_vertex_normals=False, has_vertex_texcoords=uv is not None)
            mp = mi.traverse(mesh)
            R, p = o.trajectory.pose(0)
            mp["vertex_positions"] = type(mp["vertex_positions"])(np.ascontiguousarray((V @ R.T + p).ravel(), np.float32))
            mp["faces"] = type(mp["faces"])(np.ascontiguousarray(F.ravel()))
            if uv is not None:
                mp["vertex_texcoords"] = type(mp["vertex_texcoords"])(np.ascontiguousarray(uv.ravel(), np.float32))
            mp.update()
            d[key] = mesh
            self._objects.append((key, o, V, F, float(np.linalg.norm(V, axis=1).max())))

        self._emitters = []  # (key, Emitter)
        for i, e in enumerate(sc.emitters):
            key = f"em{i}"
            # loaded one by one: inside one load_dict call, equal nested dicts (e.g. two
            # {'type': 'uniform', 'value': 1.0}) become one shared object, so scaling one light's
            # power through traverse would scale the other's too
            d[key] = mi.load_dict(self._emitter_dict(e, 0))
            self._emitters.append((key, e))

        if sum(e.sampling_weight for e in sc.emitters) == 0:
            # Mitsuba's emitter-sampling distribution needs positive mass: a dark point light
            # (zero intensity, contributes nothing) keeps non-lighting emissive surfaces possible
            d["dark_light"] = {"type": "point", "position": [0.0, 0.0, 0.0],
                               "intensity": {"type": "uniform", "value": 0.0}}
        t0 = time.perf_counter()
        quiet = self.variant.startswith("scalar") and d["integrator"]["type"] == _DIRECT_ALL
        level = mi.log_level()
        if quiet:  # not Mitsuba's "Python integrators perform terribly in scalar modes" warning
            mi.set_log_level(mi.LogLevel.Error)
        try:
            self._mscene = mi.load_dict(d)
        finally:
            mi.set_log_level(level)
        self._params = mi.traverse(self._mscene)
        self._last: dict = {}
        self.load_time_s = time.perf_counter() - t0
        # traversable power parameter of each blinking emitter (Mitsuba 3.9 exposes a spot's
        # intensity as 'texture', and a directional light's irradiance not at all)
        self._blink_keys = {}
        for key, e in self._emitters:
            if e.blink is None:
                continue
            cands = {"point": ("intensity.value",), "spot": ("intensity.value", "texture.value"),
                     "constant": ("radiance.value",), "directional": ("irradiance.value",)}[e.kind]
            found = [f"{key}.{c}" for c in cands if f"{key}.{c}" in self._params.keys()]
            if not found:
                raise SceneError(f"emitter {key[2:]} ({e.kind}): 'blink' is not supported for this emitter type "
                                 "(Mitsuba does not expose its power for updates); blink a point/spot light or "
                                 "an emissive object instead")
            self._blink_keys[key] = found[0]
        self._static_tris: dict = {}

    def _camera_matrix(self, t_us: float) -> np.ndarray:
        R, p = self.scene.camera.trajectory.pose(t_us)
        M = np.eye(4)
        M[:3, :3] = R @ _CV_TO_MI
        M[:3, 3] = p
        return M

    def _emitter_frame(self, e, t_us):
        """(position, aim point, direction) of an emitter in world coordinates at ``t_us``."""
        pos, aim, dirn = (np.asarray(v, float) for v in (e.position, e.look_at, e.direction))
        if e.attached_to_camera:
            R, p = self.scene.camera.trajectory.pose(t_us)
            pos, aim, dirn = R @ pos + p, R @ aim + p, R @ dirn
        return pos, aim, dirn

    def _emitter_dict(self, e, t_us) -> dict:
        mi = self._mi
        s = 1.0 if e.blink is None else e.blink.scale(t_us)
        pos, aim, dirn = self._emitter_frame(e, t_us)
        sw = float(e.sampling_weight)
        if e.kind == "point":
            return {"type": "point", "position": pos.tolist(), "sampling_weight": sw,
                    "intensity": {"type": "uniform", "value": e.intensity * s}}
        if e.kind == "spot":
            return {"type": "spot", "cutoff_angle": e.cutoff_deg, "beam_width": e.beam_width_deg,
                    "sampling_weight": sw, "intensity": {"type": "uniform", "value": e.intensity * s},
                    "to_world": mi.ScalarTransform4f(self._spot_matrix(pos, aim))}
        if e.kind == "directional":
            return {"type": "directional", "direction": dirn.tolist(), "sampling_weight": sw,
                    "irradiance": {"type": "uniform", "value": e.irradiance * s}}
        return {"type": "constant", "sampling_weight": sw, "radiance": {"type": "uniform", "value": e.radiance * s}}

    @staticmethod
    def _spot_matrix(pos, aim) -> np.ndarray:
        z = aim - pos
        up = (0.0, 1.0, 0.0) if abs(z[1]) < 0.99 * np.linalg.norm(z) else (1.0, 0.0, 0.0)
        M = np.eye(4)
        M[:3, :3] = look_at_rotation(pos, aim, up)
        M[:3, 3] = pos
        return M

    def _set(self, key, value) -> bool:
        last = self._last.get(key)
        if last is not None and np.array_equal(last, value):
            return False
        p = self._params
        cur = p[key]
        if isinstance(value, np.ndarray) and value.ndim >= 2 and key.endswith(".data"):
            p[key] = type(cur)(np.ascontiguousarray(value, np.float32))
        elif isinstance(value, np.ndarray) and value.shape == (4, 4):
            p[key] = type(cur)(value.tolist())
        elif isinstance(value, np.ndarray):
            p[key] = type(cur)(np.ascontiguousarray(value, np.float32) if value.ndim == 1 and value.size > 3
                               else value.tolist())
        else:
            p[key] = type(cur)(value) if not isinstance(cur, float) else float(value)
        self._last[key] = np.array(value, copy=True)
        return True

    def _update(self, t_us: int) -> None:
        changed = self._set("sensor.to_world", self._camera_matrix(t_us))
        for key, o, V, F, _ in self._objects:
            if not o.trajectory.is_static:
                R, p = o.trajectory.pose(t_us)
                changed |= self._set(f"{key}.vertex_positions", np.ascontiguousarray((V @ R.T + p).ravel(), np.float32))
        for key, base, blink in self._area:
            changed |= self._set(key, (base * blink.scale(t_us)) if isinstance(base, np.ndarray)
                                 else float(base * blink.scale(t_us)))
        for key, e in self._emitters:
            s = 1.0 if e.blink is None else e.blink.scale(t_us)
            if e.blink is not None:
                name = {"point": "intensity", "spot": "intensity", "directional": "irradiance",
                        "constant": "radiance"}[e.kind]
                changed |= self._set(self._blink_keys[key], float(getattr(e, name) * s))
            if e.attached_to_camera:
                pos, aim, dirn = self._emitter_frame(e, t_us)
                if e.kind == "point":
                    changed |= self._set(f"{key}.position", pos)
                elif e.kind == "spot":
                    changed |= self._set(f"{key}.to_world", self._spot_matrix(pos, aim))
                elif e.kind == "directional":
                    M = self._spot_matrix(np.zeros(3), dirn)
                    changed |= self._set(f"{key}.to_world", M)
        if changed:
            self._params.update()

    # ------------------------------------------------------------------------------------------
    def render(self, t_us: int) -> np.ndarray:
        """Linear radiance (H, W) float32 at ``t_us`` (clamped to [0, duration_us]); deterministic."""
        t = int(t_us)
        if t < 0 or t > self.duration_us:
            raise ValueError(f"render time: expected 0 <= t_us <= {self.duration_us}, found {t}")
        mi = self._mi
        t0 = time.perf_counter()
        if mi.variant() != self.variant:
            mi.set_variant(self.variant)
        self._update(t)
        img = np.array(mi.render(self._mscene, spp=self.spp, seed=self.seed), dtype=np.float32)
        if img.ndim == 3 and img.shape[2] >= 3:
            w = np.asarray(LUMINANCE_RGB, np.float32)
            img = img[..., 0] * w[0] + img[..., 1] * w[1] + img[..., 2] * w[2]
        elif img.ndim == 3:
            img = img[..., 0]
        img = np.ascontiguousarray(np.maximum(np.nan_to_num(img, nan=0.0, posinf=0.0), 0.0), np.float32)
        self.renders += 1
        self.render_time_s += time.perf_counter() - t0
        return img

    # ------------------------------------------------------------------------------------------
    def _world_triangles(self, idx: int, t_us: float) -> np.ndarray:
        key, o, V, F, _ = self._objects[idx]
        if o.trajectory.is_static and idx in self._static_tris:
            return self._static_tris[idx]
        R, p = o.trajectory.pose(t_us)
        tris = (V @ R.T + p)[F]
        if o.trajectory.is_static:
            self._static_tris[idx] = tris
        return tris

    def max_image_speed_px_per_s(self, t0_us: int, t1_us: int) -> float:
        """Upper bound of the image speed (px/s) of any visible scene point over [t0_us, t1_us].

        For a point at camera-frame depth Z and normalised image coordinates (x, y), the image
        velocity is f·[A·V/Z + B·ω] (Longuet-Higgins & Prazdny 1980), with V the point's
        velocity relative to the camera (camera axes), ω the camera's angular velocity,
        A = [[1, 0, -x], [0, 1, -y]] (‖A‖₂ = √(1 + x² + y²)) and B the rotational matrix bounded
        by its Frobenius norm at the image corner. Per object, ‖V‖ ≤ v_cam + v_obj + ω_obj·R_obj
        (R_obj: the farthest vertex from the object's origin), and Z ≥ d/√(1 + r²) where d is a
        lower bound of the camera-to-object distance over the interval: the exact
        point-to-triangle distance at the interval's middle minus the largest camera and object
        displacement in half the interval. Speeds are the exact trajectory maxima over the
        interval (:meth:`Trajectory.speed_bounds`). Returns ``math.inf`` when an object may
        touch the camera.
        """
        import trimesh
        t0, t1 = float(t0_us), float(t1_us)
        if t1 < t0:
            raise ValueError(f"interval: expected t0_us <= t1_us, found {t0_us} > {t1_us}")
        cam = self.scene.camera
        f = max(cam.fx, cam.fy)
        x = (max(cam.cx, cam.width - 1 - cam.cx) + 0.5) / cam.fx
        y = (max(cam.cy, cam.height - 1 - cam.cy) + 0.5) / cam.fy
        a_norm = math.sqrt(1 + x * x + y * y)
        v_c, w_c = cam.trajectory.speed_bounds(t0, t1)
        half_s = 0.5 * (t1 - t0) * 1e-6
        tm = 0.5 * (t0 + t1)
        _, pc = cam.trajectory.pose(tm)
        rot = f * _rb_frobenius(x, y) * w_c
        best = rot
        for i, (key, o, V, F, r_obj) in enumerate(self._objects):
            v_o, w_o = o.trajectory.speed_bounds(t0, t1)
            v_rel = v_c + v_o + w_o * r_obj
            if v_rel == 0:
                continue
            tris = self._world_triangles(i, tm)
            cp = trimesh.triangles.closest_point(tris, np.repeat(pc[None, :], len(tris), axis=0))
            dist = float(np.min(np.linalg.norm(cp - pc, axis=1)))
            d_min = dist - (v_c + v_o + w_o * r_obj) * half_s
            if d_min <= 1e-6:
                return math.inf
            z_min = d_min / a_norm
            best = max(best, f * a_norm * v_rel / z_min + rot)
        return float(best)

    def describe(self) -> dict:
        """Scene name, variant, spp, integrator, seed, resolution, intrinsics K and the scene's ``info``."""
        import mitsuba
        cam = self.scene.camera
        return {"source": "mitsuba", "scene": self.scene.name, "variant": self.variant,
                "mitsuba_version": getattr(mitsuba, "__version__", "unknown"), "spp": self.spp,
                "integrator": self.integrator_name, "seed": self.seed,
                "width": cam.width, "height": cam.height, "K": cam.K.tolist(),
                "duration_us": self.duration_us, "info": dict(self.scene.info)}


def preview_strip(source, path, n: int = 4, *, decades: float = 5.0) -> "os.PathLike":
    """Render ``n`` frames evenly spaced over the source's duration and save them side by side as
    a PNG (log10 radiance over ``decades`` decades below the brightest pixel, grey colour map,
    each frame labelled with its time). Written atomically; returns the path.
    """
    if n < 1:
        raise ValueError(f"preview frames: expected >= 1, found {n}")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover
        raise ImportError("the preview needs matplotlib: pip install 'hybridhdr[images]'") from e
    from pathlib import Path
    ts = np.linspace(0, source.duration_us, n).round().astype(np.int64)
    imgs = [source.render(int(t)) for t in ts]
    top = math.log10(max(float(max(im.max() for im in imgs)), 1e-12))
    h, w = source.sensor_size.height, source.sensor_size.width
    fig, axs = plt.subplots(1, n, figsize=(2.2 * n * w / max(w, h), 2.2 * h / max(w, h) + 0.3), squeeze=False)
    for ax, t, im in zip(axs[0], ts, imgs):
        ax.imshow(np.log10(np.maximum(im, 10 ** (top - decades))), cmap="gray", vmin=top - decades, vmax=top,
                  interpolation="nearest")
        ax.set_title(f"{t / 1e3:.0f} ms", fontsize=8)
        ax.axis("off")
    fig.tight_layout(pad=0.3)
    p = Path(path)
    try:
        with atomic_path(p, ".png") as tmp:
            fig.savefig(tmp, format="png", dpi=80)
    finally:
        plt.close(fig)
    return p
