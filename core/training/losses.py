"""Training losses of PGSR-DR (Eq. 7, 10–15), each a pure function with a test."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from core.evaluation.ssim import ssim
from core.scene.cameras import Camera


def rgb_loss(img: Tensor, ref: Tensor, l1_weight: float = 0.8) -> Tensor:
    """Eq. 15: l1_weight·L1 + (1 − l1_weight)·(1 − SSIM)."""
    l1 = (img - ref).abs().mean()
    if l1_weight >= 1.0:
        return l1
    return l1_weight * l1 + (1.0 - l1_weight) * (1.0 - ssim(img, ref))


def scale_loss(scales: Tensor) -> Tensor:
    """Eq. 7: mean of each Gaussian's smallest scale (drives them flat)."""
    if scales.numel() == 0:
        return scales.sum()
    return scales.min(dim=-1).values.mean()


def depth_to_points(depth: Tensor, camera: Camera) -> Tensor:
    """Camera-space points (H, W, 3) = z-depth · K⁻¹(u, v, 1)."""
    return depth[..., None] * camera.camera_rays(depth.dtype, depth.device)


def normals_from_depth(depth: Tensor, valid: Tensor, camera: Camera) -> tuple[Tensor, Tensor]:
    """Eq. 10: unit camera-space normals from central differences of back-projected points.

    Returns (normals (H, W, 3) facing the camera, valid (H, W)); a pixel is valid when
    it and its four neighbours have depth and the cross product is not degenerate.
    Border pixels are invalid.
    """
    P = depth_to_points(depth, camera)
    H, W = depth.shape
    n = torch.zeros_like(P)
    ok = torch.zeros_like(valid)
    if H < 3 or W < 3:
        return n, ok
    du = P[1:-1, 2:] - P[1:-1, :-2]
    dv = P[2:, 1:-1] - P[:-2, 1:-1]
    cross = torch.linalg.cross(dv, du)
    norm = cross.norm(dim=-1, keepdim=True)
    v = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    v = v & (norm[..., 0] > 1e-12)
    nn = cross / torch.where(norm > 1e-12, norm, torch.ones_like(norm))
    # Face the camera: a normal seen from the camera satisfies n·P < 0.
    facing = (nn * P[1:-1, 1:-1]).sum(-1, keepdim=True) <= 0
    nn = torch.where(facing, nn, -nn)
    n = F.pad(nn.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)
    ok = F.pad(v, (1, 1, 1, 1))
    return n, ok


def edge_weight(image: Tensor) -> Tensor:
    """PGSR's (1 − ∇I)² per pixel of an (H, W, C) image, in [0, 1], (H, W).

    ∇I is the larger of the channel-mean central differences in x and y, rescaled to
    [0, 1] over the image; border pixels get 0. Why: at image edges (silhouettes,
    creases, texture boundaries) depth and colour change abruptly and the local-plane
    assumption of Eq. 10 fails, so the depth-normal loss should not pull there.
    """
    H, W = image.shape[:2]
    w = torch.zeros(H, W, dtype=image.dtype, device=image.device)
    if H < 3 or W < 3:
        return w
    img = image.detach()
    gx = (img[1:-1, 2:] - img[1:-1, :-2]).abs().mean(-1)
    gy = (img[2:, 1:-1] - img[:-2, 1:-1]).abs().mean(-1)
    g = torch.maximum(gx, gy)
    span = g.max() - g.min()
    g = (g - g.min()) / span if float(span) > 0 else torch.zeros_like(g)
    w[1:-1, 1:-1] = (1.0 - g) ** 2
    return w


def single_view_loss(
    rendered_normal: Tensor,
    depth: Tensor,
    valid: Tensor,
    camera: Camera,
    weight: Tensor | None = None,
) -> Tensor:
    """Eq. 11: mean over valid pixels of 1 − n·N (rendered vs depth-derived normal),
    each pixel weighted by ``weight`` (H, W) when given (e.g. :func:`edge_weight`)."""
    N, ok = normals_from_depth(depth, valid, camera)
    if not bool(ok.any()):
        return rendered_normal.sum() * 0.0
    n = rendered_normal[ok]
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    per_pixel = 1.0 - (n * N[ok]).sum(-1)
    if weight is None:
        return per_pixel.mean()
    return (weight[ok] * per_pixel).mean()


