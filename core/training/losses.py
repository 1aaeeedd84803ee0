"""Training losses of PGSR-DR (Eq. 7, 10–15), each a pure function with a test."""

from __future__ import annotations

import torch
from torch import Tensor

from core.evaluation.ssim import ssim
from core.kernels.dispatch import cpu_float
from core.render.depth_geometry import (
    bilinear_lookup,
    normals_from_depth,
    project_in_front,
)
from core.scene.cameras import Camera


def rgb_loss(img: Tensor, ref: Tensor, l1_weight: float = 0.8) -> Tensor:
    """Eq. 15: l1_weight·L1 + (1 − l1_weight)·(1 − SSIM)."""
    l1 = (img - ref).abs().mean()
    if l1_weight >= 1.0:
        return l1
    return l1_weight * l1 + (1.0 - l1_weight) * (1.0 - ssim(img, ref))


def mask_loss(alpha: Tensor, mask: Tensor) -> Tensor:
    """Mean over the image of the coverage the mask does not have, max(α − mask, 0)
    (antialiased masks are coverages too): a halo outside the silhouette or a veil
    over a gap costs its area, coverage short of the mask costs nothing here.

    Why a term of its own: the RGB loss sees coverage only through the contrast between
    the object and the background it is composited over, so on a white background a
    bright object's halo costs almost nothing there and shows on any other background.
    One-sided because the two-sided |α − mask| also pushed coverage into every pixel
    the mask covers, which on a capture of fine parts (lego_real's studs and gaps) cost
    0.5 dB of held-out PSNR (docs/benchmarks.md)."""
    if alpha.shape != mask.shape:
        raise ValueError(f"alpha {tuple(alpha.shape)} and mask {tuple(mask.shape)} differ")
    return torch.relu(alpha - mask.to(alpha)).mean()  # no gradient where they agree


def scale_loss(scales: Tensor) -> Tensor:
    """Eq. 7: mean of each Gaussian's smallest scale (drives them flat)."""
    if scales.numel() == 0:
        return scales.sum()
    return scales.min(dim=-1).values.mean()


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


# A pixel whose step to one neighbour is more than this many times its step to the
# other sits at a depth jump: its depth normal uses the shorter side only. Measured on
# spot_plastic at 3000 its (bench/single_view_target.py): with central differences
# 1.6% of pixels had a depth normal ≥ 45° off the truth and drew 42% of L_single's
# pull, three quarters of them at true depth jumps the image-gradient weight misses;
# ratios 1.5, 2 and 3 each cut that pull to 9–11%.
SAME_SURFACE_JUMP_RATIO = 2.0


def single_view_loss(
    rendered_normal: Tensor,
    depth: Tensor,
    valid: Tensor,
    camera: Camera,
    weight: Tensor | None = None,
    *,
    same_surface: bool = False,
    compiled: bool | None = None,
) -> Tensor:
    """Eq. 11: mean over valid pixels of 1 − n·N (rendered vs depth-derived normal),
    each pixel weighted by ``weight`` (H, W) when given (e.g. :func:`edge_weight`).

    ``same_surface``: N from one-sided differences across depth jumps
    (:func:`normals_from_depth` with :data:`SAME_SURFACE_JUMP_RATIO`). ``compiled``:
    the fused passes of ``core.training.depth_normal_compiled`` (None: for CPU
    tensors), False: the torch ops below, the reference."""
    ratio = SAME_SURFACE_JUMP_RATIO if same_surface else None
    if compiled is None:
        compiled = cpu_float(depth)
    if compiled:
        from core.training.depth_normal_compiled import single_view_loss_compiled

        rays = camera.camera_rays(depth.dtype, depth.device)
        return single_view_loss_compiled(rendered_normal, depth, valid, rays, weight, ratio)
    N, ok = normals_from_depth(depth, valid, camera, ratio)
    if not bool(ok.any()):
        return rendered_normal.sum() * 0.0
    n = rendered_normal[ok]
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    per_pixel = 1.0 - (n * N[ok]).sum(-1)
    if weight is None:
        return per_pixel.mean()
    return (weight[ok] * per_pixel).mean()


