"""Decode ``sensor_msgs/Image`` pixel data (ROS 1 and ROS 2) into NumPy frames.

A ``sensor_msgs/Image`` is ``{header, uint32 height, uint32 width, string encoding,
uint8 is_bigendian, uint32 step, uint8[] data}``: ``step`` is the length of one row in bytes
(it may exceed ``width * channels * bytes per channel``: row padding) and ``data`` holds
``step * height`` bytes (``sensor_msgs/msg/Image.msg``). The encodings are the names of
``sensor_msgs/image_encodings.h``; those decoded here are :data:`ENCODINGS`:

* ``mono8``, ``mono16``: grey, (H, W);
* ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8`` and their 16-bit versions: colour, returned as
  (H, W, 3) in R, G, B order (BGR reversed, alpha dropped);
* ``bayer_rggb8``, ``bayer_bggr8``, ``bayer_gbrg8``, ``bayer_grbg8`` and their 16-bit versions:
  the raw mosaic of a Bayer sensor, (H, W); the name gives the 2×2 tile from the top-left pixel
  in reading order, the convention of :mod:`hybridhdr.camera.cfa` (``bayer_rggb8`` -> ``RGGB``).

16-bit samples are big-endian when ``is_bigendian`` is non-zero, little-endian otherwise; the
result is native-endian. The sizes are checked before anything is allocated:
``height``/``width`` within the sensor limit (:func:`hybridhdr._util.limits.check_sensor_size`),
``step`` at least one row of pixels, and ``step * height`` equal to the length of ``data``.
"""

from __future__ import annotations

import numpy as np

from .._util.limits import check_sensor_size
from ..errors import FormatError

__all__ = ["ENCODINGS", "IMAGE", "INT32", "image_kind", "decode_image"]

IMAGE = "sensor_msgs/msg/Image"
INT32 = "std_msgs/msg/Int32"


def _table() -> dict[str, tuple[int, int, str, str | None]]:
    out: dict[str, tuple[int, int, str, str | None]] = {}
    for bits in (8, 16):
        nb = bits // 8
        out[f"mono{bits}"] = (1, nb, "mono", None)
        for order in ("rgb", "bgr"):
            out[f"{order}{bits}"] = (3, nb, order, None)
            out[f"{order}a{bits}"] = (4, nb, order, None)
        for pat in ("rggb", "bggr", "gbrg", "grbg"):
            out[f"bayer_{pat}{bits}"] = (1, nb, "bayer", pat.upper())
    return out


#: encoding -> (channels in ``data``, bytes per channel, kind ``mono``/``rgb``/``bgr``/``bayer``,
#: Bayer pattern or None)
ENCODINGS: dict[str, tuple[int, int, str, str | None]] = _table()


def image_kind(encoding: str, path=None, where: str = "") -> tuple[int, int, str, str | None]:
    """The :data:`ENCODINGS` entry of ``encoding``; a :class:`FormatError` naming the supported
    encodings for any other."""
    try:
        return ENCODINGS[encoding]
    except KeyError:
        raise FormatError(path, f"{where}image encoding {encoding!r} is not supported; supported: "
                                f"{', '.join(ENCODINGS)}") from None


def decode_image(height: int, width: int, encoding: str, is_bigendian: int, step: int, data,
                 path=None, where: str = "", record: int | None = None) -> np.ndarray:
    """One image's pixels: (H, W) for grey and Bayer encodings, (H, W, 3) RGB for colour ones.

    Parameters
    ----------
    height, width, step : int
        As in the message (rows, columns, bytes per row).
    encoding : str
        One of :data:`ENCODINGS`.
    is_bigendian : int
        Non-zero: 16-bit samples are big-endian.
    data : bytes-like
        The ``data`` field, ``step * height`` bytes.
    path, where, record
        For the error messages (``where`` prefixes them, e.g. ``"message 3 of /dvs/image_raw: "``).

    Returns
    -------
    ndarray of shape (H, W) or (H, W, 3), dtype uint8 or uint16 (native byte order), a copy.
    """
    ch, nb, kind, _ = image_kind(encoding, path, where)
    height, width, step = int(height), int(width), int(step)
    if height <= 0 or width <= 0:
        raise FormatError(path, f"{where}image of {height}x{width} pixels (height x width must be positive)",
                          record=record)
    check_sensor_size(height, width, path, what=f"{where}image")
    row = width * ch * nb
    if step < row:
        raise FormatError(path, f"{where}step {step} is shorter than one row of {width} {encoding} pixels "
                                f"({row} bytes)", record=record)
    n = len(data)
    if step * height != n:
        raise FormatError(path, f"{where}{height} rows of step {step} need {step * height} bytes of data, the "
                                f"message has {n} (truncated or inconsistent image)", record=record)
    buf = np.frombuffer(data, np.uint8, count=n).reshape(height, step)[:, :row]
    dt = np.dtype(np.uint8) if nb == 1 else np.dtype(">u2" if is_bigendian else "<u2")
    px = np.ascontiguousarray(buf).view(dt).reshape(height, width, ch)
    if ch == 1:
        px = px[..., 0]
    elif kind == "bgr":
        px = px[..., 2::-1]
    else:
        px = px[..., :3]
    return np.ascontiguousarray(px, dtype=dt.newbyteorder("="))