def bilinear_lookup(img: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
    """Sample (H, W) ``img`` at pixel coordinates ``uv`` (M, 2) (centres at +0.5).

    Returns (values (M,), inside (M,)); ``inside`` means within the pixel-centre hull.
    """
    H, W = img.shape
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
    flat = img.reshape(-1)
    i00 = y0i * W + x0i
    v00, v01 = flat[i00], flat[i00 + 1]
    v10, v11 = flat[i00 + W], flat[i00 + W + 1]
    val = (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy
    return val, inside


def _project_in_front(camera: Camera, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
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


def multi_view_loss(
    depth_ref: Tensor,
    valid_ref: Tensor,
    cam_ref: Camera,
    depth_nb: Tensor,
    valid_nb: Tensor,
    cam_nb: Camera,
    *,
    max_error_px: float = 1.0,
    n_pixels: int | None = None,
    generator: torch.Generator | None = None,
    error_weighting: bool = False,
) -> tuple[Tensor, dict[str, float]]:
    """Eq. 12–14: forward–backward reprojection error between two depth maps.

    A reference pixel p_r is lifted with its depth (Eq. 12), projected into the
    neighbour (Eq. 13), lifted again with the neighbour's bilinearly sampled depth,
    and projected back to p̃_r. The loss is the mean of ‖p_r − p̃_r‖ over pixels
    whose error is at most ``max_error_px`` (larger errors are occlusions or
    mismatches, excluded as in the paper). With ``error_weighting`` each kept pixel
    is weighted by exp(−error) (detached), as PGSR does, so pixels that are probably
    mismatched pull less. Returns (loss, stats).
    """
    dtype, device = depth_ref.dtype, depth_ref.device
    flat_valid = valid_ref.reshape(-1)
    idx = flat_valid.nonzero()[:, 0]
    if n_pixels is not None and idx.numel() > n_pixels:
        # One random key per pixel of the image, valid or not, so the generator
        # advances by the same amount whatever the valid count: a single pixel's
        # validity flipping by rounding must not reshuffle every later random draw.
        keys = torch.rand(flat_valid.numel(), generator=generator, device="cpu")
        pick = torch.argsort(keys[idx.cpu()], stable=True)[:n_pixels]
        idx = idx[pick.to(device)]
    zero = depth_ref.sum() * 0.0
    if idx.numel() == 0:
        return zero, {"pixels": 0.0, "kept": 0.0}
    W = depth_ref.shape[1]
    uv_r = torch.stack([(idx % W).to(dtype) + 0.5, (idx // W).to(dtype) + 0.5], dim=-1)
    d_r = depth_ref.reshape(-1)[idx]
    P = cam_ref.backproject(uv_r, d_r)
    uv_n, z_n, front_n = _project_in_front(cam_nb, P)
    d_n, inside = bilinear_lookup(depth_nb, uv_n)
    v_n, _ = bilinear_lookup(valid_nb.to(dtype), uv_n)
    ok = front_n & inside & (z_n > 0) & (v_n > 0.999) & (d_n > 0)
    d_n = torch.where(ok, d_n, torch.ones_like(d_n))
    uv_n_safe = torch.where(ok[:, None], uv_n, torch.zeros_like(uv_n))
    P2 = cam_nb.backproject(uv_n_safe, d_n)
    uv_back, z_back, front_back = _project_in_front(cam_ref, P2)
    ok = ok & front_back & (z_back > 0)
    # sqrt(·+1e-12): the norm's gradient is undefined at exactly zero error.
    err = ((uv_back - uv_r) ** 2).sum(-1).add(1e-12).sqrt()
    keep = ok & torch.isfinite(err) & (err <= max_error_px)
    stats = {"pixels": float(idx.numel()), "kept": float(keep.sum())}
    if not bool(keep.any()):
        return zero, stats
    e = err[keep]
    if error_weighting:
        return (torch.exp(-e.detach()) * e).mean(), stats
    return e.mean(), stats
