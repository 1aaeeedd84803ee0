"""Small builders shared by tests (cameras, single Gaussians)."""

from __future__ import annotations

import math

import torch

from core.scene.cameras import Camera, Intrinsics


def identity_camera(size: int = 32, f: float | None = None, dtype=torch.float64) -> Camera:
    """Camera at the origin looking down +z (world = camera frame), principal point off-centre."""
    f = f if f is not None else float(size)
    intr = Intrinsics(f, f * 1.1, size / 2 + 0.7, size / 2 - 0.4, size, size)
    return Camera(intr, torch.eye(4, dtype=torch.float64), "identity")


def rot_y(deg: float, dtype=torch.float64) -> torch.Tensor:
    """Quaternion (w, x, y, z) of a rotation by ``deg`` about +y."""
    h = math.radians(deg) / 2
    return torch.tensor([[math.cos(h), 0.0, math.sin(h), 0.0]], dtype=dtype)


def rotmat_y(deg: float, dtype=torch.float64) -> torch.Tensor:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=dtype)
