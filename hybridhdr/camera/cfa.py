"""Colour filter arrays (Bayer patterns): names, per-pixel channels, mosaic and demosaic.

A Bayer sensor sees at each pixel one channel of the scene's RGB radiance. The pattern names
the colours of the 2×2 tile from the top-left pixel (row 0, column 0) in reading order:
``RGGB`` is ``R G / G B``, ``BGGR`` is ``B G / G R``, ``GRBG`` is ``G R / B G`` and ``GBRG`` is
``G B / R G`` (the names of OpenCV's ``COLOR_Bayer*`` codes and of dcraw/LibRaw). Pixel
``(y, x)`` has the colour of tile position ``(y mod 2, x mod 2)`` in the recording's own pixel
coordinates (the axes of ``docs/conventions.md``), so a crop by an odd number of rows or columns
changes the pattern's name (:func:`crop_pattern`).

:func:`mosaic` takes each pixel's own channel of an RGB image (what the sensor measures);
:func:`demosaic` interpolates the two missing channels of a mosaic:

``"bilinear"``
    Each channel by normalised convolution of its known samples: R and B with the kernel
    ``[1 2 1; 2 4 2; 1 2 1]/4``, G with ``[0 1 0; 1 4 1; 0 1 0]/4``; at the border only the
    samples inside the image count (their weights renormalised), so no value is invented from
    padding. A pixel's own channel is returned unchanged, bit for bit.
``"log_bilinear"``
    The same interpolation of ``ln max(v, eps)``, exponentiated: geometric instead of
    arithmetic means of the neighbours. The events and the AKF state are log intensity and an
    HDR scene's textures and edges are multiplicative, so this is the scale-invariant choice
    (an interpolated value does not depend on the exposure); on the colour edge sweep
    (``benchmarks/colour.py``) it has the smallest log error of the three, also on the true
    radiance (0.022 against 0.025 bilinear on the band-limited scene, 0.071 against 0.091 on
    the sharp one).
``"log_cubic"``
    Log intensity throughout, cubic instead of bilinear, and colour as a difference of logs: G
    at R and B pixels is the mean of the 1-D cubic interpolations along the row and along the
    column (both have G at every other pixel), R and B are G plus the cubic interpolation of
    ``ln R - ln G`` (``ln B - ln G``) on their quarter grid, separable along rows and columns.
    The cubic is Keys' convolution kernel with a = -1/2 (R. Keys, "Cubic convolution
    interpolation for digital image processing", IEEE Trans. ASSP 29(6), 1981), whose weights at
    half-way points are (-1, 9, 9, -1)/16; it reproduces quadratics where bilinear reproduces
    only constants and lines, and the difference of logs (the constant-hue assumption of Cok,
    below) is smoother than either channel on its own. At the border the weights of the samples
    inside the image are renormalised, as for bilinear (they never sum to less than 1/2). In
    the log domain every output is positive. On the colour edge sweep (``benchmarks/colour.py``)
    it has the smallest log error of the four on the true radiance (0.0125 band-limited, 0.041
    sharp) and on the AKF's outputs (0.027 against 0.030 log-bilinear; 0.048 against 0.075), so
    it is the reconstruction's default.
``"edge_aware"``
    G at R and B pixels from the two G neighbours along the direction of the smaller G
    gradient (mirrored at the border, which keeps the Bayer parity) (measured in log units, so the choice does not depend on the brightness of an
    HDR scene; equal gradients average all four); then R and B from the bilinear interpolation
    of the ratios R/G and B/G (the constant-hue assumption of Cok, US patent 4,642,678, 1987,
    i.e. colour differences in the log domain), multiplied by G. Sharper than bilinear at
    luminance edges, positive wherever the input is.

Why not OpenCV: ``cv2.demosaicing`` (and ``cvtColor`` with ``COLOR_Bayer*``) accepts only 8- and
16-bit integer images, while reconstructed HDR video is float32 linear radiance spanning many
decades; quantising it to 16 bits would lose either the dark end or the highlights. All methods
here are float throughout (computed in float64, returned as float32) and keep positive inputs
positive (bilinear and edge-aware: non-negative weights; the log methods: an exponential), which
the log-domain metrics need.

Pure NumPy and ``scipy.ndimage``; nothing here depends on the reconstruction.
"""

from __future__ import annotations

import numpy as np

from ..model import CFA_CHOICES, CFA_PATTERNS, Frames, parse_cfa  # CFA names: with CameraInfo, which validates its cfa

__all__ = ["CFA_PATTERNS", "CFA_CHOICES", "DEMOSAIC_METHODS", "parse_cfa", "channel_index", "channel_masks",
           "mosaic", "demosaic", "crop_pattern", "mosaic_frames"]

#: :func:`demosaic` methods.
DEMOSAIC_METHODS = ("bilinear", "log_bilinear", "log_cubic", "edge_aware")
_CHANNEL = {"R": 0, "G": 1, "B": 2}


