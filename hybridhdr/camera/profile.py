"""Camera profiles: the frame-noise model of the AKF (eqs. 3-9 of Wang et al. 2021).

A :class:`CameraProfile` maps raw pixel codes ``I^F`` of a frame camera to

* the scaled irradiance ``I = CRF^-1(I^F)`` (eq. 3), as a lookup table ``inverse_crf``;
* the weighting function ``f_w(I^F)`` (eq. 5, maximum 1), as a lookup table ``weighting``;
* the intensity-domain variance ``R̄ = 1 / (frame_precision_scale * max(f_w, min_weighting))``
  (eq. 6, with the saturation of eq. 6 expressed as a floor on ``f_w``).

``frame_precision_scale`` is the paper's "σ²_im" read as a *precision* (1/variance), which is how
the authors' implementation uses it (``ziweiWWANG/AKF:akf_reconstruction.m``): 7e5 for the DAVIS240C
and 7e7 for the FLIR camera (paper §6).

The file format is JSON; it is documented in ``docs/camera-profile.md``.

References
----------
Z. Wang, Y. Ng, C. Scheerlinck, R. Mahony, "An Asynchronous Kalman Filter for Hybrid Event
Cameras", ICCV 2021, pp. 448-457, doi:10.1109/ICCV48922.2021.00050.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._util.atomic import write_json_atomic
from .._util.checks import check_shape

__all__ = ["CameraProfile", "default_profile", "load_profile", "profile_for_frames", "profile_from_inverse_crf",
           "weighting_from_inverse_crf", "check_codes_in_profile", "PROFILE_FORMAT", "PROFILE_VERSION"]

PROFILE_FORMAT = "hybridhdr-camera-profile"
PROFILE_VERSION = 1


def _as_lut(values, name: str, n: int | None) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    check_shape(arr, "N", f"CameraProfile.{name} (max_code + 1 entries)", sizes=None if n is None else {"N": n})
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"CameraProfile.{name} must be finite, got non-finite entries")
    arr = arr.copy()
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class CameraProfile:
    """Frame-camera noise model: weighting LUT, inverse CRF LUT and precision scale (eqs. 3-6).

    Parameters
    ----------
    weighting : array_like of shape (max_code + 1,)
        Weighting function ``f_w`` (eq. 5) per raw code, in [0, 1] with maximum 1.
    inverse_crf : array_like of shape (max_code + 1,), optional
        Scaled irradiance ``CRF^-1(code)`` (eq. 3) per code, non-decreasing, normalised so that
        the largest code maps to 1. ``None`` means a linear response, ``code / max_code``.
    frame_precision_scale : float
        Precision scale 1/σ²_im of eq. 6 in 1/intensity²: 7e5 for DAVIS240C, 7e7 for FLIR (§6).
    min_weighting : float
        Floor on ``f_w`` before inversion: the saturation of eq. 6 (reference code: 0.09).
    clip_low_code, clip_high_code : int or None
        Clip levels: a code ``<= clip_low_code`` only says the intensity is *at most* that of
        the code's upper quantisation edge, a code ``>= clip_high_code`` that it is *at least*
        that of the code's lower edge (saturation as a bound, :meth:`bounds`). Defaults: 0 and
        ``max_code``. ``clip_high_code`` is the code whose intensity the frame-linear unit is
        (1.0 = the clip level): a measured ``inverse_crf`` is normalised there.
    name, source : str
        Free text: camera name and where the profile came from.

    Notes
    -----
    Codes between LUT entries (float frames) are linearly interpolated; codes outside
    ``[0, max_code]`` are clipped.
    """

    weighting: np.ndarray
    inverse_crf: np.ndarray | None = None
    frame_precision_scale: float = 7e5
    min_weighting: float = 0.09
    name: str = ""
    source: str = ""
    extra: dict = field(default_factory=dict)
    clip_low_code: int = 0
    clip_high_code: int | None = None

    def __post_init__(self):
        w = _as_lut(self.weighting, "weighting", None)
        if w.shape[0] < 2:
            raise ValueError(f"CameraProfile.weighting needs at least 2 entries, got {w.shape[0]}")
        if np.any(w < 0) or np.any(w > 1 + 1e-12):
            raise ValueError("CameraProfile.weighting must lie in [0, 1] (eq. 5 is normalised to a "
                             f"maximum of 1), got range [{w.min()}, {w.max()}]")
        object.__setattr__(self, "weighting", w)
        if self.inverse_crf is not None:
            c = _as_lut(self.inverse_crf, "inverse_crf", w.shape[0])
            if np.any(np.diff(c) < 0):
                raise ValueError("CameraProfile.inverse_crf must be non-decreasing")
            if c[0] < 0:
                raise ValueError(f"CameraProfile.inverse_crf must be >= 0, got {c[0]} at code 0")
            object.__setattr__(self, "inverse_crf", c)
        for name in ("frame_precision_scale", "min_weighting"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
                raise TypeError(f"CameraProfile.{name} must be a number, got {type(v).__name__}")
            object.__setattr__(self, name, float(v))
        if not (math.isfinite(self.frame_precision_scale) and self.frame_precision_scale > 0):
            raise ValueError(f"CameraProfile.frame_precision_scale must be > 0, got {self.frame_precision_scale}")
        if not 0 < self.min_weighting <= 1:
            raise ValueError(f"CameraProfile.min_weighting must be in (0, 1], got {self.min_weighting}")
        hi = self.max_code if self.clip_high_code is None else self.clip_high_code
        lo = self.clip_low_code
        for name, v in (("clip_low_code", lo), ("clip_high_code", hi)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise TypeError(f"CameraProfile.{name} must be an int code, got {type(v).__name__} {v!r}")
        if not 0 <= int(lo) < int(hi) <= self.max_code:
            raise ValueError(f"CameraProfile clip codes must satisfy 0 <= clip_low_code < clip_high_code <= "
                             f"max_code = {self.max_code}, got {lo} and {hi}")
        object.__setattr__(self, "clip_low_code", int(lo))
        object.__setattr__(self, "clip_high_code", int(hi))

    @property
    def max_code(self) -> int:
        """Largest raw code (255 for 8-bit frames)."""
        return int(self.weighting.shape[0] - 1)

    # -- evaluation --------------------------------------------------------------------------
    def _codes(self, codes) -> np.ndarray:
        c = np.asarray(codes)
        if c.dtype.kind not in "uif":
            raise TypeError(f"frame codes must be numeric, got dtype {c.dtype}")
        return np.clip(c.astype(np.float64, copy=False), 0.0, float(self.max_code))

    def intensity(self, codes) -> np.ndarray:
        """Scaled irradiance ``I = CRF^-1(code)`` (eq. 3), float64, same shape as ``codes``."""
        c = self._codes(codes)
        if self.inverse_crf is None:
            return c / float(self.max_code)
        return np.interp(c, np.arange(self.max_code + 1, dtype=np.float64), self.inverse_crf)

    def censor(self, codes) -> np.ndarray:
        """Censoring direction per code: +1 for a clipped bright code (the intensity is a lower
        bound), -1 for a clipped dark code (an upper bound), 0 for a value; float64."""
        c = self._codes(codes)
        return np.where(c >= self.clip_high_code, 1.0, np.where(c <= self.clip_low_code, -1.0, 0.0))

    def bounds(self) -> tuple[float, float]:
        """``(dark, bright)``: the intensity bounds a clipped code carries (frame-linear units).

        A code ``<= clip_low_code`` says ``I <= CRF^-1(clip_low_code + 1/2)`` and a code
        ``>= clip_high_code`` says ``I >= CRF^-1(clip_high_code - 1/2)``: the edges of the
        quantisation intervals next to the clip levels.
        """
        lo, hi = self.intensity([self.clip_low_code + 0.5, self.clip_high_code - 0.5])
        return float(lo), float(hi)

    def variance(self, codes) -> np.ndarray:
        """Intensity-domain variance ``R̄ = 1/(scale * max(f_w, floor))`` of eq. 6, float64."""
        c = self._codes(codes)
        w = np.interp(c, np.arange(self.max_code + 1, dtype=np.float64), self.weighting)
        return 1.0 / (self.frame_precision_scale * np.maximum(w, self.min_weighting))

    # -- file format -------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"format": PROFILE_FORMAT, "version": PROFILE_VERSION, "name": self.name,
                "source": self.source, "max_code": self.max_code,
                "frame_precision_scale": self.frame_precision_scale,
                "min_weighting": self.min_weighting,
                "weighting": [float(v) for v in self.weighting],
                "inverse_crf": None if self.inverse_crf is None else [float(v) for v in self.inverse_crf],
                "clip_low_code": self.clip_low_code, "clip_high_code": self.clip_high_code,
                "extra": dict(self.extra)}

    @classmethod
    def from_dict(cls, d: dict) -> "CameraProfile":
        if not isinstance(d, dict):
            raise TypeError(f"camera profile must be a JSON object, got {type(d).__name__}")
        if d.get("format") != PROFILE_FORMAT:
            raise ValueError(f"camera profile 'format' must be {PROFILE_FORMAT!r}, got {d.get('format')!r}")
        if d.get("version") != PROFILE_VERSION:
            raise ValueError(f"camera profile 'version' must be {PROFILE_VERSION}, got {d.get('version')!r}")
        for key in ("weighting", "frame_precision_scale"):
            if key not in d:
                raise ValueError(f"camera profile is missing the required key {key!r}")
        known = {"format", "version", "name", "source", "max_code", "frame_precision_scale",
                 "min_weighting", "weighting", "inverse_crf", "extra", "clip_low_code", "clip_high_code"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"camera profile has unknown keys {unknown}; expected a subset of {sorted(known)}")
        prof = cls(weighting=d["weighting"], inverse_crf=d.get("inverse_crf"),
                   frame_precision_scale=d["frame_precision_scale"],
                   min_weighting=d.get("min_weighting", 0.09), name=str(d.get("name", "")),
                   source=str(d.get("source", "")), extra=dict(d.get("extra") or {}),
                   clip_low_code=d.get("clip_low_code", 0), clip_high_code=d.get("clip_high_code"))
        if "max_code" in d and int(d["max_code"]) != prof.max_code:
            raise ValueError(f"camera profile max_code {d['max_code']} disagrees with the weighting "
                             f"table length {prof.max_code + 1}")
        return prof

    def save(self, path) -> Path:
        """Write the profile as JSON, atomically (temporary file, then rename)."""
        return write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path) -> "CameraProfile":
        """Read a profile written by :meth:`save` (or by ``hybridhdr calibrate``)."""
        path = Path(path)
        from .._util.limits import read_text_bounded
        try:  # regular files only, size-bounded (/dev/zero or a FIFO as --profile is one error line)
            d = json.loads(read_text_bounded(path, "camera profile"))
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not a JSON camera profile ({e})") from None
        return cls.from_dict(d)


#: Gamma of the built-in profile for ``Frames.encoding == "gamma"`` (code = max (I)^(1/2.2)).
DEFAULT_GAMMA = 2.2


def _trapezoid(n: int) -> np.ndarray:
    """1 over the well-exposed codes, falling linearly to 0 over the lowest and highest 1/16."""
    codes = np.arange(n, dtype=np.float64)
    ramp = max((n - 1) / 16.0, 1.0)
    return np.clip(np.minimum(codes / ramp, (n - 1 - codes) / ramp), 0.0, 1.0)


def weighting_from_inverse_crf(inverse_crf, trapezoid=None) -> np.ndarray:
    """Weighting function ``f_w(code)`` (eqs. 4-5) of a camera with the given inverse CRF.

    The certainty ``f_c = dCRF/dI`` (eq. 4) composed with ``CRF^-1`` (eq. 5) is the reciprocal of
    the slope of the inverse CRF, ``1 / (dCRF^-1/dcode)``, taken here by central differences of
    the lookup table. Where that slope vanishes (flat or clipped ends of the table) the
    certainty is 0. A gamma curve's slope is unbounded at code 0, so ``f_c`` is normalised to a
    maximum of 1 over the codes where ``trapezoid`` is 1 (the well-exposed codes) and clipped at
    1 below them, then multiplied by ``trapezoid`` (quantisation, dark current and clipping,
    paper §3.2.1).

    Parameters
    ----------
    inverse_crf : array_like of shape (max_code + 1,)
        Scaled irradiance per code, non-decreasing.
    trapezoid : array_like of shape (max_code + 1,), optional
        Extra per-code factor in [0, 1]; default the built-in trapezoid.

    Returns
    -------
    ndarray of shape (max_code + 1,), float64, in [0, 1]
    """
    inv = np.asarray(inverse_crf, dtype=np.float64)
    n = inv.shape[0]
    tr = _trapezoid(n) if trapezoid is None else np.asarray(trapezoid, dtype=np.float64)
    slope = np.gradient(inv)
    fc = np.where(slope > 0, 1.0 / np.where(slope > 0, slope, 1.0), 0.0)
    good = tr >= 1.0
    top = fc[good].max() if good.any() and fc[good].max() > 0 else fc.max()
    if not top > 0:
        raise ValueError("the inverse CRF is flat everywhere; it gives no certainty (eq. 4)")
    return np.clip(fc / top, 0.0, 1.0) * tr


def default_profile(bit_depth: int = 8, frame_precision_scale: float = 7e5, *, encoding: str = "linear",
                    gamma: float = DEFAULT_GAMMA) -> CameraProfile:
    """Built-in profile for ``bit_depth``-bit codes with a linear or gamma response.

    Parameters
    ----------
    bit_depth : int
        Code depth, 1..16 (``max_code = 2**bit_depth - 1``).
    frame_precision_scale : float
        1/σ²_im of eq. 6; default the paper's DAVIS240C value 7e5 (§6).
    encoding : {"linear", "raw", "unknown", "gamma"}
        The frames' ``Frames.encoding``. "gamma" means ``code = max_code (I)^(1/gamma)``; every
        other value is read as a linear response.
    gamma : float
        Display gamma of a "gamma" encoding (2.2: the sRGB-like curve of
        :func:`hybridhdr.simulate.procedural.procedural_recording`).

    Notes
    -----
    Linear response: ``CRF^-1(code) = code / max_code`` and the weighting function is a
    trapezoid, 1 over the well-exposed codes and falling linearly to 0 over the lowest and
    highest 1/16 of the code range, where quantisation, dark current and clipping dominate
    (paper §3.2.1). Gamma response: ``CRF^-1(code) = (code / max_code)**gamma`` (eq. 3) and the
    weighting is that trapezoid times the certainty of eqs. 4-5 derived from this CRF (see
    :func:`weighting_from_inverse_crf`): dark codes, where the curve is steep, resolve
    irradiance more finely and weigh more than bright ones. Eq. 6 floors either at
    ``min_weighting = 0.09``. Measured profiles (``hybridhdr calibrate``) should replace this.

    The profile is marked built-in (``extra["builtin"]``), so :class:`FrameMeasurements` swaps it
    for the one matching ``Frames.encoding`` (see :func:`profile_for_frames`).
    """
    if isinstance(bit_depth, bool) or not isinstance(bit_depth, (int, np.integer)) or not 1 <= bit_depth <= 16:
        raise ValueError(f"bit_depth must be an int in 1..16, got {bit_depth!r}")
    if encoding not in ("linear", "raw", "unknown", "gamma"):
        raise ValueError(f"encoding must be 'linear', 'raw', 'unknown' or 'gamma', got {encoding!r}")
    if isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or not (math.isfinite(gamma) and gamma > 0):
        raise ValueError(f"gamma must be a positive number, got {gamma!r}")
    n = 1 << int(bit_depth)
    tr = _trapezoid(n)
    extra = {"builtin": True, "bit_depth": int(bit_depth)}
    if encoding == "gamma":
        inv = (np.arange(n, dtype=np.float64) / (n - 1)) ** float(gamma)
        extra.update(encoding="gamma", gamma=float(gamma))
        return CameraProfile(weighting=weighting_from_inverse_crf(inv, tr), inverse_crf=inv,
                             frame_precision_scale=frame_precision_scale, min_weighting=0.09,
                             name=f"default-{bit_depth}bit-gamma{float(gamma):g}",
                             source=f"hybridhdr built-in: gamma {float(gamma):g} response, trapezoid times "
                                    f"the CRF certainty (eqs. 4-5)", extra=extra)
    extra.update(encoding="linear")
    return CameraProfile(weighting=tr, inverse_crf=None, frame_precision_scale=frame_precision_scale,
                         min_weighting=0.09, name=f"default-{bit_depth}bit",
                         source="hybridhdr built-in trapezoid weighting, linear response", extra=extra)


def profile_from_inverse_crf(inverse_crf, *, clip_codes=None, frame_precision_scale: float = 7e5,
                             name: str = "", source: str = "") -> CameraProfile:
    """The profile of a camera with a known inverse CRF (a simulated camera, a measured table).

    The table is normalised so that the highest unclipped code ``clip_codes[1]`` (default the
    top code) maps to 1.0 (frame-linear units) and made non-decreasing; the weighting is eqs.
    4-5 of it (:func:`weighting_from_inverse_crf`) with the clipped codes at 0 (a clipped code
    is a bound, :meth:`CameraProfile.censor`); ``clip_codes = (lo, hi)`` become the profile's
    clip levels.
    """
    inv = np.maximum.accumulate(np.asarray(inverse_crf, dtype=np.float64))
    n = inv.shape[0]
    lo, hi = (0, n - 1) if clip_codes is None else (int(clip_codes[0]), int(clip_codes[1]))
    if not 0 <= lo < hi <= n - 1:
        raise ValueError(f"clip_codes must satisfy 0 <= lo < hi <= {n - 1}, got {clip_codes}")
    if not inv[hi] > 0:
        raise ValueError(f"the inverse CRF is 0 at the clip code {hi}; it cannot set the frame-linear unit")
    inv = np.minimum(inv / inv[hi], 1.0)
    w = weighting_from_inverse_crf(inv)
    if clip_codes is not None:
        w[: lo + 1] = 0.0
        w[hi:] = 0.0
    return CameraProfile(weighting=w, inverse_crf=inv, frame_precision_scale=frame_precision_scale,
                         name=name, source=source, clip_low_code=lo, clip_high_code=hi)


def check_codes_in_profile(images, profile: CameraProfile) -> None:
    """Integer frame codes above the profile's last code are refused (ValueError): 16-bit frames
    read with an 8-bit profile would all clip to its top code without a word. Every verb that
    reads frame codes through a profile (reconstruct, evaluate overexpose) makes this check."""
    im = np.asarray(images)
    if im.dtype.kind not in "ui" or im.size == 0:
        return
    top = int(im.max())
    if top > profile.max_code:
        raise ValueError(f"frame codes reach {top} but the camera profile {profile.name!r} stops at code "
                         f"{profile.max_code} ({im.dtype} frames); give the frames' profile (--profile), e.g. "
                         f"one of {int(top).bit_length()} bits from 'hybridhdr calibrate crf'")


def profile_for_frames(profile: CameraProfile, frames) -> CameraProfile:
    """The profile to read ``frames`` with: the built-in one adapted to ``frames.encoding``.

    A built-in profile (``extra["builtin"]``, from :func:`default_profile`) whose response does
    not match the frames' encoding is replaced by the built-in profile of that encoding, with
    the same bit depth and precision scale; e.g. gamma-encoded frames get the inverse CRF
    ``(code/max)**2.2``. Any other (measured) profile is returned unchanged: it states the
    camera's response itself.
    """
    extra = profile.extra or {}
    if not extra.get("builtin"):
        return profile
    enc = getattr(frames, "encoding", "unknown")
    want = enc if enc in ("gamma", "srgb") else "linear"
    if extra.get("encoding", "linear") == want:
        return profile
    bits = int(extra.get("bit_depth", int(round(math.log2(profile.max_code + 1)))))
    if want == "srgb":
        from .encoding import inverse_crf_table
        n = 1 << bits
        if n - 1 != profile.max_code:
            return profile
        inv = inverse_crf_table("srgb", n - 1)
        return CameraProfile(weighting=weighting_from_inverse_crf(inv, _trapezoid(n)), inverse_crf=inv,
                             frame_precision_scale=profile.frame_precision_scale, min_weighting=0.09,
                             name=f"default-{bits}bit-srgb",
                             source="hybridhdr built-in: IEC 61966-2-1 sRGB response, trapezoid times the CRF "
                                    "certainty (eqs. 4-5)",
                             extra={"builtin": True, "bit_depth": bits, "encoding": "srgb"})
    kw = {"gamma": float(extra.get("gamma", DEFAULT_GAMMA))} if want == "gamma" else {}
    prof = default_profile(bits, profile.frame_precision_scale, encoding=want, **kw)
    if prof.max_code != profile.max_code:
        return profile
    return prof


def load_profile(profile) -> CameraProfile:
    """Accept a :class:`CameraProfile`, a path to a JSON profile, or ``None`` (built-in 8-bit)."""
    if profile is None:
        return default_profile(8)
    if isinstance(profile, CameraProfile):
        return profile
    if isinstance(profile, (str, os.PathLike)):
        return CameraProfile.load(profile)
    raise TypeError(f"profile must be a CameraProfile, a path or None, got {type(profile).__name__}")
