"""Per-pixel plane order (``TrainConfig.splat_order = 'plane'``): each pixel composites
its splats in the order in which their planes meet its ray.

Why. Tile lists are sorted by centre depth, one order for every pixel of a tile. Along
a tilted surface the splats of one stretch of surface overlap at a pixel with centres
at different depths, so the one whose centre lies toward the camera comes first and
weighs most wherever it reaches, even where its own plane lies behind its neighbours'.
Colours and normals then lean toward the splats displaced toward the camera (measured:
the slab order, which removes the centre order inside a surface, made images and
normals better on most dev scenes; docs/benchmarks.md, issue 36). A planar splat's
place along a pixel's ray is where its plane meets the ray, so this order sorts each
pixel's contributors by that depth (StopThePop sorts 3D Gaussians per pixel by their
density maximum along the ray, which is the same point for a flat one).

What. Per splat: its plane in camera space (unit normal ``n``, the axis of its smallest
scale; ``d = n·μ``), its centre depth ``z`` and a reach ``h`` (three times its largest
scale). On the ray through pixel centre (u, v), ``r = ((u - cx)/fx, (v - cy)/fy, 1)``,
the plane lies at camera depth ``d / (n·r)``, clamped to ``[z - h, z + h]`` (an
edge-on splat's plane meets the ray arbitrarily far away; where the splat has any
alpha its plane is within its reach). Ties (equal keys) keep the tile's centre order.
The order is piecewise constant, so it carries no gradient: the weights are the usual
``alpha_i Π_{j before i} (1 - alpha_j)`` in that order, early termination included.

The torch reference (:func:`rasterize_reference_plane`) sorts per pixel with a stable
argsort; the numba kernels (``plane_order_kernels``; pixel-major: each pixel gathers
its contributors from the tile list, insertion-sorts them, stops gathering what lies
behind the point where its compositing saturates, and composites; the forward keeps
the composited runs with their transmittances for the backward within
``RUN_STORE_BYTES``; the backward sums a tile's gradients per entry before adding them
to the Gaussians') are tested against it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from core.kernels.pool import (
    BufferPool,
    kernel_threads,
    run_ranges,
    run_workers,
    scratch_zeros,
    store_dtype,
    zeros_touched,
)
from core.render.raster.binning import TileBins
from core.render.raster.cpu import (
    _G_A,
    _G_F,
    _G_MX,
    _G_O,
    _compute_dtype,
    _np,
    _reduce_split_range,
    _Setup,
    has_gradient,
)
from core.render.raster.plane_order_kernels import _backward_worker, _forward_worker
from core.render.raster.projection import ALPHA_MAX, ALPHA_MIN, T_MIN, Projected
from core.render.raster.reference import tile_pixels
from core.render.rotations import normalize_quats, quat_to_rotmat
from core.scene.cameras import Camera

__all__ = [
    "PlaneKeys", "plane_keys", "plane_reach", "rasterize_cpu_plane", "rasterize_reference_plane",
]  # fmt: skip

# A splat's plane is searched for within this many of its largest standard deviations
# of its centre along the ray (its alpha is below 1/255 beyond about 3.3 σ).
REACH_SIGMAS = 3.0


@dataclass
class PlaneKeys:
    """What the per-pixel order needs: ``planes`` (N, 6) float64 rows
    (n_x, n_y, n_z, d, z, h) in camera space, and the pinhole intrinsics."""

    planes: Tensor
    fx: float
    fy: float
    cx: float
    cy: float

    def rays(self, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """Camera-ray x and y slopes of pixel-centre coordinates (float64)."""
        return (u.to(torch.float64) - self.cx) / self.fx, (v.to(torch.float64) - self.cy) / self.fy

    def keys(self, ids: Tensor, rx: Tensor, ry: Tensor) -> Tensor:
        """(P, K) depth along each pixel's ray (rx, ry: (P,)) of the planes ``ids`` (K,)."""
        p = self.planes[ids]
        nx, ny, nz, d, z, h = (p[:, k][None, :] for k in range(6))
        ndot = nx * rx[:, None] + ny * ry[:, None] + nz
        t = d / ndot
        t = torch.where(torch.isfinite(t), t, z.expand_as(t))
        return torch.minimum(torch.maximum(t, z - h), z + h)


