"""Deferred shading (paper Sect. 4.2, Eq. 9): C = base + w_r · E(reflect(r̂, n̂)) per pixel.

Compositing. The rasteriser blends every G-buffer channel like a colour,
X = Σ_i x_i α_i T_i, so ``base`` and ``w_r`` are premultiplied by the pixel's coverage
``alpha`` = Σ_i α_i T_i. The specular term uses that premultiplied w_r as is, so it is
weighted by coverage exactly like the base colour (a half-covered mirror pixel reflects
half the environment), and the background fills the uncovered part:

    final = base + w_r · E(reflect(r̂, n̂)) + (1 − alpha) · background

The blended normal is premultiplied too, but only its direction is used (it is
normalised), so coverage does not bend the reflection. Where alpha ≈ 0 the normal is
≈ 0: the safe normalisation maps it to the zero vector, the reflection of the view
ray about a zero normal is the view ray itself, and everything stays finite.

Roughness. When the G-buffer carries a blended roughness (``core.render.roughness``),
E is read from the env map's mip chain at the level of detail that the pixel's ρ gives
(``core.render.envmap_mips``); ρ is un-premultiplied by alpha first (it is a property
of the surface, not of its coverage). Without it the lookup is the sharp one.

Fresnel. With ``fresnel=True`` (``Ablation.fresnel``) the reflection rises toward grazing
angles from the scene's learned head-on reflectance (``EnvMap.fresnel_f0``), taking its
light from the base colour (``core.render.fresnel``); off, Eq. 9 as published.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from core.kernels.dispatch import cpu_float
from core.render.envmap import EnvMap
from core.render.envmap_mips import lod_range, mip_sizes, roughness_to_lod, sample_cube_lod
from core.render.fresnel import apply_fresnel
from core.render.fresnel_compiled import fresnel_compiled
from core.render.gbuffer import GBuffer
from core.render.reflection_compiled import reflection_and_lod
from core.render.shading_compiled import can_shade_compiled, shade_compiled
from core.stages import stage


@dataclass
class ShadeResult:
    """Deferred-shading outputs of one view, all (H, W[, 3]) on the G-buffer's device.

    - ``final``: base + specular + (1 − alpha) · background, (H, W, 3).
    - ``base``: the blended (premultiplied) base colour, (H, W, 3).
    - ``specular``: w_r · E(reflected_dir), (H, W, 3); zeros when shading is disabled.
    - ``w_r``: blended (premultiplied) reflection strength, (H, W).
    - ``reflected_dir``: unit world-space reflection directions, (H, W, 3); ``None``
      when shading is disabled (nothing is computed then).
    """

    final: Tensor
    base: Tensor
    specular: Tensor
    w_r: Tensor
    reflected_dir: Tensor | None


def safe_normalize(x: Tensor, eps: float = 1e-12) -> Tensor:
    """x / |x| along the last axis; vectors shorter than ``eps`` shrink towards 0 instead
    of dividing by ~0, so a zero vector gives 0 with a finite gradient."""
    return x * torch.rsqrt((x * x).sum(dim=-1, keepdim=True).clamp_min(eps * eps))


def reflect(view_dirs: Tensor, normals: Tensor) -> Tensor:
    """Mirror r̂ about n̂: r̂ − 2 (r̂·n̂) n̂ with both inputs normalised safely, (..., 3).

    The sign of the normal does not matter. A zero normal leaves r̂ unchanged.
    """
    r = safe_normalize(view_dirs)
    n = safe_normalize(normals)
    return r - 2.0 * (r * n).sum(dim=-1, keepdim=True) * n


def world_normals(gbuffer: GBuffer) -> Tensor:
    """Unit world-space normals R^T n̂ from the G-buffer's camera-space normals, (H, W, 3)."""
    n = gbuffer.normal
    R = gbuffer.camera.R.to(dtype=n.dtype, device=n.device)
    return safe_normalize(n @ R)  # row-vector form of R^T n


def pixel_roughness(blended: Tensor, alpha: Tensor) -> Tensor:
    """ρ of the surface seen in each pixel: the blended (premultiplied) ρ over alpha;
    0 where nothing covers the pixel (alpha below 1e-6), with a finite gradient."""
    covered = alpha > 1e-6
    return torch.where(covered, blended / torch.where(covered, alpha, 1.0), 0.0).clamp(0.0, 1.0)


