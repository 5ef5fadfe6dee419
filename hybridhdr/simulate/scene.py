"""Scene descriptions for the simulator: meshes, materials, emitters, camera and trajectories.

A :class:`Scene` is a tree of frozen dataclasses that a TOML file (format in ``docs/simulate.md``)
or Python code builds. It holds no renderer state: :class:`hybridhdr.simulate.render.MitsubaSource`
turns it into a Mitsuba 3 scene.

Conventions
-----------
- World units are metres; times are int64 µs (``docs/conventions.md``).
- The camera frame follows OpenCV: x right, y down, z forward (optical axis). A camera pose is
  the camera-to-world rotation (columns are the camera axes in world coordinates) and the camera
  centre. Objects' poses map object coordinates to world coordinates.
- Quaternions are ``[w, x, y, z]`` (Hamilton, unit norm).
- Intrinsics are the pinhole ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` with pixel centres at
  integer coordinates (OpenCV), ``u = fx·X/Z + cx``.
- Radiance, intensity and irradiance are linear, in arbitrary but consistent units (a sun 10⁴×
  brighter than the shadow is simply a radiance ratio of 10⁴).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .._util.atomic import write_text_atomic
from .._util.confine import confine
from .._util.toml import TOMLDecodeError, load_toml

__all__ = [
    "SceneError", "Blink", "Pattern", "Material", "Emission", "MeshSpec", "Keyframe", "Trajectory",
    "CameraSpec", "Emitter", "SceneObject", "RenderSettings", "Scene", "load_scene", "save_scene",
    "quat_from_matrix", "matrix_from_quat", "look_at_rotation", "load_calibration",
]

MESH_KINDS = ("box", "sphere", "icosphere", "plane", "cylinder", "cone", "capsule", "file")
EMITTER_KINDS = ("point", "spot", "directional", "constant")
INTERPOLATIONS = ("linear", "catmull_rom")
INTEGRATORS = ("direct", "path")


class SceneError(ValueError):
    """A scene description is invalid; the message names the key, the expected and the found value."""


# ----------------------------------------------------------------------------------------------
# small validated readers
# ----------------------------------------------------------------------------------------------

def _err(key: str, expected: str, found) -> SceneError:
    return SceneError(f"scene key {key!r}: expected {expected}, found {found!r}")


def _num(d: dict, key: str, where: str, default=None, *, positive=False, nonneg=False) -> float:
    if key not in d:
        if default is None:
            raise SceneError(f"scene key {where + key!r} is required (expected a number)")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _err(where + key, "a finite number", v)
    if positive and v <= 0:
        raise _err(where + key, "a number > 0", v)
    if nonneg and v < 0:
        raise _err(where + key, "a number >= 0", v)
    return float(v)


def _int(d: dict, key: str, where: str, default=None, *, minimum=None) -> int:
    if key not in d:
        if default is None:
            raise SceneError(f"scene key {where + key!r} is required (expected an integer)")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise _err(where + key, "an integer", v)
    if minimum is not None and v < minimum:
        raise _err(where + key, f"an integer >= {minimum}", v)
    return int(v)


def _vec(d: dict, key: str, where: str, n: int, default=None) -> tuple:
    if key not in d:
        if default is None:
            raise SceneError(f"scene key {where + key!r} is required (expected {n} numbers)")
        return tuple(float(x) for x in default)
    v = d[key]
    if (not isinstance(v, (list, tuple)) or len(v) != n
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in v)):
        raise _err(where + key, f"a list of {n} finite numbers", v)
    return tuple(float(x) for x in v)


def _str(d: dict, key: str, where: str, default=None, choices=None) -> str:
    if key not in d:
        if default is None:
            raise SceneError(f"scene key {where + key!r} is required (expected a string)")
        return default
    v = d[key]
    if not isinstance(v, str):
        raise _err(where + key, "a string", v)
    if choices is not None and v not in choices:
        raise _err(where + key, "one of " + ", ".join(choices), v)
    return v


def _table(d: dict, key: str, where: str, required=False) -> dict | None:
    if key not in d:
        if required:
            raise SceneError(f"scene key {where + key!r} is required (expected a table)")
        return None
    v = d[key]
    if not isinstance(v, dict):
        raise _err(where + key, "a table", v)
    return v


def _check_keys(d: dict, allowed, where: str) -> None:
    if not isinstance(d, dict):
        raise _err(where.rstrip(".") or "<root>", "a table", d)
    extra = sorted(set(d) - set(allowed))
    if extra:
        raise SceneError(f"unknown scene key {where + extra[0]!r}; expected one of: {', '.join(sorted(allowed))}")


def _floats(obj, *names) -> None:
    """Normalise numeric fields of a frozen dataclass to float / tuples of float (exact round trips)."""
    for n in names:
        v = getattr(obj, n)
        if v is None:
            continue
        object.__setattr__(obj, n, tuple(float(x) for x in v) if isinstance(v, (tuple, list, np.ndarray)) else float(v))


# ----------------------------------------------------------------------------------------------
# rotations
# ----------------------------------------------------------------------------------------------

def matrix_from_quat(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion ``[w, x, y, z]``."""
    w, x, y, z = (float(c) for c in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quat_from_matrix(R) -> tuple[float, float, float, float]:
    """Unit quaternion ``[w, x, y, z]`` (w >= 0) of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return tuple(float(c) for c in q)


def look_at_rotation(position, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Camera-to-world rotation (OpenCV axes: x right, y down, z forward) looking at ``target``.

    ``up`` is the world direction that appears upwards in the image.
    """
    z = np.asarray(target, float) - np.asarray(position, float)
    nz = np.linalg.norm(z)
    if nz == 0:
        raise SceneError(f"look_at target {tuple(target)} equals the position")
    z /= nz
    x = np.cross(z, np.asarray(up, float))
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise SceneError(f"look_at: up {tuple(up)} is parallel to the viewing direction")
    x /= nx
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9999995:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    th = math.acos(min(1.0, d))
    return (math.sin((1 - s) * th) * q0 + math.sin(s * th) * q1) / math.sin(th)


def _quat_angle(q0, q1) -> float:
    d = abs(float(np.dot(q0, q1)))
    return 2.0 * math.acos(min(1.0, d))


# ----------------------------------------------------------------------------------------------
# dataclasses
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Blink:
    """Square-wave modulation of an emitter: scale 1 for ``duty`` of each period, ``off_scale`` otherwise.

    Parameters
    ----------
    period_us : int
        Period in µs.
    duty : float
        Fraction of the period that is "on", in (0, 1].
    off_scale : float
        Radiance scale while "off" (0 = black).
    phase_us : int
        The first "on" phase starts at ``phase_us``.
    """

    period_us: int
    duty: float = 0.5
    off_scale: float = 0.0
    phase_us: int = 0

    def __post_init__(self):
        if self.period_us <= 0:
            raise SceneError(f"blink.period_us: expected > 0, found {self.period_us}")
        if not 0 < self.duty <= 1:
            raise SceneError(f"blink.duty: expected in (0, 1], found {self.duty}")
        if self.off_scale < 0:
            raise SceneError(f"blink.off_scale: expected >= 0, found {self.off_scale}")

    def scale(self, t_us: int) -> float:
        ph = ((int(t_us) - self.phase_us) % self.period_us) / self.period_us
        return 1.0 if ph < self.duty else self.off_scale

    def edges_us(self, t0_us: int, t1_us: int) -> list[int]:
        """Times of the on/off switches in ``(t0_us, t1_us]``."""
        out = []
        k0 = (t0_us - self.phase_us) // self.period_us
        k = k0
        while True:
            base = self.phase_us + k * self.period_us
            if base > t1_us:
                break
            for e in (base, base + int(round(self.duty * self.period_us))):
                if t0_us < e <= t1_us:
                    out.append(e)
            k += 1
        return sorted(set(out))

    @classmethod
    def from_dict(cls, d: dict, where: str) -> "Blink":
        _check_keys(d, ("period_us", "duty", "off_scale", "phase_us"), where)
        return cls(period_us=_int(d, "period_us", where, minimum=1), duty=_num(d, "duty", where, 0.5),
                   off_scale=_num(d, "off_scale", where, 0.0, nonneg=True),
                   phase_us=_int(d, "phase_us", where, 0))

    def to_dict(self) -> dict:
        return {"period_us": self.period_us, "duty": self.duty, "off_scale": self.off_scale,
                "phase_us": self.phase_us}


@dataclass(frozen=True)
class Pattern:
    """A scalar surface quantity over the mesh's UV square: a constant, an image file, a checkerboard
    or a procedural texture.

    Parameters
    ----------
    value : float
        The constant value, or the scale of the texture image (image values in [0, 1] times ``value``).
    texture : str or None
        Image file (PNG/JPEG/EXR/HDR, via imageio), relative to the scene file. 8-bit images are
        decoded from sRGB to linear; colour is converted to luminance (Rec. 709 weights).
    checkerboard : (int, int) or None
        Number of squares along u and v; square (i, j) (column i, row j, from the u = 0, v = 0
        corner: the top-left of a plane as its camera sees it) has ``high`` when i + j is even,
        else ``low``.
    low, high : float
        Checkerboard values.
    procedural : str or None
        A texture generated in code (:data:`hybridhdr.simulate.textures.TEXTURES`, relative values
        up to 1) times ``value``; ``seed`` picks the instance.
    seed : int
        Seed of the procedural texture.
    """

    value: float = 1.0
    texture: str | None = None
    checkerboard: tuple[int, int] | None = None
    low: float = 0.0
    high: float = 1.0
    procedural: str | None = None
    seed: int = 0

    def __post_init__(self):
        _floats(self, "value", "low", "high")
        if sum(x is not None for x in (self.texture, self.checkerboard, self.procedural)) > 1:
            raise SceneError("a pattern has one of 'texture', 'checkerboard' or 'procedural', not several")
        if self.procedural is not None:
            from .textures import TEXTURES
            if self.procedural not in TEXTURES:
                raise SceneError(f"procedural: expected one of {', '.join(TEXTURES)}, found {self.procedural!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise SceneError(f"seed: expected an int >= 0, found {self.seed!r}")
        if self.checkerboard is not None and (len(self.checkerboard) != 2 or min(self.checkerboard) < 1):
            raise SceneError(f"checkerboard: expected two integers >= 1, found {self.checkerboard}")
        if min(self.value, self.low, self.high) < 0:
            raise SceneError(f"pattern values must be >= 0, found value={self.value}, low={self.low}, high={self.high}")

    @property
    def is_constant(self) -> bool:
        return self.texture is None and self.checkerboard is None and self.procedural is None

    def image(self, base_dir: Path | None = None) -> np.ndarray:
        """The pattern as float32 (rows, cols) texels (row 0 at v = 0, the top edge of a plane), or a 1×1 constant."""
        if self.checkerboard is not None:
            nu, nv = self.checkerboard
            jj, ii = np.mgrid[0:nv, 0:nu]
            img = np.where((ii + jj) % 2 == 0, self.high, self.low)
            return img.astype(np.float32)
        if self.texture is not None:
            return (_read_texture(self.texture, base_dir) * self.value).astype(np.float32)
        if self.procedural is not None:
            from .textures import texture
            return (texture(self.procedural, int(self.seed)) * self.value).astype(np.float32)
        return np.full((1, 1), self.value, np.float32)

    @classmethod
    def from_value(cls, v, where: str) -> "Pattern":
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            if not (math.isfinite(v) and v >= 0):
                raise _err(where.rstrip("."), "a finite number >= 0", v)
            return cls(value=float(v))
        if not isinstance(v, dict):
            raise _err(where.rstrip("."), "a number or a table {texture=..} / {checkerboard=[nu, nv], low, high} / "
                       "{procedural=NAME, seed}", v)
        _check_keys(v, ("value", "texture", "checkerboard", "low", "high", "procedural", "seed"), where)
        cb = None
        if "checkerboard" in v:
            c = v["checkerboard"]
            if not (isinstance(c, list) and len(c) == 2 and all(isinstance(x, int) and not isinstance(x, bool) and x >= 1 for x in c)):
                raise _err(where + "checkerboard", "two integers >= 1 (squares along u and v)", c)
            cb = (int(c[0]), int(c[1]))
        tex = _str(v, "texture", where) if "texture" in v else None
        proc = _str(v, "procedural", where) if "procedural" in v else None
        return cls(value=_num(v, "value", where, 1.0, nonneg=True), texture=tex, checkerboard=cb,
                   low=_num(v, "low", where, 0.0, nonneg=True), high=_num(v, "high", where, 1.0, nonneg=True),
                   procedural=proc, seed=_int(v, "seed", where, 0, minimum=0))

    def to_value(self):
        if self.is_constant:
            return self.value
        d: dict[str, Any] = {}
        if self.value != 1.0:
            d["value"] = self.value
        if self.texture is not None:
            d["texture"] = self.texture
        if self.checkerboard is not None:
            d["checkerboard"] = list(self.checkerboard)
            d["low"] = self.low
            d["high"] = self.high
        if self.procedural is not None:
            d["procedural"] = self.procedural
            d["seed"] = int(self.seed)
        return d


def _bounded(value, what: str, *, limit: str | None = None, hi=None) -> None:
    """Scene numbers that size memory or work are bounded before anything is built (a duration of
    9e18 µs used to end in a segfault, subdivisions = 30 or spp = 1e9 in hours of work); the
    ``limit`` ones are lifted by ``HYBRIDHDR_ALLOW_HUGE=1`` (``docs/security.md``)."""
    from .._util.limits import LimitExceeded, check_number
    try:
        check_number(value, what, lo=0, limit=limit, hi=hi)
    except LimitExceeded as e:
        raise SceneError(str(e)) from None
    except ValueError as e:
        raise SceneError(str(e)) from None


def _read_texture(name: str, base_dir: Path | None) -> np.ndarray:
    p = Path(name)
    if not p.is_absolute() and base_dir is not None:
        p = Path(base_dir) / p
    if not p.exists():
        raise FileNotFoundError(f"texture file {str(p)!r} not found")
    import imageio.v3 as iio
    from .._util.limits import LimitExceeded, check_input_file, open_image
    from ..errors import FormatError
    check_input_file(p, "texture")  # a FIFO or device would hang the decoder
    try:  # the header's size checked first: a decompression bomb is one error line
        img = np.asarray(open_image(p, "texture"))
    except LimitExceeded as e:
        raise SceneError(f"texture {str(p)!r}: {e}") from None
    except FormatError:  # not a format PIL reads (EXR ...): imageio
        img = np.asarray(iio.imread(p))
    if img.dtype == np.uint8 or img.dtype == np.uint16:
        x = img.astype(np.float64) / np.iinfo(img.dtype).max
        x = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)  # sRGB EOTF (IEC 61966-2-1)
    else:
        x = img.astype(np.float64)
    if x.ndim == 3:
        if x.shape[2] >= 3:
            x = 0.2126 * x[..., 0] + 0.7152 * x[..., 1] + 0.0722 * x[..., 2]  # Rec. 709 luminance
        else:
            x = x[..., 0]
    if x.ndim != 2:
        raise SceneError(f"texture {str(p)!r}: expected a 2-D image, found shape {img.shape}")
    return np.clip(x, 0, None).astype(np.float32)


@dataclass(frozen=True)
class Material:
    """Diffuse (Lambertian) reflectance, constant or a :class:`Pattern` over the UV square."""

    reflectance: Pattern = field(default_factory=lambda: Pattern(0.5))

    @classmethod
    def from_dict(cls, d: dict, where: str) -> "Material":
        _check_keys(d, ("reflectance",), where)
        return cls(reflectance=Pattern.from_value(d.get("reflectance", 0.5), where + "reflectance."))

    def to_dict(self) -> dict:
        return {"reflectance": self.reflectance.to_value()}


@dataclass(frozen=True)
class Emission:
    """Emitted radiance of a surface (Mitsuba ``area`` emitter), optionally blinking.

    ``sampling_weight`` is the Mitsuba emitter-sampling weight: 0 (default) means the surface is
    seen by the camera with its radiance but does not light other surfaces, which keeps the
    ``direct`` integrator noise free (``docs/simulate.md``, "Rendering").
    """

    radiance: Pattern
    blink: Blink | None = None
    sampling_weight: float = 0.0

    @classmethod
    def from_dict(cls, d: dict, where: str) -> "Emission":
        _check_keys(d, ("radiance", "blink", "sampling_weight"), where)
        if "radiance" not in d:
            raise SceneError(f"scene key {where + 'radiance'!r} is required")
        b = _table(d, "blink", where)
        return cls(radiance=Pattern.from_value(d["radiance"], where + "radiance."),
                   blink=None if b is None else Blink.from_dict(b, where + "blink."),
                   sampling_weight=_num(d, "sampling_weight", where, 0.0, nonneg=True))

    def to_dict(self) -> dict:
        d = {"radiance": self.radiance.to_value(), "sampling_weight": self.sampling_weight}
        if self.blink is not None:
            d["blink"] = self.blink.to_dict()
        return d


@dataclass(frozen=True)
class MeshSpec:
    """Geometry of an object, in object coordinates (metres).

    Kinds: ``box`` (``extents`` [x, y, z]), ``sphere``/``icosphere`` (``radius``,
    ``subdivisions``), ``plane`` (``size`` [u, v]: a quad in the object's x-y plane, normal -z,
    i.e. facing a camera that looks along +z; u along +x, v along -y so an image appears upright
    to that camera, UVs on [0, 1]²), ``cylinder``/``cone``/``capsule`` (``radius``, ``height``,
    ``sections``; axis z), ``file`` (``path``: PLY/OBJ/GLB/STL loaded with trimesh, relative to the
    scene file).
    """

    kind: str
    extents: tuple[float, float, float] | None = None
    radius: float | None = None
    height: float | None = None
    size: tuple[float, float] | None = None
    subdivisions: int = 2
    sections: int = 24
    path: str | None = None

    def __post_init__(self):
        _floats(self, "extents", "radius", "height", "size")
        _bounded(self.subdivisions, "mesh.subdivisions", limit="max_subdivisions")
        _bounded(self.sections, "mesh.sections", hi=65536)
        if self.kind not in MESH_KINDS:
            raise SceneError(f"mesh.type: expected one of {', '.join(MESH_KINDS)}, found {self.kind!r}")
        need = {"box": ("extents",), "sphere": ("radius",), "icosphere": ("radius",), "plane": ("size",),
                "cylinder": ("radius", "height"), "cone": ("radius", "height"), "capsule": ("radius", "height"),
                "file": ("path",)}[self.kind]
        for n in need:
            if getattr(self, n) is None:
                raise SceneError(f"mesh of type {self.kind!r} needs {n!r}")

    _KEYS = {"box": ("extents",), "sphere": ("radius", "subdivisions"), "icosphere": ("radius", "subdivisions"),
             "plane": ("size",), "cylinder": ("radius", "height", "sections"),
             "cone": ("radius", "height", "sections"), "capsule": ("radius", "height", "sections"),
             "file": ("path",)}

    @classmethod
    def from_dict(cls, d: dict, where: str) -> "MeshSpec":
        kind = _str(d, "type", where, choices=MESH_KINDS)
        _check_keys(d, ("type",) + cls._KEYS[kind], where)
        kw: dict[str, Any] = {"kind": kind}
        if "extents" in d:
            kw["extents"] = _vec(d, "extents", where, 3)
        if "size" in d:
            kw["size"] = _vec(d, "size", where, 2)
        if "radius" in d:
            kw["radius"] = _num(d, "radius", where, positive=True)
        if "height" in d:
            kw["height"] = _num(d, "height", where, positive=True)
        if "subdivisions" in d:
            kw["subdivisions"] = _int(d, "subdivisions", where, minimum=0)
        if "sections" in d:
            kw["sections"] = _int(d, "sections", where, minimum=3)
        if "path" in d:
            kw["path"] = _str(d, "path", where)
        return cls(**kw)

    def to_dict(self) -> dict:
        d: dict[str, Any] = {"type": self.kind}
        for k in self._KEYS[self.kind]:
            v = getattr(self, k)
            d[k] = list(v) if isinstance(v, tuple) else v
        return d

    def build(self, base_dir: Path | None = None):
        """A ``trimesh.Trimesh`` in object coordinates, with UVs where the kind defines them.

        Returns
        -------
        (trimesh.Trimesh, ndarray of shape (V, 2) float32 or None)
        """
        import trimesh
        uv = None
        if self.kind == "box":
            m = trimesh.creation.box(extents=self.extents)
        elif self.kind in ("sphere", "icosphere"):
            m = trimesh.creation.icosphere(subdivisions=self.subdivisions, radius=self.radius)
        elif self.kind == "plane":
            su, sv = self.size
            v = np.array([[-su / 2, sv / 2, 0], [su / 2, sv / 2, 0], [su / 2, -sv / 2, 0], [-su / 2, -sv / 2, 0]])
            # faces wound so the normal is -z (towards a camera looking along +z)
            f = np.array([[0, 1, 2], [0, 2, 3]])
            m = trimesh.Trimesh(vertices=v, faces=f, process=False)
            # Mitsuba reads texel row 0 at v = 0: v = 0 on the top edge (-y) so images appear upright
            uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
        elif self.kind == "cylinder":
            m = trimesh.creation.cylinder(radius=self.radius, height=self.height, sections=self.sections)
        elif self.kind == "cone":
            m = trimesh.creation.cone(radius=self.radius, height=self.height, sections=self.sections)
        elif self.kind == "capsule":
            m = trimesh.creation.capsule(radius=self.radius, height=self.height, count=[self.sections, self.sections])
        else:
            p = Path(self.path)
            if not p.is_absolute() and base_dir is not None:
                p = Path(base_dir) / p
            if not p.exists():
                raise FileNotFoundError(f"mesh file {str(p)!r} not found")
            from .._util.limits import check_input_file
            check_input_file(p, "mesh file")  # a FIFO or device would hang the parser
            ext = p.suffix.lower().lstrip(".")
            if ext not in trimesh.available_formats():
                raise SceneError(f"mesh file {str(p)!r}: format {ext or '(no extension)'!r} is not one trimesh reads; "
                                 f"expected one of {', '.join(sorted(trimesh.available_formats()))}")
            try:
                m = trimesh.load(p, force="mesh", process=False)
            except Exception as e:  # a malformed file: trimesh's parsers raise anything (KeyError, ValueError...)
                raise SceneError(f"mesh file {str(p)!r}: not a readable {ext.upper()} mesh "
                                 f"({type(e).__name__}: {e})") from e
            if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
                raise SceneError(f"mesh file {str(p)!r}: expected a triangle mesh, found {type(m).__name__}")
            vis_uv = getattr(getattr(m, "visual", None), "uv", None)
            if vis_uv is not None and len(vis_uv) == len(m.vertices):
                uv = np.asarray(vis_uv, np.float32)
        return m, uv


@dataclass(frozen=True)
class Keyframe:
    """A pose at a time: ``position`` (metres) and ``quaternion`` [w, x, y, z] (local-to-world)."""

    t_us: int
    position: tuple[float, float, float]
    quaternion: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)

    def __post_init__(self):
        object.__setattr__(self, "t_us", int(self.t_us))
        _floats(self, "position", "quaternion")
        n = math.sqrt(sum(c * c for c in self.quaternion))
        if not 0.999 < n < 1.001:
            raise SceneError(f"keyframe at t_us={self.t_us}: quaternion {self.quaternion} is not unit length (norm {n:.4g})")

    @classmethod
    def from_dict(cls, d: dict, where: str, *, camera: bool) -> "Keyframe":
        _check_keys(d, ("t_us", "position", "quaternion", "look_at", "up"), where)
        pos = _vec(d, "position", where, 3, default=(0, 0, 0))
        if "look_at" in d and "quaternion" in d:
            raise SceneError(f"scene keys {where + 'quaternion'!r} and {where + 'look_at'!r}: give one, not both")
        if "look_at" in d:
            # cameras: the optical axis (+z) points at the target; objects: their +z axis does
            R = look_at_rotation(pos, _vec(d, "look_at", where, 3), _vec(d, "up", where, 3, default=(0, 1, 0)))
            q = quat_from_matrix(R)
        else:
            if "up" in d:
                raise SceneError(f"scene key {where + 'up'!r} only goes with 'look_at'")
            q4 = _vec(d, "quaternion", where, 4, default=(1, 0, 0, 0))
            n = math.sqrt(sum(c * c for c in q4))
            if not 0.999 < n < 1.001:
                raise _err(where + "quaternion", "a unit quaternion [w, x, y, z]", list(q4))
            q = tuple(c / n for c in q4)
        return cls(t_us=_int(d, "t_us", where, 0), position=pos, quaternion=q)

    def to_dict(self) -> dict:
        return {"t_us": self.t_us, "position": list(self.position), "quaternion": list(self.quaternion)}


