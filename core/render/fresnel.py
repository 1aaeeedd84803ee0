"""Fresnel: how much more a surface reflects when seen at a grazing angle.

Why. Eq. 9 reflects w_r · E whatever the angle, but every real surface, coated plastic
and metal alike, reflects more toward grazing angles (Schlick: F = F0 + (1 − F0)(1 −
cos θ)⁵, the factor in glTF's and every split-sum renderer's BRDF). A model without it
can only fake the bright rims of a coated object by bending the rim's normals or raising
w_r, which is then wrong where the same splats face the camera.

How far a reflection rises is relative: from F0 head-on to 1 edge-on, a factor 1 / F0.
Eq. 9 fixes only the product w_r · E (a mirror learned with w_r = 0.05 has a map twenty
times the true radiance), so w_r is not F0 and cannot say how far to rise. The scene's
F0 is learned instead (``EnvMap.fresnel_f0``, one value with the map whose scale it
reads): a coated plastic learns ~0.04 and rises up to 25×, a gold ~1 and hardly rises.

What, per pixel (c = |view ray · normal|, ρ the pixel's roughness, F0 the scene's):

    rise  = (1 − ρ)(1 − c)⁵                 Schlick's term, its grazing peak lowered on
                                           rough surfaces (as Lagarde's max(1 − ρ, F0))
    w_r'  = w_r · (1 + (1 − F0) / F0 · rise) the reflection F / F0 times the head-on one
    base' = base · (1 − rise)               the light the stronger reflection takes from
                                           the diffuse part: base was learned head-on as
                                           (1 − F0)·D, the coat now passes (1 − F)·D

Seen head-on (c = 1) or fully rough (ρ = 1) nothing changes; edge-on a smooth surface
reflects the true radiance (w_r / F0 · E) and shows no base. Both buffers stay
premultiplied by coverage (the factors are per pixel). ``core.render.shading_compiled``
does the same per pixel for frames without gradients; ``tests/test_fresnel.py`` holds
the two together and checks Schlick's curve.
"""

from __future__ import annotations

import torch
from torch import Tensor

from core.scene.cameras import Camera


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


def fresnel_rise(cos: Tensor, rho: Tensor | float) -> Tensor:
    """(1 − ρ)(1 − c)⁵ per pixel (H, W)."""
    return (1.0 - rho) * (1.0 - cos) ** 5


def apply_fresnel(
    base: Tensor,
    normal: Tensor,
    w_r: Tensor,
    rho: Tensor | float,
    f0: Tensor | float,
    camera: Camera,
) -> tuple[Tensor, Tensor]:
    """(base', w_r') of the module docstring: the premultiplied base colour (H, W, 3) and
    reflection strength (H, W) a pixel shows at its viewing angle. ``rho`` is the pixel's
    un-premultiplied roughness (``shading.pixel_roughness``), or 0 for mirror lookups;
    ``f0`` the scene's head-on reflectance (``EnvMap.fresnel_f0``)."""
    rise = fresnel_rise(cos_view(normal, camera), rho)
    return base * (1.0 - rise).unsqueeze(-1), w_r * (1.0 + (1.0 - f0) / f0 * rise)
