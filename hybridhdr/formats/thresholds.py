"""The per-pixel ON/OFF contrast threshold map (:class:`ThresholdMap`) and its sidecar file.

``thresholds.npz`` (:meth:`ThresholdMap.save`, :func:`load_thresholds`) holds ``c_on``, ``c_off``
(H, W) float64 (log units; NaN: not estimable), the counts ``n_on``, ``n_off`` (events in the
usable intervals), ``n_intervals`` (usable intervals), the fallback values, the ``method`` and a
JSON ``provenance``. :func:`hybridhdr.calibrate.thresholds.estimate_thresholds` produces the map;
the container stores it too (``/thresholds``, :func:`hybridhdr.formats.container.store_thresholds`);
reconstruct uses it per pixel. The estimator is derived in ``docs/calibrate.md``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from .._util.atomic import atomic_path
from .._util.checks import check_range, check_shape

__all__ = ["ThresholdMap", "load_thresholds", "THRESHOLDS_FORMAT", "THRESHOLDS_VERSION", "METHOD"]

THRESHOLDS_FORMAT = "hybridhdr-thresholds"
THRESHOLDS_VERSION = 1
#: Name of the estimator stored in the file.
METHOD = "frame_event_nnls"


def _num(v, name) -> float:
    return check_range(v, f"ThresholdMap.{name}", lo=0, lo_open=True, unit="log units")


@dataclasses.dataclass(frozen=True, eq=False)
class ThresholdMap:
    """Per-pixel ON/OFF contrast thresholds (natural-log units) with a global fallback.

    Attributes
    ----------
    c_on, c_off : ndarray (H, W) float64
        Thresholds; finite and > 0 where estimated, NaN where not estimable (never ±inf).
    fallback_on, fallback_off : float
        Global estimates (> 0) for the NaN pixels (:meth:`filled`).
    n_on, n_off, n_intervals : ndarray (H, W) int64, optional
        ON and OFF events in the usable intervals and the number of usable intervals per pixel
        (zeros when not given).
    method : str
    provenance : dict
        JSON-serialisable: recording, profile, I0, settings, summary statistics.
    """

    c_on: np.ndarray
    c_off: np.ndarray
    fallback_on: float
    fallback_off: float
    n_on: np.ndarray | None = None
    n_off: np.ndarray | None = None
    n_intervals: np.ndarray | None = None
    method: str = METHOD
    provenance: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        arrs = {}
        for name in ("c_on", "c_off"):
            a = np.array(getattr(self, name), dtype=np.float64)
            check_shape(a, "H W", f"ThresholdMap.{name}")
            if np.isinf(a).any():
                raise ValueError(f"ThresholdMap.{name} has infinite entries; use NaN for 'not estimable'")
            fin = np.isfinite(a)
            if np.any(a[fin] <= 0):
                raise ValueError(f"ThresholdMap.{name} must be > 0 where finite, got min {a[fin].min()}")
            arrs[name] = a
        shape = arrs["c_on"].shape
        check_shape(arrs["c_off"], "H W", "ThresholdMap.c_off (like c_on)", sizes=dict(zip("HW", shape)))
        for name in ("n_on", "n_off", "n_intervals"):
            v = getattr(self, name)
            a = np.zeros(shape, np.int64) if v is None else np.asarray(v)
            check_shape(a, "H W", f"ThresholdMap.{name}", sizes=dict(zip("HW", shape)))
            if a.size and (a.dtype.kind not in "iu" or a.min() < 0):
                raise ValueError(f"ThresholdMap.{name} must hold non-negative integers")
            arrs[name] = a.astype(np.int64)
        for a in arrs.values():
            a.setflags(write=False)
        for k, a in arrs.items():
            object.__setattr__(self, k, a)
        object.__setattr__(self, "fallback_on", _num(self.fallback_on, "fallback_on"))
        object.__setattr__(self, "fallback_off", _num(self.fallback_off, "fallback_off"))
        if not isinstance(self.method, str):
            raise TypeError(f"ThresholdMap.method must be a str, got {type(self.method).__name__}")
        if not isinstance(self.provenance, dict):
            raise TypeError(f"ThresholdMap.provenance must be a dict, got {type(self.provenance).__name__}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return tuple(self.c_on.shape)

    @property
    def valid(self) -> np.ndarray:
        """Pixels with both thresholds estimated (bool (H, W))."""
        return np.isfinite(self.c_on) & np.isfinite(self.c_off)

    def filled(self) -> tuple[np.ndarray, np.ndarray]:
        """``(c_on, c_off)`` with every NaN replaced by the fallback (finite, > 0 everywhere).

        The rule is per polarity: a pixel whose ON estimate is NaN gets ``fallback_on``, one
        whose OFF estimate is NaN gets ``fallback_off`` (the estimator sets both or neither).
        """
        on = np.where(np.isfinite(self.c_on), self.c_on, self.fallback_on)
        off = np.where(np.isfinite(self.c_off), self.c_off, self.fallback_off)
        return on, off

    def summary(self) -> dict:
        """Medians, quartiles and the estimable fraction (JSON-serialisable)."""
        v = self.valid
        out = {"shape": list(self.shape), "n_pixels": int(v.size), "n_estimated": int(v.sum()),
               "fraction_estimated": float(v.mean()) if v.size else 0.0,
               "fallback_on": self.fallback_on, "fallback_off": self.fallback_off}
        for name, a in (("on", self.c_on), ("off", self.c_off)):
            x = a[v]
            q = np.percentile(x, [25, 50, 75]) if x.size else [float("nan")] * 3
            out[f"median_{name}"] = float(q[1])
            out[f"q25_{name}"], out[f"q75_{name}"] = float(q[0]), float(q[2])
        return out

    # -- file -------------------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write the sidecar ``.npz`` atomically (no pickles: the provenance is a JSON string)."""
        path = Path(path)
        with atomic_path(path, suffix=".npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, format=np.array(THRESHOLDS_FORMAT), version=np.array(THRESHOLDS_VERSION),
                                    c_on=self.c_on, c_off=self.c_off, n_on=self.n_on, n_off=self.n_off,
                                    n_intervals=self.n_intervals, fallback_on=np.array(self.fallback_on),
                                    fallback_off=np.array(self.fallback_off), method=np.array(self.method),
                                    provenance=np.array(json.dumps(self.provenance, default=_json_default)))
        return path


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


