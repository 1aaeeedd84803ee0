"""EWA projection of 3D Gaussians to screen-space ellipses (3DGS, Zwicker et al.).

Shared by every backend so they differ only in how they composite. Written in
plain differentiable torch; works in float32 and float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from core.render.rotations import normalize_quats, quat_to_rotmat
from core.scene.cameras import Camera

# 3DGS's opacity threshold: contributions below 1/255 are skipped.
ALPHA_MIN = 1.0 / 255.0
# Per-Gaussian alpha is clamped to this so 1 - alpha never reaches 0.
ALPHA_MAX = 0.99
# Compositing stops before transmittance would drop below this.
T_MIN = 1e-4


@dataclass
class Projected:
    """Screen-space footprint of each Gaussian for one camera.

    ``means2d`` (N, 2) in pixels (pixel centres at +0.5), ``conics`` (N, 3) the
    inverse 2D covariance as (a, b, c) for [[a, b], [b, c]], ``depths`` (N,) camera
    z, ``radii`` (N,) int pixel radius (0 = culled), ``cov2d`` (N, 2, 2) the filtered
    2D covariance (None from the compiled projection: nothing downstream reads it),
    ``compensation`` (N,) the antialiasing opacity factor (see ``project_gaussians``).
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    cov2d: Tensor | None = None
    compensation: Tensor | None = None

    @property
    def visible(self) -> Tensor:
        return self.radii > 0


def covariances_from(quats: Tensor, scales: Tensor) -> Tensor:
    """Σ = R S² Rᵀ, (N, 3, 3)."""
    R = quat_to_rotmat(normalize_quats(quats))
    return (R * scales[:, None, :] ** 2) @ R.transpose(1, 2)


def project_gaussians(
    means: Tensor,
    covs: Tensor,
    camera: Camera,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> Projected:
    """Project world-space Gaussians into ``camera`` (Eq. 3 with the 3DGS low-pass).

    The Jacobian is evaluated at the centre clamped to 1.3× the field of view (as in
    3DGS) so Gaussians far off-screen do not get huge footprints. Gaussians with
    z ≤ near or z ≥ far, a non-positive 2D determinant, or a footprint entirely
    off-screen get radius 0 and contribute nothing.
    """
    dtype, device = means.dtype, means.device
    R = camera.R.to(device=device, dtype=dtype)
    t = camera.t.to(device=device, dtype=dtype)
    intr = camera.intrinsics
    fx, fy, cx, cy = intr.fx, intr.fy, intr.cx, intr.cy
    W, H = intr.width, intr.height

    pc = means @ R.T + t
    x, y, z = pc.unbind(-1)
    in_depth = (z > near) & (z < far)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))

    # 1.3 × tan(fov/2) past each image edge, as 3DGS and gsplat (tan(fov/2) = W / 2fx).
    lim_x_pos = (W - cx) / fx + 0.3 * (0.5 * W / fx)
    lim_x_neg = cx / fx + 0.3 * (0.5 * W / fx)
    lim_y_pos = (H - cy) / fy + 0.3 * (0.5 * H / fy)
    lim_y_neg = cy / fy + 0.3 * (0.5 * H / fy)
    tx = z_safe * torch.clamp(x / z_safe, -lim_x_neg, lim_x_pos)
    ty = z_safe * torch.clamp(y / z_safe, -lim_y_neg, lim_y_pos)

    zero = torch.zeros_like(z)
    J = torch.stack(
        [fx / z_safe, zero, -fx * tx / z_safe**2, zero, fy / z_safe, -fy * ty / z_safe**2], dim=-1
    ).reshape(-1, 2, 3)
    cov_cam = R @ covs @ R.T
    cov2d = J @ cov_cam @ J.transpose(1, 2)
    # Σ is singular by design (Eq. 7 flattens every Gaussian), so a planar Gaussian
    # seen edge-on projects to a rank-1 cov2d, and rounding leaves it indefinite by
    # ~eps·λmax: past ~1e3 px in float32 that outweighs the low-pass, and a·c − b²
    # cancels to garbage (footprints vanished or came out non-positive-definite).
    # Clamp cov2d to the PSD cone (|b| ≤ √(ac)·(1 − 4ε): a rounding-size change that
    # keeps the *stored* entries PSD despite the rounding of √) and form the
    # determinant of the filtered matrix as det₀ + eps·(a + c) + eps² with det₀ ≥ 0,
    # so it is > 0 for every finite footprint.
    a0 = cov2d[:, 0, 0].clamp_min(0.0)
    c0 = cov2d[:, 1, 1].clamp_min(0.0)
    lim = (torch.sqrt(a0 * c0) * (1.0 - 4.0 * torch.finfo(dtype).eps)).detach()
    b = torch.minimum(torch.maximum(cov2d[:, 0, 1], -lim), lim)
    a, c = a0 + eps2d, c0 + eps2d
    cov2d = torch.stack([a, b, b, c], dim=-1).reshape(-1, 2, 2)
    det = (a0 * c0 - b * b).clamp_min(0.0) + eps2d * (a0 + c0) + eps2d * eps2d
    ok = in_depth & (det > 0) & torch.isfinite(det)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)

    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt((mid * mid - det_safe).clamp_min(0.1))
    radii = torch.ceil(3.0 * torch.sqrt(lam.detach())).to(torch.int64)

    u = fx * x / z_safe + cx
    v = fy * y / z_safe + cy
    means2d = torch.stack([u, v], dim=-1)

    ud, vd = u.detach(), v.detach()
    on_screen = (ud + radii > 0) & (ud - radii < W) & (vd + radii > 0) & (vd - radii < H)
    ok = ok & on_screen & torch.isfinite(ud) & torch.isfinite(vd)
    radii = torch.where(ok, radii, torch.zeros_like(radii))
    # Mip-Splatting / gsplat "antialiased": the low-pass widens every footprint; scaling
    # opacity by √(det Σ₂ᴰ / det(Σ₂ᴰ + εI)) keeps each Gaussian's total coverage, so an
    # edge-on planar Gaussian (det → 0) fades out instead of smearing a 1-px halo.
    det0 = (a0 * c0 - b * b).clamp_min(0.0)
    compensation = torch.sqrt((det0 / det_safe).clamp_min(1e-12))
    return Projected(
        means2d=means2d, conics=conics, depths=z, radii=radii, cov2d=cov2d,
        compensation=compensation,
    )  # fmt: skip
