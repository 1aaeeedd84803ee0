"""Slab order (``TrainConfig.splat_order = 'slab'``): the splats of one stretch of
surface are composited in index order, not in the order of their centres' depth."""

from __future__ import annotations

import pytest
import torch

from core.config import TrainConfig
from core.errors import BackendUnavailableError
from core.model.schedule import phase_at
from core.render.gbuffer import order_slab
from core.render.raster import bin_gaussians, covariances_from, project_gaussians, rasterize
from core.render.raster.binning import bin_gaussians_torch, slab_depths
from core.scene.cameras import Camera, Intrinsics
from tests.gsplat_twin import twin_as_cuda  # noqa: F401  (fixture)
from tests.helpers import rot_y


def _camera() -> Camera:
    return Camera(Intrinsics(16.0, 16.0, 8.0, 8.0, 16, 16), torch.eye(4, dtype=torch.float64))


def _tilted_pair() -> tuple[torch.Tensor, ...]:
    """Two flat splats on one plane tilted 45° about the y axis (z = 3 + x), 0.1 apart
    along it: index 0 (red) lies on the far side, index 1 (blue) on the near side.
    The pixel ray through the plane's point between them sees both equally."""
    t = 0.05
    means = torch.tensor([[t, 0.0, 3.0 + t], [-t, 0.0, 3.0 - t]], dtype=torch.float64)
    quats = rot_y(-45.0).expand(2, 4).clone()  # normal (−1, 0, 1)/√2: the plane z = 3 + x
    scales = torch.tensor([[0.2, 0.2, 1e-4]] * 2, dtype=torch.float64)
    op = torch.tensor([0.6, 0.6], dtype=torch.float64)
    feats = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)  # red, blue
    return means, quats, scales, op, feats


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_slab_order_weighs_a_surfaces_splats_by_index_not_by_centre_depth(backend: str) -> None:
    means, quats, scales, op, feats = _tilted_pair()
    cam = _camera()
    # the pixel whose ray meets the plane at its point between the two centres (0, 0, 3)
    px = (8, 8)
    centre = rasterize(means, quats, scales, op, feats, cam, backend=backend)
    red, blue = centre.features[px].tolist()
    # centre order: the near-side splat (blue, centre z 2.95) first, weighing 0.6·g
    # against the far one's (1 − 0.6·g)·0.6·g: the colour leans toward the camera side
    assert blue > red > 0
    slab = rasterize(means, quats, scales, op, feats, cam, backend=backend, order_slab=10.0)
    red_s, blue_s = slab.features[px].tolist()
    # one slab: index order, red first. The two alphas at this pixel, read off the
    # centre-order result (blue = a1, red = (1 − a1)·a0), give what red-first must be
    a1 = blue
    a0 = red / (1.0 - a1)
    assert red_s == pytest.approx(a0, rel=1e-9)
    assert blue_s == pytest.approx((1.0 - a0) * a1, rel=1e-9)
    assert red_s > blue_s
    torch.testing.assert_close(slab.alpha, centre.alpha)  # coverage does not depend on order


def test_slabs_keep_surfaces_apart_that_lie_further_apart_than_a_slab() -> None:
    means, quats, scales, op, feats = _tilted_pair()
    far = means.clone()
    far[:, 2] += torch.tensor([0.0, 1.0])  # the blue splat now 0.9 behind the red one
    r = rasterize(far, quats, scales, op, feats, _camera(), backend="cpu", order_slab=0.2)
    proj = project_gaussians(far, covariances_from(quats, scales), _camera())
    bins = bin_gaussians(proj.means2d, proj.depths, proj.radii, 16, 16, slab=0.2)
    for t in range(len(bins.offsets) - 1):
        ids = bins.tile(t).tolist()
        assert ids == sorted(ids, key=lambda i: float(proj.depths[i]))  # depth order
    assert r.features[8, 8, 0] > r.features[8, 8, 1]  # the red surface in front


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_slab_binning_compiled_equals_torch(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(3)
    n, size = 3000, 64
    means2d = (torch.rand(n, 2, generator=g, dtype=dtype) * 1.2 - 0.1) * size
    radii = torch.randint(0, 20, (n,), generator=g)
    depths = 1.0 + torch.rand(n, generator=g, dtype=dtype) * 3.0
    depths[:10] = -depths[:10]  # behind the camera: left as they are
    a = bin_gaussians(means2d, depths, radii, size, size, slab=0.05)
    b = bin_gaussians_torch(means2d, slab_depths(depths, 0.05), radii, size, size)
    assert torch.equal(a.gauss_ids, b.gauss_ids) and torch.equal(a.offsets, b.offsets)
    # and the slabs did change the order somewhere
    c = bin_gaussians(means2d, depths, radii, size, size)
    assert not torch.equal(a.gauss_ids, c.gauss_ids)


def test_slab_depths_round_up_to_the_slab_and_leave_invisible_depths() -> None:
    d = torch.tensor([0.01, 0.1, 0.1000001, 0.25, 0.0, -0.3], dtype=torch.float64)
    got = slab_depths(d, 0.1).tolist()
    assert got[:4] == pytest.approx([0.1, 0.2, 0.2, 0.3])
    assert got[4:] == [0.0, -0.3]


def test_order_slab_is_twice_the_median_largest_extent() -> None:
    scales = torch.tensor([[0.01, 0.02, 0.0], [0.04, 0.01, 0.0], [0.03, 0.03, 0.0]])
    assert order_slab(scales, None) == pytest.approx(0.06)
    covs = covariances_from(torch.tensor([[1.0, 0, 0, 0]] * 3), scales + 1e-9)
    assert order_slab(None, covs) == pytest.approx(0.06, rel=1e-4)
    assert order_slab(torch.zeros(0, 3), None) is None
    assert order_slab(None, None) is None


def test_the_config_switches_slab_order_in_every_phase() -> None:
    assert phase_at(TrainConfig(iterations=100), 50).splat_order == "auto"  # the default
    cfg = TrainConfig(iterations=100, splat_order="slab")
    assert all(phase_at(cfg, it).splat_order == "slab" for it in (0, 50, 99))
    with pytest.raises(ValueError, match="splat_order"):
        TrainConfig(splat_order="random")


@pytest.mark.usefixtures("twin_as_cuda")
def test_gsplat_refuses_slab_order_with_a_reason() -> None:
    """gsplat sorts by centre depth itself: a slab-ordered model would render otherwise
    on it, so the cuda backend says so instead of ignoring the setting."""
    means, quats, scales, op, feats = _tilted_pair()
    rasterize(means, quats, scales, op, feats, _camera(), backend="cuda")  # the twin runs
    with pytest.raises(BackendUnavailableError, match="splat_order 'slab' needs the cpu"):
        rasterize(means, quats, scales, op, feats, _camera(), backend="cuda", order_slab=0.1)
