"""Frame encodings: how pixel codes relate to frame-linear intensity, and colour to luminance.

``Frames.encoding`` (:data:`hybridhdr.model.FRAME_ENCODINGS`) states the transfer function of
the codes. The closed forms here map codes ``c`` in ``[0, max_code]`` to frame-linear intensity
``I`` in ``[0, 1]`` (:func:`decode`) and back (:func:`encode`), with ``v = c / max_code``:

``"linear"`` and ``"raw"``
    ``I = v`` (``"raw"``: sensor numbers proportional to exposure; any black level is the
    caller's business).
``"gamma"``
    Display gamma 2.2: ``c = max_code * I**(1/2.2)``, so ``I = v**2.2``.
``"srgb"``
    The sRGB transfer function of IEC 61966-2-1:1999 (also W3C/Stokes et al., "A Standard
    Default Color Space for the Internet - sRGB", 1996), piecewise:
    ``I = v / 12.92`` for ``v <= 0.04045``, else ``I = ((v + 0.055) / 1.055)**2.4``;
    inversely ``v = 12.92 I`` for ``I <= 0.0031308``, else ``v = 1.055 I**(1/2.4) - 0.055``.
``"unknown"``
    No transfer function is known: :func:`decode` refuses it (declare one, e.g. with
    ``--frame-encoding``).

The command line names the encodings :data:`ENCODING_CHOICES` (``linear``, ``gamma2.2``,
``srgb``); :func:`parse_frame_encoding` maps them to ``Frames.encoding`` values.

Colour (:func:`to_luminance`): relative luminance ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` with
the Rec. 709 / sRGB primaries and D65 white (coefficients of ITU-R BT.709-6 Part 1, item 3.2;
sRGB, IEC 61966-2-1, uses the same primaries). As relative luminance the weights apply to
*linear* values, so gamma and sRGB codes are decoded, weighted and re-encoded to codes of the
same encoding.

Pure NumPy; nothing here depends on the reconstruction.
"""

from __future__ import annotations

import math

import numpy as np

from .._util.checks import check_range
from ..model import Frames

__all__ = ["DEFAULT_INTENSITY_OFFSET", "frames_to_codes", "WELL_EXPOSED_8BIT", "well_exposed_range", "ENCODING_CHOICES", "LUMINANCE_WEIGHTS", "DISPLAY_GAMMA", "parse_frame_encoding", "decode",
           "encode", "inverse_crf_table", "to_luminance", "luminance_frames", "with_encoding"]

#: Command-line names of the declarable encodings (``--frame-encoding``).
ENCODING_CHOICES = ("linear", "gamma2.2", "srgb")
_CLI_TO_MODEL = {"linear": "linear", "gamma2.2": "gamma", "srgb": "srgb"}
#: ``Frames.encoding`` values accepted as they are (besides the command-line names).
_MODEL_VALUES = ("raw", "linear", "gamma", "srgb", "unknown")
#: Exponent of the ``"gamma"`` encoding: ``code = max_code * I**(1/2.2)``.
DISPLAY_GAMMA = 2.2
#: Rec. 709 / sRGB relative-luminance weights of linear R, G, B (ITU-R BT.709-6 Part 1, item 3.2).
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)

# IEC 61966-2-1:1999 sRGB transfer-function constants.
_SRGB_DECODE_KNEE = 0.04045
_SRGB_ENCODE_KNEE = 0.0031308
_SRGB_SLOPE = 12.92
_SRGB_A = 0.055
_SRGB_EXP = 2.4


def parse_frame_encoding(name) -> str:
    """The ``Frames.encoding`` value for a command-line or model encoding name.

    Parameters
    ----------
    name : str
        One of :data:`ENCODING_CHOICES` (``linear``, ``gamma2.2``, ``srgb``) or a
        ``Frames.encoding`` value (``raw``, ``linear``, ``gamma``, ``srgb``, ``unknown``);
        case and surrounding blanks are ignored.

    Returns
    -------
    str
        ``"linear"``, ``"gamma"``, ``"srgb"``, ``"raw"`` or ``"unknown"``.

    Raises
    ------
    ValueError
        For any other name.

    Examples
    --------
    >>> parse_frame_encoding("gamma2.2"), parse_frame_encoding("SRGB")
    ('gamma', 'srgb')
    """
    if not isinstance(name, str):
        raise ValueError(f"frame encoding must be a string, one of {', '.join(ENCODING_CHOICES)}; "
                         f"got {type(name).__name__} {name!r}")
    key = name.strip().lower()
    if key in _CLI_TO_MODEL:
        return _CLI_TO_MODEL[key]
    if key in _MODEL_VALUES:
        return key
    raise ValueError(f"unknown frame encoding {name!r}; expected one of {', '.join(ENCODING_CHOICES)} "
                     f"(linear = codes proportional to intensity, gamma2.2 = code = max*I^(1/2.2), "
                     f"srgb = IEC 61966-2-1), or a Frames.encoding value ({', '.join(_MODEL_VALUES)})")


