"""The compiled per-Gaussian G-buffer channels against the torch path."""

from __future__ import annotations

import pytest
import torch

from core.kernels.pool import set_kernel_threads
from core.render.gbuffer import gbuffer_features
from core.render.gbuffer_compiled import FeatureLayout, can_build_compiled, features_compiled
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


LAYOUTS = {
    "full": dict(),
    "roughness": dict(roughness=True),
    "held": dict(roughness=True, held=True),
    "geometry": dict(geometry_only=True),
}


def _features(inputs, rough, *, geometry_only=False, roughness=False, held=False, compiled):
    means, colors, normals, w_r, cam = inputs
    return gbuffer_features(
        means, None if geometry_only else colors, normals, None if geometry_only else w_r, cam,
        roughness=rough if roughness else None, held=held, compiled=compiled,
    )  # fmt: skip


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_gradients_match_torch(layout, dtype):
    """Values and the gradients of every input (centres, colours, normals, w_r,
    roughness) equal autograd through the torch path, for each channel layout a pass
    splats; the held pair sends nothing to the normals."""
    set_kernel_threads(2)
    kw = LAYOUTS[layout]
    g = torch.Generator().manual_seed(7)

    def leaves():
        ins = _inputs(2000, dtype, 3)
        means, colors, normals, w_r, cam = ins
        # keep the facing sign clear of its flip (the same rows both ways)
        far = (means @ cam.R.to(dtype).T + cam.t.to(dtype)).norm(dim=-1) * normals.norm(dim=-1)
        rough = torch.linspace(0.05, 0.9, 2000, dtype=dtype)
        t = [x.clone().requires_grad_(True) for x in (means, colors, normals, w_r, rough)]
        return (*t[:4], cam), t[4], t, far

    ins_c, rough_c, leaves_c, far = leaves()
    ins_t, rough_t, leaves_t, _ = leaves()
    got = _features(ins_c, rough_c, compiled=True, **kw)
    want = _features(ins_t, rough_t, compiled=False, **kw)
    assert got.shape == want.shape and got.dtype == dtype
    layout_obj = FeatureLayout(**kw)
    assert got.shape[1] == layout_obj.channels
    plane = want[:, layout_obj.plane].detach()
    clear = plane.abs() > 1e-4 * far
    assert int(clear.sum()) > 1900
    tol = dict(rtol=2e-5, atol=2e-5) if dtype == torch.float32 else dict(rtol=1e-11, atol=1e-11)
    torch.testing.assert_close(got[clear].detach(), want[clear].detach(), **tol)
    upstream = torch.randn(got.shape, generator=g, dtype=torch.float64).to(dtype)
    upstream[~clear] = 0.0  # rows whose sign may differ under rounding carry no gradient
    (got * upstream).sum().backward()
    (want * upstream).sum().backward()
    for name, a, b in zip(("means", "colors", "normals", "w_r", "roughness"), leaves_c, leaves_t,
                          strict=True):  # fmt: skip
        if b.grad is None:
            assert a.grad is None or not a.grad.any(), name
            continue
        torch.testing.assert_close(a.grad, b.grad, **tol, msg=lambda m, n=name: f"{n}: {m}")


def test_compiled_features_pass_gradcheck():
    """Finite differences agree with the hand-written backward (float64, every input;
    not the held pair, whose detached normals finite differences cannot see)."""
    means, colors, normals, w_r, cam = _inputs(12, torch.float64, 4)
    normals[:5] = torch.tensor([0.3, -0.8, 0.5], dtype=torch.float64)  # no sign flip within eps
    rough = torch.rand(12, dtype=torch.float64)
    ins = [t.clone().requires_grad_(True) for t in (means, colors, normals, w_r, rough)]

    def f(m, c, n, w, r):
        return gbuffer_features(m, c, n, w, cam, roughness=r)

    assert torch.autograd.gradcheck(f, tuple(ins), eps=1e-6, atol=1e-6)


def test_which_inputs_take_the_compiled_path():
    means, colors, normals, w_r, cam = _inputs(50, torch.float32, 2)
    assert can_build_compiled(means.requires_grad_(True), colors, normals, w_r, None)
    assert not can_build_compiled(means.detach().double(), colors, normals, w_r)
    with pytest.raises(ValueError, match="feature layout"):
        features_compiled(means, None, normals, w_r, cam, FeatureLayout())


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
