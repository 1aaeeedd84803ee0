"""Eq. 8 depth, compiled, against the torch path: depth, valid and gradients."""

from __future__ import annotations

import pytest
import torch

from core.render.gbuffer import planar_depth
from core.scene.cameras import Camera, Intrinsics


def buffers(dtype: torch.dtype, size: int = 48, seed: int = 0):
    """Normals from facing to grazing and away, plane distances of both signs, alphas
    around the threshold, a non-finite pixel, in strided views as the G-buffer has."""
    g = torch.Generator().manual_seed(seed)
    cam = Camera.look_at(
        [0.1, 0.2, 3.0], [0, 0, 0], [0, 1, 0], Intrinsics(50, 50, 24, 24, size, size)
    )
    feats = torch.randn(size, size, 6, generator=g, dtype=dtype)
    feats[..., 2] -= 1.5  # mostly facing the camera (−z)
    feats[..., 3] = -feats[..., 3].abs() * 3  # D < 0 facing: positive depth
    feats[::7, ::5, 3] *= -1
    feats[..., 4] = torch.rand(size, size, generator=g, dtype=dtype) * 0.2  # alpha near 0.05
    feats[5, 5, 0] = float("inf")
    return cam, feats[..., 0:3], feats[..., 3], feats[..., 4]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_matches_the_torch_planar_depth(dtype):
    cam, normal, plane, alpha = buffers(dtype)
    grad_out = torch.randn(plane.shape, dtype=dtype)
    out = {}
    for compiled in (False, True):
        n = normal.clone().requires_grad_(True)
        p = plane.clone().requires_grad_(True)
        depth, valid = planar_depth(n, p, alpha, cam, compiled=compiled)
        (depth * grad_out).sum().backward()
        out[compiled] = (depth.detach(), valid, n.grad, p.grad)
    (d0, v0, gn0, gp0), (d1, v1, gn1, gp1) = out[False], out[True]
    same = v0 == v1
    assert int((~same).sum()) <= (0 if dtype == torch.float64 else 2)  # a threshold may flip
    assert 0 < int(v1.sum()) < v1.numel()
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(d1[same], d0[same], rtol=tol, atol=tol)
    torch.testing.assert_close(gp1[same], gp0[same], rtol=tol, atol=tol)
    torch.testing.assert_close(gn1[same], gn0[same], rtol=tol, atol=tol)
    assert float(d1[~v1].abs().sum()) == 0.0 and float(gp1[~v1].abs().sum()) == 0.0
    assert torch.isfinite(gn1).all()


def test_a_fronto_parallel_plane_is_its_distance():
    """The stated answer: normal (0, 0, −1), D = −2 gives depth 2 at every pixel."""
    cam = Camera.look_at([0, 0, 3.0], [0, 0, 0], [0, 1, 0], Intrinsics(30, 30, 10, 10, 20, 20))
    normal = torch.zeros(20, 20, 3)
    normal[..., 2] = -1.0
    depth, valid = planar_depth(normal, torch.full((20, 20), -2.0), torch.ones(20, 20), cam,
                                compiled=True)  # fmt: skip
    assert bool(valid.all())
    torch.testing.assert_close(depth, torch.full((20, 20), 2.0))
