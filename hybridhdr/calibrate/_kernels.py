"""Numba kernels of the calibration (private): the blinking-board event images (wrappers in
``event_images``) and the camera model's nearest-code lookup (:func:`nearest_codes`, wrapper
``camera_model._codes_of``).

Every kernel takes separate contiguous 1-D event arrays: ``x``, ``y`` (uint16) and ``p``
(int8, ±1), already cut into windows by the wrapper (``win_i0``/``win_i1`` event-index bounds
found with ``searchsorted`` on ``t``, half-open). Per-pixel scratch arrays are flattened row-major
(index ``y * width + x``) and reset through a list of touched pixels, so a window costs
O(events in it), not O(pixels).
"""

from __future__ import annotations

import numpy as np
from numba import njit

# columns of the per-window statistics array returned by ``blink_window_stats``
S_EVENTS, S_BOTH, S_ON_ONLY, S_OFF_ONLY, S_OVERLAP = range(5)
N_STATS = 5


@njit(cache=True, nogil=True)
def blink_window_stats(x, y, p, win_i0, win_i1, width, n_pixels, use, min_each, binary, out_image, stats):
    """Classify the pixels of each window by polarity; accumulate the selected windows.

    For window ``k`` (events ``[win_i0[k], win_i1[k])``), a pixel is *both* when it fired at
    least ``min_each`` ON and ``min_each`` OFF events, *ON-only* / *OFF-only* when it fired only
    one polarity (any number of events of it). ``stats[k]`` receives ``(events, both, on_only,
    off_only, overlap)``, where ``overlap`` counts the *both* pixels of window ``k`` that were
    also *both* in window ``k - 1`` (for the pose segmentation).

    When ``use[k]`` is true, every *both* pixel adds to ``out_image`` (flat float64, length
    ``n_pixels``): 1 when ``binary``, else its ON + OFF event count in the window.

    Returns the number of windows processed.
    """
    n_win = win_i0.shape[0]
    on = np.zeros(n_pixels, np.int32)
    off = np.zeros(n_pixels, np.int32)
    touched = np.empty(0, np.int64)
    last_both = np.full(n_pixels, -2, np.int64)
    for k in range(n_win):
        i0 = win_i0[k]
        i1 = win_i1[k]
        n = i1 - i0
        if touched.shape[0] < n:
            touched = np.empty(max(n, 2 * touched.shape[0]), np.int64)
        m = 0
        for i in range(i0, i1):
            idx = np.int64(y[i]) * width + np.int64(x[i])
            if on[idx] == 0 and off[idx] == 0:
                touched[m] = idx
                m += 1
            if p[i] > 0:
                on[idx] += 1
            else:
                off[idx] += 1
        n_both = 0
        n_on = 0
        n_off = 0
        n_overlap = 0
        for j in range(m):
            idx = touched[j]
            a = on[idx]
            b = off[idx]
            if a >= min_each and b >= min_each:
                n_both += 1
                if last_both[idx] == k - 1:
                    n_overlap += 1
                last_both[idx] = k
                if use[k]:
                    if binary:
                        out_image[idx] += 1.0
                    else:
                        out_image[idx] += a + b
            elif b == 0:
                n_on += 1
            elif a == 0:
                n_off += 1
            on[idx] = 0
            off[idx] = 0
        stats[k, S_EVENTS] = n
        stats[k, S_BOTH] = n_both
        stats[k, S_ON_ONLY] = n_on
        stats[k, S_OFF_ONLY] = n_off
        stats[k, S_OVERLAP] = n_overlap
    return n_win


@njit(cache=True, nogil=True)
def binned_signed_rate(t, p, t0, bin_us, n_bins, out_signed, out_total):
    """Histogram events into ``n_bins`` bins of ``bin_us`` µs from ``t0``: signed (ON − OFF) and total."""
    for i in range(t.shape[0]):
        b = (t[i] - t0) // bin_us
        if b < 0 or b >= n_bins:
            continue
        out_total[b] += 1
        if p[i] > 0:
            out_signed[b] += 1
        else:
            out_signed[b] -= 1
    return n_bins


@njit(cache=True, nogil=True)
def nearest_codes(mids, m0, step, x):
    """``np.searchsorted(mids, x)`` (side left: how many of ``mids`` are < x; NaN counts them all)
    as float64, for sorted ``mids`` spaced about ``step`` from ``m0`` (a linear camera response):
    the index is computed, then moved until it is exact, so the result is searchsorted's bit for
    bit for any sorted ``mids`` (the walk is one step or none when the spacing is uniform). About
    3x numpy's binary search on the calibration's arrays, where it is the inner loop."""
    m = mids.size
    out = np.empty(x.size)
    for i in range(x.size):
        v = x[i]
        if not v == v:  # NaN sorts last
            out[i] = m
            continue
        f = (v - m0) / step
        if f <= 0.0:
            k = 0
        elif f >= m:
            k = m
        else:
            k = int(np.ceil(f))
        while k > 0 and mids[k - 1] >= v:
            k -= 1
        while k < m and mids[k] < v:
            k += 1
        out[i] = k
    return out
