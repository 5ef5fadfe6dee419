"""Procedural textures for built-in scenes: generated in code from a seed, no image files.

Each generator returns float32 texels ``(rows, cols)`` (row 0 at the top edge of a plane as its
camera sees it), >= 0, relative to 1 (a :class:`~hybridhdr.simulate.scene.Pattern` scales them by
its ``value``). Same name and seed, same bits (NumPy's PCG64 and SciPy's spline zoom only).

Bright-region textures (``scenery``: six window panes, ``lampshade``: four panels of a shade,
``facade``: a facade between six pillars) have **soft borders**: towards the edges of each
pane the radiance falls log-linearly (a smoothstep in log intensity) to ``BORDER_FLOOR`` of its
level over ``BORDER_MARGIN`` of the pane's size, and the bars between panes (mullions, ribs,
pillars) sit at ``BORDER_FLOOR``. Narrow panes with dark bars are what a hand-held camera can
sweep: a pane's pixels are seen unclipped (on a bar) within half a pane's width of motion. It stands in for what keeps a real
bright region's edge followable by an event pixel: the lens's blur and glare, a window's
daylit reveal, a shade's dimmer rim, a doorway's penumbra. A pixel that crosses a hard
10³× step in a few ms rises by ~7 log units in well under a millisecond, which a pixel with a
refractory period cannot report (the HDR *stress* set keeps such hard edges on purpose).

Interior textures (``plaster``, ``wallpaper``, ``wood``) are reflectances in [0.1, 0.8] with
moderate contrast, so the shadows carry structure for SSIM and for events.

>>> from hybridhdr.simulate.textures import texture, TEXTURES
>>> sorted(TEXTURES)[:3]
['facade', 'lampshade', 'plaster']
>>> t = texture("scenery", seed=1)
>>> t.dtype, t.shape, float(t.max()) <= 1.0
(dtype('float32'), (160, 224), True)
"""

from __future__ import annotations

import numpy as np

__all__ = ["TEXTURES", "texture", "BORDER_FLOOR", "BORDER_MARGIN"]

#: Relative radiance at a bright texture's very edge (log-linear ramp from there to the inside).
BORDER_FLOOR = {"scenery": 0.025, "lampshade": 0.025, "facade": 0.02}
#: Width of that ramp as a fraction of the texture's width and height.
BORDER_MARGIN = 0.25


def _smooth_noise(rng, shape, cells) -> np.ndarray:
    """Value noise in [0, 1]: a random (cells+3)-grid upsampled with a cubic spline, cropped."""
    from scipy.ndimage import zoom
    h, w = shape
    cv, cu = max(1, int(cells[0])), max(1, int(cells[1]))
    g = rng.random((cv + 3, cu + 3))
    z = zoom(g, ((h * (cv + 3) / cv) / (cv + 3), (w * (cu + 3) / cu) / (cu + 3)), order=3, mode="reflect")
    oy, ox = (z.shape[0] - h) // 2, (z.shape[1] - w) // 2
    z = z[oy:oy + h, ox:ox + w]
    lo, hi = float(z.min()), float(z.max())
    return (z - lo) / ((hi - lo) or 1.0)


def _fbm(rng, shape, base_cells, octaves=4, gain=0.5) -> np.ndarray:
    """Fractal sum of value noise, normalised to [0, 1]."""
    acc = np.zeros(shape)
    a, tot = 1.0, 0.0
    for o in range(octaves):
        c = (base_cells[0] * 2 ** o, base_cells[1] * 2 ** o)
        acc += a * _smooth_noise(rng, shape, c)
        tot += a
        a *= gain
    acc /= tot
    lo, hi = float(acc.min()), float(acc.max())
    return (acc - lo) / ((hi - lo) or 1.0)


