"""One-sided splats: which side of each planar Gaussian is the outside, and culling.

Why. A planar Gaussian's normal (Eq. 6) has no sign: the paper flips it to face each
camera, so every splat is two-sided. On a closed surface that makes the far side's
splats near the rim show their tails beyond the silhouette, next to the near side's:
discs lying exactly on a sphere render a silhouette 0.40 px too wide, 0.09 px when
the far side is culled (tests/test_silhouette.py). Training then either shrinks the
surface to match the photos' silhouettes or, when the surface is held in place
(silhouette points), pays with wrong alpha along every silhouette (teapot_gold at
3000 iterations: 28.7 dB without culling → 26.5 dB; 28.7 dB with it).

How. A surface is seen from its outside. Each training step, every Gaussian whose
centre lies on the rendered surface of that view (not behind it) records the unit
direction towards that camera (``seen_dir``, summed, with ``seen_count``). Its
outside is the side of its plane those directions point to. A view culls (opacity
0) the Gaussians whose outside faces away from it, once they are flat (a round
blob's "normal" is an arbitrary axis) and have been seen from ``MIN_VIEWS`` views
that agree (the mean direction's length, 1 for agreeing views and ~0 for a sheet
seen from both sides, at least ``MIN_AGREEMENT``) on one side of the plane; the
others stay two-sided. The sums are per-Gaussian tensors among the model's
parameters (not trained), so densification hands them to clones and split children
and checkpoints keep them.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from core.kernels.dispatch import cpu_float
from core.render.depth_geometry import bilinear_lookup
from core.render.gaussians import UNTRAINED_KEYS, Gaussians
from core.scene.cameras import Camera

SEEN_DIR, SEEN_COUNT = UNTRAINED_KEYS
MIN_VIEWS = 3
MIN_AGREEMENT = 0.25
# Only a flat splat has a side: its smallest scale at most this fraction of the middle one
# (the Eq. 7 scale loss makes them ~1e-3 after the RGB phase; a round blob's "normal"
# is an arbitrary axis).
MAX_FLATNESS = 0.2
# The directions it was seen from must lie clearly on one side of its plane.
MIN_SIDE_COS = 0.3
# A centre counts as on the rendered surface up to this many pixel footprints behind it.
SURFACE_TOLERANCE_PX = 2.0


def has_orientation(gaussians: Gaussians) -> bool:
    return SEEN_DIR in gaussians.params and SEEN_COUNT in gaussians.params


def add_orientation_state(gaussians: Gaussians) -> None:
    """Give a model the (untrained) sums, zero, if it has none."""
    if has_orientation(gaussians):
        return
    p = gaussians.params["means"]
    gaussians.params[SEEN_DIR] = torch.nn.Parameter(torch.zeros_like(p), requires_grad=False)
    gaussians.params[SEEN_COUNT] = torch.nn.Parameter(
        torch.zeros(p.shape[0], dtype=p.dtype, device=p.device), requires_grad=False
    )


@torch.no_grad()
def record_visibility(
    gaussians: Gaussians,
    camera: Camera,
    depth: Tensor,
    valid: Tensor,
    *,
    compiled: bool | None = None,
) -> int:
    """Add this view's direction to the Gaussians on its rendered surface; returns how
    many. ``depth``/``valid`` are the view's rendered geometry depth (H, W).
    ``compiled``: one numba pass (core.render.orientation_compiled; None: for CPU
    models), False: these torch ops, the reference."""
    if not has_orientation(gaussians):
        return 0
    mu = gaussians.params["means"].detach()
    seen_p, count_p = gaussians.params[SEEN_DIR], gaussians.params[SEEN_COUNT]
    if compiled is None:
        compiled = cpu_float(mu, depth) and seen_p.is_contiguous() and count_p.is_contiguous()
    if compiled:
        from core.render.orientation_compiled import record_compiled

        return record_compiled(
            mu, seen_p.data, count_p.data, camera, depth, valid, SURFACE_TOLERANCE_PX
        )
    uv, z = camera.project(mu.double())
    uv, z = uv.to(depth.dtype), z.to(depth.dtype)
    d, inside = bilinear_lookup(depth, uv)
    ok, _ = bilinear_lookup(valid.to(depth.dtype), uv)
    footprint = z / float(camera.intrinsics.fx)
    on_surface = inside & (ok > 0.999) & (z > 0) & (z <= d + SURFACE_TOLERANCE_PX * footprint)
    if not bool(on_surface.any()):
        return 0
    to_cam = camera.center.to(mu)[None, :] - mu[on_surface]
    gaussians.params[SEEN_DIR].data[on_surface] += to_cam / to_cam.norm(dim=-1, keepdim=True)
    gaussians.params[SEEN_COUNT].data[on_surface] += 1.0
    return int(on_surface.sum())


def facing(gaussians: Gaussians, camera: Camera, normals: Tensor | None = None) -> Tensor | None:
    """(N,) 1.0 for the Gaussians this camera may see, 0.0 for those whose known outside
    faces away from it; None when the model records no orientation. ``normals``: the
    unoriented Eq. 6 normals when the caller has them (they are recomputed otherwise)."""
    if not has_orientation(gaussians):
        return None
    p = gaussians.params
    seen, count = p[SEEN_DIR].detach(), p[SEEN_COUNT].detach()
    n = gaussians.normals().detach() if normals is None else normals.detach()
    mu = p["means"].detach()
    seen_len = seen.norm(dim=-1)
    side = (n * seen).sum(-1)
    scales = p["log_scales"].detach().sort(dim=-1).values
    flat = scales[:, 0] - scales[:, 1] <= math.log(MAX_FLATNESS)
    known = (
        flat
        & (count >= MIN_VIEWS)
        & (seen_len >= MIN_AGREEMENT * count)
        & (side.abs() >= MIN_SIDE_COS * seen_len)
    )
    outward = n * torch.sign(side)[:, None]
    to_cam = camera.center.to(mu)[None, :] - mu
    back = known & ((outward * to_cam).sum(-1) < 0)
    return (~back).to(mu.dtype)
