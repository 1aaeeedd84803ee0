"""L_single's fused passes against the torch definition: value and both gradients."""

from __future__ import annotations

import pytest
import torch

from core.scene.cameras import Camera, Intrinsics
from core.training.losses import single_view_loss


def scene(dtype: torch.dtype, seed: int = 0, size: int = 40):
    """A bumpy depth map with a step (a self-occlusion edge), holes in the valid mask,
    noisy rendered normals (a few of them zero) and an edge weight."""
    g = torch.Generator().manual_seed(seed)
    cam = Camera.look_at(
        [0.2, 0.1, 3.0], [0, 0, 0], [0, 1, 0], Intrinsics(45, 47, 20.3, 19.6, size, size)
    )
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    depth = (
        3.0
        + 0.2 * torch.sin(3 * xx) * torch.cos(2 * yy)
        + 0.05 * torch.rand(size, size, generator=g)
    )
    depth[:, size // 2 :] -= 0.6  # a jump: the same-surface differences take one side
    valid = torch.rand(size, size, generator=g) > 0.08
    normal = torch.randn(size, size, 3, generator=g)
    normal[3, 3] = 0.0
    weight = torch.rand(size, size, generator=g)
    return cam, depth.to(dtype), valid, normal.to(dtype), weight.to(dtype)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
@pytest.mark.parametrize("same_surface", [False, True])
@pytest.mark.parametrize("weighted", [False, True])
def test_matches_the_torch_loss(dtype, tol, same_surface, weighted):
    cam, depth, valid, normal, weight = scene(dtype)
    out = {}
    for compiled in (False, True):
        d = depth.clone().requires_grad_(True)
        n = normal.clone().requires_grad_(True)
        loss = single_view_loss(n, d, valid, cam, weight if weighted else None,
                                same_surface=same_surface, compiled=compiled)  # fmt: skip
        loss.backward()
        out[compiled] = (loss.detach(), d.grad, n.grad)
    for a, b, name in zip(out[False], out[True], ("loss", "depth", "normal"), strict=True):
        torch.testing.assert_close(b, a, rtol=tol, atol=tol, msg=name)
    assert float(out[True][1].abs().sum()) > 0 and float(out[True][2].abs().sum()) > 0


def test_no_valid_pixel_gives_zero_and_no_gradient():
    cam, depth, valid, normal, _ = scene(torch.float32)
    d = depth.clone().requires_grad_(True)
    n = normal.clone().requires_grad_(True)
    loss = single_view_loss(n, d, torch.zeros_like(valid), cam, compiled=True)
    loss.backward()
    assert float(loss.detach()) == 0.0
    assert float(d.grad.abs().sum()) == 0.0 and float(n.grad.abs().sum()) == 0.0


def test_a_plane_seen_with_its_own_normal_costs_nothing():
    """The stated answer: a fronto-parallel plane rendered with normal (0, 0, −1)."""
    cam = Camera.look_at([0, 0, 3.0], [0, 0, 0], [0, 1, 0], Intrinsics(30, 30, 10, 10, 20, 20))
    depth = torch.full((20, 20), 3.0, dtype=torch.float64)
    normal = torch.zeros(20, 20, 3, dtype=torch.float64)
    normal[..., 2] = -1.0
    valid = torch.ones(20, 20, dtype=torch.bool)
    loss = single_view_loss(normal, depth, valid, cam, compiled=True)
    assert float(loss) == pytest.approx(0.0, abs=1e-12)
