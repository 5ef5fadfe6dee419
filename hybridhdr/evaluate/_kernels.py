"""Numba kernels of the evaluation datasets (private; validated wrappers in ``datasets.py``)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def requantise_events(t, x, y, p, width, c_fine, c_on, c_off, refractory_us, out_t, out_x, out_y, out_p):
    """Re-quantise ideal fine-threshold events into a sensor with per-pixel thresholds.

    Each input event is a log-intensity step of ``p·c_fine`` at its pixel. A pixel accumulates
    the steps since its last reference level; when the accumulated change reaches ``c_on[pix]``
    (or ``−c_off[pix]``), it emits events of that polarity and moves its reference by the
    emitted thresholds. With ``refractory_us > 0`` a pixel that fired less than
    ``refractory_us`` before keeps accumulating silently; when it may fire again it emits a
    single event and its reference jumps to the current level (the backlog of ``n − 1``
    thresholds is lost, as a DVS pixel resets to the current level after firing).

    Returns ``(n_written, overflow)``; the outputs must hold at least ``n_written`` events.
    """
    npix = c_on.shape[0]
    acc = np.zeros(npix, np.float64)
    last = np.full(npix, np.iinfo(np.int64).min // 2, np.int64)
    cap = out_t.shape[0]
    n = 0
    for i in range(t.shape[0]):
        pix = np.int64(y[i]) * width + np.int64(x[i])
        acc[pix] += p[i] * c_fine
        a = acc[pix]
        if a >= 0.0:
            c = c_on[pix]
            k = np.int64(np.floor(a / c + 1e-9))
            pol = 1
        else:
            c = c_off[pix]
            k = np.int64(np.floor(-a / c + 1e-9))
            pol = -1
        if k < 1:
            continue
        if refractory_us > 0:
            if t[i] - last[pix] < refractory_us:
                continue
            emit = 1
            acc[pix] = a - pol * k * c
        else:
            emit = k
            acc[pix] = a - pol * k * c
        last[pix] = t[i]
        for _ in range(emit):
            if n >= cap:
                return n, True
            out_t[n] = t[i]
            out_x[n] = x[i]
            out_y[n] = y[i]
            out_p[n] = pol
            n += 1
    return n, False
