"""A simplified per-pixel AKF walk on the GPU, for ``benchmarks/gpu.py``'s cost breakdown only.

One thread per pixel over events grouped by pixel (``reconstruct.cuda._Grouper``), with the AKF's
terms added one by one (``level``): 0 the events alone (L̂ jumps by the threshold, eq. 15, and the
update time moves), 1 plus the process noise (P grows with Δt, eq. 2's first term), 2 plus the
frame fusion with R held (eqs. 17 and 20: the pull towards L^A and P's shrinking). The package's
walk (``_cuda_kernels.k_akf_walk``) adds the isolated-pixel term (t* from the neighbours'
groups), the refractory term, R's interpolation (eq. 7) and the censored bounds. Not a filter
anyone should use: its output is not compared with anything, only timed.
"""

from __future__ import annotations

import numpy as np
from numba import cuda

from hybridhdr.reconstruct import _kernels as K

US = K.US


@cuda.jit
def k_simple(t, p, start, grp, S, level, c_on, c_off, s_proc, n_pix):
    for pix in range(cuda.grid(1), n_pix, cuda.gridsize(1)):
        lo = start[pix]
        hi = start[pix + 1]
        if lo == hi:
            continue
        sl = S[pix, K.A_L]
        sp = S[pix, K.A_P]
        la = S[pix, K.A_LA]
        rinv = S[pix, K.A_RINV]
        tu = S[pix, K.A_TU]
        for g in range(lo, hi):
            i = grp[g]
            tif = np.float64(t[i])
            if level >= 2:
                d = 1.0 / (1.0 + sp * (rinv * ((tif - tu) * US)))
                sl = la + (sl - la) * d
                sp = sp * d
            if level >= 1:
                sp += s_proc * ((tif - tu) * US)
            sl += c_on if p[i] > 0 else -c_off
            tu = tif
        S[pix, K.A_L] = sl
        S[pix, K.A_P] = sp
        S[pix, K.A_TU] = tu
