"""Fresnel: how much more a surface reflects when seen at a grazing angle.

Why. Eq. 9 reflects w_r · E whatever the angle, but every real surface, coated plastic
and metal alike, reflects more towards grazing angles (Schlick: F = F0 + (1 − F0)(1 −
cos θ)⁵, the factor glTF's and every split-sum renderer's BRDF carry). A model without
it can only fake the bright rims of a coated object by bending the rim's normals or
raising w_r, which is then wrong where the same splats face the camera. With it, w_r is
the reflectance at normal incidence (F0) and the angle does the rest.

What, per pixel (all buffers premultiplied by coverage alpha, as the rasteriser blends
them; F0 = w_r / alpha, ρ = the pixel's roughness, c = |view ray · normal|):

    boost = max(1 − ρ − F0, 0) · (1 − c)⁵          Schlick, with the grazing peak
                                                    lowered for rough surfaces (Lagarde's
                                                    roughness-aware form, max(1 − ρ, F0))
    w_r'  = w_r + alpha · boost                     the reflectance at this angle
    base' = base · (1 − boost / (1 − F0))           the light the stronger reflection
                                                    takes from the diffuse part: base was
                                                    learned as (1 − F0)·diffuse, the
                                                    surface now passes (1 − F)·diffuse

A mirror (F0 = 1) or a fully rough surface (ρ = 1) is unchanged, and so is every pixel
seen head-on (c = 1). ``core.render.shading_compiled`` does the same per pixel for frames
without gradients; ``tests/test_fresnel.py`` holds the two together and checks the
formula's ends.
"""

from __future__ import annotations

import torch
from torch import Tensor

from core.scene.cameras import Camera

COVERED = 1e-6  # as shading.pixel_roughness: below it a pixel has no surface
ONE_MINUS_F0_FLOOR = 1e-6  # boost is 0 wherever 1 − F0 is this small (ρ ≥ 0)


def cos_view(normal: Tensor, camera: Camera) -> Tensor:
    """|cos θ| between each pixel's view ray and its blended camera-space normal (H, W);
    0 where the normal is 0 (nothing covers the pixel). The normal is normalised twice
    with shading.safe_normalize's floor, as the reflection it shades with is."""
    rays = camera.camera_rays(normal.dtype, normal.device)
    d = rays * torch.rsqrt((rays * rays).sum(-1, keepdim=True))
    n = normal
    for _ in range(2):
        n = n * torch.rsqrt((n * n).sum(-1, keepdim=True).clamp_min(1e-24))
    return (n * d).sum(-1).abs().clamp(0.0, 1.0)


def fresnel_boost(
    w_r: Tensor, alpha: Tensor, rho: Tensor | float, cos: Tensor
) -> tuple[Tensor, Tensor]:
    """(boost, F0) per pixel (H, W): boost = max(1 − ρ − F0, 0)(1 − c)⁵, F0 = w_r / alpha
    (0 where nothing covers the pixel)."""
    covered = alpha > COVERED
    f0 = torch.where(covered, w_r / torch.where(covered, alpha, 1.0), 0.0).clamp(0.0, 1.0)
    return torch.relu(1.0 - rho - f0) * (1.0 - cos) ** 5, f0


def apply_fresnel(
    base: Tensor,
    normal: Tensor,
    w_r: Tensor,
    alpha: Tensor,
    rho: Tensor | float,
    camera: Camera,
) -> tuple[Tensor, Tensor]:
    """(base', w_r') of the module docstring: the premultiplied base colour (H, W, 3) and
    reflection strength (H, W) a pixel shows at its viewing angle. ``rho`` is the pixel's
    un-premultiplied roughness (``shading.pixel_roughness``), or 0 for mirror lookups."""
    boost, f0 = fresnel_boost(w_r, alpha, rho, cos_view(normal, camera))
    keep = 1.0 - boost / (1.0 - f0).clamp_min(ONE_MINUS_F0_FLOOR)
    return base * keep.unsqueeze(-1), w_r + alpha * boost
