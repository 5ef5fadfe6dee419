"""ColorVideoVDP (Mantiuk et al., SIGGRAPH 2024) as the perceptual quality score of HDR video.

``cvvdp_jod(test, reference)`` returns a :class:`CVVDPResult`: quality in JOD (just-objectionable
differences; 10 = identical to the reference, each unit below is one JOD further away) of a test
video against its reference, for a **stated display model**. The default is cvvdp's
``standard_hdr_linear``: a 30-inch 4K HDR monitor, peak 1500 cd/m², contrast 10⁶:1, 10 lux
ambient, seen from 0.7472 m (2 × display height), linear BT.709 input. Every result carries the
display's name, its description and the viewing distance, and reports print them.

Inputs are relative linear intensities (the reconstructions and references of this toolkit):
test and reference are multiplied by the *same* factor so that the reference's maximum
(``anchor="max"``) or 99.9th percentile (``"p99.9"``) sits at the display's peak luminance,
then clipped to the display's range by the display model. Grey (K, H, W) videos are luminance;
(K, H, W, 3) are linear BT.709 RGB. ``fps`` > 0 evaluates a video (temporal channels), 0 each
frame as an image (the mean of their JODs).

Only cvvdp's base metric is used; it needs no download (its ML variants would fetch weights
and are never called). ``pip install 'hybridhdr[evaluate]'`` installs it (``cvvdp`` on PyPI,
with PyTorch >= 2.1). torchvision is used whenever it loads (torch and torchvision from one
source at matched versions, e.g. the PyTorch CPU index). PyPI's torchvision is linked against
CUDA PyTorch and cannot load beside a CPU build (a local wheel cache's ``+cpu`` torch, where
the CPU index cannot be reached); cvvdp uses only torchvision's Gaussian blur (and imports,
unused, an MLP class for its ML variant), so when torchvision cannot be imported this module
supplies those two names from a small pure-PyTorch stand-in for the duration of cvvdp's import
(tests/evaluate/test_cvvdp_torchvision.py runs both paths).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sys
import threading
import time
import types
import warnings
from dataclasses import asdict, dataclass

import numpy as np

from .._util.checks import check_shape

__all__ = ["CVVDPResult", "CVVDPNotAvailable", "cvvdp_jod", "cvvdp_available", "DEFAULT_DISPLAY", "display_model",
           "SCALE"]

DEFAULT_DISPLAY = "standard_hdr_linear"
SCALE = "JOD (10 = identical to the reference)"


class CVVDPNotAvailable(ImportError):
    """cvvdp (or PyTorch) is not installed: ``pip install 'hybridhdr[evaluate]'``."""


@dataclass(frozen=True)
class CVVDPResult:
    jod: float
    display: str                 # cvvdp display model key, e.g. "standard_hdr_linear"
    display_description: str     # the model's own description (size, peak, ambient, distance)
    viewing_distance_m: float
    peak_luminance_cd_m2: float
    pixels_per_degree: float
    fps: float
    n_frames: int
    seconds: float
    cvvdp_version: str

    def to_dict(self) -> dict:
        return asdict(self)

    def display_line(self) -> str:
        """One line for reports: the display model and viewing distance every score refers to."""
        return (f"ColorVideoVDP {self.cvvdp_version} ({SCALE}), display '{self.display}': "
                f"{self.display_description}; viewing distance {self.viewing_distance_m:.4g} m, "
                f"{self.pixels_per_degree:.1f} px/deg, peak {self.peak_luminance_cd_m2:g} cd/m²")


def _gaussian_blur_class(torch):
    class GaussianBlur(torch.nn.Module):
        """torchvision.transforms.GaussianBlur(kernel_size, sigma) with a fixed sigma: separable
        normalised Gaussian, reflect padding, over the last two axes."""

        def __init__(self, kernel_size, sigma=(0.1, 2.0)):
            super().__init__()
            k = (kernel_size, kernel_size) if isinstance(kernel_size, int) else tuple(kernel_size)
            s = (float(sigma), float(sigma)) if isinstance(sigma, (int, float)) else tuple(map(float, sigma))
            if s[0] != s[1]:
                raise ValueError("this stand-in supports a fixed sigma only")
            self.kernel_size, self.sigma = k, s[0]

        def _k1(self, n, dtype, device):
            x = torch.linspace(-(n - 1) / 2, (n - 1) / 2, n, dtype=dtype, device=device)
            w = torch.exp(-0.5 * (x / self.sigma) ** 2)
            return w / w.sum()

        def forward(self, img):
            shape = img.shape
            x = img.reshape((-1, 1) + tuple(shape[-2:]))
            kh, kw = self.kernel_size
            x = torch.nn.functional.pad(x, [kw // 2, kw // 2, kh // 2, kh // 2], mode="reflect")
            x = torch.nn.functional.conv2d(x, self._k1(kh, x.dtype, x.device).view(1, 1, kh, 1))
            x = torch.nn.functional.conv2d(x, self._k1(kw, x.dtype, x.device).view(1, 1, 1, kw))
            return x.reshape(shape)
    return GaussianBlur


def _import_pycvvdp():
    try:
        import torch
    except ImportError as e:
        raise CVVDPNotAvailable("ColorVideoVDP needs PyTorch: pip install 'hybridhdr[evaluate]'") from e
    try:
        import pycvvdp
        return pycvvdp
    except ModuleNotFoundError as e:
        if e.name and e.name.split(".")[0] == "pycvvdp":
            raise CVVDPNotAvailable("ColorVideoVDP is not installed: pip install 'hybridhdr[evaluate]' "
                                    "(cvvdp on PyPI)") from e
        if not (e.name and e.name.startswith("torchvision")):
            raise
    except (RuntimeError, OSError, ImportError) as e:  # torchvision built for another PyTorch
        if "torchvision" not in repr(e) and not any("torchvision" in m for m in sys.modules):
            raise
    for name in [m for m in sys.modules if m == "pycvvdp" or m.startswith(("pycvvdp.", "torchvision"))]:
        del sys.modules[name]
    tv = types.ModuleType("torchvision")
    tr = types.ModuleType("torchvision.transforms")
    ops = types.ModuleType("torchvision.ops")
    tr.GaussianBlur = _gaussian_blur_class(torch)

    class MLP:  # only cvvdp's ML variant (never used here) builds one
        def __init__(self, *a, **k):
            raise CVVDPNotAvailable("torchvision is unusable here; cvvdp's ML variants are not supported")
    ops.MLP = MLP
    tv.transforms, tv.ops = tr, ops
    saved = {k: sys.modules.get(k) for k in ("torchvision", "torchvision.transforms", "torchvision.ops")}
    sys.modules.update({"torchvision": tv, "torchvision.transforms": tr, "torchvision.ops": ops})
    try:
        import pycvvdp
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    return pycvvdp


_METRICS: dict = {}


def cvvdp_available() -> bool:
    try:
        _import_pycvvdp()
        return True
    except ImportError:
        return False


def _metric(display: str, device: str):
    key = (display, device)
    if key not in _METRICS:
        pycvvdp = _import_pycvvdp()
        import torch
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _METRICS[key] = pycvvdp.cvvdp(display_name=display, heatmap=None, quiet=True,
                                          device=torch.device(device))
    return _METRICS[key]


def display_model(display: str = DEFAULT_DISPLAY) -> dict:
    """The display model's description, peak luminance, viewing distance and px/deg."""
    pycvvdp = _import_pycvvdp()
    m = _metric(display, "cpu")
    geo, pho = m.display_geometry, m.display_photometry
    desc = ""
    try:
        import json
        from pathlib import Path
        models = json.loads((Path(pycvvdp.__file__).parent / "vvdp_data" / "display_models.json").read_text())
        desc = models.get(display, {}).get("name", "")
    except (OSError, ValueError):
        pass
    return {"display": display, "description": desc, "viewing_distance_m": float(geo.distance_m),
            "pixels_per_degree": float(m.pix_per_deg), "peak_luminance_cd_m2": float(pho.get_peak_luminance()),
            "version": str(getattr(pycvvdp, "__version__", "") or _version())}


