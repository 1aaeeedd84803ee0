"""Grazing opacity: each splat learns how much to fade when seen nearly edge-on.

Why. Flat splats tile a curved surface; a ray that grazes it near the silhouette
passes many of them, and each is blurred by the pixel filter *before* compositing,
while a camera filters *after*. Their footprints then pile up beyond the true edge.
Measured on spot_plastic at 3000 iterations (``python -m bench.edge_error --splats``):
each pixel just outside the silhouette is reached by ~9 splats of effective opacity
~0.2 whose centres lie 0.25 px inside it, 57–85° from facing the view; the rendered
alpha there is 0.13 too high and holds 41% of the held-out squared error. With the
surface held on the truth (silhouette points) the optimiser cannot shrink it away,
and splat opacity is one number for face-on and edge-on views alike.

What. Opacity seen from a view is scaled by ``1 − k·(1 − |cos θ|)²``, θ the angle
between the splat's normal and the ray to its centre, ``k = sigmoid(graze_logits)``
learned per splat (initially ≈ 0.02: nothing changes until the images ask for it).
Face-on views see the opacity unchanged; the surface, its normals and its depth are
left where the other losses put them. Models without the state render as before.
"""

from __future__ import annotations

import torch
from torch import Tensor

from core.render.gaussians import Gaussians
from core.scene.cameras import Camera

GRAZE_KEY = "graze_logits"
INIT_LOGIT = -4.0  # k = 0.018
EXPONENT = 2.0


def has_grazing(gaussians: Gaussians) -> bool:
    return GRAZE_KEY in gaussians.params


def add_grazing_state(gaussians: Gaussians) -> None:
    """Give a model the learnable per-splat logits (k ≈ 0.02) if it has none."""
    if has_grazing(gaussians):
        return
    p = gaussians.params["means"]
    logits = torch.full((p.shape[0],), INIT_LOGIT, dtype=p.dtype, device=p.device)
    gaussians.params[GRAZE_KEY] = torch.nn.Parameter(logits)


def grazing_factor(
    gaussians: Gaussians, camera: Camera, normals: Tensor | None = None
) -> Tensor | None:
    """(N,) opacity factor for this camera, differentiable in the logits only (the
    normals and centres are detached: fading must not rotate or move the surface);
    None when the model has no grazing state. ``normals``: the Eq. 6 normals when the
    caller has them."""
    if not has_grazing(gaussians):
        return None
    n = gaussians.normals() if normals is None else normals
    n = n.detach()
    mu = gaussians.params["means"].detach()
    to_cam = camera.center.to(mu)[None, :] - mu
    denom = (n.norm(dim=-1) * to_cam.norm(dim=-1)).clamp_min(1e-12)
    cos = ((n * to_cam).sum(-1) / denom).abs().clamp(max=1.0)
    k = torch.sigmoid(gaussians.params[GRAZE_KEY])
    return 1.0 - k * (1.0 - cos) ** EXPONENT
