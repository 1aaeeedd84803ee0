"""Real spherical harmonics up to degree 3, exactly as 3D Gaussian Splatting evaluates them.

The constants, the basis order and the signs are those of 3DGS (``sh_utils.py`` and
the CUDA ``computeColorFromSH``), so SH coefficients written to a PLY by Glint mean the
same colours in any 3DGS viewer, and vice versa. Coefficients are stored (N, K, 3):
K = (max_degree + 1)² basis functions, RGB last; only the first (degree + 1)² are used.

The raw expansion (:func:`eval_sh`) is centred at zero; a colour is ``eval + 0.5``
clamped at 0 (:func:`sh_to_rgb`), which is what 3DGS rasterises. The basis is
orthonormal on the unit sphere (∫ Y_i Y_j dω = δ_ij), which the tests check.
"""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)

MAX_SH_DEGREE = 3

# Below this length a direction is treated as the zero vector (see safe_normalize).
_EPS = 1e-12


def num_sh_bases(degree: int) -> int:
    """Number of basis functions of degree ≤ ``degree``: (degree + 1)²."""
    _check_degree(degree)
    return (degree + 1) ** 2


def sh_degree_from_bases(k: int) -> int:
    """Inverse of :func:`num_sh_bases`; raises ``ValueError`` for a non-square count."""
    for d in range(MAX_SH_DEGREE + 1):
        if (d + 1) ** 2 == k:
            return d
    raise ValueError(f"{k} SH coefficients per channel is not (d + 1)² for a degree d ≤ 3")


def _check_degree(degree: int) -> None:
    if not 0 <= int(degree) <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")


def safe_normalize(v: Tensor, eps: float = _EPS) -> Tensor:
    """Unit vectors along the last axis; a (near) zero vector stays zero, gradients finite.

    The squared length is clamped (not the length), so the backward pass never sees
    the 0/0 of d|v|/dv at v = 0. A zero direction therefore evaluates to the DC term
    alone, i.e. the sphere-averaged colour: a defined, view-independent answer.
    """
    n2 = (v * v).sum(dim=-1, keepdim=True)
    return v * torch.rsqrt(n2.clamp_min(eps * eps))


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """The 3DGS real SH basis at ``dirs`` (..., 3) → (..., (degree + 1)²).

    ``dirs`` are normalised here (safely); callers may pass raw view vectors.
    """
    _check_degree(degree)
    d = safe_normalize(dirs)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = [torch.full_like(x, C0)]
    if degree > 0:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
        if degree > 2:
            out += [
                C3[0] * y * (3.0 * xx - yy),
                C3[1] * xy * z,
                C3[2] * y * (4.0 * zz - xx - yy),
                C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                C3[4] * x * (4.0 * zz - xx - yy),
                C3[5] * z * (xx - yy),
                C3[6] * x * (xx - 3.0 * yy),
            ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Raw SH expansion Σ_k c_k Y_k(d): ``sh`` (N, K, 3), ``dirs`` (N, 3) → (N, 3).

    K ≥ (degree + 1)² coefficients are stored; the first (degree + 1)² are used, so a
    degree-3 model can be rendered at degree 0 during the warm-up phase. No +0.5
    offset and no clamp here (see :func:`sh_to_rgb`).
    """
    n = num_sh_bases(degree)
    if sh.shape[-2] < n:
        raise ValueError(f"degree {degree} needs {n} SH coefficients, got {sh.shape[-2]}")
    basis = sh_basis(degree, dirs).to(sh.dtype)
    return torch.einsum("...k,...kc->...c", basis, sh[..., :n, :])


def sh_to_rgb(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Colour as 3DGS rasterises it: ``eval_sh + 0.5`` clamped at 0 (no upper clamp)."""
    return (eval_sh(degree, sh, dirs) + 0.5).clamp_min(0.0)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """DC coefficient whose colour is ``rgb`` (3DGS ``RGB2SH``)."""
    return (rgb - 0.5) / C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    """Colour of a DC coefficient (3DGS ``SH2RGB``), without clamping."""
    return sh0 * C0 + 0.5