#: Contrast thresholds a file may hold (natural-log units). 1e-4 is a 0.01 % change of
#: intensity per event, two orders of magnitude below the finest threshold of any event sensor
#: (about 1 %); 10 is a factor of 22,000 per event, more than a frame's whole dynamic range. A
#: value outside is not a sensor's: c = 1e308 used to make reconstruct write +inf frames.
C_MIN_LOG, C_MAX_LOG = 1e-4, 10.0

#: Arrays of a thresholds file and the dtype kinds they may have.
_ARRAYS = {"c_on": "f", "c_off": "f", "n_on": "iu", "n_off": "iu", "n_intervals": "iu"}


def _check_members(path: Path, zf) -> None:
    """Every array's shape and size from its .npy header (read from the zip, before anything is
    decompressed in full): 2-D maps within the sensor-size limits, scalars for the rest, and no
    member that inflates beyond what its header declares."""
    from .._util.limits import check_frame_bytes, check_packet_size, check_sensor_size
    for info in zf.infolist():
        name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
        with zf.open(info) as f:
            try:
                version = np.lib.format.read_magic(f)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, fortran, dtype = read(f, max_header_size=10000)
            except (ValueError, OSError, EOFError) as e:
                raise ValueError(f"{path}: member {info.filename!r} is not a .npy array ({e})") from None
        if dtype.hasobject:
            raise ValueError(f"{path}: member {info.filename!r} holds Python objects; not read")
        n_bytes = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
        if name in _ARRAYS:
            if len(shape) != 2:
                raise ValueError(f"{path}: {name} must be a 2-D (H, W) map, its header declares shape {shape}")
            check_sensor_size(shape[0], shape[1], path, f"thresholds map {name}")
            check_frame_bytes(n_bytes, path, f"thresholds map {name}")
            if dtype.kind not in _ARRAYS[name]:
                raise ValueError(f"{path}: {name} has dtype {dtype}, expected "
                                 f"{'floating-point' if _ARRAYS[name] == 'f' else 'integer'}")
        else:
            check_packet_size(n_bytes, path, f"thresholds member {info.filename!r}")
        if info.file_size > n_bytes + 65536:
            raise ValueError(f"{path}: member {info.filename!r} inflates to {info.file_size:,} bytes, more than its "
                             f"header's {n_bytes:,}")


