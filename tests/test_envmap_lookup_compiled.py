"""The compiled roughness-aware lookup against the torch path: values and gradients."""

from __future__ import annotations

import pytest
import torch

from core.render.envmap import sample_cube
from core.render.envmap_mips import mip_sizes, sample_cube_lod


def inputs(res: int, n: int, dtype: torch.dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    texels = torch.rand(6, res, res, 3, generator=g, dtype=dtype) * 4
    dirs = torch.randn(n, 3, generator=g, dtype=dtype)
    # exact ties between axes, face edges and corners, bad directions
    dirs[:6] = torch.tensor(
        [[1, 1, 0], [1, -1, 1], [-2, 2, -2], [0, 0, 0], [float("nan"), 1, 0], [1e-200, 0, 0]],
        dtype=dtype,
    )
    levels = len(mip_sizes(res))
    lod = torch.rand(n, generator=g, dtype=dtype) * (levels + 1) - 0.5  # below 0, above top
    lod[6:9] = torch.tensor([0.0, float(levels - 1), 1.0], dtype=dtype)  # exactly on levels
    return texels, dirs, lod


def both(texels, dirs, lod, grad_out):
    out = {}
    for compiled in (False, True):
        t = texels.clone().requires_grad_(True)
        d = dirs.clone().requires_grad_(True)
        lo = lod.clone().requires_grad_(True)
        val = sample_cube_lod(t, d, lo, compiled=compiled)
        (val * grad_out).sum().backward()
        # a one-level map does not read the LOD: no gradient (None) in the torch path
        g_lod = torch.zeros_like(lo) if lo.grad is None else lo.grad
        out[compiled] = (val.detach(), t.grad, d.grad, g_lod)
    return out[False], out[True]


@pytest.mark.parametrize("res", [16, 12, 1])
def test_float64_matches_values_and_gradients(res):
    texels, dirs, lod = inputs(res, 4000, torch.float64)
    grad_out = torch.randn(4000, 3, dtype=torch.float64)
    ref, new = both(texels, dirs, lod, grad_out)
    for a, b, name in zip(ref, new, ("value", "texels", "dirs", "lod"), strict=True):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-10, msg=name)
    assert float(new[0][3:6].abs().sum()) == 0.0  # bad directions: 0 out, no gradient
    assert float(new[2][3:6].abs().sum()) == 0.0


def test_pixels_no_gradient_reaches_are_skipped_exactly():
    """The backward skips pixels whose incoming gradient is zero (a training view's
    uncovered pixels): the gradients still equal the torch path's, and a pixel that
    does get one, even in one channel, is not skipped."""
    texels, dirs, lod = inputs(16, 4000, torch.float64, seed=5)
    grad_out = torch.randn(4000, 3, dtype=torch.float64)
    grad_out[::2] = 0.0  # half the pixels uncovered
    grad_out[1::4, 1:] = 0.0  # a quarter reached in one channel only
    ref, new = both(texels, dirs, lod, grad_out)
    for a, b, name in zip(ref, new, ("value", "texels", "dirs", "lod"), strict=True):
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-10, msg=name)
    assert float(new[2][10::2].abs().sum()) == 0.0 and float(new[2][1::4].abs().sum()) > 0.0


def test_float32_matches_and_leading_shape_is_kept():
    texels, dirs, lod = inputs(32, 128 * 128, torch.float32, seed=3)
    # its own generator: from the global one, grad_out changed with whatever test ran
    # before on the worker, and 3 in 40 draws failed the direction check below
    grad_out = torch.randn(128 * 128, 3, generator=torch.Generator().manual_seed(4))
    ref, new = both(texels, dirs, lod, grad_out)
    for a, b, name in zip(ref[:2] + ref[3:], new[:2] + new[3:], ("value", "texels", "lod"),
                          strict=True):  # fmt: skip
        torch.testing.assert_close(b, a, rtol=2e-4, atol=2e-4, msg=name)
    # a direction's gradient is g − d(d·g) over |v|: a small component is what is left
    # of cancelling large ones (rows reach 160 where |v| is small), so float32 rounding
    # is judged against the row's size, not the component's own
    ga, gb = ref[2], new[2]
    row = ga.norm(dim=-1, keepdim=True)
    assert bool(((gb - ga).abs() <= 2e-4 + 2e-4 * row).all()), "dirs"
    out = sample_cube_lod(texels, dirs.view(128, 128, 3), lod.view(128, 128), compiled=True)
    assert out.shape == (128, 128, 3) and out.dtype == torch.float32


def test_gradcheck_away_from_kinks():
    """Numerical against analytic gradients of the compiled path (directions inside
    faces, LODs between levels, so no floor or clamp is crossed by the step)."""
    g = torch.Generator().manual_seed(1)
    texels = torch.rand(6, 8, 8, 2, generator=g, dtype=torch.float64).requires_grad_(True)
    dirs = torch.tensor([[0.9, 0.21, -0.33], [-0.2, 0.93, 0.4], [0.1, -0.3, -0.95]],
                        dtype=torch.float64).requires_grad_(True)  # fmt: skip
    lod = torch.tensor([0.3, 1.6, 2.45], dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda t, d, lo: sample_cube_lod(t, d, lo, compiled=True), (texels, dirs, lod)
    )


def test_nan_lod_gives_nan_like_the_reference():
    texels, dirs, lod = inputs(8, 20, torch.float64)
    lod[10] = float("nan")
    for compiled in (False, True):
        out = sample_cube_lod(texels, dirs, lod, compiled=compiled)
        assert torch.isnan(out[10]).all() and torch.isfinite(out[11:]).all()


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_sample_cube_compiled_matches_the_torch_lookup(dtype, tol):
    """The one-level case (no roughness): ``sample_cube`` through the same kernel."""
    texels, dirs, _ = inputs(16, 3000, dtype, seed=5)
    grad_out = torch.randn(3000, 3, dtype=dtype)
    out = {}
    for compiled in (False, True):
        t = texels.clone().requires_grad_(True)
        d = dirs.clone().requires_grad_(True)
        val = sample_cube(t, d, compiled=compiled)
        (val * grad_out).sum().backward()
        out[compiled] = (val.detach(), t.grad, d.grad)
    for a, b, name in zip(out[False], out[True], ("value", "texels", "dirs"), strict=True):
        torch.testing.assert_close(b, a, rtol=tol, atol=tol, msg=name)
