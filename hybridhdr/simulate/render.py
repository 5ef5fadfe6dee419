"""Mitsuba 3.9 rendering of a :class:`~hybridhdr.simulate.scene.Scene` as a radiance source.

:class:`MitsubaSource` implements :class:`hybridhdr.simulate.source.RadianceSource`: it loads the
scene into Mitsuba once, then for each render time moves the camera (``sensor.to_world``),
rewrites the vertex positions of moving objects, rescales blinking emitters through
``mi.traverse`` parameters, and renders with a fixed sampler seed, so a static pixel gets the same
bits in every render (no render-noise events). Output is linear float32 radiance (H, W).

Variants (``../shared/reference/simulator.md``, Mitsuba recipe): ``llvm_ad_mono`` when Dr.Jit's
LLVM backend works (libLLVM 17-19; LLVM 15/16 abort the process on the first render, so the
check runs a tiny render in a subprocess), otherwise ``scalar_rgb``, whose RGB output is converted
to luminance Y = 0.2126 R + 0.7152 G + 0.0722 B (Rec. ITU-R BT.709 primaries, the sRGB/Rec.709
luminance coefficients). The variant in use is in :meth:`MitsubaSource.describe`.
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

from ..events import SensorSize
from .scene import Scene, SceneError

__all__ = ["MitsubaSource", "select_variant", "llvm_available", "LUMINANCE_RGB", "mitsuba_camera_params", "preview_strip"]

#: Rec. ITU-R BT.709 luminance weights used to convert ``scalar_rgb`` renders to radiance.
LUMINANCE_RGB = (0.2126, 0.7152, 0.0722)

_VARIANTS = ("llvm_ad_mono", "scalar_rgb", "llvm_ad_rgb")
_LLVM_OK: bool | None = None
_PROBE_CODE = r"""
import mitsuba as mi
mi.set_variant('llvm_ad_mono')
s = mi.load_dict({'type': 'scene', 'integrator': {'type': 'direct'},
    'sensor': {'type': 'perspective', 'fov': 45, 'film': {'type': 'hdrfilm', 'width': 8, 'height': 6,
               'pixel_format': 'luminance', 'rfilter': {'type': 'box'}}},
    'light': {'type': 'point', 'position': [0, 0, 0], 'intensity': {'type': 'uniform', 'value': 1.0}},
    'sp': {'type': 'sphere', 'center': [0, 0, 5]}})
import numpy as np
a = np.array(mi.render(s, spp=1, seed=0))
print('OK' if a.shape == (6, 8, 1) and np.isfinite(a).all() and a.max() > 0 else 'BAD')
"""


def _find_libllvm() -> str | None:
    """Path of a libLLVM with major version 17-19 in the system library folders (newest first)."""
    cands = []
    for d in ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
              "/usr/local/lib", "/opt/homebrew/opt/llvm/lib"):
        for p in glob.glob(os.path.join(d, "libLLVM*")):
            m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(p))
            if m and 17 <= int(m.group(1)) <= 19:
                cands.append((int(m.group(1)), p))
    return max(cands)[1] if cands else None


def _prepare_llvm_env() -> None:
    # Dr.Jit picks the last libLLVM*.so.* of the system folder unless told; LLVM 15/16 crash
    # (uncatchable SIGABRT), so point it at 17-19 before mitsuba is first imported.
    if "DRJIT_LIBLLVM_PATH" not in os.environ and "drjit" not in sys.modules:
        p = _find_libllvm()
        if p is not None:
            os.environ["DRJIT_LIBLLVM_PATH"] = p


def llvm_available(timeout_s: float = 120.0) -> bool:
    """Whether ``llvm_ad_mono`` renders, checked once per process in a subprocess (a failing
    LLVM can abort the process that loads it)."""
    global _LLVM_OK
    if _LLVM_OK is None:
        _prepare_llvm_env()
        try:
            r = subprocess.run([sys.executable, "-c", _PROBE_CODE], capture_output=True, text=True,
                               timeout=timeout_s, env=dict(os.environ))
            _LLVM_OK = r.returncode == 0 and r.stdout.strip().endswith("OK")
        except (OSError, subprocess.TimeoutExpired):
            _LLVM_OK = False
    return _LLVM_OK


def select_variant(variant: str | None = None) -> str:
    """The Mitsuba variant to use: ``variant`` if given, else ``$HYBRIDHDR_MITSUBA_VARIANT``, else
    ``llvm_ad_mono`` when :func:`llvm_available`, else ``scalar_rgb``."""
    v = variant or os.environ.get("HYBRIDHDR_MITSUBA_VARIANT") or None
    if v is None:
        v = "llvm_ad_mono" if llvm_available() else "scalar_rgb"
    if v not in _VARIANTS:
        raise ValueError(f"Mitsuba variant: expected one of {', '.join(_VARIANTS)}, found {v!r}")
    if v.startswith("llvm") and not llvm_available():
        raise ImportError(f"Mitsuba variant {v!r} needs a working LLVM (libLLVM 17-19) and none was "
                          "found or it failed a test render; use --variant scalar_rgb")
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

    class _DirectAll(mi.SamplingIntegrator):
        def __init__(self, props):
            super().__init__(props)

        def sample(self, scene, sampler, ray, medium=None, active=True):
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
        any_area_lit = any(o.emission is not None and o.emission.sampling_weight > 0 for o in sc.objects)
        integ: dict
        self.integrator_name = sc.render.integrator
        if sc.render.integrator == "direct" and self.variant.startswith("llvm"):
            _register_direct_all(mi)
            integ = {"type": _DIRECT_ALL}
            self.integrator_name = "direct (every light per sample)"
        elif sc.render.integrator == "direct":
            # scalar fallback: Mitsuba's own integrator picks one light per sample (noise with
            # several lights: raise spp). BSDF samples only find area/environment emitters.
            integ = {"type": "direct", "emitter_samples": 1, "bsdf_samples": 1 if (any_env or any_area_lit) else 0}
            self.integrator_name = "direct (mitsuba, one light per sample)"
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
        self._mscene = mi.load_dict(d)
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
        from .scene import look_at_rotation
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
    tmp = p.with_name(p.name + ".partial")
    fig.savefig(tmp, format="png", dpi=80)
    plt.close(fig)
    os.replace(tmp, p)
    return p
