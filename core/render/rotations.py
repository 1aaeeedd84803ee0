"""Quaternions to rotation matrices: the one PyTorch implementation (3DGS's w, x, y, z).

The compiled CPU projection (``raster/projection_compiled.py``) has its own numba
twin of :func:`quat_to_rotmat`, tested against this one.
"""

from __future__ import annotations

import torch
from torch import Tensor

# Quaternions shorter than this are treated as zero and map to the identity.
QUAT_EPS = 1e-12


def normalize_quats(q: Tensor, eps: float = QUAT_EPS) -> Tensor:
    """Unit quaternions; a (near) zero one becomes the identity with zero (finite) gradient.

    ``torch.where`` on the inputs (not the outputs) keeps 0/0 out of the backward pass.
    """
    n2 = (q * q).sum(dim=-1, keepdim=True)
    degenerate = n2 < eps * eps
    ident = torch.zeros_like(q)
    ident[..., 0] = 1.0
    q_safe = torch.where(degenerate, ident, q)
    n2_safe = torch.where(degenerate, torch.ones_like(n2), n2)
    return q_safe * torch.rsqrt(n2_safe)


def quat_to_rotmat(q: Tensor) -> Tensor:
    """Unit (w, x, y, z) quaternions (..., 4) → rotation matrices (..., 3, 3).

    Quaternions of any length go through :func:`normalize_quats` first.
    """
    w, x, y, z = q.unbind(-1)
    row0 = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1)
    row1 = torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1)
    row2 = torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)
    return torch.stack([row0, row1, row2], dim=-2)
