"""The prefetch hint compiles for the arrays the kernels use and changes nothing."""

import numpy as np
from numba import njit

from hybridhdr._util.nbprefetch import prefetch


@njit(cache=False)
def _sum_with_prefetch(a, b, idx):
    s = 0.0
    for k in range(idx.shape[0]):
        if k + 4 < idx.shape[0]:
            prefetch(a, idx[k + 4] * np.uint64(a.shape[1]))
            prefetch(b, idx[k + 4])
        s += a[idx[k], 0] + b[idx[k]]
    prefetch(a, np.uint64(10**12))  # far outside the array: a hint never faults
    return s


def test_prefetch_is_only_a_hint():
    rng = np.random.default_rng(0)
    a = rng.random((1000, 8))
    b = rng.random(2000)[::2]  # strided: accepted, still only a hint
    idx = rng.integers(0, 1000, 5000).astype(np.uint64)
    assert _sum_with_prefetch(a, b, idx) == sum(a[i, 0] + b[i] for i in idx)