def pixel_lod(blended: Tensor, alpha: Tensor, resolution: int) -> Tensor:
    """The env map's level of detail per pixel for a blended roughness (H, W)."""
    levels = len(mip_sizes(resolution))
    return roughness_to_lod(pixel_roughness(blended, alpha), resolution, levels)


def deferred_shade(
    gbuffer: GBuffer,
    envmap: EnvMap | None,
    background: Tensor,
    enabled: bool = True,
    *,
    compiled: bool = True,
    fresnel: bool = False,
) -> ShadeResult:
    """Eq. 9 for one view; see the module docstring for how coverage is composited.

    ``enabled=False`` is the "no deferred shading" ablation: the image is the SH/base
    colour over the background, and ``envmap`` is neither read nor required (may be None).
    On the CPU, when no gradient is wanted (viewer frames, evaluation renders), the
    compiled kernel of ``core.render.shading_compiled`` shades the frame in one pass;
    with gradients (training) the reflected directions and LOD come from
    ``core.render.reflection_compiled`` and the Fresnel rise from
    ``core.render.fresnel_compiled``; ``compiled=False`` keeps the PyTorch path, the
    reference both are tested against.

    ``fresnel``: the reflection rises toward grazing angles and takes its light from
    the base colour (``core.render.fresnel``; ``Ablation.fresnel``; the env map must be
    an ``EnvMap``, whose ``fresnel_f0`` it reads). ``base`` and ``w_r`` of the result stay
    the G-buffer's (the material head-on).
    """
    base, alpha, w_r = gbuffer.base, gbuffer.alpha, gbuffer.w_r
    h, w = base.shape[:2]
    cam = gbuffer.camera
    if (cam.height, cam.width) != (h, w):
        raise ValueError(f"G-buffer is {h}x{w} but its camera is {cam.height}x{cam.width} (H x W)")
    bg = torch.as_tensor(background, dtype=base.dtype, device=base.device).reshape(-1)
    if bg.numel() != base.shape[-1]:
        raise ValueError(f"background must have {base.shape[-1]} values, got {bg.numel()}")
    if not enabled:
        fill = (1.0 - alpha).unsqueeze(-1) * bg
        return ShadeResult(base + fill, base, torch.zeros_like(base), w_r, None)
    if envmap is None:
        raise ValueError("deferred shading is enabled but no environment map was given")

    tensors = (base, gbuffer.normal, w_r, alpha)
    rough = gbuffer.roughness
    if compiled and can_shade_compiled(tensors if rough is None else (*tensors, rough), envmap):
        # the kernel composites the background itself (no image-sized fill here)
        f0 = float(envmap.fresnel_f0.detach()) if fresnel else None
        final, specular, refl = shade_compiled(*tensors, bg, cam, envmap, rough, fresnel_f0=f0)
        return ShadeResult(final, base, specular, w_r, refl)
    fill = (1.0 - alpha).unsqueeze(-1) * bg
    buffers = (gbuffer.normal, alpha) if rough is None else (gbuffer.normal, alpha, rough)
    if compiled and cpu_float(*buffers) and len({t.dtype for t in buffers}) == 1:
        # a training step: directions and LOD in one pass with a hand-written backward
        scale, top = (0.0, 0.0) if rough is None else lod_range(envmap.resolution)
        refl, lod = reflection_and_lod(gbuffer.normal, rough, alpha, cam, scale, top)
    else:
        _, view = cam.world_rays(dtype=base.dtype, device=base.device)
        refl = reflect(view, world_normals(gbuffer))
        lod = None if rough is None else pixel_lod(rough, alpha, envmap.resolution)
    with stage("envmap_lookup"):
        if lod is None:
            radiance = envmap.sample(refl)
        else:
            radiance = sample_cube_lod(envmap.texels(), refl, lod)
    shown_base, shown_w_r = base, w_r
    if fresnel:
        with stage("fresnel"):
            f0 = envmap.fresnel_f0
            both = (base, gbuffer.normal, w_r, alpha) + (() if rough is None else (rough,))
            if compiled and cpu_float(*both) and len({t.dtype for t in both}) == 1:
                shown_base, shown_w_r = fresnel_compiled(
                    base, gbuffer.normal, w_r, rough, alpha, f0, cam
                )
            else:
                rho = 0.0 if rough is None else pixel_roughness(rough, alpha)
                shown_base, shown_w_r = apply_fresnel(base, gbuffer.normal, w_r, rho, f0, cam)
    specular = shown_w_r.unsqueeze(-1) * radiance
    return ShadeResult(shown_base + specular + fill, base, specular, w_r, refl)