def plane_reach(scales: Tensor) -> Tensor:
    """(N,) how far along the ray from its centre a splat's plane is searched for:
    REACH_SIGMAS of its largest scale (no gradient)."""
    return REACH_SIGMAS * scales.detach().to(torch.float64).amax(-1)


def plane_keys(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    camera: Camera,
    covariances: Tensor | None = None,
    normals: Tensor | None = None,
    reach: Tensor | None = None,
) -> PlaneKeys:
    """Each splat's camera-space plane, centre depth and reach (no gradient).

    ``normals`` (N, 3, world, any sign): the planes' normals where the caller has them
    (the G-buffer's Eq. 6 normals), so that a model rendered from its rotations and the
    same model rendered from frozen covariances sort their splats alike; otherwise the
    axis of the smallest scale, or of the covariance's smallest eigenvalue. ``reach``
    (N,): :func:`plane_reach` where the caller kept it (a frozen model: otherwise every
    frame would take the eigenvalues of every covariance, ~0.1 s at 134k splats)."""
    with torch.no_grad():
        if reach is not None and normals is not None:
            reach = reach.detach().to(torch.float64)
        elif quats is not None and scales is not None:
            s = scales.detach().to(torch.float64)
            reach = plane_reach(scales)
            if normals is None:
                R = quat_to_rotmat(normalize_quats(quats.detach().to(torch.float64)))
                k = s.argmin(-1)[:, None, None].expand(-1, 3, 1)
                normals = torch.gather(R, 2, k)[..., 0]
        elif covariances is not None:
            covs = covariances.detach().to(torch.float64)
            if normals is None:
                evals, evecs = torch.linalg.eigh(covs)
                normals = evecs[..., 0]
            else:
                evals = torch.linalg.eigvalsh(covs)
            reach = REACH_SIGMAS * evals[..., -1].clamp_min(0.0).sqrt()
        else:
            raise ValueError("plane order needs quats and scales, or covariances")
        n_world = normals.detach().to(torch.float64)
        Rc = camera.R.to(torch.float64)
        tc = camera.t.to(torch.float64)
        mu = means.detach().to(torch.float64) @ Rc.T + tc
        n = n_world @ Rc.T
        d = (n * mu).sum(-1)
        planes = torch.cat([n, d[:, None], mu[:, 2:3], reach[:, None]], dim=1).contiguous()
    i = camera.intrinsics
    return PlaneKeys(planes, float(i.fx), float(i.fy), float(i.cx), float(i.cy))


# ---------------------------------------------------------------------------------------
# torch reference
# ---------------------------------------------------------------------------------------


def rasterize_reference_plane(
    proj: Projected,
    opacities: Tensor,
    features: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    order: PlaneKeys,
) -> tuple[Tensor, Tensor]:
    """(H, W, C) features and (H, W) alpha, each pixel composited in plane order.

    Plain autograd over dense (pixels × tile list) tensors: the oracle for small
    scenes, not for training."""
    dtype, device = features.dtype, features.device
    C = features.shape[1]
    ts = bins.tile_size
    img = torch.zeros(height * width, C, dtype=dtype, device=device)
    alpha_img = torch.zeros(height * width, dtype=dtype, device=device)
    offsets = bins.offsets.tolist()
    opac = opacities.reshape(-1)
    for ty in range(bins.tiles_y):
        for tx in range(bins.tiles_x):
            t = ty * bins.tiles_x + tx
            lo, hi = offsets[t], offsets[t + 1]
            if hi == lo:
                continue
            pix, uu, vv = tile_pixels(tx, ty, ts, width, height, dtype, device)
            ids = bins.gauss_ids[lo:hi].long()
            d = pix[:, None, :] - proj.means2d[ids][None, :, :]
            dx, dy = d[..., 0], d[..., 1]
            a, b, c = (proj.conics[ids, k] for k in range(3))
            power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
            alpha = torch.clamp(opac[ids] * torch.exp(power.clamp_max(0.0)), max=ALPHA_MAX)
            keep = (power <= 0) & (alpha >= ALPHA_MIN)
            alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
            rx, ry = order.rays(pix[:, 0], pix[:, 1])
            perm = torch.sort(order.keys(ids, rx, ry), dim=1, stable=True).indices
            alpha = alpha.gather(1, perm)
            one_minus = 1.0 - alpha
            T_after = torch.cumprod(one_minus, dim=1)
            T_before = T_after / one_minus
            included = T_after >= T_MIN
            w = torch.where(included, alpha * T_before, torch.zeros_like(alpha))
            f = features[ids][perm]  # (P, K, C)
            out = (w[..., None] * f).sum(1)
            T = torch.where(included, one_minus, torch.ones_like(one_minus)).prod(dim=1)
            idx = vv * width + uu
            img = img.index_copy(0, idx, out)
            alpha_img = alpha_img.index_copy(0, idx, 1.0 - T)
    return img.reshape(height, width, C), alpha_img.reshape(height, width)