def _version() -> str:
    try:
        from importlib.metadata import version
        return version("cvvdp")
    except Exception:  # noqa: BLE001
        return "unknown"


class _DropCvvdpWarnings:
    """A root-logger filter that drops pycvvdp's own warnings and notes (it logs "not in absolute
    photometric units" once per frame with ``logging.warning`` on the root logger); every other
    record passes. A filter, not ``logging.disable``: that is process-wide, and two metrics
    computed at once (a bench's threads) would restore each other's level, leaving every warning
    of the process off."""

    def filter(self, record) -> bool:
        return not (record.levelno <= logging.WARNING and f"{os.sep}pycvvdp{os.sep}" in (record.pathname or ""))


_DROP = _DropCvvdpWarnings()
_drop_lock = threading.Lock()
_drop_users = 0
_predict_lock = threading.Lock()


@contextlib.contextmanager
def _quiet_cvvdp():
    """pycvvdp's warnings off while the block runs (reference-counted across threads)."""
    global _drop_users
    root = logging.getLogger()
    with _drop_lock:
        _drop_users += 1
        if _drop_users == 1:
            root.addFilter(_DROP)
    try:
        yield
    finally:
        with _drop_lock:
            _drop_users -= 1
            if _drop_users == 0:
                root.removeFilter(_DROP)


