"""The per-view opacity factor of a model: one-sided culling times grazing fade."""

from __future__ import annotations

from torch import Tensor

from core.render.gaussians import Gaussians
from core.render.grazing import grazing_factor
from core.render.orientation import facing
from core.scene.cameras import Camera


def view_opacity_scale(
    gaussians: Gaussians,
    camera: Camera,
    *,
    one_sided: bool,
    grazing: bool,
    normals: Tensor | None = None,
) -> Tensor | None:
    """(N,) factor on each opacity for ``camera`` (None: every opacity as stored).
    ``one_sided``: cull splats seen from behind (core.render.orientation); ``grazing``:
    the learned edge-on fade (core.render.grazing). Either is skipped when the model
    lacks its state."""
    if not (one_sided or grazing):
        return None
    n = (gaussians.normals() if normals is None else normals).detach()
    cull = facing(gaussians, camera, n) if one_sided else None
    fade = grazing_factor(gaussians, camera, n) if grazing else None
    if cull is None:
        return fade
    return cull if fade is None else cull * fade