# Memory the forward may keep its composited runs in for the backward (which otherwise
# rebuilds them: about half its time); a tile whose runs do not fit is rebuilt. 12 bytes
# an entry in float32: 8M entries, 32 a pixel at 512².
RUN_STORE_BYTES = 96 * 2**20


def _run_room(n_tiles: int, npdt: type) -> int:
    """Entries a tile may keep: an equal share of the budget (the buffers are allocated
    untouched, so only what the runs fill costs memory)."""
    per_entry = 4 + 2 * np.dtype(npdt).itemsize
    return int(RUN_STORE_BYTES // max(1, n_tiles * per_entry))


# The kept runs' buffers, reused from step to step so their pages stay mapped (a fresh
# store paid about 2 ms of page faults per MiB it filled): a training step has two
# forwards (the view and its neighbour) waiting for their backwards, four arrays each.
_RUNS = BufferPool(keep=8)


def _take_runs(entries: int, pixels: int, npdt: type) -> tuple[np.ndarray, ...]:
    """Pooled flat buffers for a forward's kept runs: places, exp(power), transmittances
    and each pixel's start."""
    return (
        _RUNS.take(entries, np.int32),
        _RUNS.take(entries, npdt),
        _RUNS.take(entries, npdt),
        _RUNS.take(pixels, np.int64),
    )


def _kept_views(pooled: tuple[np.ndarray, ...], entries: int, height: int, width: int):
    """The kernels' views of the pooled buffers."""
    k, G, T, at = pooled
    return k[:entries], G[:entries], T[:entries], at[: height * width].reshape(height, width)


def _no_runs(npdt: type) -> tuple[np.ndarray, ...]:
    """Nothing kept (no gradient wanted): empty arrays of the kernels' types."""
    return (
        np.empty(0, np.int32),
        np.empty(0, npdt),
        np.empty(0, npdt),
        np.empty((0, 0), np.int64),
    )


def _need(pixels: Tensor | None, height: int, width: int) -> np.ndarray:
    """The kernels' per-pixel flags (H, W) bool of a caller's pixel mask, or an empty
    array for every pixel."""
    if pixels is None:
        return np.empty((0, 0), np.bool_)
    if tuple(pixels.shape) != (height, width):
        raise ValueError(f"pixels must be ({height}, {width}), got {tuple(pixels.shape)}")
    return np.ascontiguousarray(pixels.detach().cpu().numpy())


def _give_runs(ctx) -> None:
    """Return a forward's run buffers to the pool once its backward has read them; a
    second backward (retain_graph) then rebuilds every tile instead of reading them."""
    if ctx.pooled:
        ctx.state[-1][:] = 0  # tile_kept: nothing kept any more
        for buf in ctx.pooled:
            _RUNS.give(buf)
        ctx.pooled = ()


class PlaneOrderComposite(torch.autograd.Function):
    """Differentiable plane-order compositing on the CPU (numba, pixel-major)."""

    @staticmethod
    def forward(
        ctx,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        features: Tensor,
        bins: TileBins,
        width: int,
        height: int,
        order: PlaneKeys,
        keep_runs: bool = True,
        pixels: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        dtype = _compute_dtype(means2d, conics, opacities, features)
        n_ch = features.shape[1]
        npdt = np.float32 if dtype == torch.float32 else np.float64
        out_feat = zeros_touched((height, width, n_ch), npdt)
        out_T = np.ones((height, width), npdt)
        out_last = zeros_touched((height, width), np.int32)
        setup = None
        extra: tuple = ()
        ctx.pooled = ()
        if bins.gauss_ids.numel() > 0 and n_ch > 0:
            setup = _Setup(means2d, conics, opacities, features, bins, width, height, dtype)
            intr = np.array([order.fx, order.fy, order.cx, order.cy], np.float64)
            planes = order.planes.detach().to(torch.float64).contiguous().numpy()
            extra = (planes, intr)
            n_tiles = int(bins.offsets.numel()) - 1
            room = _run_room(n_tiles, npdt) if keep_runs else 0
            pooled = _take_runs(n_tiles * room, height * width, npdt) if room > 0 else ()
            runs = (
                *(_kept_views(pooled, n_tiles * room, height, width) if pooled else _no_runs(npdt)),
                np.zeros(n_tiles, np.int8),
            )
            need = _need(pixels, height, width)
            args = (*setup.args(), *extra, out_feat, out_T, out_last, *runs, need)
            run_workers(_forward_worker, kernel_threads(), args)
            ctx.pooled = pooled
        ctx.save_for_backward(means2d, conics, opacities, features)
        ctx.setup, ctx.extra = setup, extra
        ctx.meta = (dtype, width, height, n_ch)
        ctx.in_dtypes = (means2d.dtype, conics.dtype, opacities.dtype, features.dtype)
        ctx.shapes = (means2d.shape, conics.shape, opacities.shape, features.shape)
        ctx.state = (out_T, out_last, *runs) if setup is not None else None
        return torch.from_numpy(out_feat), 1.0 - torch.from_numpy(out_T)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_feat: Tensor | None, grad_alpha: Tensor | None):
        ctx.saved_tensors  # noqa: B018  (raises if an input was modified in place)
        dtype, width, height, n_ch = ctx.meta
        setup: _Setup | None = ctx.setup
        shapes, in_dtypes = ctx.shapes, ctx.in_dtypes
        n = shapes[0][0]
        n_workers = kernel_threads() if setup is not None and n > 0 else 1
        with scratch_zeros((n_workers, n, 6 + n_ch)) as gbuf:
            if setup is not None and n > 0:
                out_T, out_last, *runs = ctx.state
                gf = (
                    np.zeros((height, width, n_ch), out_T.dtype)
                    if grad_feat is None
                    else _np(grad_feat, dtype)
                )
                ga = (
                    np.zeros((height, width), out_T.dtype)
                    if grad_alpha is None
                    else _np(grad_alpha, dtype)
                )
                need = has_gradient(gf, ga, out_last)
                args = (*setup.args(), *ctx.extra, out_T, out_last, *runs, gf, ga, gbuf, need)
                run_workers(_backward_worker, n_workers, args)
                _give_runs(ctx)
            widths = (_G_A - _G_MX, _G_O - _G_A, _G_F - _G_O, n_ch)
            parts = [
                np.empty((n, w), store_dtype(d)) for w, d in zip(widths, in_dtypes, strict=True)
            ]
            run_ranges(_reduce_split_range, n, (gbuf, *parts))
            out = [
                torch.from_numpy(g).to(d).reshape(s) if need else None
                for g, s, d, need in zip(
                    parts, shapes, in_dtypes, ctx.needs_input_grad[:4], strict=True
                )
            ]
        return (*out, None, None, None, None, None, None)


def rasterize_cpu_plane(
    proj: Projected,
    opacities: Tensor,
    features: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    order: PlaneKeys,
    pixels: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """The compiled backend's compositing in per-pixel plane order (float32 or float64);
    ``pixels`` (H, W) bool: only these are composited, the others come back empty."""
    tensors = (proj.means2d, proj.conics, opacities.reshape(-1), features)
    keep = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    feats, alpha = PlaneOrderComposite.apply(*tensors, bins, width, height, order, keep, pixels)
    return feats.to(features.dtype), alpha.to(features.dtype)
