"""Tile binning: which Gaussians touch which 16×16 tile, front to back.

A Gaussian is assigned to every tile its 3σ box (``radii``) overlaps, and it is
evaluated at every pixel of those tiles (the 3DGS rule). All backends share this
so their results agree pixel for pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


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


def bin_gaussians(
    means2d: Tensor, depths: Tensor, radii: Tensor, width: int, height: int, tile_size: int = 16
) -> TileBins:
    """Build the per-tile, depth-sorted Gaussian lists (vectorised, no Python loop)."""
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