def _check_max_code(max_code) -> float:
    return check_range(max_code, "max_code", lo=0, lo_open=True)


def _transfer(encoding: str, what: str) -> str:
    enc = parse_frame_encoding(encoding)
    if enc == "unknown":
        raise ValueError(f"cannot {what} frames of encoding 'unknown': the transfer function is not known; "
                         f"declare it (one of {', '.join(ENCODING_CHOICES)}, e.g. --frame-encoding)")
    return enc


def decode(codes, encoding: str, max_code) -> np.ndarray:
    """Frame-linear intensity in [0, 1] of pixel codes (closed forms in the module notes).

    Parameters
    ----------
    codes : array_like
        Pixel codes (any numeric dtype); values outside ``[0, max_code]`` are clipped.
    encoding : str
        ``"linear"``, ``"raw"``, ``"gamma"`` (2.2) or ``"srgb"`` (or a command-line name).
    max_code : number
        The code of full scale (255 for 8-bit frames).

    Returns
    -------
    ndarray, float64, same shape as ``codes``
    """
    enc = _transfer(encoding, "decode")
    c = np.asarray(codes)
    if c.dtype.kind not in "uifb":
        raise TypeError(f"codes must be numeric, got dtype {c.dtype}")
    v = np.clip(c.astype(np.float64) / _check_max_code(max_code), 0.0, 1.0)
    if enc in ("linear", "raw"):
        return v
    if enc == "gamma":
        return v ** DISPLAY_GAMMA
    return np.where(v <= _SRGB_DECODE_KNEE, v / _SRGB_SLOPE, ((v + _SRGB_A) / (1.0 + _SRGB_A)) ** _SRGB_EXP)


def encode(intensity, encoding: str, max_code, dtype=None) -> np.ndarray:
    """Pixel codes of frame-linear intensity: the inverse of :func:`decode`.

    Parameters
    ----------
    intensity : array_like
        Frame-linear intensity; clipped to [0, 1] (the sensor's range).
    encoding : str
        As for :func:`decode`.
    max_code : number
        Code of full scale.
    dtype : numpy dtype, optional
        None (default) returns unrounded float64 codes; an integer dtype rounds to the nearest
        code (``np.rint``) and casts; a float dtype casts.

    Returns
    -------
    ndarray, same shape as ``intensity``
    """
    enc = _transfer(encoding, "encode")
    m = _check_max_code(max_code)
    i = np.asarray(intensity, dtype=np.float64)
    if np.isnan(i).any():
        raise ValueError("intensity has NaN values")
    i = np.clip(i, 0.0, 1.0)
    if enc in ("linear", "raw"):
        v = i
    elif enc == "gamma":
        v = i ** (1.0 / DISPLAY_GAMMA)
    else:
        v = np.where(i <= _SRGB_ENCODE_KNEE, _SRGB_SLOPE * i,
                     (1.0 + _SRGB_A) * i ** (1.0 / _SRGB_EXP) - _SRGB_A)
    c = np.clip(v * m, 0.0, m)
    if dtype is None:
        return c
    dt = np.dtype(dtype)
    return (np.rint(c) if dt.kind in "ui" else c).astype(dt)


def inverse_crf_table(encoding: str, max_code: int) -> np.ndarray | None:
    """``CameraProfile.inverse_crf`` of an encoding: ``decode(0..max_code)``, or None when linear.

    ``"linear"``, ``"raw"`` and ``"unknown"`` give None (the profile's linear default,
    ``code / max_code``); ``"gamma"`` and ``"srgb"`` give their ``max_code + 1`` table.
    """
    enc = parse_frame_encoding(encoding)
    if enc in ("linear", "raw", "unknown"):
        return None
    if isinstance(max_code, bool) or not isinstance(max_code, (int, np.integer)) or max_code < 1:
        raise ValueError(f"max_code must be an int >= 1, got {max_code!r}")
    return decode(np.arange(int(max_code) + 1), enc, max_code)


def _default_max_code(dtype: np.dtype) -> float:
    if dtype.kind in "ui":
        return float(np.iinfo(dtype).max)
    return 1.0