def multi_view_pixels(
    valid_ref: Tensor, n_pixels: int | None, generator: torch.Generator | None = None
) -> Tensor:
    """The reference pixels (flat indices, in pixel order) :func:`multi_view_loss`
    reads: every valid one, or ``n_pixels`` of them drawn at random."""
    flat_valid = valid_ref.reshape(-1)
    idx = flat_valid.nonzero()[:, 0]
    if n_pixels is not None and idx.numel() > n_pixels:
        # One random key per pixel of the image, valid or not, so the generator
        # advances by the same amount whatever the valid count: a single pixel's
        # validity flipping by rounding must not reshuffle every later random draw.
        keys = torch.rand(flat_valid.numel(), generator=generator, device="cpu")
        # the n_pixels smallest keys, in pixel order (topk: 14× a full argsort at 128²)
        pick = torch.topk(keys[idx.cpu()], n_pixels, largest=False, sorted=False).indices
        idx = idx[pick.sort().values.to(idx.device)]
    return idx


def multi_view_footprint(
    depth_ref: Tensor, idx: Tensor, cam_ref: Camera, cam_nb: Camera
) -> Tensor | None:
    """(H, W) bool: the neighbour pixels :func:`multi_view_loss` will read for the
    reference pixels ``idx`` (:func:`multi_view_pixels`), so the neighbour need only be
    rendered there (``render_gbuffer(pixels=...)``): at 128² with 4096 pixels drawn
    about half a view, at 800² 3%. None where the loss runs as torch ops
    (not CPU float tensors), whose arithmetic the footprint does not repeat."""
    if not cpu_float(depth_ref):
        return None
    from core.training.multi_view_compiled import neighbour_footprint

    return neighbour_footprint(depth_ref, idx, cam_ref, cam_nb)


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
    compiled: bool | None = None,
    pixels: Tensor | None = None,
) -> tuple[Tensor, dict[str, float]]:
    """Eq. 12–14: forward–backward reprojection error between two depth maps.

    A reference pixel p_r is lifted with its depth (Eq. 12), projected into the
    neighbour (Eq. 13), lifted again with the neighbour's bilinearly sampled depth,
    and projected back to p̃_r. The loss is the mean of ‖p_r − p̃_r‖ over pixels
    whose error is at most ``max_error_px`` (larger errors are occlusions or
    mismatches, excluded as in the paper). With ``error_weighting`` each kept pixel
    is weighted by exp(−error) (detached), as PGSR does, so pixels that are probably
    mismatched pull less. Returns (loss, stats). ``compiled``: the round trip and its
    backward as one numba pass (core.training.multi_view_compiled; None: for CPU
    tensors), False: the torch ops below, the reference. ``pixels``: the reference
    pixels drawn beforehand (:func:`multi_view_pixels`; then ``n_pixels`` and
    ``generator`` are not used), as a step that renders the neighbour at their
    :func:`multi_view_footprint` only does.
    """
    dtype = depth_ref.dtype
    idx = multi_view_pixels(valid_ref, n_pixels, generator) if pixels is None else pixels
    zero = depth_ref.sum() * 0.0
    if idx.numel() == 0:
        return zero, {"pixels": 0.0, "kept": 0.0}
    if compiled is None:
        compiled = cpu_float(depth_ref)
    if compiled:
        from core.training.multi_view_compiled import multi_view_loss_compiled

        loss, kept = multi_view_loss_compiled(
            depth_ref, depth_nb, idx, valid_nb, cam_ref, cam_nb, max_error_px, error_weighting
        )
        stats = {"pixels": float(idx.numel()), "kept": float(kept)}
        return (loss if kept else zero), stats
    W = depth_ref.shape[1]
    uv_r = torch.stack([(idx % W).to(dtype) + 0.5, (idx // W).to(dtype) + 0.5], dim=-1)
    d_r = depth_ref.reshape(-1)[idx]
    P = cam_ref.backproject(uv_r, d_r)
    uv_n, z_n, front_n = project_in_front(cam_nb, P)
    d_n, inside = bilinear_lookup(depth_nb, uv_n)
    v_n, _ = bilinear_lookup(valid_nb.to(dtype), uv_n)
    ok = front_n & inside & (z_n > 0) & (v_n > 0.999) & (d_n > 0)
    d_n = torch.where(ok, d_n, torch.ones_like(d_n))
    uv_n_safe = torch.where(ok[:, None], uv_n, torch.zeros_like(uv_n))
    P2 = cam_nb.backproject(uv_n_safe, d_n)
    uv_back, z_back, front_back = project_in_front(cam_ref, P2)
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
