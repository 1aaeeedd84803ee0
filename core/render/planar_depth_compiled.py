"""Eq. 8 planar depth per pixel in one compiled pass, with its backward (CPU).

``gbuffer.planar_depth`` is a dozen image-sized torch ops (ray dot products, norms,
the guards, the division, masks) and their autograd, read twice a training step (the
view and its neighbour). Here one loop gives depth and valid, and the backward is two
lines per pixel: ∂d/∂D = 1/(N·r̃), ∂d/∂N = −d r̃/(N·r̃), nothing where invalid. Same
guards as the torch path (alpha, |cos| of the normal against the ray, positive and
finite depth); float64 inside (``tests/test_planar_depth_compiled.py``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.kernels.pool import run_ranges

__all__ = ["planar_depth_compiled"]


@njit(nogil=True, cache=True)
def _forward_rows(
    lo, hi, normal, plane, alpha, rays, min_alpha, min_cos, depth, valid, inv_den
):  # pragma: no cover
    w = plane.shape[1]
    for j in range(lo, hi):
        for i in range(w):
            nx, ny, nz = (np.float64(normal[j, i, 0]), np.float64(normal[j, i, 1]),
                          np.float64(normal[j, i, 2]))  # fmt: skip
            rx, ry, rz = rays[j, i, 0], rays[j, i, 1], rays[j, i, 2]
            ndotr = nx * rx + ny * ry + nz * rz
            norm = math.sqrt(nx * nx + ny * ny + nz * nz) * math.sqrt(rx * rx + ry * ry + rz * rz)
            cos = abs(ndotr) / max(norm, 1e-30)
            ok = np.float64(alpha[j, i]) > min_alpha and cos > min_cos and norm > 0.0
            d = np.float64(plane[j, i]) / ndotr if ok else 0.0
            ok = ok and d > 0.0 and math.isfinite(d)
            depth[j, i] = d if ok else 0.0
            valid[j, i] = ok
            inv_den[j, i] = 1.0 / ndotr if ok else 0.0


@njit(nogil=True, cache=True)
def _backward_rows(
    lo, hi, depth, inv_den, rays, grad, g_normal, g_plane
):  # pragma: no cover - numba
    w = depth.shape[1]
    for j in range(lo, hi):
        for i in range(w):
            k = inv_den[j, i]
            g = np.float64(grad[j, i])
            if k == 0.0 or g == 0.0:
                g_normal[j, i, 0] = g_normal[j, i, 1] = g_normal[j, i, 2] = 0.0
                g_plane[j, i] = 0.0
                continue
            g_plane[j, i] = g * k
            c = -g * np.float64(depth[j, i]) * k
            g_normal[j, i, 0] = c * rays[j, i, 0]
            g_normal[j, i, 1] = c * rays[j, i, 1]
            g_normal[j, i, 2] = c * rays[j, i, 2]


class _PlanarDepth(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal, plane, alpha, rays, min_alpha, min_cos):  # type: ignore[override]
        h, w = plane.shape
        # thresholds in the buffers' dtype, as torch compares a tensor with a scalar
        dt = np.float32 if plane.dtype == torch.float32 else np.float64
        depth = np.empty((h, w), dt)
        valid = np.empty((h, w), np.bool_)
        inv_den = np.empty((h, w))
        r = rays.detach().to(torch.float64).contiguous().numpy()
        args = (
            normal.detach().numpy(), plane.detach().numpy(), alpha.detach().numpy(), r,
            dt(min_alpha), dt(min_cos), depth, valid, inv_den,
        )  # fmt: skip
        run_ranges(_forward_rows, h, args)
        ctx.meta = (depth, inv_den, r, normal.dtype, plane.dtype)
        valid_t = torch.from_numpy(valid)
        ctx.mark_non_differentiable(valid_t)
        return torch.from_numpy(depth), valid_t

    @staticmethod
    @once_differentiable
    def backward(ctx, grad, _g_valid):  # type: ignore[override]
        depth, inv_den, r, n_dtype, p_dtype = ctx.meta
        h, w = depth.shape
        g_normal = np.empty((h, w, 3), np.float32 if n_dtype == torch.float32 else np.float64)
        g_plane = np.empty((h, w), np.float32 if p_dtype == torch.float32 else np.float64)
        g = grad.detach().contiguous().numpy()
        run_ranges(_backward_rows, h, (depth, inv_den, r, g, g_normal, g_plane))
        return torch.from_numpy(g_normal), torch.from_numpy(g_plane), None, None, None, None


def planar_depth_compiled(
    normal: Tensor, plane_dist: Tensor, alpha: Tensor, rays: Tensor, min_alpha: float,
    min_cos: float,
) -> tuple[Tensor, Tensor]:  # fmt: skip
    """(depth, valid) of Eq. 8 from CPU buffers (any strides) and the view's camera
    rays (H, W, 3); differentiable in ``normal`` and ``plane_dist``."""
    return _PlanarDepth.apply(normal, plane_dist, alpha, rays, min_alpha, min_cos)
