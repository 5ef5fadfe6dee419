"""Event voxel grids (E2VID, Rebecq et al. TPAMI 2019, §3.1; FireNet uses the same input).

A window of N events e_i = (t_i, x_i, y_i, p_i) becomes B temporal bins

    E_k(x, y) = Σ_{i: (x_i, y_i) = (x, y)} p_i · max(0, 1 − |k − t*_i|),   k = 0 … B−1,

with t*_i = (B − 1)(t_i − t_0)/(t_{N−1} − t_0) the timestamps scaled by the window's first and
last event (ΔT = 1 if they coincide), p_i = ±1. Each event is shared linearly between its two
nearest bins. Per window, the non-zero entries are then normalised to mean 0 and standard
deviation 1 (zeros stay zero), as the networks were trained.
"""

from __future__ import annotations

import numpy as np

__all__ = ["events_to_voxel_grid", "normalize_voxel_grid", "voxel_grid_torch"]


def events_to_voxel_grid(t, x, y, p, num_bins: int, shape) -> np.ndarray:
    """(num_bins, H, W) float32 voxel grid of time-sorted events (see the module docstring).

    ``p`` is the polarity: > 0 is ON (+1), anything else OFF (−1).
    """
    H, W = int(shape[0]), int(shape[1])
    B = int(num_bins)
    if B < 1:
        raise ValueError(f"num_bins must be >= 1, got {num_bins}")
    t = np.asarray(t)
    n = t.shape[0]
    grid = np.zeros(B * H * W, np.float64)
    if n == 0:
        return grid.reshape(B, H, W).astype(np.float32)
    x = np.asarray(x, np.int64)
    y = np.asarray(y, np.int64)
    if x.min() < 0 or y.min() < 0 or x.max() >= W or y.max() >= H:
        raise ValueError(f"event coordinates outside the {W}x{H} sensor")
    t0 = int(t[0])
    dt = int(t[-1]) - t0
    if dt < 0:
        raise ValueError("events must be sorted by time")
    dt = dt if dt > 0 else 1
    ts = (B - 1) * ((t.astype(np.int64) - t0).astype(np.float64) / dt)
    ti = np.floor(ts).astype(np.int64)
    frac = ts - ti
    pol = np.where(np.asarray(p) > 0, 1.0, -1.0)
    pix = y * W + x
    HW = H * W
    grid += np.bincount(ti * HW + pix, weights=pol * (1.0 - frac), minlength=B * HW)[:B * HW]
    right = ti + 1 < B
    if right.any():
        grid += np.bincount((ti[right] + 1) * HW + pix[right], weights=pol[right] * frac[right],
                            minlength=B * HW)[:B * HW]
    return grid.reshape(B, H, W).astype(np.float32)


def normalize_voxel_grid(grid: np.ndarray) -> np.ndarray:
    """Non-zero entries shifted and scaled to mean 0, standard deviation 1 (zeros untouched);
    returned unchanged when there are none, only shifted when their deviation is 0."""
    g = np.asarray(grid, np.float32)
    nz = g != 0
    n = int(nz.sum())
    if n == 0:
        return g.copy()
    v = g[nz].astype(np.float64)
    mean = v.mean()
    std = v.std()
    out = np.zeros_like(g)
    out[nz] = ((v - mean) / (std if std > 0 else 1.0)).astype(np.float32)
    return out


def voxel_grid_torch(t, x, y, p, num_bins: int, shape, normalize: bool = True):
    """:func:`events_to_voxel_grid` (then :func:`normalize_voxel_grid` when ``normalize``) with
    PyTorch on the tensors' device: (num_bins, H, W) float32 tensor, never leaving the device.

    ``t`` int64, ``x``, ``y``, ``p`` integer tensors of one window, time-sorted. The same
    arithmetic in float64 (scaled time, bilinear weights, sums, mean and standard deviation of
    the non-zero entries), then float32; on a GPU the sums are accumulated with atomics, in an
    order that can differ from :func:`numpy.bincount`'s by the last float64 bits, far below the
    float32 result's precision.
    """
    import torch
    H, W = int(shape[0]), int(shape[1])
    B = int(num_bins)
    if B < 1:
        raise ValueError(f"num_bins must be >= 1, got {num_bins}")
    dev = t.device
    n = int(t.shape[0])
    grid = torch.zeros(B * H * W, dtype=torch.float64, device=dev)
    if n == 0:
        return grid.view(B, H, W).float()
    x = x.long()
    y = y.long()
    t0 = t[0]
    dt = (t[-1] - t0).clamp(min=1).double()
    ts = (B - 1) * ((t - t0).double() / dt)
    ti = torch.floor(ts).long()
    frac = ts - ti
    pol = torch.where(p > 0, 1.0, -1.0).double()
    pix = y * W + x
    HW = H * W
    grid.index_add_(0, ti * HW + pix, pol * (1.0 - frac))
    # no boolean indexing (its data-dependent size makes the host wait for the device): the events
    # in the last bin add an exact +0.0 to a bin of their pixel instead (x + 0.0 == x; no bin is -0.0)
    right = ti + 1 < B
    grid.index_add_(0, torch.where(right, (ti + 1) * HW + pix, pix), torch.where(right, pol * frac, 0.0))
    g = grid.float()
    if normalize:
        # mean and (population) standard deviation of the non-zero entries, as masked sums over the
        # whole grid (float64), again with nothing that waits for the device; no non-zero entry:
        # every entry stays 0
        nz = g != 0
        cnt = nz.sum().double().clamp(min=1.0)
        gd = torch.where(nz, g.double(), 0.0)
        mean = gd.sum() / cnt
        dev_ = torch.where(nz, gd - mean, 0.0)
        std = torch.sqrt((dev_ * dev_).sum() / cnt)
        std = torch.where(std > 0, std, torch.ones_like(std))
        g = torch.where(nz, (dev_ / std).float(), torch.zeros_like(g))
    return g.view(B, H, W)
