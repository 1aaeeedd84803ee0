"""Tile binning: which Gaussians touch which 16×16 tile, front to back.

A Gaussian is assigned to every tile its 3σ box (``radii``) overlaps, and it is
evaluated at every pixel of those tiles (the 3DGS rule). All backends share this
so their results agree pixel for pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import njit
from torch import Tensor

from core.kernels.pool import kernel_threads, run_ranges, run_workers


@dataclass
class TileBins:
    """Gaussian ids per tile, each list sorted by depth (near first).

    ``gauss_ids[offsets[t]:offsets[t + 1]]`` are the Gaussians of tile t, where
    tiles are numbered row-major over a ``tiles_x`` × ``tiles_y`` grid.
    """

    gauss_ids: Tensor
    offsets: Tensor
    tiles_x: int
    tiles_y: int
    tile_size: int

    def tile(self, t: int) -> Tensor:
        return self.gauss_ids[int(self.offsets[t]) : int(self.offsets[t + 1])]


def tile_ranges(
    means2d: Tensor, radii: Tensor, width: int, height: int, tile_size: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Inclusive tile bounds (x0, x1, y0, y1) of each Gaussian's 3σ box."""
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    m = means2d.detach().to(torch.float64)
    r = radii.to(torch.float64)
    x0 = torch.floor((m[:, 0] - r) / tile_size).clamp(0, tiles_x - 1).to(torch.int64)
    x1 = torch.floor((m[:, 0] + r) / tile_size).clamp(0, tiles_x - 1).to(torch.int64)
    y0 = torch.floor((m[:, 1] - r) / tile_size).clamp(0, tiles_y - 1).to(torch.int64)
    y1 = torch.floor((m[:, 1] + r) / tile_size).clamp(0, tiles_y - 1).to(torch.int64)
    return x0, x1, y0, y1


def slab_depths(depths: Tensor, slab: float) -> Tensor:
    """The sort key of slab order: each positive depth rounded up to a multiple of
    ``slab``, so Gaussians in one slab tie and keep their index order (the stable sorts
    below); zero and negative depths (never visible) stay as they are."""
    return torch.where(depths > 0, (torch.floor(depths / slab) + 1.0) * slab, depths)


def bin_gaussians(
    means2d: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    tile_size: int = 16,
    *,
    slab: float | None = None,
) -> TileBins:
    """Per-tile, depth-sorted Gaussian lists; a compiled counting sort on the CPU.

    Both paths give identical lists (tested); the torch one also serves CUDA tensors.
    ``slab``: sort by :func:`slab_depths` instead of the depth itself.
    """
    if slab is not None:
        depths = slab_depths(depths.detach(), slab)
    if means2d.device.type == "cpu":
        return _bin_gaussians_cpu(means2d, depths, radii, width, height, tile_size)
    return bin_gaussians_torch(means2d, depths, radii, width, height, tile_size)


@njit(cache=True, nogil=True)
def _radix_order(keys, idx, n_bits):  # pragma: no cover - numba
    """Stable LSD radix sort of ``idx`` by ``keys[idx]`` (unsigned ints), 11 bits a pass.

    The bit patterns of positive IEEE floats sort like the floats, so this is the
    depth order (ties keep index order, as a stable argsort) in 3 passes for float32
    and 6 for float64, about 10x faster than torch.argsort on 100k depths.
    """
    a = idx.copy()
    b = np.empty_like(a)
    shift = 0
    while shift < n_bits:
        counts = np.zeros(2049, np.int64)
        for k in range(a.shape[0]):
            counts[((keys[a[k]] >> shift) & 2047) + 1] += 1
        for d in range(2048):
            counts[d + 1] += counts[d]
        for k in range(a.shape[0]):
            digit = (keys[a[k]] >> shift) & 2047
            b[counts[digit]] = a[k]
            counts[digit] += 1
        a, b = b, a
        shift += 11
    return a


@njit(cache=True, nogil=True)
def _boxes_range(
    lo, hi, order, means2d, radii, tile_size, tiles_x, tiles_y, box
):  # pragma: no cover
    """Tile bounds (x0, x1, y0, y1) of the Gaussians order[lo:hi], as :func:`tile_ranges`."""
    for k in range(lo, hi):
        g = order[k]
        mx = np.float64(means2d[g, 0])
        my = np.float64(means2d[g, 1])
        r = np.float64(radii[g])
        box[k, 0] = int(min(max(math.floor((mx - r) / tile_size), 0.0), tiles_x - 1.0))
        box[k, 1] = int(min(max(math.floor((mx + r) / tile_size), 0.0), tiles_x - 1.0))
        box[k, 2] = int(min(max(math.floor((my - r) / tile_size), 0.0), tiles_y - 1.0))
        box[k, 3] = int(min(max(math.floor((my + r) / tile_size), 0.0), tiles_y - 1.0))


