"""Numba kernels of the capture package (no I/O, no state; wrappers validate the inputs)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def assign_slots(t, period, tol_frac, slot, status):
    """Give each time of a periodic sequence its slot number, relative to the last good time.

    Parameters
    ----------
    t : int64 (N,) sorted times (µs)
    period : float, expected spacing (µs)
    tol_frac : float, largest allowed distance from the grid, as a fraction of ``period``
    slot : int64 (N,) output slot numbers (slot[0] = 0)
    status : int8 (N,) output: 0 on the grid, 1 duplicate of the previous slot, 2 off the grid

    Returns the number of times with status 0. Times with status != 0 do not move the reference,
    so one stray pulse cannot shift the numbering of the following ones.
    """
    n = t.shape[0]
    if n == 0:
        return 0
    ref_t = t[0]
    ref_n = 0
    slot[0] = 0
    status[0] = 0
    good = 1
    for k in range(1, n):
        x = (t[k] - ref_t) / period
        r = np.floor(x + 0.5)
        if abs(x - r) > tol_frac:
            slot[k] = ref_n + np.int64(r)
            status[k] = 2
        elif r == 0:
            slot[k] = ref_n
            status[k] = 1
        else:
            ref_n = ref_n + np.int64(r)
            ref_t = t[k]
            slot[k] = ref_n
            status[k] = 0
            good += 1
    return good


@njit(cache=True, nogil=True)
def pack_columns(t, x, y, p, out_t, out_x, out_y, out_p):
    """Copy event fields (strided views of an EVENT_DTYPE array) into contiguous columns in one
    pass, without holding the GIL (the recorder's writer thread runs beside the sources)."""
    for i in range(t.shape[0]):
        out_t[i] = t[i]
        out_x[i] = x[i]
        out_y[i] = y[i]
        out_p[i] = p[i]
    return t.shape[0]