def _pattern(pattern) -> str:
    p = parse_cfa(pattern)
    if p is None:
        raise ValueError("a colour filter array pattern is needed here (RGGB, BGGR, GRBG or GBRG), got none")
    return p


def channel_index(pattern, shape) -> np.ndarray:
    """Per-pixel channel (0 = R, 1 = G, 2 = B) of an ``(H, W)`` sensor, int8 array of ``shape``."""
    p = _pattern(pattern)
    h, w = (int(s) for s in shape)
    tile = np.array([[_CHANNEL[p[0]], _CHANNEL[p[1]]], [_CHANNEL[p[2]], _CHANNEL[p[3]]]], np.int8)
    return np.tile(tile, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


def channel_masks(pattern, shape) -> np.ndarray:
    """``(H, W, 3)`` bool: ``[..., c]`` is True where the pixel sees channel ``c`` (R, G, B)."""
    ch = channel_index(pattern, shape)
    return ch[..., None] == np.arange(3, dtype=np.int8)


def crop_pattern(pattern, y0: int, x0: int) -> str:
    """The pattern of a crop starting at row ``y0``, column ``x0`` of a ``pattern`` sensor."""
    p = _pattern(pattern)
    tile = [[p[0], p[1]], [p[2], p[3]]]
    a, b = int(y0) % 2, int(x0) % 2
    return "".join(tile[(a + i) % 2][(b + j) % 2] for i in range(2) for j in range(2))


def mosaic(rgb, pattern) -> np.ndarray:
    """Each pixel's own channel of RGB images: ``(..., H, W, 3)`` -> ``(..., H, W)``, dtype kept.

    Works on codes of any per-channel encoding as well as on linear values: the transfer
    functions of :mod:`hybridhdr.camera.encoding` act on each channel alone, so taking a channel
    commutes with decoding it.
    """
    im = np.asarray(rgb)
    if im.ndim < 3 or im.shape[-1] != 3:
        raise ValueError(f"RGB images must have shape (..., H, W, 3), got {im.shape}")
    ch = channel_index(pattern, im.shape[-3:-1])
    return np.take_along_axis(im, np.broadcast_to(ch[..., None], im.shape[:-1] + (1,)).astype(np.intp),
                              axis=-1)[..., 0]


_K_RB = np.array([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]])
_K_G = np.array([[0.0, 1.0, 0.0], [1.0, 4.0, 1.0], [0.0, 1.0, 0.0]])


def _normconv(values, mask, kernel):
    """Normalised convolution of the samples ``values[mask]`` (2-D float64): zero padding for
    both the samples and the weights, so borders use the in-image samples only."""
    from scipy.ndimage import convolve
    num = convolve(np.where(mask, values, 0.0), kernel, mode="constant", cval=0.0)
    den = convolve(mask.astype(np.float64), kernel, mode="constant", cval=0.0)
    return num / np.where(den > 0, den, 1.0)


#: Keys' cubic (a = -1/2) on a grid of every other pixel: 1 at a sample, (-1, 9, 9, -1)/16 from the
#: four nearest samples half-way between them (offsets -3, -1, 1, 3).
_K_CUBIC = np.array([-1.0, 0.0, 9.0, 16.0, 9.0, 0.0, -1.0]) / 16.0


def _normconv_cubic(values, mask, axes):
    """Normalised convolution with :data:`_K_CUBIC` along ``axes`` (separable), zero padding."""
    from scipy.ndimage import convolve1d
    num = np.where(mask, values, 0.0)
    den = mask.astype(np.float64)
    for ax in axes:
        num = convolve1d(num, _K_CUBIC, axis=ax, mode="constant", cval=0.0)
        den = convolve1d(den, _K_CUBIC, axis=ax, mode="constant", cval=0.0)
    return num / np.where(den > 0, den, 1.0)