def cvvdp_jod(test, reference, *, fps: float = 0.0, display: str = DEFAULT_DISPLAY, anchor: str = "max",
              device: str = "cpu") -> CVVDPResult:
    """ColorVideoVDP quality of ``test`` against ``reference`` in JOD (10 = identical).

    Parameters
    ----------
    test, reference : array (H, W), (K, H, W) or (K, H, W, 3)
        Linear intensities (relative units; scaled together, see the module docstring).
    fps : float
        Frame rate for video evaluation; 0 scores each frame as an image and averages the JODs.
    display : str
        cvvdp display model (default ``standard_hdr_linear``; see ``display_model``).
    anchor : {"max", "p99.9"}
        Which reference level maps to the display's peak luminance.
    """
    _import_pycvvdp()  # CVVDPNotAvailable (an ImportError) first when cvvdp or PyTorch is missing
    import torch
    t = np.asarray(test, np.float64)
    r = np.asarray(reference, np.float64)
    if t.shape != r.shape:
        raise ValueError(f"test and reference shapes differ: {t.shape} vs {r.shape}")
    if t.ndim == 2:
        t, r = t[None], r[None]
    check_shape(np.shape(test), "H W | K H W | K H W 3", "frames")
    if not (np.isfinite(t).all() and np.isfinite(r).all()):
        raise ValueError("test and reference must be finite")
    if anchor not in ("max", "p99.9"):
        raise ValueError(f"anchor must be 'max' or 'p99.9', got {anchor!r}")
    if not (isinstance(fps, (int, float)) and fps >= 0 and math.isfinite(fps)):
        raise ValueError(f"fps must be >= 0, got {fps!r}")
    m = _metric(display, device)
    peak = float(m.display_photometry.get_peak_luminance())
    level = float(r.max() if anchor == "max" else np.percentile(r, 99.9))
    gain = peak / level if level > 0 else 1.0
    t = np.clip(t * gain, 0, None).astype(np.float32)
    r = np.clip(r * gain, 0, None).astype(np.float32)
    order = "HW" if t.ndim == 3 else "HWC"
    t0 = time.perf_counter()
    # one prediction at a time per process: warnings.catch_warnings saves and restores the
    # process's filters, which two threads (a Dask cluster's) would cross like logging.disable
    with _predict_lock, _quiet_cvvdp(), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if fps > 0 and t.shape[0] > 1:
            q, _ = m.predict(torch.from_numpy(t), torch.from_numpy(r), dim_order="F" + order,
                             frames_per_second=float(fps))
            q = float(q)
        else:  # images: the mean JOD of the frames
            q = float(np.mean([float(m.predict(torch.from_numpy(a), torch.from_numpy(b), dim_order=order)[0])
                               for a, b in zip(t, r)]))
    dm = display_model(display)
    return CVVDPResult(jod=float(q), display=display, display_description=dm["description"],
                       viewing_distance_m=dm["viewing_distance_m"], peak_luminance_cd_m2=peak,
                       pixels_per_degree=dm["pixels_per_degree"], fps=float(fps), n_frames=int(t.shape[0]),
                       seconds=time.perf_counter() - t0, cvvdp_version=dm["version"])