@dataclass(frozen=True)
class Trajectory:
    """Keyframed pose over time.

    Positions are interpolated linearly or with a Catmull-Rom (finite-difference cardinal) cubic
    Hermite spline; rotations with quaternion slerp (constant angular velocity between keys).
    Before the first and after the last keyframe the pose is held.
    """

    keyframes: tuple[Keyframe, ...]
    interpolation: str = "linear"

    def __post_init__(self):
        if len(self.keyframes) == 0:
            raise SceneError("a trajectory needs at least one keyframe")
        if self.interpolation not in INTERPOLATIONS:
            raise SceneError(f"interpolation: expected one of {', '.join(INTERPOLATIONS)}, found {self.interpolation!r}")
        ts = [k.t_us for k in self.keyframes]
        for i in range(1, len(ts)):
            if ts[i] <= ts[i - 1]:
                raise SceneError(f"keyframe times must increase; keyframe {i} has t_us={ts[i]} after {ts[i - 1]}")

    @classmethod
    def static(cls, position=(0.0, 0.0, 0.0), quaternion=(1.0, 0.0, 0.0, 0.0)) -> "Trajectory":
        return cls((Keyframe(0, tuple(float(x) for x in position), tuple(float(x) for x in quaternion)),))

    @property
    def is_static(self) -> bool:
        k0 = self.keyframes[0]
        return all(k.position == k0.position and k.quaternion == k0.quaternion for k in self.keyframes)

    def _seg(self, t_us: float) -> tuple[int, float]:
        ts = [k.t_us for k in self.keyframes]
        if t_us <= ts[0] or len(ts) == 1:
            return 0, 0.0
        if t_us >= ts[-1]:
            return len(ts) - 2, 1.0
        i = int(np.searchsorted(ts, t_us, side="right")) - 1
        return i, (t_us - ts[i]) / (ts[i + 1] - ts[i])

    def _tangents(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Position derivatives (m/µs) at keys i and i+1 (finite differences, one-sided at the ends)."""
        P = [np.asarray(k.position, float) for k in self.keyframes]
        T = [k.t_us for k in self.keyframes]

        def m(j):
            a, b = max(0, j - 1), min(len(P) - 1, j + 1)
            return (P[b] - P[a]) / (T[b] - T[a])
        return m(i), m(i + 1)

    def _hermite(self, i: int):
        """Cubic coefficients c0..c3 (positions in m, s in [0, 1]) of segment i."""
        k0, k1 = self.keyframes[i], self.keyframes[i + 1]
        dt = k1.t_us - k0.t_us
        p0, p1 = np.asarray(k0.position, float), np.asarray(k1.position, float)
        m0, m1 = self._tangents(i)
        m0, m1 = m0 * dt, m1 * dt
        return p0, m0, 3 * (p1 - p0) - 2 * m0 - m1, 2 * (p0 - p1) + m0 + m1

    def pose(self, t_us: float) -> tuple[np.ndarray, np.ndarray]:
        """(R (3, 3) local-to-world rotation, p (3,) position in m) at ``t_us``."""
        if len(self.keyframes) == 1:
            k = self.keyframes[0]
            return matrix_from_quat(k.quaternion), np.asarray(k.position, float)
        i, s = self._seg(t_us)
        k0, k1 = self.keyframes[i], self.keyframes[i + 1]
        if self.interpolation == "linear":
            p = (1 - s) * np.asarray(k0.position, float) + s * np.asarray(k1.position, float)
        else:
            c0, c1, c2, c3 = self._hermite(i)
            p = c0 + s * (c1 + s * (c2 + s * c3))
        q = _slerp(np.asarray(k0.quaternion, float), np.asarray(k1.quaternion, float), s)
        return matrix_from_quat(q), p

    def speed_bounds(self, t0_us: float, t1_us: float) -> tuple[float, float]:
        """(max linear speed m/s, max angular speed rad/s) over ``[t0_us, t1_us]`` (exact for both
        interpolations: piecewise-constant for linear/slerp; for Catmull-Rom the maximum of the
        quadratic velocity's norm at the interval ends and its critical points)."""
        ks = self.keyframes
        if len(ks) == 1:
            return 0.0, 0.0
        vmax = wmax = 0.0
        for i in range(len(ks) - 1):
            a, b = ks[i].t_us, ks[i + 1].t_us
            lo, hi = max(a, t0_us), min(b, t1_us)
            if lo > hi:
                continue
            dt_s = (b - a) * 1e-6
            wmax = max(wmax, _quat_angle(np.asarray(ks[i].quaternion), np.asarray(ks[i + 1].quaternion)) / dt_s)
            if self.interpolation == "linear":
                v = np.linalg.norm(np.subtract(ks[i + 1].position, ks[i].position)) / dt_s
            else:
                _, c1, c2, c3 = self._hermite(i)
                s0, s1 = (lo - a) / (b - a), (hi - a) / (b - a)
                # p'(s) = c1 + 2 c2 s + 3 c3 s^2; |p'|^2 is quartic, its critical points solve a cubic
                A, B, C = c1, 2 * c2, 3 * c3
                poly = [2 * np.dot(C, C), 3 * np.dot(B, C), np.dot(B, B) + 2 * np.dot(A, C), np.dot(A, B)]
                cands = [s0, s1]
                if any(abs(c) > 0 for c in poly):
                    for r in np.roots(np.trim_zeros(poly, "f")) if np.any(poly) else []:
                        if abs(r.imag) < 1e-9 and s0 <= r.real <= s1:
                            cands.append(r.real)
                v = max(np.linalg.norm(A + B * s + C * s * s) for s in cands) / dt_s
            vmax = max(vmax, float(v))
        return vmax, wmax

    @classmethod
    def from_dict(cls, d: dict, where: str, *, camera: bool) -> "Trajectory":
        """From a table holding ``keyframes`` (array of tables) or a static ``position``/``quaternion``/``look_at``."""
        interp = _str(d, "interpolation", where, "linear", choices=INTERPOLATIONS)
        if "keyframes" in d:
            kfs = d["keyframes"]
            if not isinstance(kfs, list) or not kfs or not all(isinstance(k, dict) for k in kfs):
                raise _err(where + "keyframes", "a non-empty array of tables", kfs)
            for n in ("position", "quaternion", "look_at", "up"):
                if n in d:
                    raise SceneError(f"scene key {where + n!r}: give the pose in 'keyframes' or directly, not both")
            return cls(tuple(Keyframe.from_dict(k, f"{where}keyframes[{i}].", camera=camera) for i, k in enumerate(kfs)),
                       interp)
        sub = {k: d[k] for k in ("position", "quaternion", "look_at", "up") if k in d}
        return cls((Keyframe.from_dict(sub, where, camera=camera),), interp)

    def to_dict(self) -> dict:
        if len(self.keyframes) == 1:
            k = self.keyframes[0]
            return {"position": list(k.position), "quaternion": list(k.quaternion)}
        return {"interpolation": self.interpolation, "keyframes": [k.to_dict() for k in self.keyframes]}


def load_calibration(path) -> tuple[float, float, float, float, int, int]:
    """Read a pinhole calibration JSON: ``{"K": [[fx,0,cx],[0,fy,cy],[0,0,1]], "image_size": [W, H]}``.

    Returns (fx, fy, cx, cy, width, height). Extra keys (distortion etc.) are ignored: the
    renderer is an ideal pinhole.
    """
    p = Path(path)
    try:
        from .._util.limits import read_text_bounded
        d = json.loads(read_text_bounded(p, "calibration file"))
    except json.JSONDecodeError as e:
        raise SceneError(f"calibration file {str(p)!r}: not valid JSON ({e})") from None
    K = d.get("K") if isinstance(d, dict) else None
    try:
        K = np.asarray(K, dtype=float)
    except (TypeError, ValueError):
        K = None
    if K is None or K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise SceneError(f"calibration file {str(p)!r}: expected 'K' as a 3x3 matrix, found {d.get('K') if isinstance(d, dict) else d!r}")
    size = d.get("image_size")
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        raise SceneError(f"calibration file {str(p)!r}: expected 'image_size' as [width, height] integers, found {size!r}")
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(size[0]), int(size[1])


@dataclass(frozen=True)
class CameraSpec:
    """Pinhole camera: intrinsics (pixels, OpenCV pixel-centre convention) and trajectory.

    Mitsuba's perspective sensor has square pixels, so ``fx`` must equal ``fy`` (within 0.1 %).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    trajectory: Trajectory = field(default_factory=Trajectory.static)

    def __post_init__(self):
        _floats(self, "fx", "fy", "cx", "cy")
        if self.width < 1 or self.height < 1:
            raise SceneError(f"camera size: expected positive width and height, found {self.width}x{self.height}")
        _bounded(self.width, "camera.width", limit="max_side")
        _bounded(self.height, "camera.height", limit="max_side")
        if self.fx <= 0 or self.fy <= 0:
            raise SceneError(f"camera fx, fy: expected > 0, found {self.fx}, {self.fy}")
        if abs(self.fx - self.fy) > 1e-3 * self.fx:
            raise SceneError(f"camera fx={self.fx} and fy={self.fy} differ: the renderer has square pixels "
                             "(expected fx == fy within 0.1 %)")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def resized(self, width: int, height: int) -> "CameraSpec":
        """The same horizontal field of view on a ``width`` × ``height`` grid: fx and fy scale with the
        width (pixels stay square), the principal point keeps its relative position (scaled about
        pixel edges); a different aspect ratio changes the vertical field of view."""
        sx, sy = width / self.width, height / self.height
        return replace(self, width=int(width), height=int(height), fx=self.fx * sx, fy=self.fy * sx,
                       cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5)

    def project(self, X_world, t_us: float = 0.0) -> np.ndarray:
        """Pixel coordinates (N, 2) [u, v] of world points (N, 3) at ``t_us`` (no visibility test)."""
        R, p = self.trajectory.pose(t_us)
        Xc = (np.atleast_2d(np.asarray(X_world, float)) - p) @ R
        return np.stack([self.fx * Xc[:, 0] / Xc[:, 2] + self.cx, self.fy * Xc[:, 1] / Xc[:, 2] + self.cy], axis=1)

    @classmethod
    def from_dict(cls, d: dict, where: str, base_dir: Path | None) -> "CameraSpec":
        _check_keys(d, ("width", "height", "fx", "fy", "cx", "cy", "fov_deg", "calibration", "interpolation",
                        "keyframes", "position", "quaternion", "look_at", "up"), where)
        traj = Trajectory.from_dict(d, where, camera=True)
        if "calibration" in d:
            cp = Path(_str(d, "calibration", where))
            if not cp.is_absolute() and base_dir is not None:
                cp = Path(base_dir) / cp
            if not cp.exists():
                raise FileNotFoundError(f"calibration file {str(cp)!r} (scene key {where + 'calibration'!r}) not found")
            fx, fy, cx, cy, w, h = load_calibration(cp)
            cam = cls(w, h, fx, fy, cx, cy, traj)
            if "width" in d or "height" in d:
                cam = cam.resized(_int(d, "width", where, w, minimum=1), _int(d, "height", where, h, minimum=1))
            return cam
        w = _int(d, "width", where, minimum=1)
        h = _int(d, "height", where, minimum=1)
        if "fov_deg" in d:
            fov = _num(d, "fov_deg", where, positive=True)
            if fov >= 180:
                raise _err(where + "fov_deg", "a horizontal field of view in (0, 180) degrees", fov)
            f = w / (2 * math.tan(math.radians(fov) / 2))
            fx = fy = f
        else:
            fx = _num(d, "fx", where, positive=True)
            fy = _num(d, "fy", where, fx, positive=True)
        return cls(w, h, fx, fy, _num(d, "cx", where, (w - 1) / 2), _num(d, "cy", where, (h - 1) / 2), traj)

    def to_dict(self) -> dict:
        d = {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy}
        d.update(self.trajectory.to_dict())
        return d


@dataclass(frozen=True)
class Emitter:
    """A light source (Mitsuba delta lights or a constant environment).

    Kinds and their fields:

    - ``point``: ``position``, ``intensity`` (radiant intensity, W/sr).
    - ``spot``: ``position``, ``look_at`` (a point the spot aims at), ``intensity``,
      ``cutoff_deg`` (half-angle of the cone), ``beam_width_deg`` (half-angle of the full-intensity core).
    - ``directional``: ``direction`` (the direction light travels), ``irradiance`` (W/m²).
    - ``constant``: ``radiance`` of an environment seen in every direction (noisy with ``direct``:
      keep it dim and give it a low ``sampling_weight``).

    ``attached_to_camera`` puts ``position``/``look_at``/``direction`` in the camera frame (OpenCV
    axes), e.g. car headlights. ``blink`` modulates the emitted power.
    """

    kind: str
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    look_at: tuple[float, float, float] = (0.0, 0.0, 1.0)
    direction: tuple[float, float, float] = (0.0, -1.0, 0.0)
    intensity: float = 1.0
    irradiance: float = 1.0
    radiance: float = 1.0
    cutoff_deg: float = 20.0
    beam_width_deg: float = 15.0
    attached_to_camera: bool = False
    blink: Blink | None = None
    sampling_weight: float = 1.0

    def __post_init__(self):
        _floats(self, "position", "look_at", "direction", "intensity", "irradiance", "radiance", "cutoff_deg",
                "beam_width_deg", "sampling_weight")
        if self.kind not in EMITTER_KINDS:
            raise SceneError(f"emitter type: expected one of {', '.join(EMITTER_KINDS)}, found {self.kind!r}")
        if min(self.intensity, self.irradiance, self.radiance) < 0:
            raise SceneError("emitter intensity/irradiance/radiance must be >= 0")
        if not 0 < self.beam_width_deg <= self.cutoff_deg < 90:
            raise SceneError(f"spot angles: expected 0 < beam_width_deg <= cutoff_deg < 90, found "
                             f"{self.beam_width_deg}, {self.cutoff_deg}")

    _FIELDS = {"point": ("position", "intensity"),
               "spot": ("position", "look_at", "intensity", "cutoff_deg", "beam_width_deg"),
               "directional": ("direction", "irradiance"), "constant": ("radiance",)}

    @classmethod
    def from_dict(cls, d: dict, where: str) -> "Emitter":
        kind = _str(d, "type", where, choices=EMITTER_KINDS)
        own = cls._FIELDS[kind]
        _check_keys(d, ("type", "attached_to_camera", "blink", "sampling_weight") + own, where)
        kw: dict[str, Any] = {"kind": kind}
        for n in own:
            if n in ("position", "look_at", "direction"):
                kw[n] = _vec(d, n, where, 3)
            elif n in ("cutoff_deg", "beam_width_deg"):
                if n in d:
                    kw[n] = _num(d, n, where, positive=True)
            else:
                kw[n] = _num(d, n, where, nonneg=True)
        if "attached_to_camera" in d:
            if not isinstance(d["attached_to_camera"], bool):
                raise _err(where + "attached_to_camera", "true or false", d["attached_to_camera"])
            kw["attached_to_camera"] = d["attached_to_camera"]
        b = _table(d, "blink", where)
        if b is not None:
            kw["blink"] = Blink.from_dict(b, where + "blink.")
        kw["sampling_weight"] = _num(d, "sampling_weight", where, 1.0, nonneg=True)
        return cls(**kw)

    def to_dict(self) -> dict:
        d: dict[str, Any] = {"type": self.kind}
        for n in self._FIELDS[self.kind]:
            v = getattr(self, n)
            d[n] = list(v) if isinstance(v, tuple) else v
        if self.attached_to_camera:
            d["attached_to_camera"] = True
        if self.blink is not None:
            d["blink"] = self.blink.to_dict()
        d["sampling_weight"] = self.sampling_weight
        return d


@dataclass(frozen=True)
class SceneObject:
    """A mesh with a material, an optional emission, a scale and a pose trajectory."""

    name: str
    mesh: MeshSpec
    material: Material = field(default_factory=Material)
    emission: Emission | None = None
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    trajectory: Trajectory = field(default_factory=Trajectory.static)

    def __post_init__(self):
        _floats(self, "scale")
        if len(self.scale) != 3 or min(self.scale) <= 0:
            raise SceneError(f"object {self.name!r}: scale must be 3 numbers > 0, found {self.scale}")

    @classmethod
    def from_dict(cls, d: dict, where: str) -> "SceneObject":
        _check_keys(d, ("name", "mesh", "material", "emission", "scale", "interpolation", "keyframes",
                        "position", "quaternion", "look_at", "up"), where)
        name = _str(d, "name", where)
        mesh = MeshSpec.from_dict(_table(d, "mesh", where, required=True), where + "mesh.")
        mt = _table(d, "material", where)
        em = _table(d, "emission", where)
        sc = d.get("scale", 1.0)
        if isinstance(sc, (int, float)) and not isinstance(sc, bool):
            if sc <= 0:
                raise _err(where + "scale", "a number > 0 or 3 numbers", sc)
            scale = (float(sc),) * 3
        else:
            scale = _vec(d, "scale", where, 3)
        return cls(name=name, mesh=mesh, material=Material() if mt is None else Material.from_dict(mt, where + "material."),
                   emission=None if em is None else Emission.from_dict(em, where + "emission."),
                   scale=scale, trajectory=Trajectory.from_dict(d, where, camera=False))

    def to_dict(self) -> dict:
        d: dict[str, Any] = {"name": self.name, "scale": list(self.scale)}
        d.update(self.trajectory.to_dict())
        d["mesh"] = self.mesh.to_dict()
        d["material"] = self.material.to_dict()
        if self.emission is not None:
            d["emission"] = self.emission.to_dict()
        return d


@dataclass(frozen=True)
class RenderSettings:
    """Mitsuba settings: samples per pixel, integrator (``direct`` keeps delta-light scenes noise
    free apart from anti-aliasing; ``path`` adds indirect light and noise), ``max_depth`` for
    ``path``, and the sampler seed used for every render (fixed so static pixels do not flicker)."""

    spp: int = 4
    integrator: str = "direct"
    max_depth: int = 3
    seed: int = 0

    def __post_init__(self):
        if self.spp < 1:
            raise SceneError(f"render.spp: expected >= 1, found {self.spp}")
        _bounded(self.spp, "render.spp", limit="max_spp")
        if self.integrator not in INTEGRATORS:
            raise SceneError(f"render.integrator: expected one of {', '.join(INTEGRATORS)}, found {self.integrator!r}")

    @classmethod
    def from_dict(cls, d: dict, where: str) -> "RenderSettings":
        _check_keys(d, ("spp", "integrator", "max_depth", "seed"), where)
        return cls(spp=_int(d, "spp", where, 4, minimum=1),
                   integrator=_str(d, "integrator", where, "direct", choices=INTEGRATORS),
                   max_depth=_int(d, "max_depth", where, 3, minimum=1), seed=_int(d, "seed", where, 0, minimum=0))

    def to_dict(self) -> dict:
        return {"spp": self.spp, "integrator": self.integrator, "max_depth": self.max_depth, "seed": self.seed}


@dataclass(frozen=True)
class Scene:
    """A complete scene: camera, objects, emitters, render settings and duration.

    ``base_dir`` resolves relative file names (textures, meshes); ``info`` is free-form metadata
    copied into ``describe()`` (e.g. the checkerboard geometry of a calibration scene).
    """

    name: str
    duration_us: int
    camera: CameraSpec
    objects: tuple[SceneObject, ...] = ()
    emitters: tuple[Emitter, ...] = ()
    render: RenderSettings = field(default_factory=RenderSettings)
    info: dict = field(default_factory=dict, compare=True)
    base_dir: str | None = field(default=None, compare=False)

    def __post_init__(self):
        if self.duration_us <= 0:
            raise SceneError(f"duration_us: expected > 0, found {self.duration_us}")
        _bounded(self.duration_us, "duration_us", limit="max_duration_us")
        names = [o.name for o in self.objects]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise SceneError(f"object names must be unique; repeated: {sorted(dup)}")
        if not self.emitters and not any(o.emission is not None for o in self.objects):
            raise SceneError("the scene has no light: add an [[emitters]] entry or an object with 'emission'")

    _KEYS = ("name", "duration_us", "camera", "objects", "emitters", "render", "info")

    @classmethod
    def from_dict(cls, d: dict, base_dir=None) -> "Scene":
        """Build from a dict of the TOML layout (see ``docs/simulate.md``); raises :class:`SceneError`."""
        _check_keys(d, cls._KEYS, "")
        cam = CameraSpec.from_dict(_table(d, "camera", "", required=True), "camera.",
                                   None if base_dir is None else Path(base_dir))
        objs = d.get("objects", [])
        if not isinstance(objs, list) or not all(isinstance(o, dict) for o in objs):
            raise _err("objects", "an array of tables ([[objects]])", objs)
        ems = d.get("emitters", [])
        if not isinstance(ems, list) or not all(isinstance(o, dict) for o in ems):
            raise _err("emitters", "an array of tables ([[emitters]])", ems)
        r = _table(d, "render", "")
        info = _table(d, "info", "") or {}
        return cls(name=_str(d, "name", "", "scene"), duration_us=_int(d, "duration_us", "", minimum=1),
                   camera=cam, objects=tuple(SceneObject.from_dict(o, f"objects[{i}].") for i, o in enumerate(objs)),
                   emitters=tuple(Emitter.from_dict(e, f"emitters[{i}].") for i, e in enumerate(ems)),
                   render=RenderSettings() if r is None else RenderSettings.from_dict(r, "render."),
                   info=dict(info), base_dir=None if base_dir is None else os.fspath(base_dir))

    def to_dict(self) -> dict:
        d: dict[str, Any] = {"name": self.name, "duration_us": self.duration_us,
                             "render": self.render.to_dict(), "camera": self.camera.to_dict()}
        if self.info:
            d["info"] = dict(self.info)
        d["emitters"] = [e.to_dict() for e in self.emitters]
        d["objects"] = [o.to_dict() for o in self.objects]
        return d

    def with_changes(self, *, width: int | None = None, height: int | None = None,
                     duration_us: int | None = None, spp: int | None = None, seed: int | None = None) -> "Scene":
        """A copy with another resolution (intrinsics scaled), duration, spp or render seed."""
        cam = self.camera
        if width is not None or height is not None:
            cam = cam.resized(width or cam.width, height or cam.height)
        r = self.render
        if spp is not None:
            r = replace(r, spp=int(spp))
        if seed is not None:
            r = replace(r, seed=int(seed))
        return replace(self, camera=cam, render=r,
                       duration_us=self.duration_us if duration_us is None else int(duration_us))


# ----------------------------------------------------------------------------------------------
# TOML
# ----------------------------------------------------------------------------------------------

def _toml_load(path: Path) -> dict:
    try:
        return load_toml(path)
    except TOMLDecodeError as e:
        raise SceneError(f"scene file {str(path)!r}: invalid TOML ({e})") from None


def scene_files(scene: Scene) -> list[tuple[str, str]]:
    """``[(key, path as written), ...]``: the files a scene reads when rendered (textures, meshes)."""
    out = []
    for i, o in enumerate(scene.objects):
        if o.mesh.kind == "file" and o.mesh.path:
            out.append((f"objects[{i}].mesh.path", o.mesh.path))
        if o.material.reflectance.texture:
            out.append((f"objects[{i}].material texture", o.material.reflectance.texture))
        if o.emission is not None and o.emission.radiance.texture:
            out.append((f"objects[{i}].emission texture", o.emission.radiance.texture))
    return out


def load_scene(path, allow_outside=()) -> Scene:
    """Read a scene TOML file (format: ``docs/simulate.md``); relative file names resolve against its folder.

    Every file the scene names (camera ``calibration``, mesh files, textures) must resolve inside
    the scene's folder or one of the ``allow_outside`` folders (``--allow-outside``), else
    :class:`hybridhdr._util.confine.OutsideFolderError` (``docs/security.md``)."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"scene file {str(p)!r} not found")
    d = _toml_load(p)
    base = p.resolve().parent
    cam = d.get("camera")
    if isinstance(cam, dict) and isinstance(cam.get("calibration"), str):  # read while the scene is built
        confine(cam["calibration"], base, allow_outside, what="camera.calibration", source=str(p))
    try:
        sc = Scene.from_dict(d, base_dir=base)
    except SceneError as e:
        raise SceneError(f"{p}: {e}") from None
    for key, f in scene_files(sc):
        confine(f, base, allow_outside, what=key, source=str(p))
    return sc


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # JSON basic strings are valid TOML basic strings
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, np.generic):
        return _toml_value(v.item())
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _toml_key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() and k.isascii() else json.dumps(k)


def _is_aot(v) -> bool:
    return isinstance(v, list) and len(v) > 0 and all(isinstance(x, dict) for x in v)


def _toml_dump(d: dict, prefix: str, out: list[str]) -> None:
    for k, v in d.items():
        if not isinstance(v, dict) and not _is_aot(v):
            out.append(f"{_toml_key(k)} = {_toml_value(v)}")
    for k, v in d.items():
        if isinstance(v, dict):
            out.append(f"\n[{prefix}{_toml_key(k)}]")
            _toml_dump(v, f"{prefix}{_toml_key(k)}.", out)
        elif _is_aot(v):
            for item in v:
                out.append(f"\n[[{prefix}{_toml_key(k)}]]")
                _toml_dump(item, f"{prefix}{_toml_key(k)}.", out)


def dumps_toml(d: dict) -> str:
    """A minimal TOML writer for scene dicts (tables, arrays of tables, scalars, arrays)."""
    out: list[str] = []
    _toml_dump(d, "", out)
    return "\n".join(out).lstrip("\n") + "\n"


def save_scene(scene: Scene, path) -> Path:
    """Write ``scene`` as TOML (atomically: a temporary name, then rename). Returns the path."""
    return write_text_atomic(path, dumps_toml(scene.to_dict()))