def _cell_distance(n: int, cells: int, bar: float) -> np.ndarray:
    """Per texel along one axis: distance to the nearest edge of its cell, as a fraction of the
    cell's width (0 at an edge, 0.5 at the centre), or -1 in a bar between two cells."""
    x = (np.arange(n) + 0.5) / n
    cw = (1.0 - (cells - 1) * bar) / cells
    k = np.minimum(np.floor(x / (cw + bar)), cells - 1)
    loc = x - k * (cw + bar)
    return np.where(loc < cw, np.minimum(loc, cw - loc) / cw, -1.0)


def _soft_border(shape, floor: float, margin: float = BORDER_MARGIN, cells=(1, 1), bar: float = 0.0) -> np.ndarray:
    """Factor 1 inside each of ``cells`` (rows, cols) cells, falling to ``floor`` at the cells'
    edges (a smoothstep in log over ``margin`` of the cell's size) and ``floor`` in the bars of
    width ``bar`` (fraction of the texture) between them (a window's mullions, a shade's ribs)."""
    h, w = shape
    dv = _cell_distance(h, cells[0], bar)[:, None]
    du = _cell_distance(w, cells[1], bar)[None, :]
    d = np.minimum(dv, du) / margin
    s = np.clip(d, 0.0, 1.0)
    s = s * s * (3 - 2 * s)
    return np.exp(np.log(floor) * (1 - s))


def _scenery(rng, shape=(160, 224)) -> np.ndarray:
    """Outdoor scenery through a window: sky with clouds, hills, trees; 1 = the brightest sky."""
    h, w = shape
    y = (np.arange(h) + 0.5)[:, None] / h
    x = (np.arange(w) + 0.5)[None, :] / w
    sky = 0.8 + 0.2 * (1 - y) + 0.25 * (_fbm(rng, shape, (2, 3), 4) - 0.5)       # clouds ±12 %
    ridge = 0.45 + 0.08 * np.sin(2 * np.pi * (1.3 * x + rng.random())) + 0.1 * (_smooth_noise(rng, (1, w), (1, 6)) - 0.5)
    hills = 0.30 + 0.12 * _fbm(rng, shape, (3, 5), 3)
    treeline = 0.62 + 0.1 * (_smooth_noise(rng, (1, w), (1, 14)) - 0.5)
    trees = 0.10 + 0.14 * _fbm(rng, shape, (6, 9), 3)
    img = np.where(y < ridge, sky, np.where(y < treeline, hills, trees))
    img = np.clip(img, 0.05, 1.0)
    # six panes (2 x 3) between mullions
    return img * _soft_border(shape, BORDER_FLOOR["scenery"], cells=(2, 3), bar=0.05)


def _lampshade(rng, shape=(128, 160)) -> np.ndarray:
    """A lit fabric lamp shade: pleats, weave, the bulb's hot spot, a seam; 1 = the hot spot."""
    h, w = shape
    y = (np.arange(h) + 0.5)[:, None] / h
    x = (np.arange(w) + 0.5)[None, :] / w
    pleats = 0.8 + 0.2 * np.cos(2 * np.pi * 9 * x) ** 2
    weave = 0.9 + 0.2 * (_fbm(rng, shape, (10, 12), 2) - 0.5)
    hot = 0.45 + 0.55 * np.exp(-(((x - 0.5) / 0.3) ** 2 + ((y - 0.45) / 0.35) ** 2))
    seam = 1 - 0.35 * np.exp(-((x - 0.31) / 0.012) ** 2)
    img = pleats * weave * hot * seam
    img = img / img.max()
    # four panels between the dark ribs of the shade's frame
    return img * _soft_border(shape, BORDER_FLOOR["lampshade"], cells=(1, 4), bar=0.05)


