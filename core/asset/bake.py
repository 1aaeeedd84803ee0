"""Bake the model's G-buffer into the atlas's texels by projecting them into views.

Each covered texel's surface point is projected into every baked view; where the
view's rendered depth agrees with the point's depth (it is the surface seen there)
the view's un-premultiplied base colour, reflection strength w_r, roughness ρ and
world normal are read bilinearly and averaged with weight alpha · cos²(view angle):
grazing looks blur the splats and carry little. Memory is O(texels + one view's
G-buffer); time is O(views × (render + texels)).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from core.asset.texels import TexelSamples
from core.model.trained import TrainedModel
from core.scene.views import View

# A point counts as seen when |its depth − the rendered depth| is below this fraction
# of the scene radius plus 1.5 pixels' footprint at its depth (the TSDF mesh sits
# within about a voxel of the rendered depth it was fused from).
DEPTH_TOLERANCE = 0.01
MIN_COS = 0.1  # views seeing the surface more grazing than ~84° are not baked
MIN_ALPHA = 0.5  # pixels the model barely covers are edges: not baked


@dataclass
class BakedSurface:
    """Per texel (M of them) means over the views that saw it; ``weight`` 0 = unseen."""

    base: np.ndarray  # (M, 3) linear, un-premultiplied
    w_r: np.ndarray  # (M,)
    roughness: np.ndarray  # (M,)
    normal: np.ndarray  # (M, 3) unit world normal of the model (mesh normal if unseen)
    weight: np.ndarray  # (M,)
    grazing: np.ndarray  # (M,) mean (1 − cos θ)⁵ over the views (Schlick's Fresnel term)
    views: int

    @property
    def seen(self) -> np.ndarray:
        return self.weight > 0


def pick_views(views: Sequence[View], count: int) -> list[View]:
    """``count`` views spread evenly over the list (all when there are fewer)."""
    views = list(views)
    if count >= len(views):
        return views
    idx = np.unique(np.round(np.linspace(0, len(views) - 1, count)).astype(int))
    return [views[i] for i in idx]


@torch.no_grad()
def bake_views(
    model: TrainedModel,
    views: Sequence[View],
    texels: TexelSamples,
    *,
    progress: Callable[[int, int], None] | None = None,
) -> BakedSurface:
    """Average the model's material channels over ``views`` at the texels' points."""
    device = model.device
    pts = torch.from_numpy(texels.points).to(device, torch.float64)
    nrm = torch.from_numpy(texels.normals).to(device, torch.float64)
    m = texels.count
    acc = torch.zeros(m, 9, dtype=torch.float64, device=device)  # base3 w_r ρ normal3 (1-cos)^5
    wsum = torch.zeros(m, dtype=torch.float64, device=device)
    radius = float(model.radius) if model.radius is not None else 1.0
    for i, view in enumerate(views):
        cam = view.camera
        frame = model.render(cam, ("base", "roughness", "depth"))
        gb = frame.gbuffer
        depth, valid = frame.depth()
        alpha = gb.alpha
        a = alpha.clamp_min(1e-6)
        rough = gb.roughness if gb.roughness is not None else torch.zeros_like(alpha)
        world_n = frame.world_normals()
        world_n = world_n / world_n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        stack = torch.cat(
            [gb.base / a[..., None], (gb.w_r / a)[..., None], (rough / a)[..., None], world_n],
            -1,
        )  # (H, W, 8)
        ok = (valid & (alpha > MIN_ALPHA)).to(stack.dtype)
        stack = torch.cat([stack, depth[..., None].to(stack), ok[..., None]], -1)
        w2c = cam.world_to_cam.to(device, torch.float64)
        pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        k = cam.intrinsics
        u = k.fx * pc[:, 0] / z.clamp_min(1e-9) + k.cx
        v = k.fy * pc[:, 1] / z.clamp_min(1e-9) + k.cy
        h, w = alpha.shape
        inside = (z > 1e-6) & (u >= 0) & (u <= w) & (v >= 0) & (v <= h)
        to_cam = cam.center.to(device, torch.float64) - pts
        cos = (nrm * to_cam).sum(-1) / to_cam.norm(dim=-1).clamp_min(1e-12)
        cand = inside & (cos > MIN_COS)
        idx = torch.nonzero(cand).squeeze(1)
        if idx.numel() == 0:
            continue
        grid = torch.stack([u[idx] / w * 2 - 1, v[idx] / h * 2 - 1], -1).to(stack.dtype)
        img = stack.permute(2, 0, 1)[None]
        # depth and the validity flag nearest (no blend across a silhouette)
        near = F.grid_sample(img[:, 8:], grid[None, None], mode="nearest", align_corners=False)
        lin = F.grid_sample(img[:, :8], grid[None, None], mode="bilinear", align_corners=False)
        near = near[0, :, 0].T.to(torch.float64)
        lin = lin[0, :, 0].T.to(torch.float64)
        footprint = 1.5 * z[idx] / max(k.fx, 1e-9)
        tol = DEPTH_TOLERANCE * radius + footprint
        seen = (near[:, 1] > 0.5) & ((near[:, 0] - z[idx]).abs() < tol)
        idx, lin = idx[seen], lin[seen]
        wt = cos[idx].square()
        fres = (1.0 - cos[idx]).clamp(0, 1).pow(5)[:, None]
        acc.index_add_(0, idx, torch.cat([lin, fres], 1) * wt[:, None])
        wsum.index_add_(0, idx, wt)
        if progress is not None:
            progress(i + 1, len(views))
    mean = acc / wsum.clamp_min(1e-12)[:, None]
    seen = wsum > 0
    normal = torch.where(seen[:, None], mean[:, 5:8], nrm)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # a normal turned away from the mesh's by more than 90° is an averaging artefact
    flip = (normal * nrm).sum(-1) < 0
    normal = torch.where(flip[:, None], nrm, normal)
    return BakedSurface(
        base=mean[:, 0:3].clamp(0, None).float().cpu().numpy(),
        w_r=mean[:, 3].clamp(0, 1).float().cpu().numpy(),
        roughness=mean[:, 4].clamp(0, 1).float().cpu().numpy(),
        normal=normal.float().cpu().numpy(),
        weight=wsum.float().cpu().numpy(),
        grazing=mean[:, 8].clamp(0, 1).float().cpu().numpy(),
        views=len(views),
    )


def bake_memory_bytes(texels: int, height: int, width: int) -> int:
    """About the peak memory of :func:`bake_views`: float64 per-texel accumulators and
    projections (~30 numbers per texel) and one view's G-buffer and its stacks."""
    return int(texels * 30 * 8 + height * width * 40 * 4)
