"""Roughness-aware environment lookup: a mip chain of the cube map, read trilinearly.

A rough surface reflects a cone of directions, not one; the radiance it returns is the
environment averaged over that cone. Ref-GS and 3DGS-DR's successors get this by
reading a *prefiltered* map at a level of detail (LOD) the roughness gives. Here the
chain is built from the learned cube map itself (level 0, the sharp one) by 2×2 box
averaging of each face down to 1×1, so:

- the learned map stays the sharp one: blur is explained by the roughness, whose LOD
  selects a coarser level, and the gradient of every level flows back to level 0;
- every level is itself a cube map, read with ``envmap.sample_cube``'s seamless padded
  bilinear taps (its padding is rebuilt per level), so the lookup is continuous across
  faces at every level;
- between levels the lookup is linear in the LOD (trilinear filtering), which is what
  makes the result differentiable in the roughness.

The LOD of a roughness ρ (glTF's perceptual roughness; GGX α = ρ²) is chosen so that
one texel of the level spans the reflected lobe: the microfacet normals of GGX spread
by about α radians, reflection doubles that, so the lobe is about 4α across (both
sides). A level-k texel spans 2^k · (π/2) / R radians (a face covers 90°), giving
``lod = log2(4α R / (π/2))``, smoothed near 0 as ``½ log2(1 + x²)`` so a mirror (ρ → 0)
reads level 0 with a gradient that never jumps. ``tests/test_envmap_mips.py`` checks the
chain, the seams, the LOD endpoints and the gradients; ``core.render.shading_compiled``
does the same arithmetic per pixel for frames without gradient.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from core.kernels.dispatch import cpu_float
from core.render.cube_faces import mip_sizes
from core.render.envmap import _min_major, _PaddedBilinear, guarded_face_uv, pad_cube


def cube_mip_chain(texels: Tensor) -> list[Tensor]:
    """Levels of a cube map (6, R, R, C): level 0 is ``texels``, each next one the 2×2
    mean of the previous (:func:`mip_sizes`). Differentiable."""
    six, r, r2, ch = texels.shape
    if six != 6 or r != r2:
        raise ValueError(f"cube texels must be (6, R, R, C), got {tuple(texels.shape)}")
    levels = [texels]
    for n in mip_sizes(r)[1:]:
        levels.append(levels[-1].reshape(6, n, 2, n, 2, ch).mean(dim=(2, 4)))
    return levels


def lod_scale(resolution: int) -> float:
    """x per squared roughness in the LOD ½ log₂(1 + x²) of a map of face size R (see top)."""
    return 4.0 * resolution / (0.5 * math.pi)


def lod_range(resolution: int) -> tuple[float, float]:
    """(:func:`lod_scale`, the top level) of a map of face size R: what a compiled
    lookup needs to turn roughness into a level as :func:`roughness_to_lod` does."""
    return lod_scale(resolution), float(len(mip_sizes(resolution)) - 1)


def roughness_to_lod(roughness: Tensor, resolution: int, num_levels: int) -> Tensor:
    """Level of detail (same shape as ``roughness``) in [0, num_levels − 1] (see top)."""
    alpha = roughness.clamp(0.0, 1.0).square()
    x = alpha * lod_scale(resolution)
    lod = 0.5 * torch.log2(1.0 + x * x)
    return lod.clamp(max=float(num_levels - 1))


def _packed_levels(levels: list[Tensor]) -> tuple[Tensor, list[int], list[int]]:
    """All padded levels in one flat (Σ 6·(R_k+2)², C) buffer; first row and padded
    size of each level."""
    padded = [pad_cube(t) for t in levels]
    offsets, sizes, n = [], [], 0
    for p in padded:
        offsets.append(n)
        sizes.append(p.shape[1])
        n += p.shape[0] * p.shape[1] * p.shape[2]
    flat = torch.cat([p.reshape(-1, p.shape[-1]) for p in padded], dim=0)
    return flat, offsets, sizes


def sample_cube_lod(
    texels: Tensor, dirs: Tensor, lod: Tensor, *, compiled: bool | None = None
) -> Tensor:
    """Radiance of the cube map (6, R, R, C) toward ``dirs`` (..., 3) at level of detail
    ``lod`` (...): linear between the two nearest levels of :func:`cube_mip_chain`, each
    read with seamless bilinear taps. Degenerate directions return 0 with zero gradient,
    as in ``sample_cube``. Differentiable in texels, directions and ``lod``.
    ``compiled``: the chain and the per-pixel lookup, each with its backward, as numba
    loops (core.render.envmap_pack_compiled, core.render.envmap_lookup_compiled; None:
    for CPU tensors), False: the torch ops below, the reference."""
    if dirs.shape[-1] != 3 or lod.shape != dirs.shape[:-1]:
        raise ValueError(
            f"directions must be (..., 3) and lod (...), got {tuple(dirs.shape)} and "
            f"{tuple(lod.shape)}"
        )
    ch = texels.shape[-1]
    lead = dirs.shape[:-1]
    if compiled is None:
        compiled = cpu_float(texels, dirs, lod)
    if compiled:
        from core.render.envmap_lookup_compiled import sample_packed_lod
        from core.render.envmap_pack_compiled import packed_cube_levels

        flat, offsets, sizes = packed_cube_levels(texels, mips=True)
        out = sample_packed_lod(
            flat, offsets, sizes, dirs.reshape(-1, 3).to(texels.dtype),
            lod.reshape(-1).to(texels.dtype), _min_major(texels.dtype),
        )  # fmt: skip
        return out.reshape(*lead, ch)
    levels = cube_mip_chain(texels)
    valid, face, u, v = guarded_face_uv(dirs, texels.dtype)
    lod = lod.reshape(-1).to(texels.dtype).clamp(0.0, float(len(levels) - 1))
    # a NaN LOD reads level 0 with a NaN weight: NaN out (the trainer's guard skips the
    # step), never a garbage level index (NaN.long() is the most negative integer)
    lo = lod.detach().nan_to_num(0.0).floor().long().clamp(0, max(len(levels) - 2, 0))
    frac = (lod - lo.to(lod.dtype)).unsqueeze(-1)

    flat, offsets, sizes = _packed_levels(levels)
    off_t = torch.tensor(offsets, device=texels.device)
    res_t = torch.tensor([t.shape[1] for t in levels], device=texels.device)
    pad_t = torch.tensor(sizes, device=texels.device)

    def tap(k: Tensor) -> Tensor:
        r = res_t[k].to(u.dtype)
        x = (u + 1.0) * (0.5 * r) + 0.5
        y = (v + 1.0) * (0.5 * r) + 0.5
        p = pad_t[k]
        return _PaddedBilinear.apply(flat, x, y, off_t[k] + face * p * p, p)

    out = tap(lo)
    if len(levels) > 1:
        out = out + frac * (tap(lo + 1) - out)
    out = torch.where(valid.unsqueeze(-1), out, torch.zeros((), dtype=out.dtype, device=out.device))
    return out.reshape(*lead, ch)