def _demosaic_one(m, masks, method, eps):
    out = np.empty(m.shape + (3,), np.float64)
    if method == "log_cubic":
        lg = np.log(np.maximum(m, eps))
        gm = masks[..., 1]
        g = 0.5 * (_normconv_cubic(lg, gm, (1,)) + _normconv_cubic(lg, gm, (0,)))
        g = np.where(gm, lg, g)
        out[..., 1] = g
        for c in (0, 2):
            out[..., c] = g + _normconv_cubic(lg - g, masks[..., c], (0, 1))
        np.exp(out, out=out)
    elif method in ("bilinear", "log_bilinear"):
        v = np.log(np.maximum(m, eps)) if method == "log_bilinear" else m
        for c in range(3):
            out[..., c] = _normconv(v, masks[..., c], _K_G if c == 1 else _K_RB)
        if method == "log_bilinear":
            np.exp(out, out=out)
    else:  # edge_aware
        from scipy.ndimage import convolve
        gm = masks[..., 1]
        lg = np.log(np.maximum(m, eps))
        kh = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
        kv = kh.T
        kd = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
        # mirror padding (d c b | a b c d) keeps the Bayer parity: the pixel beyond the border
        # has the colour of the one inside, so a border pixel also has its two G neighbours
        gz = np.where(gm, m, 0.0)
        lgz = np.where(gm, lg, 0.0)
        gh = 0.5 * convolve(gz, kh, mode="mirror")
        gv = 0.5 * convolve(gz, kv, mode="mirror")
        dh = np.abs(convolve(lgz, kd, mode="mirror"))
        dv = np.abs(convolve(lgz, kd.T, mode="mirror"))
        g4 = _normconv(m, gm, _K_G)
        g = np.where(dh < dv, gh, np.where(dv < dh, gv, g4))
        g = np.where(gm, m, g)
        out[..., 1] = g
        gp = np.maximum(g, eps)
        for c in (0, 2):
            ratio = _normconv(m / gp, masks[..., c], _K_RB)
            out[..., c] = ratio * gp
    for c in range(3):  # a pixel's own channel is its measurement, exactly
        out[..., c][masks[..., c]] = m[masks[..., c]]
    return out


def demosaic(mosaic_images, pattern, method: str = "bilinear", eps: float = 1e-6) -> np.ndarray:
    """RGB images from Bayer mosaics: ``(..., H, W)`` -> ``(..., H, W, 3)`` float32.

    Parameters
    ----------
    mosaic_images : array_like of shape (H, W) or (K, H, W)
        Linear values (radiance or frame-linear intensity) of each pixel's own channel.
        Demosaicking non-linear codes works but interpolates the codes, not the light.
    pattern : str
        One of :data:`CFA_PATTERNS`.
    method : {"bilinear", "log_bilinear", "log_cubic", "edge_aware"}
        See the module notes.
    eps : float
        Floor of the values in the logarithms of ``"log_bilinear"``, ``"log_cubic"`` and the log gradients and
        ratios of ``"edge_aware"`` (unused by ``"bilinear"``); the reconstruction clamps its
        outputs at 1e-6 frame-linear.

    Returns
    -------
    ndarray of shape (..., H, W, 3), float32
        Each pixel's own channel equals the input bit for bit (for float32 input).
    """
    if method not in DEMOSAIC_METHODS:
        raise ValueError(f"unknown demosaic method {method!r}; expected one of {DEMOSAIC_METHODS}")
    m = np.asarray(mosaic_images)
    if m.ndim < 2:
        raise ValueError(f"mosaic images must have shape (H, W) or (K, H, W), got {m.shape}")
    if m.dtype.kind not in "uif":
        raise TypeError(f"mosaic images must be numeric, got dtype {m.dtype}")
    masks = channel_masks(pattern, m.shape[-2:])
    flat = m.reshape((-1,) + m.shape[-2:]).astype(np.float64)
    out = np.stack([_demosaic_one(f, masks, method, float(eps)) for f in flat]) if flat.shape[0] else \
        np.zeros(flat.shape + (3,))
    return out.reshape(m.shape + (3,)).astype(np.float32)


def mosaic_frames(frames, pattern, frame_pattern=None):
    """``frames`` as the raw mosaic of a ``pattern`` sensor: (K, H, W) codes, encoding kept.

    * RGB frames (K, H, W, 3): each pixel takes its own channel's code. No decoding is needed:
      every encoding acts per channel, so the channel of an encoded pixel is the encoded
      channel (``frame_pattern`` is ignored: demosaicked frames have all three channels).
    * Grey frames (K, H, W) whose ``frame_pattern`` equals ``pattern``: they already are that
      mosaic and are returned unchanged.
    * Grey frames of another pattern: demosaicked (bilinear, on the codes as float64) and
      re-mosaicked; the codes become float (the integer look-up tables of the AKF are not
      used) and the missing channel is interpolated, not measured.
    * Grey frames with no frame pattern: ValueError (a monochrome frame camera does not measure
      the colour of each event pixel; declare the frames' CFA, e.g. ``--cfa``).
    """
    p = _pattern(pattern)
    im = frames.images
    if im.ndim == 4:
        out = mosaic(im, p)
    else:
        fp = parse_cfa(frame_pattern)
        if fp is None:
            raise ValueError(f"the event sensor has the colour filter array {p}, but the frames are grey and "
                             f"declare none: declare the frames' CFA (a raw Bayer mosaic) or give RGB frames")
        if fp == p:
            return frames
        out = mosaic(demosaic(im.astype(np.float64), fp).astype(np.float64), p)
    return Frames(np.ascontiguousarray(out), frames.t_start_us, frames.t_end_us, frames.gain, frames.iso,
                  frames.encoding)
