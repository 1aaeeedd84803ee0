"""Geometry of rendered depth maps: back-projection, normals from depth (Eq. 10),
bilinear look-ups and projection that stays finite.

Training losses (Eq. 11-14) and the evaluation's consistency measures both use them,
so they live below both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

from core.render.fresnel import cos_view
from core.scene.cameras import Camera

if TYPE_CHECKING:  # the G-buffer module renders; this one only reads its maps
    from core.render.gbuffer import GBuffer

# Depth-based losses trust a pixel only where its surface faces the view within this
# angle. Why: Eq. 8's depth d = D / (N·r̃) turns a normal error δ into a relative depth
# error of about tan θ · δ (1.7× at 60°, 5.7× at 80°), Eq. 10's normals from the
# differences of such depths inherit it, and a point seen edge-on reprojects near the
# neighbour's silhouette where its depth is mixed with the background. Measured on
# spot_plastic at 3000 its (2026-11-25): L_single and L_multi over every covered pixel
# leave the silhouettes' alpha twice as wide as with the centre depth of Eq. 5 and cost
# 0.8 dB of held-out PSNR at the same Chamfer distance.
DEPTH_FACING_DEG = 60.0
# Where a capture never faces some side (core.training.view_coverage), L_single also
# reads pixels up to this angle from face-on, with a depth that moves from Eq. 8's at
# cos θ = cos(DEPTH_FACING_DEG) (the facing pixels keep theirs) to Eq. 5's at 0.3 (the
# mesher's lower knot, core.meshing.mesh.GRAZING_BLEND_COS): measured on a held-out
# knot shot from above (2026-11-30), Eq. 8's depth error there was 1.5x Eq. 5's below
# cos 0.4. Beyond 80° a pixel sees the surface edge-on and its depth mixes with the
# silhouette's background, so it is left out.
OBLIQUE_DEPTH_MAX_DEG = 80.0
OBLIQUE_DEPTH_COS = (0.3, math.cos(math.radians(DEPTH_FACING_DEG)))


def facing_view(normal: Tensor, camera: Camera, max_deg: float = DEPTH_FACING_DEG) -> Tensor:
    """(H, W) bool: the pixel's blended normal (camera space, any length, any sign) is
    within ``max_deg`` of the ray through it. A zero normal faces nothing."""
    rays = camera.camera_rays(normal.dtype, normal.device)
    n = normal.detach()
    dot = (n * rays).sum(-1).abs()
    norm = n.norm(dim=-1) * rays.norm(dim=-1)
    return (dot >= math.cos(math.radians(max_deg)) * norm) & (norm > 0)


def grazing_blend(
    planar: Tensor,
    valid: Tensor,
    centre: Tensor,
    normal: Tensor,
    camera: Camera,
    cos_range: tuple[float, float],
) -> Tensor:
    """Eq. 8's depth moved toward Eq. 5's where the surface is seen obliquely (H, W).

    With c = |cos| between a pixel's blended normal and its ray, the weight of the planar
    depth ramps linearly from 0 at ``cos_range[0]`` to 1 at ``cos_range[1]``. Why: Eq. 8
    divides by N·r̃, so a normal error δ becomes a relative depth error of about
    tan θ · δ; the blended centre depth of Eq. 5 has no such factor. Only ``valid``
    pixels change (the planar depth is kept elsewhere), and only where ``centre`` is
    positive."""
    lo, hi = cos_range
    if not 0.0 <= lo < hi <= 1.0:
        raise ValueError(f"cos_range must satisfy 0 <= lo < hi <= 1, got {cos_range}")
    w = ((cos_view(normal, camera) - lo) / (hi - lo)).clamp(0.0, 1.0).to(planar.dtype)
    blend = w * planar + (1.0 - w) * centre.to(planar.dtype)
    return torch.where(valid & (centre > 0), blend, planar)


def oblique_depth(
    gb: GBuffer, planar: Tensor, valid: Tensor, camera: Camera
) -> tuple[Tensor, Tensor]:
    """(depth, valid) of L_single where the plan adds oblique pixels: Eq. 8's ``planar``
    depth where the surface faces the view within DEPTH_FACING_DEG, moving to Eq. 5's
    centre depth toward OBLIQUE_DEPTH_COS's lower end, over the ``valid`` pixels seen
    within OBLIQUE_DEPTH_MAX_DEG of face-on."""
    depth = grazing_blend(planar, valid, gb.center_depth, gb.normal, camera, OBLIQUE_DEPTH_COS)
    return depth, valid & facing_view(gb.normal, camera, OBLIQUE_DEPTH_MAX_DEG)


def depth_to_points(depth: Tensor, camera: Camera) -> Tensor:
    """Camera-space points (H, W, 3) = z-depth · K⁻¹(u, v, 1)."""
    return depth[..., None] * camera.camera_rays(depth.dtype, depth.device)


def normals_from_depth(
    depth: Tensor, valid: Tensor, camera: Camera, jump_ratio: float | None = None
) -> tuple[Tensor, Tensor]:
    """Eq. 10: unit camera-space normals from differences of back-projected points.

    Returns (normals (H, W, 3) facing the camera, valid (H, W)); a pixel is valid when
    it and its four neighbours have depth and the cross product is not degenerate.
    Border pixels are invalid.

    With ``jump_ratio`` (> 1), along each image axis a pixel whose step to one
    neighbour is more than ``jump_ratio`` times its step to the other uses the shorter,
    one-sided difference instead of the central one. Why: at a depth discontinuity
    inside the object (a self-occlusion edge) the central difference spans both
    surfaces and its normal is neither's, up to 90° off; the nearer neighbour lies on
    the pixel's own surface. On a smooth surface both steps are about equal and the
    central difference is kept.
    """
    P = depth_to_points(depth, camera)
    H, W = depth.shape
    n = torch.zeros_like(P)
    ok = torch.zeros_like(valid)
    if H < 3 or W < 3:
        return n, ok
    mid = P[1:-1, 1:-1]
    du = P[1:-1, 2:] - P[1:-1, :-2]
    dv = P[2:, 1:-1] - P[:-2, 1:-1]
    if jump_ratio is not None:
        du = _same_surface_step(P[1:-1, 2:] - mid, mid - P[1:-1, :-2], du, jump_ratio)
        dv = _same_surface_step(P[2:, 1:-1] - mid, mid - P[:-2, 1:-1], dv, jump_ratio)
    cross = torch.linalg.cross(dv, du)
    norm = cross.norm(dim=-1, keepdim=True)
    v = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    v = v & (norm[..., 0] > 1e-12)
    nn = cross / torch.where(norm > 1e-12, norm, torch.ones_like(norm))
    # Face the camera: a normal seen from the camera satisfies n·P < 0.
    facing = (nn * mid).sum(-1, keepdim=True) <= 0
    nn = torch.where(facing, nn, -nn)
    n = F.pad(nn.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)
    ok = F.pad(v, (1, 1, 1, 1))
    return n, ok


def _same_surface_step(fwd: Tensor, bwd: Tensor, central: Tensor, ratio: float) -> Tensor:
    """The central step, or (where one side is ``ratio``× longer) twice the shorter side."""
    lf = fwd.detach().norm(dim=-1, keepdim=True)
    lb = bwd.detach().norm(dim=-1, keepdim=True)
    jump = torch.maximum(lf, lb) > ratio * torch.minimum(lf, lb)
    shorter = torch.where(lf <= lb, fwd, bwd)
    return torch.where(jump, 2.0 * shorter, central)


@dataclass(frozen=True)
class BilinearTaps:
    """Where :func:`bilinear_lookup` reads an (H, W) image for pixel coordinates uv:
    the top-left tap's flat index, the weights toward the right and lower taps, and
    whether the point lies within the pixel-centre hull. Fixed points seen by a fixed
    camera (the silhouette points) read the same taps every step: build them once."""

    width: int
    i00: Tensor
    fx: Tensor
    fy: Tensor
    inside: Tensor

    def sample(self, img: Tensor) -> Tensor:
        """(M,) bilinear values of ``img`` (H, W) at the taps; differentiable in ``img``."""
        flat = img.reshape(-1)
        i00, fx, fy, w = self.i00, self.fx, self.fy, self.width
        v00, v01 = flat[i00], flat[i00 + 1]
        v10, v11 = flat[i00 + w], flat[i00 + w + 1]
        return (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy


def bilinear_taps(height: int, width: int, uv: Tensor) -> BilinearTaps:
    """The taps of pixel coordinates ``uv`` (M, 2) (centres at +0.5) in an image of
    ``height`` × ``width``, in ``uv``'s dtype."""
    H, W = height, width
    x = uv[:, 0] - 0.5
    y = uv[:, 1] - 0.5
    finite = torch.isfinite(x) & torch.isfinite(y)
    x = torch.where(finite, x, torch.zeros_like(x))
    y = torch.where(finite, y, torch.zeros_like(y))
    inside = finite & (x >= 0) & (y >= 0) & (x <= W - 1) & (y <= H - 1)
    x0i = torch.floor(x).clamp(0, max(W - 2, 0)).long()
    y0i = torch.floor(y).clamp(0, max(H - 2, 0)).long()
    fx = (x - x0i.to(x.dtype)).clamp(0, 1)
    fy = (y - y0i.to(y.dtype)).clamp(0, 1)
    return BilinearTaps(W, y0i * W + x0i, fx, fy, inside)


def bilinear_lookup(img: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
    """Sample (H, W) ``img`` at pixel coordinates ``uv`` (M, 2) (centres at +0.5).

    Returns (values (M,), inside (M,)); ``inside`` means within the pixel-centre hull.
    """
    taps = bilinear_taps(img.shape[0], img.shape[1], uv)
    return taps.sample(img), taps.inside


def project_in_front(camera: Camera, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``camera.project`` with no division by ~0 in the graph: (uv, z, in_front).

    Points not clearly in front of the camera (z ≤ 1e-4·|p_cam|, i.e. within 0.006°
    of its focal plane, or non-finite) are swapped for a point one unit ahead before
    projecting and flagged ``in_front = False``. Otherwise x/z with z = 0 gives an
    infinite uv whose masked-out gradient is 0·∞ = NaN, which the trainer's guard
    would turn into a skipped step.
    """
    with torch.no_grad():
        pc = camera.world_to_camera_points(points)
        z = pc[..., 2]
        front = torch.isfinite(pc).all(-1) & (z > 1e-4 * pc.norm(dim=-1))
    ahead = (camera.center + camera.forward).to(points)
    uv, z = camera.project(torch.where(front[..., None], points, ahead))
    return uv, z, front
