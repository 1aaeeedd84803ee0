"""Eq. 6 normals in one compiled pass per Gaussian, forward and backward (CPU models).

``Gaussians.normals`` normalises every quaternion, builds all nine rotation entries and
gathers the column of the smallest scale: about twenty (N, 4)–(N, 3, 3) torch ops and
their autograd, 3.1 ms of a 60 ms multi-view step at 20k Gaussians
(docs/bench/step_breakdown.md). Only one column is needed, and its derivative in the
quaternion is a few products: here one loop does the forward and one the backward
(through the normalisation: g_q = (g_q̂ − q̂ (q̂·g_q̂)) / |q|). Same guards as
``core.render.rotations.normalize_quats`` (a near-zero quaternion is the identity with
zero gradient) and the same axis (``argmin`` of the log-scales, first on ties);
float64 inside (``tests/test_normals_compiled.py`` holds it to the torch path).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.kernels.pool import run_ranges
from core.render.rotations import QUAT_EPS

__all__ = ["normals_compiled"]


@njit(nogil=True, cache=True, inline="always")
def _axis(log_scales, i):  # pragma: no cover - numba
    """argmin of row i (first index on ties; a NaN wins, as torch.argmin)."""
    a, b, c = log_scales[i, 0], log_scales[i, 1], log_scales[i, 2]
    if a != a:
        return 0
    k, m = 0, a
    if b != b or b < m:
        if b != b:
            return 1
        k, m = 1, b
    if c != c or c < m:
        return 2
    return k


@njit(nogil=True, cache=True, inline="always")
def _unit(quats, i, eps2):  # pragma: no cover - numba
    """(w, x, y, z, 1/|q|, degenerate) of row i."""
    w, x, y, z = (np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]),
                  np.float64(quats[i, 3]))  # fmt: skip
    n2 = w * w + x * x + y * y + z * z
    if n2 < eps2:
        return 1.0, 0.0, 0.0, 0.0, 1.0, True
    inv = 1.0 / math.sqrt(n2)
    return w * inv, x * inv, y * inv, z * inv, inv, False


@njit(nogil=True, cache=True)
def _forward_range(lo, hi, quats, log_scales, eps2, out):  # pragma: no cover - numba
    for i in range(lo, hi):
        w, x, y, z, _, _ = _unit(quats, i, eps2)
        k = _axis(log_scales, i)
        if k == 0:
            out[i, 0] = 1.0 - 2.0 * (y * y + z * z)
            out[i, 1] = 2.0 * (x * y + w * z)
            out[i, 2] = 2.0 * (x * z - w * y)
        elif k == 1:
            out[i, 0] = 2.0 * (x * y - w * z)
            out[i, 1] = 1.0 - 2.0 * (x * x + z * z)
            out[i, 2] = 2.0 * (y * z + w * x)
        else:
            out[i, 0] = 2.0 * (x * z + w * y)
            out[i, 1] = 2.0 * (y * z - w * x)
            out[i, 2] = 1.0 - 2.0 * (x * x + y * y)


@njit(nogil=True, cache=True)
def _backward_range(lo, hi, quats, log_scales, eps2, grad, g_quats):  # pragma: no cover - numba
    for i in range(lo, hi):
        w, x, y, z, inv, degenerate = _unit(quats, i, eps2)
        if degenerate:
            g_quats[i, 0] = 0.0
            g_quats[i, 1] = 0.0
            g_quats[i, 2] = 0.0
            g_quats[i, 3] = 0.0
            continue
        a, b, c = np.float64(grad[i, 0]), np.float64(grad[i, 1]), np.float64(grad[i, 2])
        k = _axis(log_scales, i)
        if k == 0:  # (1 − 2(y² + z²), 2(xy + wz), 2(xz − wy))
            gw = 2.0 * (z * b - y * c)
            gx = 2.0 * (y * b + z * c)
            gy = -4.0 * y * a + 2.0 * (x * b - w * c)
            gz = -4.0 * z * a + 2.0 * (w * b + x * c)
        elif k == 1:  # (2(xy − wz), 1 − 2(x² + z²), 2(yz + wx))
            gw = 2.0 * (-z * a + x * c)
            gx = 2.0 * y * a - 4.0 * x * b + 2.0 * w * c
            gy = 2.0 * (x * a + z * c)
            gz = -2.0 * w * a - 4.0 * z * b + 2.0 * y * c
        else:  # (2(xz + wy), 2(yz − wx), 1 − 2(x² + y²))
            gw = 2.0 * (y * a - x * b)
            gx = 2.0 * z * a - 2.0 * w * b - 4.0 * x * c
            gy = 2.0 * w * a + 2.0 * z * b - 4.0 * y * c
            gz = 2.0 * (x * a + y * b)
        dot = w * gw + x * gx + y * gy + z * gz
        g_quats[i, 0] = (gw - w * dot) * inv
        g_quats[i, 1] = (gx - x * dot) * inv
        g_quats[i, 2] = (gy - y * dot) * inv
        g_quats[i, 3] = (gz - z * dot) * inv


class _Normals(torch.autograd.Function):
    @staticmethod
    def forward(ctx, quats, log_scales):  # type: ignore[override]
        q = quats.detach().contiguous().numpy()
        s = log_scales.detach().contiguous().numpy()
        out = np.empty((q.shape[0], 3), q.dtype)
        eps2 = QUAT_EPS * QUAT_EPS
        run_ranges(_forward_range, q.shape[0], (q, s, eps2, out))
        ctx.save_for_backward(quats, log_scales)
        return torch.from_numpy(out)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        quats, log_scales = ctx.saved_tensors
        q = quats.detach().contiguous().numpy()
        s = log_scales.detach().contiguous().numpy()
        g = grad.detach().contiguous().numpy()
        g_q = np.empty(q.shape, q.dtype)
        run_ranges(_backward_range, q.shape[0], (q, s, QUAT_EPS * QUAT_EPS, g, g_q))
        return torch.from_numpy(g_q), None


def normals_compiled(quats: Tensor, log_scales: Tensor) -> Tensor:
    """(N, 3) unit axis of the smallest scale of raw quaternions ``quats`` (N, 4) and
    ``log_scales`` (N, 3), CPU; differentiable in ``quats`` only."""
    return _Normals.apply(quats, log_scales)
