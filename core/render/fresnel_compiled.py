"""The Fresnel rise (``core.render.fresnel.apply_fresnel``) in one compiled pass and its
backward, for training on the CPU.

In torch the rise is some fifteen image-sized ops and their autograd (the view rays'
and the normal's normalisations, the angle, the fifth power, the two products): about
as much as the whole deferred shading's forward and backward at 128² (``python -m
bench.step_breakdown``). Here one loop writes base' and w_r', a second the gradients:

* c = |d · n̂| with n̂ the camera-space normal normalised twice (as the reflection's)
  passes g_c · sign(d · n̂) · d to n̂, then back through each safe normalisation
  (``reflection_compiled._normalise_back``); nothing where c is clamped at 1;
* rise = (1 − ρ)(1 − c)⁵ with ρ = blended ρ / alpha clamped to [0, 1] (nothing where it
  is clamped, nor where alpha ≤ 1e-6) passes −(1 − c)⁵ to ρ and −5(1 − ρ)(1 − c)⁴ to c;
* base' = base (1 − rise), w_r' = w_r (1 + q rise), q = (1 − F0) / F0: the scene's F0
  gets −Σ g_w' w_r rise / F0², summed per row and then over rows.

Float64 inside, outputs in the buffers' dtype; ``tests/test_fresnel.py`` holds values
and gradients to the torch path.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.kernels.pool import run_ranges
from core.render.reflection_compiled import COVERED, EPS, _normalise_back, _normalised
from core.scene.cameras import Camera

__all__ = ["fresnel_compiled", "fresnel_rise"]


@njit(nogil=True, cache=True, inline="always")
def _angle(j, i, normal, intr):  # pragma: no cover - numba
    """Pixel (j, i)'s camera-space unit ray d, normal n, its two normalisations a and b
    with their factors, and d · b."""
    x = (i + 0.5 - intr[2]) / intr[0]
    y = (j + 0.5 - intr[3]) / intr[1]
    inv = 1.0 / math.sqrt(x * x + y * y + 1.0)
    d0, d1, d2 = x * inv, y * inv, inv
    n0, n1 = np.float64(normal[j, i, 0]), np.float64(normal[j, i, 1])
    n2 = np.float64(normal[j, i, 2])
    a0, a1, a2, ka = _normalised(n0, n1, n2)
    b0, b1, b2, kb = _normalised(a0, a1, a2)
    dot = d0 * b0 + d1 * b1 + d2 * b2
    return (d0, d1, d2), (n0, n1, n2), (a0, a1, a2), ka, (b0, b1, b2), kb, dot


@njit(nogil=True, cache=True, inline="always")
def _rho(j, i, rough, alpha):  # pragma: no cover - numba
    """(ρ, whether it passes a gradient): shading.pixel_roughness."""
    if rough.shape[0] == 0:
        return 0.0, False
    a = np.float64(alpha[j, i])
    if not a > COVERED:
        return 0.0, False
    r = np.float64(rough[j, i]) / a
    if r >= 0.0 and r <= 1.0:
        return r, True
    return (min(max(r, 0.0), 1.0) if r == r else r), False  # NaN stays NaN


@njit(nogil=True, cache=True, inline="always")
def fresnel_rise(cos, rho):  # pragma: no cover - numba
    """(1 − ρ)(1 − c)⁵: ``core.render.fresnel.fresnel_rise`` for one pixel (this pass and
    the frame kernel of ``shading_compiled`` read it)."""
    s = 1.0 - cos
    return (1.0 - rho) * (s * s) * (s * s) * s


@njit(nogil=True, cache=True)
def _forward_rows(
    lo, hi, base, normal, w_r, rough, alpha, intr, q, out_base, out_w
):  # pragma: no cover - numba
    width = normal.shape[1]
    for j in range(lo, hi):
        for i in range(width):
            # a pixel no splat reached has a zero normal: c = 0, no square roots
            empty = normal[j, i, 0] == 0.0 and normal[j, i, 1] == 0.0 and normal[j, i, 2] == 0.0
            dot = 0.0 if empty else _angle(j, i, normal, intr)[6]
            c = min(abs(dot), 1.0)
            rise = fresnel_rise(c, _rho(j, i, rough, alpha)[0])
            keep = 1.0 - rise
            for ch in range(base.shape[2]):
                out_base[j, i, ch] = base[j, i, ch] * keep
            out_w[j, i] = w_r[j, i] * (1.0 + q * rise)


@njit(nogil=True, cache=True)
def _backward_rows(
    lo, hi, base, normal, w_r, rough, alpha, intr, q, g_base_out, g_w_out,
    g_base, g_normal, g_w, g_rough, g_alpha, g_q_rows,
):  # fmt: skip  # pragma: no cover - numba
    width = normal.shape[1]
    has_rough = rough.shape[0] != 0
    for j in range(lo, hi):
        g_q = 0.0
        for i in range(width):
            empty = normal[j, i, 0] == 0.0 and normal[j, i, 1] == 0.0 and normal[j, i, 2] == 0.0
            if empty:  # c = 0 at |·|'s kink: no gradient to the normal (below)
                dot = 0.0
                d0 = d1 = d2 = n0 = n1 = n2 = a0 = a1 = a2 = b0 = b1 = b2 = ka = kb = 0.0
            else:
                (d0, d1, d2), (n0, n1, n2), (a0, a1, a2), ka, (b0, b1, b2), kb, dot = _angle(
                    j, i, normal, intr
                )
            c = abs(dot)
            rho, rho_passes = _rho(j, i, rough, alpha)
            s = 1.0 - min(c, 1.0)
            s4 = (s * s) * (s * s)
            rise = (1.0 - rho) * s4 * s
            keep = 1.0 - rise
            gw_out = np.float64(g_w_out[j, i])
            w = np.float64(w_r[j, i])
            g_rise = gw_out * w * q
            for ch in range(base.shape[2]):
                gb = np.float64(g_base_out[j, i, ch])
                g_base[j, i, ch] = gb * keep
                g_rise -= gb * np.float64(base[j, i, ch])
            g_w[j, i] = gw_out * (1.0 + q * rise)
            g_q += gw_out * w * rise
            if has_rough:
                g_rough[j, i] = 0.0
                g_alpha[j, i] = 0.0
                if rho_passes:
                    g_rho = -s4 * s * g_rise
                    a = np.float64(alpha[j, i])
                    g_rough[j, i] = g_rho / a
                    g_alpha[j, i] = -g_rho * rho / a
            g_c = -5.0 * (1.0 - rho) * s4 * g_rise
            if c > 1.0 or dot == 0.0 or g_c == 0.0:  # clamped, |·|'s kink, or nothing
                g_normal[j, i, 0] = 0.0
                g_normal[j, i, 1] = 0.0
                g_normal[j, i, 2] = 0.0
                continue
            g_dot = g_c if dot > 0.0 else -g_c
            h0, h1, h2 = g_dot * d0, g_dot * d1, g_dot * d2
            floored_b = a0 * a0 + a1 * a1 + a2 * a2 < EPS * EPS
            h0, h1, h2 = _normalise_back(h0, h1, h2, b0, b1, b2, kb, floored_b)
            floored_a = n0 * n0 + n1 * n1 + n2 * n2 < EPS * EPS
            h0, h1, h2 = _normalise_back(h0, h1, h2, a0, a1, a2, ka, floored_a)
            g_normal[j, i, 0] = h0
            g_normal[j, i, 1] = h1
            g_normal[j, i, 2] = h2
        g_q_rows[j] = g_q


def _np(t: Tensor) -> np.ndarray:
    return t.detach().numpy()


class _Fresnel(torch.autograd.Function):
    @staticmethod
    def forward(ctx, base, normal, w_r, rough, alpha, f0, camera):  # type: ignore[override]
        h, w = normal.shape[:2]
        i = camera.intrinsics
        intr = np.array([i.fx, i.fy, i.cx, i.cy], np.float64)
        f0_value = float(f0.detach())
        q = (1.0 - f0_value) / f0_value
        npdt = np.float32 if base.dtype == torch.float32 else np.float64
        r_np = _np(rough) if rough is not None else np.empty((0, 0), npdt)
        arrays = (_np(base), _np(normal), _np(w_r), r_np, _np(alpha))
        out_base = np.empty(tuple(base.shape), npdt)
        out_w = np.empty((h, w), npdt)
        run_ranges(_forward_rows, h, (*arrays, intr, q, out_base, out_w))
        ctx.meta = (arrays, intr, q, f0_value, rough is not None)
        ctx.f0_dtype = f0.dtype
        return torch.from_numpy(out_base), torch.from_numpy(out_w)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_base_out, g_w_out):  # type: ignore[override]
        arrays, intr, q, f0_value, has_rough = ctx.meta
        base, normal, w_r, rough, alpha = arrays
        h, w = normal.shape[:2]
        if g_base_out is None:
            g_base_out = torch.zeros(base.shape, dtype=torch.from_numpy(base).dtype)
        if g_w_out is None:
            g_w_out = torch.zeros((h, w), dtype=torch.from_numpy(w_r).dtype)
        g_base = np.empty(base.shape, base.dtype)
        g_normal = np.empty(normal.shape, normal.dtype)
        g_w = np.empty(w_r.shape, w_r.dtype)
        g_rough = np.empty(rough.shape, rough.dtype)
        g_alpha = np.empty(rough.shape, alpha.dtype)
        g_q_rows = np.empty(h, np.float64)
        args = (
            *arrays, intr, q, g_base_out.detach().contiguous().numpy(),
            g_w_out.detach().contiguous().numpy(), g_base, g_normal, g_w, g_rough, g_alpha,
            g_q_rows,
        )  # fmt: skip
        run_ranges(_backward_rows, h, args)
        g_f0 = torch.tensor(-g_q_rows.sum() / (f0_value * f0_value), dtype=ctx.f0_dtype)
        return (
            torch.from_numpy(g_base), torch.from_numpy(g_normal), torch.from_numpy(g_w),
            torch.from_numpy(g_rough) if has_rough else None,
            torch.from_numpy(g_alpha) if has_rough else None, g_f0, None,
        )  # fmt: skip


def fresnel_compiled(
    base: Tensor,
    normal: Tensor,
    w_r: Tensor,
    roughness: Tensor | None,
    alpha: Tensor,
    f0: Tensor,
    camera: Camera,
) -> tuple[Tensor, Tensor]:
    """(base', w_r') as ``fresnel.apply_fresnel`` computes them with ρ =
    ``shading.pixel_roughness(roughness, alpha)`` (0 without ``roughness``), differentiable
    in the buffers and the scene's ``f0`` (a 0-dim tensor). CPU float buffers of one dtype
    (any strides)."""
    return _Fresnel.apply(base, normal, w_r, roughness, alpha, f0, camera)