def to_luminance(images, encoding: str = "linear", max_code=None, dtype=None) -> np.ndarray:
    """Luminance codes of colour images: Rec. 709 weights :data:`LUMINANCE_WEIGHTS` on linear RGB.

    Parameters
    ----------
    images : array_like of shape (..., 3)
        Colour codes, e.g. (K, H, W, 3) frames or one (H, W, 3) image.
    encoding : str
        The codes' encoding. ``"linear"``/``"raw"``: ``Y = w · (R, G, B)`` on the codes, exact.
        ``"gamma"``/``"srgb"``: each channel is decoded to linear intensity, weighted, and the
        result encoded back with the same transfer function, so the output is a code of the same
        encoding (and grey, R = G = B, stays grey up to rounding). ``"unknown"``: no transfer
        function is known, so the weights are applied to the codes as they are (the luma of
        the codes; exact only if they are in fact linear).
    max_code : number, optional
        Code of full scale; default the integer dtype's maximum (255 for uint8), 1.0 for floats.
    dtype : numpy dtype, optional
        Output dtype; default float64 (unrounded codes). An integer dtype rounds to the nearest
        code.

    Returns
    -------
    ndarray of shape ``images.shape[:-1]``
    """
    im = np.asarray(images)
    if im.ndim < 1 or im.shape[-1] != 3:
        raise ValueError(f"colour images must have a last axis of 3 (R, G, B), got shape {im.shape}")
    if im.dtype.kind not in "uif":
        raise TypeError(f"images must be numeric, got dtype {im.dtype}")
    enc = parse_frame_encoding(encoding)
    m = _check_max_code(_default_max_code(im.dtype) if max_code is None else max_code)
    w = np.asarray(LUMINANCE_WEIGHTS, dtype=np.float64)
    if enc in ("linear", "raw", "unknown"):
        y = im.astype(np.float64) @ w
        out = np.clip(y, 0.0, m) if im.dtype.kind in "ui" else y
        if dtype is None:
            return out
        dt = np.dtype(dtype)
        return (np.rint(out) if dt.kind in "ui" else out).astype(dt)
    return encode(decode(im, enc, m) @ w, enc, m, dtype=dtype)


def luminance_frames(frames, dtype=None):
    """``frames`` with colour images (K, H, W, 3) reduced to luminance codes (K, H, W).

    Grey frames are returned unchanged. The encoding is kept (see :func:`to_luminance` for what
    is done per encoding); ``dtype`` defaults to the input dtype, so 8-bit frames stay 8-bit
    codes (rounded to the nearest code); pass ``np.float64`` to keep the unrounded codes.
    """
    if frames.images.ndim != 4:
        return frames
    dt = frames.images.dtype if dtype is None else np.dtype(dtype)
    y = to_luminance(frames.images, frames.encoding, dtype=dt)
    return Frames(y, frames.t_start_us, frames.t_end_us, frames.gain, frames.iso, frames.encoding)


def with_encoding(frames, name):
    """``frames`` with ``encoding`` replaced by the declared one; ``name`` None keeps them as they are.

    Parameters
    ----------
    frames : Frames or None
    name : str or None
        A :data:`ENCODING_CHOICES` name (``linear``, ``gamma2.2``, ``srgb``) or a
        ``Frames.encoding`` value; see :func:`parse_frame_encoding`.

    Returns
    -------
    Frames or None
        A new :class:`~hybridhdr.model.Frames` sharing the image array (no copy).
    """
    if name is None or frames is None:
        return frames
    enc = parse_frame_encoding(name)
    if enc == frames.encoding:
        return frames
    return Frames(frames.images, frames.t_start_us, frames.t_end_us, frames.gain, frames.iso, enc)


#: Well-exposed codes of an 8-bit frame (inclusive); scaled to other bit depths.
WELL_EXPOSED_8BIT = (20, 235)

def well_exposed_range(max_code: int, codes_8bit=WELL_EXPOSED_8BIT) -> tuple[int, int]:
    """Well-exposed codes ``(lo, hi)`` (inclusive) for frames with top code ``max_code``: the 8-bit
    range scaled by ``max_code / 255`` (lo rounded up, hi rounded down)."""
    s = int(max_code) / 255.0
    return int(math.ceil(codes_8bit[0] * s - 1e-9)), int(math.floor(codes_8bit[1] * s + 1e-9))


#: I0 of eq. 8, in frame-linear units (1 = the frame camera's clip level): the offset of the log
#: model ln(I + I0) that the filters and the calibrations share.
#: Events measure changes of log I (up to the photoreceptor's dark current, which is small in
#: these units), so the filter's state log(I + I0) must have a small I0: with the reference
#: code's I0 = 1 a dark pixel's change is compressed by I/(I + 1), thresholds calibrated through
#: it come out too small and exp(L̂) - 1 goes negative. 1e-3 (60 dB below the clip level) keeps
#: the state within a few per cent of log I down to I = 0.03 and stays above the frames'
#: quantisation noise there; the paper gives no value, the reference code's I0 = 1 is in
#: :meth:`hybridhdr.reconstruct.AKFParams.reference_code` and ``AKFParams.paper``.
DEFAULT_INTENSITY_OFFSET = 1e-3


def frames_to_codes(frames: Frames, sensor_shape) -> np.ndarray:
    """Frame images as codes (K, H, W); colour frames become luminance codes of the same
    encoding with the Rec. 709 weights (:func:`to_luminance`, applied to linear RGB), rounded to
    the nearest code for integer frames."""
    im = frames.images
    if im.ndim == 4:
        im = to_luminance(im, frames.encoding, dtype=im.dtype)
    if tuple(im.shape[1:3]) != tuple(sensor_shape):
        raise ValueError(f"frame size {im.shape[1:3]} (H, W) differs from the event sensor size "
                         f"{tuple(sensor_shape)}; frames and events must be registered")
    return im
