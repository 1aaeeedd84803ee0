"""View-dependent colour from SH in one compiled pass per Gaussian, forward and backward.

``sh_to_rgb(degree, sh, means - centre)`` in PyTorch normalises the view vectors,
builds the 16 basis functions as separate tensors and contracts them with an einsum
whose backward runs as tiny batched matrix products: 18.6 ms for a 100k-Gaussian
viewer frame and 9.5 ms forward + backward for a 20k training step, on one core.
Here each Gaussian's direction, basis, colour and clamp are computed in registers,
and the backward (colour → coefficients and → centre, through the basis derivatives
and the normalisation) is written out.

Semantics are :func:`core.render.sh.sh_to_rgb`'s: the 3DGS basis and constants, a direction
whose squared length is below 1e-24 normalised by 1e-12 (``safe_normalize``), colour
= eval + 0.5 clamped at 0 with the gradient passed where eval + 0.5 ≥ 0, unused
higher-degree coefficients get a zero gradient. Arithmetic is float64; results match
the PyTorch path to its rounding (``tests/test_sh_compiled.py``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor

from core.kernels.pool import run_ranges
from core.render.sh import C0, C1, C2, C3, _check_degree

_EPS = 1e-12


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _direction(means, campos, i):  # pragma: no cover - numba
    """(x, y, z) unit view direction of Gaussian i and its normaliser 1/|v| (safe)."""
    vx = float(means[i, 0]) - campos[0]
    vy = float(means[i, 1]) - campos[1]
    vz = float(means[i, 2]) - campos[2]
    n2 = vx * vx + vy * vy + vz * vz
    r = 1.0 / math.sqrt(n2) if n2 >= _EPS * _EPS else 1.0 / _EPS
    return vx * r, vy * r, vz * r, r, n2 >= _EPS * _EPS


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _basis(x, y, z, degree, Y):  # pragma: no cover - numba
    """Y[:(degree+1)²] = the 3DGS real SH basis at the unit direction (x, y, z)."""
    Y[0] = C0
    if degree > 0:
        Y[1] = -C1 * y
        Y[2] = C1 * z
        Y[3] = -C1 * x
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        Y[4] = C2[0] * x * y
        Y[5] = C2[1] * y * z
        Y[6] = C2[2] * (2.0 * zz - xx - yy)
        Y[7] = C2[3] * x * z
        Y[8] = C2[4] * (xx - yy)
        if degree > 2:
            Y[9] = C3[0] * y * (3.0 * xx - yy)
            Y[10] = C3[1] * x * y * z
            Y[11] = C3[2] * y * (4.0 * zz - xx - yy)
            Y[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            Y[13] = C3[4] * x * (4.0 * zz - xx - yy)
            Y[14] = C3[5] * z * (xx - yy)
            Y[15] = C3[6] * x * (xx - 3.0 * yy)


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _basis_vjp(x, y, z, degree, w):  # pragma: no cover - numba
    """Σ_j w_j ∇Y_j at the unit direction (x, y, z): the gradient w.r.t. the direction."""
    gx = gy = gz = 0.0
    if degree > 0:
        gy -= C1 * w[1]
        gz += C1 * w[2]
        gx -= C1 * w[3]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        gx += C2[0] * y * w[4]
        gy += C2[0] * x * w[4]
        gy += C2[1] * z * w[5]
        gz += C2[1] * y * w[5]
        gx -= 2.0 * C2[2] * x * w[6]
        gy -= 2.0 * C2[2] * y * w[6]
        gz += 4.0 * C2[2] * z * w[6]
        gx += C2[3] * z * w[7]
        gz += C2[3] * x * w[7]
        gx += 2.0 * C2[4] * x * w[8]
        gy -= 2.0 * C2[4] * y * w[8]
        if degree > 2:
            gx += 6.0 * C3[0] * x * y * w[9]
            gy += 3.0 * C3[0] * (xx - yy) * w[9]
            gx += C3[1] * y * z * w[10]
            gy += C3[1] * x * z * w[10]
            gz += C3[1] * x * y * w[10]
            gx -= 2.0 * C3[2] * x * y * w[11]
            gy += C3[2] * (4.0 * zz - xx - 3.0 * yy) * w[11]
            gz += 8.0 * C3[2] * y * z * w[11]
            gx -= 6.0 * C3[3] * x * z * w[12]
            gy -= 6.0 * C3[3] * y * z * w[12]
            gz += C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * w[12]
            gx += C3[4] * (4.0 * zz - 3.0 * xx - yy) * w[13]
            gy -= 2.0 * C3[4] * x * y * w[13]
            gz += 8.0 * C3[4] * x * z * w[13]
            gx += 2.0 * C3[5] * x * z * w[14]
            gy -= 2.0 * C3[5] * y * z * w[14]
            gz += C3[5] * (xx - yy) * w[14]
            gx += 3.0 * C3[6] * (xx - yy) * w[15]
            gy -= 6.0 * C3[6] * x * y * w[15]
    return gx, gy, gz


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _coeff(dc, rest, i, j, c):  # pragma: no cover - numba
    return float(dc[i, 0, c]) if j == 0 else float(rest[i, j - 1, c])


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _expand(dc, rest, i, Y, nb, c):  # pragma: no cover - numba
    """Σ_j Y_j c_ij for channel c: the colour before the +0.5 and the clamp."""
    acc = 0.0
    for j in range(nb):
        acc += Y[j] * _coeff(dc, rest, i, j, c)
    return acc


@njit(cache=True, nogil=True, fastmath=False)
def _forward_range(lo, hi, means, campos, dc, rest, degree, rgb):  # pragma: no cover - numba
    nb = (degree + 1) * (degree + 1)
    Y = np.empty(16)
    for i in range(lo, hi):
        x, y, z, _, _ = _direction(means, campos, i)
        _basis(x, y, z, degree, Y)
        for c in range(3):
            rgb[i, c] = max(_expand(dc, rest, i, Y, nb, c) + 0.5, 0.0)


@njit(cache=True, nogil=True, fastmath=False)
def _backward_range(
    lo, hi, means, campos, dc, rest, degree, g_rgb, g_means, g_dc, g_rest
):  # pragma: no cover - numba
    nb = (degree + 1) * (degree + 1)
    Y = np.empty(16)
    w = np.zeros(16)
    g = np.zeros(3)
    want_means = g_means.shape[0] > 0
    for i in range(lo, hi):
        if g_rgb[i, 0] == 0.0 and g_rgb[i, 1] == 0.0 and g_rgb[i, 2] == 0.0:
            # no gradient reaches this colour (a splat culled or off-screen in this view:
            # 40-50% of a trained closed object's): its coefficients get zeros, g_means
            # is zeroed already
            for c in range(3):
                g_dc[i, 0, c] = 0.0
                for j in range(1, nb):
                    g_rest[i, j - 1, c] = 0.0
            continue
        x, y, z, r, unclamped = _direction(means, campos, i)
        _basis(x, y, z, degree, Y)
        for c in range(3):  # clamp_min passes the gradient at and above 0
            kept = _expand(dc, rest, i, Y, nb, c) + 0.5 >= 0.0
            g[c] = float(g_rgb[i, c]) if kept else 0.0
        for c in range(3):
            g_dc[i, 0, c] = Y[0] * g[c]
            for j in range(1, nb):
                g_rest[i, j - 1, c] = Y[j] * g[c]
        if not want_means or degree == 0:
            continue
        for j in range(nb):
            w[j] = (
                g[0] * _coeff(dc, rest, i, j, 0)
                + g[1] * _coeff(dc, rest, i, j, 1)
                + g[2] * _coeff(dc, rest, i, j, 2)
            )
        gx, gy, gz = _basis_vjp(x, y, z, degree, w)
        if unclamped:  # d = v r: dL/dv = r (g − d (d·g))
            dot = x * gx + y * gy + z * gz
            gx, gy, gz = gx - x * dot, gy - y * dot, gz - z * dot
        g_means[i, 0] = r * gx
        g_means[i, 1] = r * gy
        g_means[i, 2] = r * gz


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class CompiledSH(torch.autograd.Function):
    """(means, sh_dc, sh_rest) → colour (N, 3) seen from ``campos``; see the module doc."""

    @staticmethod
    def forward(ctx, means, sh_dc, sh_rest, campos, degree):
        n = means.shape[0]
        cam = campos.detach().to(torch.float64).numpy()
        arrays = (_np(means), cam, _np(sh_dc), _np(sh_rest), degree)
        rgb = np.empty((n, 3), arrays[2].dtype)
        run_ranges(_forward_range, n, (*arrays, rgb))
        ctx.save_for_backward(means, sh_dc, sh_rest)  # refuses a backward after in-place edits
        ctx.arrays = arrays
        return torch.from_numpy(rgb)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_rgb):
        ctx.saved_tensors  # noqa: B018  (raises if an input was modified in place)
        m, _, dc, rest, degree = ctx.arrays
        n = m.shape[0]
        need = ctx.needs_input_grad
        g_means = np.zeros((n if need[0] else 0, 3), m.dtype)
        g_dc = np.empty(dc.shape, dc.dtype)
        # rows above the degree in use get no gradient: zeros, as the PyTorch path;
        # at full degree the kernel writes every row and zeroing would be wasted
        alloc = np.empty if rest.shape[1] == (degree + 1) ** 2 - 1 else np.zeros
        g_rest = alloc(rest.shape, rest.dtype)
        args = (*ctx.arrays, _np(g_rgb).astype(dc.dtype, copy=False), g_means, g_dc, g_rest)
        run_ranges(_backward_range, n, args)
        return (
            torch.from_numpy(g_means) if need[0] else None,
            torch.from_numpy(g_dc) if need[1] else None,
            torch.from_numpy(g_rest) if need[2] else None,
            None,
            None,
        )


def sh_colors_compiled(
    degree: int, sh_dc: Tensor, sh_rest: Tensor, means: Tensor, campos: Tensor
) -> Tensor:
    """``sh_to_rgb(degree, cat([sh_dc, sh_rest], 1), means - campos)`` on CPU tensors.

    ``sh_dc`` (N, 1, 3), ``sh_rest`` (N, K − 1, 3) with K ≥ (degree + 1)², ``means``
    (N, 3), ``campos`` (3,). Gradients reach means, sh_dc and sh_rest.
    """
    _check_degree(degree)
    n = means.shape[0]
    if sh_dc.shape != (n, 1, 3) or sh_rest.ndim != 3 or sh_rest.shape[0] != n:
        raise ValueError(
            f"sh_dc must be ({n}, 1, 3) and sh_rest ({n}, K-1, 3), "
            f"got {tuple(sh_dc.shape)} and {tuple(sh_rest.shape)}"
        )
    if sh_rest.shape[1] + 1 < (degree + 1) ** 2:
        raise ValueError(
            f"degree {degree} needs {(degree + 1) ** 2} SH coefficients, got {sh_rest.shape[1] + 1}"
        )
    if any(t.device.type != "cpu" for t in (sh_dc, sh_rest, means)):
        raise ValueError("sh_colors_compiled runs on CPU tensors only")
    if not torch.is_grad_enabled():
        means, sh_dc, sh_rest = means.detach(), sh_dc.detach(), sh_rest.detach()
    return CompiledSH.apply(means, sh_dc, sh_rest.to(sh_dc.dtype), campos, int(degree))