@njit(cache=True, nogil=True)
def _place_band(w, n_workers, order, box, tiles_x, tiles_y, fill, ids):  # pragma: no cover
    """Worker w places the tiles of its band of tile rows, Gaussians in depth order.

    Bands split the rows, not the Gaussians, so each tile's list is written by one
    worker in global depth order: sorted without any sort, and race-free.
    """
    ty_lo = tiles_y * w // n_workers
    ty_hi = tiles_y * (w + 1) // n_workers
    for k in range(order.shape[0]):
        y0 = max(box[k, 2], ty_lo)
        y1 = min(box[k, 3], ty_hi - 1)
        if y0 > y1:
            continue
        g = order[k]
        for ty in range(y0, y1 + 1):
            for tx in range(box[k, 0], box[k, 1] + 1):
                t = ty * tiles_x + tx
                ids[fill[t]] = g
                fill[t] += 1


@njit(cache=True, nogil=True)
def _tile_offsets(box, tiles_x, n_tiles):  # pragma: no cover
    """Start of each tile's list (n_tiles + 1 entries; the last is the total)."""
    counts = np.zeros(n_tiles + 1, np.int64)
    for k in range(box.shape[0]):
        for ty in range(box[k, 2], box[k, 3] + 1):
            for tx in range(box[k, 0], box[k, 1] + 1):
                counts[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    return counts


def depth_order(depths: Tensor, visible: Tensor) -> np.ndarray:
    """Indices of the visible Gaussians, nearest first (ties in index order)."""
    idx = torch.nonzero(visible).reshape(-1).numpy()
    d = depths.detach()
    dv = d[visible]
    if dv.numel() and bool((dv > 0).all()) and d.dtype in (torch.float32, torch.float64):
        bits = d.contiguous().numpy().view(np.uint32 if d.dtype == torch.float32 else np.uint64)
        return _radix_order(bits, idx, 32 if d.dtype == torch.float32 else 64)
    # Zero, negative or NaN depths (never visible from the projection): the general sort.
    return idx[np.argsort(dv.numpy(), kind="stable")]


def _bin_gaussians_cpu(
    means2d: Tensor, depths: Tensor, radii: Tensor, width: int, height: int, tile_size: int
) -> TileBins:
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    order = depth_order(depths, radii > 0)
    m = means2d.detach().contiguous().numpy()
    r = radii.detach().contiguous().numpy()
    box = np.empty((order.shape[0], 4), np.int64)
    run_ranges(_boxes_range, order.shape[0], (order, m, r, tile_size, tiles_x, tiles_y, box))
    offsets = _tile_offsets(box, tiles_x, tiles_x * tiles_y)
    ids = np.empty(offsets[-1], np.int64)
    fill = offsets[:-1].copy()
    n_workers = min(kernel_threads(), tiles_y)
    run_workers(_place_band, n_workers, (order, box, tiles_x, tiles_y, fill, ids))
    return TileBins(torch.from_numpy(ids), torch.from_numpy(offsets), tiles_x, tiles_y, tile_size)


def bin_gaussians_torch(
    means2d: Tensor, depths: Tensor, radii: Tensor, width: int, height: int, tile_size: int = 16
) -> TileBins:
    """Build the per-tile, depth-sorted Gaussian lists (vectorised torch, any device)."""
    device = means2d.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = tiles_x * tiles_y
    x0, x1, y0, y1 = tile_ranges(means2d, radii, width, height, tile_size)
    vis = radii > 0
    nx = torch.where(vis, x1 - x0 + 1, torch.zeros_like(x0))
    ny = torch.where(vis, y1 - y0 + 1, torch.zeros_like(y0))
    counts = nx * ny
    total = int(counts.sum())
    if total == 0:
        return TileBins(
            torch.zeros(0, dtype=torch.int64, device=device),
            torch.zeros(n_tiles + 1, dtype=torch.int64, device=device),
            tiles_x,
            tiles_y,
            tile_size,
        )
    n = means2d.shape[0]
    gid = torch.repeat_interleave(torch.arange(n, device=device), counts)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=device) - torch.repeat_interleave(starts, counts)
    tx = x0[gid] + local % nx[gid]
    ty = y0[gid] + local // nx[gid]
    tile = ty * tiles_x + tx
    order = torch.argsort(depths.detach(), stable=True)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(n, device=device)
    key = tile * n + rank[gid]
    sort = torch.argsort(key)
    gauss_ids = gid[sort]
    per_tile = torch.bincount(tile, minlength=n_tiles)
    offsets = torch.zeros(n_tiles + 1, dtype=torch.int64, device=device)
    offsets[1:] = torch.cumsum(per_tile, 0)
    return TileBins(gauss_ids, offsets, tiles_x, tiles_y, tile_size)
