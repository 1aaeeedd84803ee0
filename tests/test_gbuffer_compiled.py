"""The compiled per-Gaussian G-buffer channels against the torch path."""

from __future__ import annotations

import pytest
import torch

from core.kernels.pool import set_kernel_threads
from core.render.gbuffer import gbuffer_features
from core.render.gbuffer_compiled import can_build_compiled
from core.scene.cameras import Camera, Intrinsics


def _inputs(n: int, dtype: torch.dtype, seed: int):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 2.0
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    normals = torch.randn(n, 3, generator=g, dtype=dtype)
    normals[:5] = 0.0  # degenerate normals stay 0
    w_r = torch.rand(n, generator=g, dtype=dtype)
    cam = Camera.look_at(
        [3.0, -4.0, 1.5], [0.2, 0.1, 0.0], [0, 0, 1], Intrinsics(60, 60, 32, 30, 64, 60)
    )
    return means, colors, normals, w_r, cam


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_features_match_torch(dtype, seed):
    set_kernel_threads(3)
    means, colors, normals, w_r, cam = _inputs(3001, dtype, seed)
    with torch.no_grad():
        got = gbuffer_features(means, colors, normals, w_r, cam)
        want = gbuffer_features(means, colors, normals, w_r, cam, compiled=False)
    assert got.dtype == want.dtype and got.shape == (3001, 9)
    # Gaussians whose plane passes (almost) through the camera may pick the other
    # facing sign under different rounding; everything else must agree to rounding.
    dist = (means @ cam.R.to(dtype).T + cam.t.to(dtype)).norm(dim=-1) * normals.norm(dim=-1)
    clear = want[:, 6].abs() > 1e-4 * dist
    assert int(clear.sum()) > 2900
    tol = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got[clear], want[clear], **tol)
    flip = torch.where((got[:, 3:6] * want[:, 3:6]).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(dtype)
    torch.testing.assert_close(got[:, 3:6] * flip, want[:, 3:6], **tol)


def test_gradients_keep_the_torch_path():
    means, colors, normals, w_r, cam = _inputs(50, torch.float32, 2)
    means.requires_grad_(True)
    assert not can_build_compiled(means, colors, normals, w_r)
    gbuffer_features(means, colors, normals, w_r, cam).sum().backward()
    assert means.grad is not None and torch.isfinite(means.grad).all()
    with torch.no_grad():
        assert can_build_compiled(means, colors, normals, w_r)
    assert not can_build_compiled(means.detach().double(), colors, normals, w_r)


@pytest.mark.parametrize("n", [1, 2, 7, 100_000])
def test_near_plane_median_is_torchs_lower_median(n):
    """The radix-select median equals torch's (lower) median of the finite positive
    values, ties, negatives, NaN and Inf included."""
    from core.render.gbuffer_compiled import lower_median_positive

    g = torch.Generator().manual_seed(n)
    z = torch.randn(n, generator=g).abs() * 3 + 0.01
    z[::5] = -1.0
    z[1::9] = float("nan")
    z[2::11] = float("inf")
    z[3::13] = z[0] if n > 3 else z[3::13]  # ties
    keep = z[torch.isfinite(z) & (z > 0)]
    want = None if keep.numel() == 0 else float(keep.median())
    assert lower_median_positive(z) == want
    assert lower_median_positive(z[:0]) is None
    assert lower_median_positive(torch.tensor([-1.0, 0.0, float("nan")])) is None
