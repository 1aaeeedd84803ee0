"""Reflected directions and the env map's level of detail per pixel in one compiled
pass, with its backward, for training on the CPU.

Before the lookup, deferred shading turns the G-buffer into what it reads: the unit
view ray through each pixel, the world normal (Rᵀ n, normalised twice, as
``shading.world_normals`` and then ``shading.reflect`` do), the mirror direction
r − 2(r·n̂)n̂, and with roughness ρ = blended ρ / alpha clamped to [0, 1] and its LOD
(``envmap_mips.roughness_to_lod``). In torch that is about twenty image-sized ops and
their autograd, 3.5 ms of a 43 ms masked-capture step at 128² (``python -m
bench.step_breakdown``). Here one loop writes the directions and LOD, and a second the
gradients of the blended normal, roughness and alpha by hand:

* each safe normalisation y = x / max(|x|, 1e-12) passes g ↦ (g − (g·ŷ)ŷ) / |x|, or
  g / 1e-12 below the floor (where torch's clamp stops the norm's own gradient);
* the mirror passes ∂/∂n̂ = −2((r·n̂) g + (g·n̂) r) (the view ray is a constant);
* the LOD ½ log₂(1 + x²), x = ρ² s, passes 2 s ρ x / ((1 + x²) ln 2), nothing where it
  is clamped at the top level or ρ is clamped to [0, 1], and ρ = b / alpha passes
  1 / alpha to b and −b / alpha² to alpha where alpha > 1e-6.

Float64 inside, outputs in the buffers' dtype; ``tests/test_reflection_compiled.py``
holds values and gradients to the torch path.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.kernels.pool import run_ranges
from core.scene.cameras import Camera

__all__ = ["reflection_and_lod"]

EPS = 1e-12  # shading.safe_normalize's floor
COVERED = 1e-6  # shading.pixel_roughness's alpha threshold
INV_LN2 = 1.0 / math.log(2.0)


@njit(nogil=True, cache=True, inline="always")
def _view_dir(j, i, rot, intr):  # pragma: no cover - numba
    """Unit world direction of the ray through pixel (row j, column i): Rᵀ K⁻¹(u, v, 1)."""
    xc = (i + 0.5 - intr[2]) / intr[0]
    yc = (j + 0.5 - intr[3]) / intr[1]
    dx = rot[0, 0] * xc + rot[1, 0] * yc + rot[2, 0]
    dy = rot[0, 1] * xc + rot[1, 1] * yc + rot[2, 1]
    dz = rot[0, 2] * xc + rot[1, 2] * yc + rot[2, 2]
    inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
    return dx * inv, dy * inv, dz * inv


@njit(nogil=True, cache=True, inline="always")
def _normalised(x0, x1, x2):  # pragma: no cover - numba
    """safe_normalize and the factor it applied (1/|x|, or 1/EPS at the floor)."""
    k = 1.0 / math.sqrt(max(x0 * x0 + x1 * x1 + x2 * x2, EPS * EPS))
    return x0 * k, x1 * k, x2 * k, k


@njit(nogil=True, cache=True, inline="always")
def _normalise_back(g0, g1, g2, y0, y1, y2, k, floored):  # pragma: no cover - numba
    """Gradient through y = k x (safe_normalize) given the output y and factor k."""
    if floored:
        return g0 * k, g1 * k, g2 * k
    gy = g0 * y0 + g1 * y1 + g2 * y2
    return (g0 - gy * y0) * k, (g1 - gy * y1) * k, (g2 - gy * y2) * k


@njit(nogil=True, cache=True, inline="always")
def _world_normals(j, i, normal, rot):  # pragma: no cover - numba
    n0, n1, n2 = np.float64(normal[j, i, 0]), np.float64(normal[j, i, 1]), normal[j, i, 2]
    n2 = np.float64(n2)
    w0 = rot[0, 0] * n0 + rot[1, 0] * n1 + rot[2, 0] * n2
    w1 = rot[0, 1] * n0 + rot[1, 1] * n1 + rot[2, 1] * n2
    w2 = rot[0, 2] * n0 + rot[1, 2] * n1 + rot[2, 2] * n2
    return w0, w1, w2


@njit(nogil=True, cache=True, inline="always")
def _pixel(j, i, normal, rot, intr):  # pragma: no cover - numba
    """Pixel (j, i)'s unit view ray d, world normal w, its two safe normalisations a
    and b with their factors: what the forward reads, and the backward recomputes
    instead of storing."""
    d = _view_dir(j, i, rot, intr)
    w = _world_normals(j, i, normal, rot)
    a0, a1, a2, ka = _normalised(w[0], w[1], w[2])
    b0, b1, b2, kb = _normalised(a0, a1, a2)
    return d, w, (a0, a1, a2), ka, (b0, b1, b2), kb


@njit(nogil=True, cache=True)
def _forward_rows(
    lo, hi, normal, rough, alpha, rot, intr, lod_scale, top, refl, lod
):  # pragma: no cover - numba
    width = normal.shape[1]
    for j in range(lo, hi):
        for i in range(width):
            (dx, dy, dz), _, _, _, (b0, b1, b2), _ = _pixel(j, i, normal, rot, intr)
            k = 2.0 * (dx * b0 + dy * b1 + dz * b2)
            refl[j, i, 0] = dx - k * b0
            refl[j, i, 1] = dy - k * b1
            refl[j, i, 2] = dz - k * b2
            if rough.shape[0] > 0:
                a = np.float64(alpha[j, i])
                rho = np.float64(rough[j, i]) / a if a > COVERED else 0.0
                rho = min(max(rho, 0.0), 1.0) if rho == rho else rho  # NaN stays NaN
                x = rho * rho * lod_scale
                lod[j, i] = min(0.5 * math.log2(1.0 + x * x), top)


@njit(nogil=True, cache=True)
def _backward_rows(
    lo, hi, normal, rough, alpha, rot, intr, lod_scale, top, g_refl, g_lod,
    g_normal, g_rough, g_alpha,
):  # fmt: skip  # pragma: no cover - numba
    width = normal.shape[1]
    has_lod = rough.shape[0] != 0
    for j in range(lo, hi):
        for i in range(width):
            g0, g1 = np.float64(g_refl[j, i, 0]), np.float64(g_refl[j, i, 1])
            g2 = np.float64(g_refl[j, i, 2])
            if g0 == 0.0 and g1 == 0.0 and g2 == 0.0 and (not has_lod or g_lod[j, i] == 0.0):
                # nothing reaches this pixel (an uncovered one in training): zeros, exactly
                g_normal[j, i, 0] = 0.0
                g_normal[j, i, 1] = 0.0
                g_normal[j, i, 2] = 0.0
                if has_lod:
                    g_rough[j, i] = 0.0
                    g_alpha[j, i] = 0.0
                continue
            (dx, dy, dz), (w0, w1, w2), (a0, a1, a2), ka, (b0, b1, b2), kb = _pixel(
                j, i, normal, rot, intr
            )
            rn = dx * b0 + dy * b1 + dz * b2
            gn = g0 * b0 + g1 * b1 + g2 * b2
            # refl = r − 2(r·b)b
            h0 = -2.0 * (rn * g0 + gn * dx)
            h1 = -2.0 * (rn * g1 + gn * dy)
            h2 = -2.0 * (rn * g2 + gn * dz)
            floored_b = a0 * a0 + a1 * a1 + a2 * a2 < EPS * EPS
            h0, h1, h2 = _normalise_back(h0, h1, h2, b0, b1, b2, kb, floored_b)
            floored_a = w0 * w0 + w1 * w1 + w2 * w2 < EPS * EPS
            h0, h1, h2 = _normalise_back(h0, h1, h2, a0, a1, a2, ka, floored_a)
            # w = Rᵀ n: back to camera space through R
            g_normal[j, i, 0] = rot[0, 0] * h0 + rot[0, 1] * h1 + rot[0, 2] * h2
            g_normal[j, i, 1] = rot[1, 0] * h0 + rot[1, 1] * h1 + rot[1, 2] * h2
            g_normal[j, i, 2] = rot[2, 0] * h0 + rot[2, 1] * h1 + rot[2, 2] * h2
            if not has_lod:
                continue
            a = np.float64(alpha[j, i])
            b = np.float64(rough[j, i])
            g_rough[j, i] = 0.0
            g_alpha[j, i] = 0.0
            if not a > COVERED:
                continue
            rho = b / a
            if not (rho >= 0.0 and rho <= 1.0):  # clamped (or NaN): no gradient
                continue
            x = rho * rho * lod_scale
            if 0.5 * math.log2(1.0 + x * x) > top:  # clamped at the top level
                continue
            g_rho = np.float64(g_lod[j, i]) * 2.0 * lod_scale * rho * x / (1.0 + x * x) * INV_LN2
            g_rough[j, i] = g_rho / a
            g_alpha[j, i] = -g_rho * rho / a


def _np_dtype(t: Tensor) -> type:
    return np.float32 if t.dtype == torch.float32 else np.float64


class _Reflection(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal, rough, alpha, camera, lod_scale, top):  # type: ignore[override]
        h, w = normal.shape[:2]
        rot = camera.R.detach().to(torch.float64).contiguous().numpy()
        i = camera.intrinsics
        intr = np.array([i.fx, i.fy, i.cx, i.cy], np.float64)
        n_np = normal.detach().numpy()
        has_rough = rough is not None
        r_np = rough.detach().numpy() if has_rough else np.empty((0, 0), _np_dtype(normal))
        a_np = alpha.detach().numpy()
        refl = np.empty((h, w, 3), _np_dtype(normal))
        lod = np.empty((h, w) if has_rough else (0, 0), _np_dtype(normal))
        args = (n_np, r_np, a_np, rot, intr, float(lod_scale), float(top), refl, lod)
        run_ranges(_forward_rows, h, args)
        ctx.meta = (n_np, r_np, a_np, rot, intr, float(lod_scale), float(top))
        ctx.dtypes = (normal.dtype, alpha.dtype)
        lod_t = torch.from_numpy(lod) if has_rough else None
        return torch.from_numpy(refl), lod_t

    @staticmethod
    @once_differentiable
    def backward(ctx, g_refl, g_lod):  # type: ignore[override]
        n_np, r_np, a_np, rot, intr, lod_scale, top = ctx.meta
        h, w = n_np.shape[:2]
        has_rough = r_np.shape[0] > 0
        if g_refl is None:
            g_refl = torch.zeros(h, w, 3, dtype=ctx.dtypes[0])
        if g_lod is None or not has_rough:
            g_lod = torch.zeros((h, w) if has_rough else (0, 0), dtype=ctx.dtypes[0])
        g_normal = np.empty((h, w, 3), n_np.dtype)
        g_rough = np.empty((h, w) if has_rough else (0, 0), r_np.dtype)
        g_alpha = np.empty((h, w) if has_rough else (0, 0), a_np.dtype)
        args = (
            n_np, r_np, a_np, rot, intr, lod_scale, top,
            g_refl.detach().contiguous().numpy(), g_lod.detach().contiguous().numpy(),
            g_normal, g_rough, g_alpha,
        )  # fmt: skip
        run_ranges(_backward_rows, h, args)
        if not has_rough:
            return torch.from_numpy(g_normal), None, None, None, None, None
        return (
            torch.from_numpy(g_normal), torch.from_numpy(g_rough), torch.from_numpy(g_alpha),
            None, None, None,
        )  # fmt: skip


def reflection_and_lod(
    normal: Tensor,
    roughness: Tensor | None,
    alpha: Tensor,
    camera: Camera,
    lod_scale: float,
    top_level: float,
) -> tuple[Tensor, Tensor | None]:
    """(reflected directions (H, W, 3), LOD (H, W) or None without ``roughness``) of a
    G-buffer's blended camera-space ``normal``, blended ``roughness`` and ``alpha``, as
    ``shading.reflect``/``world_normals``/``pixel_lod`` compute them; differentiable in
    the three buffers. ``lod_scale`` is roughness_to_lod's 4R/(π/2), ``top_level`` the
    chain's last level. CPU float buffers of one dtype (any strides)."""
    return _Reflection.apply(normal, roughness, alpha, camera, lod_scale, top_level)
