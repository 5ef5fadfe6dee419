"""Numba kernels of the event-sensor model (private; the wrapper is :mod:`hybridhdr.simulate.sensor`).

Per-pixel state is flattened row-major (index ``y * width + x``). Times inside the kernels are
float64 µs *relative to the start of the step* (``t0``), so precision does not depend on the
absolute time; timestamps leave the kernels as int64 µs.

:func:`crossings` runs twice per step with the same inputs: first with ``fill=False`` it only
counts the events of each output microsecond (``hist``) without touching the state; the wrapper
turns the histogram into start offsets (a counting sort, O(N + Δt)) and the second call with
``fill=True`` writes every event straight into its time-sorted slot and updates the state. Ties
within one microsecond keep a fixed order: signal events by pixel index (row-major) then by time,
then the noise events in the order given.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def crossings(l0, l1, ref, blind, c_on, c_off, leak_per_us, dt_us, refractory_us, width,
              noise_k, noise_pix, noise_p, fill, hist, pos, t_base, out_t, out_x, out_y, out_p):
    """Threshold crossings of per-pixel linearly interpolated log intensity over one step.

    Parameters
    ----------
    l0, l1 : float64 (n_pixels,)
        (Filtered) log intensity at the start and the end of the step.
    ref : float64 (n_pixels,)
        Reference level at the start of the step; with ``fill`` it is replaced by the level at
        the end. Leak makes the reference drift down at ``leak_per_us`` log units per µs.
    blind : float64 (n_pixels,)
        End of each pixel's refractory period in µs relative to the step start (``<= 0``: not
        blind); with ``fill`` it is updated and re-based to the end of the step.
    c_on, c_off : float64 (n_pixels,)
        Positive ON and OFF contrast thresholds (natural-log units).
    leak_per_us, dt_us, refractory_us : float
        Leak drift, step length (> 0) and refractory period (0 = off), µs based.
    width : int
        Row length, to split pixel indices into x and y.
    noise_k, noise_pix, noise_p : int64, int64, int8 (M,)
        Noise events: microsecond offset in ``1..dt_us``, pixel index and polarity.
    fill : bool
        False: count into ``hist`` (one bin per µs, bin ``k - 1`` for offset ``k``), state kept.
        True: write events at ``pos[k - 1]`` (incremented) and update ``ref`` and ``blind``.
    t_base : int64
        Absolute time of the step start; events get ``t_base + k``.
    out_t, out_x, out_y, out_p : output columns (any stride)

    Returns
    -------
    int
        Number of signal events (noise not included).
    """
    n = l0.shape[0]
    nb = hist.shape[0]
    dtf = dt_us
    n_sig = 0
    for i in range(n):
        a = l0[i]
        b1 = l1[i]
        s = (b1 - a) / dtf + leak_per_us  # slope of d = L - ref in log units per µs
        d = a - ref[i]
        tc = 0.0
        bl = blind[i]
        tracking = False  # True when the step ends inside a refractory period
        if bl > 0.0:
            if bl >= dtf:
                tracking = True
            else:
                tc = bl
                d = 0.0  # re-referenced at the end of the refractory period (IEBCS behaviour)
        if s > 0.0:
            target = c_on[i]
            pol = 1
        else:
            target = -c_off[i]
            pol = -1
        if s != 0.0 and not tracking:
            inv_s = 1.0 / s
            px = i % width
            py = i // width
            while True:
                tx = tc + (target - d) * inv_s
                if tx < tc:
                    tx = tc
                if tx > dtf:
                    break
                k = int(math.floor(tx + 0.5))
                if k < 1:
                    k = 1
                elif k > nb:
                    k = nb
                if fill:
                    j = pos[k - 1]
                    pos[k - 1] = j + 1
                    out_t[j] = t_base + k
                    out_x[j] = px
                    out_y[j] = py
                    out_p[j] = pol
                else:
                    hist[k - 1] += 1
                n_sig += 1
                tc = tx
                d = 0.0  # the reference moves to the crossing (ESIM)
                if refractory_us > 0.0:
                    tb = tc + refractory_us
                    if fill:
                        bl = tb
                    if tb >= dtf:
                        tracking = True
                        break
                    tc = tb  # blind until tb; the reference follows the input meanwhile
        if fill:
            if tracking:
                ref[i] = b1
            else:
                ref[i] = b1 - (d + s * (dtf - tc))
            blind[i] = bl - dtf
    for m in range(noise_k.shape[0]):
        k = noise_k[m]
        if fill:
            j = pos[k - 1]
            pos[k - 1] = j + 1
            q = noise_pix[m]
            out_t[j] = t_base + k
            out_x[j] = q % width
            out_y[j] = q // width
            out_p[j] = noise_p[m]
        else:
            hist[k - 1] += 1
    return n_sig


@njit(cache=True, nogil=True)
def exclusive_cumsum(hist, pos):
    """``pos[b] = sum(hist[:b])``; returns the total."""
    acc = 0
    for b in range(hist.shape[0]):
        pos[b] = acc
        acc += hist[b]
    return acc


@njit(cache=True, nogil=True)
def lowpass_step(lp, x0, x1, inten0, inten1, dt_s, two_pi_fc_per_radiance, out):
    """First-order photoreceptor low-pass on log intensity over one step (v2e, Tier 4).

    The input ``x`` ramps linearly from ``x0`` to ``x1``; the corner frequency
    ``f3dB = fc * I / I_white`` (``two_pi_fc_per_radiance = 2π fc / I_white``) is held at the
    mean radiance of the two samples, and the exact solution of ``τ y' = x - y`` for a ramp,
    ``y1 = x1 - (x1 - x0) h + (y0 - x0) e`` with ``u = Δt/τ``, ``e = exp(-u)``, ``h = (1 - e)/u``,
    is written to ``out`` (``h -> 1`` as ``u -> 0``: a dark pixel holds its value).
    """
    for i in range(lp.shape[0]):
        w = two_pi_fc_per_radiance * 0.5 * (inten0[i] + inten1[i])  # 1/τ in 1/s
        u = dt_s * w
        if u < 1e-8:
            e = 1.0 - u
            h = 1.0 - 0.5 * u
        else:
            e = math.exp(-u)
            h = -math.expm1(-u) / u
        out[i] = x1[i] - (x1[i] - x0[i]) * h + (lp[i] - x0[i]) * e
    return out


@njit(cache=True, nogil=True)
def robust_abs_max(a, b, k):
    """The ``k``-th largest of ``|a - b|`` (k >= 1), by a bounded insertion buffer (k small)."""
    buf = np.zeros(k, dtype=np.float64)
    for i in range(a.shape[0]):
        v = abs(a[i] - b[i])
        if v > buf[k - 1]:
            j = k - 1
            while j > 0 and buf[j - 1] < v:
                buf[j] = buf[j - 1]
                j -= 1
            buf[j] = v
    return buf[k - 1]


@njit(cache=True, nogil=True)
def decode_rgbe(data, start, height, width, out):
    """Decode Radiance RGBE scanlines (new-style run-length or flat) from ``data[start:]`` into
    ``out`` (height, width, 4) uint8. Returns the byte offset after the pixels, or -1 if the data
    end early, -2 on a corrupt run."""
    pos = start
    n = data.shape[0]
    for y in range(height):
        if pos + 4 <= n and data[pos] == 2 and data[pos + 1] == 2 and (data[pos + 2] & 0x80) == 0 \
                and 8 <= width < 32768 and (int(data[pos + 2]) * 256 + int(data[pos + 3])) == width:
            pos += 4
            for c in range(4):
                x = 0
                while x < width:
                    if pos >= n:
                        return -1
                    cnt = int(data[pos])
                    pos += 1
                    if cnt > 128:
                        cnt -= 128
                        if x + cnt > width:
                            return -2
                        if pos >= n:
                            return -1
                        v = data[pos]
                        pos += 1
                        for k in range(cnt):
                            out[y, x + k, c] = v
                        x += cnt
                    else:
                        if cnt == 0 or x + cnt > width:
                            return -2
                        if pos + cnt > n:
                            return -1
                        for k in range(cnt):
                            out[y, x + k, c] = data[pos + k]
                        pos += cnt
                        x += cnt
        else:  # flat (uncompressed) scanline
            if pos + 4 * width > n:
                return -1
            for x in range(width):
                for c in range(4):
                    out[y, x, c] = data[pos + 4 * x + c]
            pos += 4 * width
    return pos
