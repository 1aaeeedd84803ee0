"""Reference rasteriser in plain PyTorch: small, obviously correct, autograd-driven.

It is the oracle the fast backends are tested against. Per tile, every pixel is
composited front to back over the tile's depth-sorted Gaussians exactly as 3DGS
does: alpha = min(0.99, o·exp(-½ dᵀ Σ⁻¹ d)), skipped below 1/255, and compositing
stops before transmittance would drop below 1e-4. Work is chunked (tiles ×
Gaussian chunks) and, when gradients are needed, each chunk is recomputed in the
backward pass (activation checkpointing) so memory stays bounded.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from core.render.raster.binning import TileBins
from core.render.raster.projection import ALPHA_MAX, ALPHA_MIN, T_MIN, Projected


def composite_chunk(
    pix: Tensor,
    means2d: Tensor,
    conics: Tensor,
    opac: Tensor,
    feats: Tensor,
    T_chain: Tensor,
    T_inc: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite K depth-sorted Gaussians over P pixels.

    ``T_chain`` is the product of (1 - alpha) over every earlier Gaussian, excluded
    ones too: once it drops below T_MIN the pixel is finished, also in later chunks.
    ``T_inc`` is the product over included Gaussians only (1 - final alpha).
    Returns (features (P, C) added by this chunk, T_chain after, T_inc after).
    """
    d = pix[:, None, :] - means2d[None, :, :]  # (P, K, 2)
    dx, dy = d[..., 0], d[..., 1]
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = torch.clamp(opac * torch.exp(power.clamp_max(0.0)), max=ALPHA_MAX)
    keep = (power <= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    T_after = T_chain[:, None] * torch.cumprod(one_minus, dim=1)
    T_before = T_after / one_minus  # exact: one_minus ≥ 0.01
    included = T_after >= T_MIN  # a prefix per pixel: the early-termination rule
    w = torch.where(included, alpha * T_before, torch.zeros_like(alpha))
    out = w @ feats
    T_inc = T_inc * torch.where(included, one_minus, torch.ones_like(one_minus)).prod(dim=1)
    return out, T_after[:, -1], T_inc


def tile_pixels(
    tx: int, ty: int, ts: int, width: int, height: int, dtype: torch.dtype, device: torch.device
) -> tuple[Tensor, Tensor, Tensor]:
    """Pixel centres (P, 2) of tile (tx, ty) in row-major order, and their columns and
    rows (P,) as integers."""
    us = torch.arange(tx * ts, min(tx * ts + ts, width), device=device)
    vs = torch.arange(ty * ts, min(ty * ts + ts, height), device=device)
    vv, uu = torch.meshgrid(vs, us, indexing="ij")
    uu, vv = uu.reshape(-1), vv.reshape(-1)
    return torch.stack([uu, vv], dim=-1).to(dtype) + 0.5, uu, vv


def rasterize_reference(
    proj: Projected,
    opacities: Tensor,
    features: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    chunk: int = 2048,
) -> tuple[Tensor, Tensor]:
    """Composite projected Gaussians into (H, W, C) features and (H, W) alpha."""
    dtype, device = features.dtype, features.device
    C = features.shape[1]
    ts = bins.tile_size
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (proj.means2d, proj.conics, opacities, features)
    )
    offsets = bins.offsets.tolist()
    vals: list[Tensor] = []
    alphas: list[Tensor] = []
    pix_ids: list[Tensor] = []
    for ty in range(bins.tiles_y):
        for tx in range(bins.tiles_x):
            t = ty * bins.tiles_x + tx
            lo, hi = offsets[t], offsets[t + 1]
            if hi == lo:
                continue
            pix, uu, vv = tile_pixels(tx, ty, ts, width, height, dtype, device)
            ids_tile = bins.gauss_ids[lo:hi]
            T_chain = torch.ones(pix.shape[0], dtype=dtype, device=device)
            T = torch.ones_like(T_chain)
            acc = torch.zeros(pix.shape[0], C, dtype=dtype, device=device)
            for k in range(0, hi - lo, chunk):
                ids = ids_tile[k : k + chunk]
                m2, con = proj.means2d[ids], proj.conics[ids]
                args = (pix, m2, con, opacities[ids], features[ids], T_chain, T)
                if needs_grad:
                    out, T_chain, T = checkpoint(composite_chunk, *args, use_reentrant=False)
                else:
                    out, T_chain, T = composite_chunk(*args)
                acc = acc + out
                if bool((T_chain < T_MIN).all()):
                    break
            vals.append(acc)
            alphas.append(1.0 - T)
            pix_ids.append(vv * width + uu)
    img = torch.zeros(height * width, C, dtype=dtype, device=device)
    alpha = torch.zeros(height * width, dtype=dtype, device=device)
    if vals:
        idx = torch.cat(pix_ids)
        img = img.index_copy(0, idx, torch.cat(vals))
        alpha = alpha.index_copy(0, idx, torch.cat(alphas))
    return img.reshape(height, width, C), alpha.reshape(height, width)