def _facade(rng, shape=(160, 224)) -> np.ndarray:
    """A sunlit brick facade with two windows: per-brick albedo, mortar, glass; 1 = the brightest brick."""
    h, w = shape
    rows, cols = 20, 12
    yy, xx = np.mgrid[0:h, 0:w]
    r = (yy * rows) // h
    xb = xx * cols / w + 0.5 * (r % 2)
    c = np.floor(xb).astype(int)
    alb = 0.45 + 0.25 * rng.random((rows + 1, cols + 2))[r, c]
    fy = (yy * rows / h) % 1.0
    fx = xb % 1.0
    mortar = (fy < 0.14) | (fx < 0.07)
    img = np.where(mortar, 0.8, alb) * (0.9 + 0.2 * _fbm(rng, shape, (8, 10), 2))
    for x0 in (0.22, 0.62):  # two windows: dark glass reflecting the sky a little
        win = (xx / w > x0) & (xx / w < x0 + 0.18) & (yy / h > 0.3) & (yy / h < 0.62)
        img = np.where(win, 0.12 + 0.05 * _smooth_noise(rng, shape, (3, 3)), img)
    img = img / img.max()
    # seen between the dark pillars of an arcade (pure camera rotation: no parallax, so
    # pillars at any depth look the same as dark bars in the facade's plane)
    return img * _soft_border(shape, BORDER_FLOOR["facade"], cells=(1, 6), bar=0.06)


def _plaster(rng, shape=(96, 128)) -> np.ndarray:
    """Painted plaster: blotchy low-frequency shading and grain, reflectance 0.45-0.75."""
    return 0.45 + 0.2 * _fbm(rng, shape, (2, 3), 4) + 0.1 * _smooth_noise(rng, shape, (24, 32))


def _wallpaper(rng, shape=(96, 128)) -> np.ndarray:
    """Striped wallpaper with a soft print, reflectance 0.25-0.65."""
    x = (np.arange(shape[1]) + 0.5)[None, :] / shape[1]
    stripes = 0.5 + 0.5 * np.cos(2 * np.pi * 10 * x)
    return 0.25 + 0.25 * stripes + 0.15 * _fbm(rng, shape, (6, 8), 2)


def _wood(rng, shape=(96, 160)) -> np.ndarray:
    """Wooden floor boards: per-board tone, grain along the boards, reflectance 0.15-0.5."""
    h, w = shape
    boards = 6
    yy = np.arange(h)[:, None]
    b = (yy * boards) // h
    tone = 0.2 + 0.15 * rng.random(boards + 1)[b]
    grain = 0.12 * np.sin(2 * np.pi * (yy * boards / h) * 3 + 6 * _fbm(rng, shape, (2, 12), 2))
    gap = ((yy * boards / h) % 1.0) < 0.06
    return np.clip(np.where(gap, 0.1, tone + grain + 0.05), 0.1, 0.6) * np.ones((1, w))


#: name -> (generator, one-line description)
TEXTURES = {
    "scenery": (_scenery, "outdoor scenery through a window (sky, clouds, hills, trees), soft daylit border"),
    "lampshade": (_lampshade, "a lit fabric lamp shade (pleats, weave, hot spot, seam), dimmer rim"),
    "facade": (_facade, "a sunlit brick facade with two dark windows, soft penumbra border"),
    "plaster": (_plaster, "painted plaster, reflectance 0.45-0.75"),
    "wallpaper": (_wallpaper, "striped wallpaper, reflectance 0.25-0.65"),
    "wood": (_wood, "wooden floor boards, reflectance 0.1-0.6"),
}


def texture(name: str, seed: int = 0) -> np.ndarray:
    """The procedural texture ``name`` (one of :data:`TEXTURES`) for ``seed``: float32 (rows, cols)."""
    if name not in TEXTURES:
        raise ValueError(f"unknown procedural texture {name!r}; expected one of {', '.join(TEXTURES)}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"texture seed: expected an int >= 0, found {seed!r}")
    rng = np.random.default_rng([int(seed), sum(map(ord, name))])
    return np.ascontiguousarray(TEXTURES[name][0](rng), dtype=np.float32)
