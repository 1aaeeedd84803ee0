"""Which surface orientations a capture sees face-on.

The depth losses trust Eq. 8's depth only where a view faces the surface within
``DEPTH_FACING_DEG`` (its error grows as tan θ). A capture from all around (a sphere of
views) faces every orientation from some view, so every part of the surface gets
those losses somewhere; a capture from above only (a turntable, NeRF-synthetic, Shiny
Blender) or from the front (LLFF) never faces the undersides, which then get no depth
loss at all. The scene plan reads this share to decide whether the depth losses also
take oblique pixels, there with Eq. 5's centre depth (``core.training.planner``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from core.render.depth_geometry import DEPTH_FACING_DEG


def fibonacci_directions(n: int) -> Tensor:
    """``n`` nearly uniform unit vectors (n, 3), float64."""
    if n < 1:
        raise ValueError(f"n must be at least 1, got {n}")
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * k / n
    r = (1.0 - z * z).clamp_min(0.0).sqrt()
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def unfaced_share(
    camera_centres: Tensor,
    target: Tensor,
    max_deg: float = DEPTH_FACING_DEG,
    samples: int = 4096,
) -> float:
    """Share of surface normal directions that no camera sees within ``max_deg`` of
    face-on, for a surface at ``target`` (the object's centre; exact for a small
    object far from the cameras). 0 for a sphere of views; (1 - sin 60°) / 2 ≈ 6.7% for
    views over the whole upper hemisphere down to the horizon (every normal more than
    60° below it), 8.7% for bench.render_unseen's ``--upper`` layout."""
    c = camera_centres.detach().to(torch.float64).reshape(-1, 3)
    to_cam = c - target.detach().to(torch.float64).reshape(1, 3)
    norm = to_cam.norm(dim=-1, keepdim=True)
    away = norm[:, 0] > 0  # a camera at the target itself faces nothing
    to_cam = to_cam[away] / norm[away]
    if to_cam.shape[0] == 0:
        return 1.0
    dirs = fibonacci_directions(samples)
    best = (dirs @ to_cam.T).amax(dim=1)
    return float((best < math.cos(math.radians(max_deg))).to(torch.float64).mean())
