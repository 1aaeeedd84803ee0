"""The per-view opacity factor of a model: one-sided culling times grazing fade."""

from __future__ import annotations

import torch
from torch import Tensor

from core.kernels.dispatch import cpu_float
from core.render import grazing as gz
from core.render import orientation as ori
from core.render.gaussians import Gaussians
from core.render.raster.projection import ALPHA_MIN
from core.scene.cameras import Camera


def view_opacity_scale(
    gaussians: Gaussians,
    camera: Camera,
    *,
    one_sided: bool,
    grazing: bool,
    normals: Tensor | None = None,
    compiled: bool | None = None,
) -> Tensor | None:
    """(N,) factor on each opacity for ``camera`` (None: every opacity as stored).
    ``one_sided``: cull splats seen from behind (core.render.orientation); ``grazing``:
    the learned edge-on fade (core.render.grazing). Either is skipped when the model
    lacks its state. ``compiled``: one numba pass for CPU models
    (core.render.view_opacity_compiled; None: wherever the model is on the CPU),
    False: the torch functions, the reference."""
    cull_on = one_sided and ori.has_orientation(gaussians)
    fade_on = grazing and gz.has_grazing(gaussians)
    if not (cull_on or fade_on):
        return None
    n = (gaussians.normals() if normals is None else normals).detach()
    if compiled is None:
        compiled = cpu_float(n)
    if compiled:
        return _compiled(gaussians, camera, n, cull_on, fade_on)
    cull = ori.facing(gaussians, camera, n) if cull_on else None
    fade = gz.grazing_factor(gaussians, camera, n) if fade_on else None
    if cull is None:
        return fade
    return cull if fade is None else cull * fade


def _compiled(
    gaussians: Gaussians, camera: Camera, n: Tensor, cull_on: bool, fade_on: bool
) -> Tensor:
    from core.render.view_opacity_compiled import view_factors

    p = gaussians.params
    mu = p["means"].detach()
    cull, angle = view_factors(
        n.to(mu.dtype), mu, camera.center,
        seen=p[ori.SEEN_DIR].detach() if cull_on else None,
        count=p[ori.SEEN_COUNT].detach() if cull_on else None,
        log_scales=p["log_scales"].detach() if cull_on else None,
        exponent=gz.EXPONENT if fade_on else None,
    )  # fmt: skip
    if angle is None:
        assert cull is not None
        return cull
    fade = 1.0 - torch.sigmoid(p[gz.GRAZE_KEY]) * angle
    return fade if cull is None else cull * fade


def visible_index(opacities: Tensor) -> Tensor | None:
    """Indices of the Gaussians whose opacity reaches the rasteriser's ALPHA_MIN (a
    splat's alpha is at most its opacity, so the others add nothing to any pixel), or
    None when every one does. A frozen model's frame drops the rest before projecting:
    one-sided culling leaves 40-50% of a closed object's splats at zero in any view."""
    keep = opacities >= ALPHA_MIN
    if bool(keep.all()):
        return None
    return keep.nonzero()[:, 0]
