"""The reference rasteriser: analytic single-Gaussian cases, culling, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from core.errors import BackendUnavailableError
from core.render.raster import (
    bin_gaussians,
    covariances_from,
    project_gaussians,
    rasterize,
    resolve_backend,
)
from core.render.raster.projection import ALPHA_MAX
from core.scene.cameras import Camera, Intrinsics
from tests.helpers import identity_camera


def _one(mean, scale, opacity, dtype=torch.float64):
    means = torch.tensor([mean], dtype=dtype)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=dtype)
    scales = torch.tensor([scale], dtype=dtype)
    op = torch.tensor([opacity], dtype=dtype)
    return means, quats, scales, op


def test_isotropic_gaussian_matches_closed_form():
    cam = identity_camera(32)
    means, quats, scales, op = _one([0.0, 0.0, 4.0], [0.2, 0.2, 0.2], 0.8)
    feats = torch.tensor([[0.25, 0.5, 1.0]], dtype=torch.float64)
    r = rasterize(means, quats, scales, op, feats, cam, backend="reference")
    i = cam.intrinsics
    # Σ2D = J Σ Jᵀ + 0.3 I with J = diag(fx/z, fy/z) at the optical axis.
    sx2 = (i.fx * 0.2 / 4) ** 2 + 0.3
    sy2 = (i.fy * 0.2 / 4) ** 2 + 0.3
    uv = cam.pixel_centers(torch.float64)
    du, dv = uv[..., 0] - i.cx, uv[..., 1] - i.cy
    g = 0.8 * torch.exp(-0.5 * (du**2 / sx2 + dv**2 / sy2))
    expected = torch.where(g >= 1 / 255, g.clamp(max=ALPHA_MAX), torch.zeros_like(g))
    covered = r.radii[0] > 0
    assert covered
    # Inside the 3σ box the closed form holds exactly; outside the tile set it is 0.
    mask = (du.abs() < 2 * math.sqrt(sx2)) & (dv.abs() < 2 * math.sqrt(sy2))
    torch.testing.assert_close(r.alpha[mask], expected[mask], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(r.features[..., 2], r.alpha)  # feature 1.0 blended = alpha
    torch.testing.assert_close(r.features[..., 0], 0.25 * r.alpha)


def test_front_to_back_order_and_early_termination():
    # Principal point on a pixel centre: that pixel sees each Gaussian at its peak.
    cam = Camera(Intrinsics(16.0, 16.0, 8.5, 8.5, 16, 16), torch.eye(4, dtype=torch.float64))
    means = torch.tensor([[0.0, 0, z] for z in (2.0, 3.0, 4.0, 5.0)], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 4, dtype=torch.float64)
    scales = torch.full((4, 3), 5.0, dtype=torch.float64)
    op = torch.tensor([0.99, 0.9, 0.5, 0.9], dtype=torch.float64)
    feats = torch.eye(4, dtype=torch.float64)
    r = rasterize(means, quats, scales, op, feats, cam, backend="reference")
    c = r.features[8, 8]
    # T: 1 → 0.01 → 1e-3 → 5e-4; the fourth would take it to 5e-5 < 1e-4: excluded.
    torch.testing.assert_close(c, torch.tensor([0.99, 0.009, 0.0005, 0.0], dtype=torch.float64))
    assert r.alpha[8, 8].item() == pytest.approx(1 - 5e-4, abs=1e-12)
    # Shuffling the inputs does not change the result (depth sort).
    perm = torch.tensor([2, 0, 3, 1])
    r2 = rasterize(means[perm], quats, scales, op[perm], feats[perm], cam, backend="reference")
    torch.testing.assert_close(r2.features, r.features)


def test_behind_camera_and_offscreen_culled():
    cam = identity_camera(16)
    means = torch.tensor([[0.0, 0, -2.0], [50.0, 0, 2.0], [0.0, 0, 0.001]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64)
    scales = torch.full((3, 3), 0.05, dtype=torch.float64)
    op = torch.full((3,), 0.9, dtype=torch.float64)
    feats = torch.ones(3, 1, dtype=torch.float64)
    r = rasterize(means, quats, scales, op, feats, cam, backend="reference")
    assert r.radii.tolist() == [0, 0, 0]
    assert r.alpha.abs().max() == 0


def test_backend_selection_errors():
    assert resolve_backend("auto", "cpu") in ("cpu", "reference")
    with pytest.raises(BackendUnavailableError, match="unknown rasteriser backend 'nope'"):
        resolve_backend("nope", "cpu")


def _random_scene(n: int, seed: int, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.3 + torch.tensor(
        [0, 0, 3.0], dtype=dtype
    )
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.15 + 0.05
    op = torch.rand(n, generator=g, dtype=dtype) * 0.6 + 0.2
    feats = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, op, feats


@pytest.mark.parametrize("seed", [0, 1])
def test_gradients_match_finite_differences(seed):
    cam = identity_camera(12, f=14.0)
    means, quats, scales, op, feats = _random_scene(4, seed)
    w = torch.rand(12, 12, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(9))

    def f(means, quats, scales, op, feats):
        r = rasterize(means, quats, scales, op, feats, cam, backend="reference", tile_size=4)
        return (r.features * w[..., :3]).sum() + (r.alpha * w[..., 3]).sum()

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, op, feats)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_means2d_gradient_is_exposed():
    cam = identity_camera(16)
    means, quats, scales, op, feats = _random_scene(6, 3, torch.float32)
    means.requires_grad_(True)
    r = rasterize(means, quats, scales, op, feats, cam, backend="reference")
    r.means2d.retain_grad()
    r.features.sum().backward()
    assert r.means2d.grad is not None and r.means2d.grad.shape == (6, 2)
    assert r.means2d.grad[r.radii > 0].abs().sum() > 0


def test_projection_matches_camera_project():
    intr = Intrinsics(40.0, 42.0, 17.3, 14.1, 32, 30)
    cam = Camera.look_at([1.0, 2.0, -3.0], [0, 0, 0], [0, -1, 0], intr)
    pts = torch.randn(20, 3, dtype=torch.float64) * 0.3
    covs = covariances_from(
        torch.randn(20, 4, dtype=torch.float64), torch.full((20, 3), 0.01, dtype=torch.float64)
    )
    p = project_gaussians(pts, covs, cam)
    uv, z = cam.project(pts)
    torch.testing.assert_close(p.means2d, uv)
    torch.testing.assert_close(p.depths, z)


def test_memory_bounded_chunking_gives_same_result():
    cam = identity_camera(24)
    # float64: in float32 the rounding of T can flip the 1e-4 termination test.
    means, quats, scales, op, feats = _random_scene(300, 5, torch.float64)
    r1 = rasterize(means, quats, scales, op, feats, cam, backend="reference")
    from core.render.raster.reference import rasterize_reference

    covs = covariances_from(quats, scales)
    proj = project_gaussians(means, covs, cam)
    bins = bin_gaussians(proj.means2d, proj.depths, proj.radii, 24, 24)
    f2, a2 = rasterize_reference(proj, op, feats, bins, 24, 24, chunk=7)
    torch.testing.assert_close(f2, r1.features, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(a2, r1.alpha, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize(("size", "n"), [(37, 400), (64, 3000)])
def test_compiled_binning_equals_torch_binning(size, n):
    from core.render.raster.binning import bin_gaussians_torch

    cam = identity_camera(size)
    means, quats, scales, _, _ = _random_scene(n, 11, torch.float32)
    means[: n // 10, 2] = -1.0  # some behind the camera: culled
    p = project_gaussians(means, covariances_from(quats, scales), cam)
    a = bin_gaussians_torch(p.means2d, p.depths, p.radii, size, size)
    b = bin_gaussians(p.means2d, p.depths, p.radii, size, size)
    assert torch.equal(a.gauss_ids, b.gauss_ids) and torch.equal(a.offsets, b.offsets)
    assert a.gauss_ids.numel() > n  # Gaussians spanning several tiles are listed in each


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(("negative", "threads"), [(False, 1), (True, 1), (False, 3)])
def test_compiled_binning_sorts_ties_and_any_depths_like_torch(dtype, negative, threads):
    """Radix depth order (positive depths) and its general fallback: equal depths keep
    index order, Gaussians off-screen or with radius 0 are left out, as in torch; tile
    rows split over several workers give the same lists."""
    from core.kernels.pool import set_kernel_threads
    from core.render.raster.binning import bin_gaussians_torch

    set_kernel_threads(threads)  # reset after each test (conftest)

    g = torch.Generator().manual_seed(5)
    n, size = 2000, 70
    means2d = (torch.rand(n, 2, generator=g, dtype=dtype) * 1.4 - 0.2) * size
    radii = torch.randint(0, 30, (n,), generator=g)
    depths = torch.randint(1, 50, (n,), generator=g).to(dtype) * 0.37  # many exact ties
    depths[:5] = torch.tensor([1e-30, 3e38, 2.0, 2.0, 1e-45]).to(dtype)
    if negative:
        depths[10:20] = -depths[10:20]
    a = bin_gaussians_torch(means2d, depths, radii, size, size)
    b = bin_gaussians(means2d, depths, radii, size, size)
    assert torch.equal(a.gauss_ids, b.gauss_ids) and torch.equal(a.offsets, b.offsets)