def load_thresholds(path) -> ThresholdMap:
    """Read a ``thresholds.npz`` written by :meth:`ThresholdMap.save` (or ``calibrate thresholds``).

    Raises ValueError with the reason for a file of another format or version, a missing key or
    invalid values (shapes, non-positive or infinite thresholds, thresholds outside
    [:data:`C_MIN_LOG`, :data:`C_MAX_LOG`]). The file must be a regular one (never a FIFO or a
    device); each array's shape is checked from its header before anything is allocated.
    """
    import zipfile

    from .._util.limits import check_input_file
    from ..errors import FormatError
    path = Path(path)
    try:
        check_input_file(path, "thresholds file")
        if path.is_dir():
            raise ValueError(f"{path}: is a folder; expected a thresholds .npz file")
        with zipfile.ZipFile(path) as zf:
            _check_members(path, zf)
        z = np.load(path, allow_pickle=False)
    except FormatError as e:
        raise ValueError(str(e)) from None
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, NotImplementedError, KeyError) as e:
        raise ValueError(f"{path}: not a thresholds .npz file (a damaged zip archive: {e})") from None
    except (ValueError, OSError) as e:
        if isinstance(e, ValueError) and str(e).startswith(str(path)):
            raise
        raise ValueError(f"{path}: not a thresholds .npz file ({e})") from None
    with z:
        keys = set(z.files)
        need = {"format", "version", "c_on", "c_off", "fallback_on", "fallback_off"}
        if not need <= keys:
            raise ValueError(f"{path}: missing keys {sorted(need - keys)}; expected a file written by "
                             f"'hybridhdr calibrate thresholds'")
        fmt = str(z["format"][()])
        if fmt != THRESHOLDS_FORMAT:
            raise ValueError(f"{path}: format {fmt!r}, expected {THRESHOLDS_FORMAT!r}")
        ver = int(z["version"][()])
        if ver != THRESHOLDS_VERSION:
            raise ValueError(f"{path}: version {ver}, this hybridhdr reads version {THRESHOLDS_VERSION}")
        try:
            prov = json.loads(str(z["provenance"][()])) if "provenance" in keys else {}
        except (ValueError, RecursionError) as e:
            raise ValueError(f"{path}: provenance is not valid JSON ({type(e).__name__})") from None
        if not isinstance(prov, dict):
            raise ValueError(f"{path}: provenance must be a JSON object")
        try:
            for name in ("c_on", "c_off"):
                a = np.asarray(z[name], dtype=np.float64)
                fin = a[np.isfinite(a)]
                if fin.size and (fin.min() < C_MIN_LOG or fin.max() > C_MAX_LOG):
                    raise ValueError(f"{name} holds values from {fin.min():g} to {fin.max():g} log units; a "
                                     f"contrast threshold lies in [{C_MIN_LOG:g}, {C_MAX_LOG:g}]")
            for name in ("fallback_on", "fallback_off"):
                check_range(float(z[name][()]), name, lo=C_MIN_LOG, hi=C_MAX_LOG, unit="log units")
            return ThresholdMap(c_on=z["c_on"], c_off=z["c_off"], fallback_on=float(z["fallback_on"][()]),
                                fallback_off=float(z["fallback_off"][()]),
                                n_on=z["n_on"] if "n_on" in keys else None,
                                n_off=z["n_off"] if "n_off" in keys else None,
                                n_intervals=z["n_intervals"] if "n_intervals" in keys else None,
                                method=str(z["method"][()]) if "method" in keys else "unknown", provenance=prov)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{path}: {e}") from None
