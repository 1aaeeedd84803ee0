"""The compiled SH colour pass against the PyTorch one (core.render.sh.sh_to_rgb)."""

from __future__ import annotations

import pytest
import torch

from core.render.gaussians import Gaussians
from core.render.sh import sh_to_rgb
from core.render.sh_compiled import sh_colors_compiled
from core.scene.cameras import Camera, Intrinsics

CAM = torch.tensor([0.3, -3.0, 0.7], dtype=torch.float64)


def _inputs(n: int, dtype: torch.dtype, seed: int, rest_rows: int = 15):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64).to(dtype)
    dc = torch.randn(n, 1, 3, generator=g, dtype=torch.float64).to(dtype)
    rest = (0.4 * torch.randn(n, rest_rows, 3, generator=g, dtype=torch.float64)).to(dtype)
    return [t.requires_grad_(True) for t in (means, dc, rest)]


def _grads(out: torch.Tensor, inputs: list[torch.Tensor], weight: torch.Tensor) -> list:
    for t in inputs:
        t.grad = None
    out.backward(weight)
    return [torch.zeros_like(t) if t.grad is None else t.grad.clone() for t in inputs]


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize(("dtype", "tol"), [(torch.float64, 1e-12), (torch.float32, 2e-6)])
def test_matches_the_pytorch_path(degree: int, dtype: torch.dtype, tol: float):
    inputs = _inputs(400, dtype, seed=degree)
    means, dc, rest = inputs
    weight = torch.randn(400, 3, generator=torch.Generator().manual_seed(9), dtype=dtype)
    weight[::3] = 0.0  # colours no gradient reaches (culled splats): skipped, zeros
    ref = sh_to_rgb(degree, torch.cat([dc, rest], 1), means - CAM.to(dtype))
    want = _grads(ref, inputs, weight)
    out = sh_colors_compiled(degree, dc, rest, means, CAM)
    got = _grads(out, inputs, weight)
    assert out.dtype == dtype
    assert 0.02 < float((ref == 0).float().mean()) < 0.5  # the clamp is exercised
    torch.testing.assert_close(out, ref.detach(), rtol=tol, atol=tol)
    for name, a, b in zip(("means", "sh_dc", "sh_rest"), got, want, strict=True):
        scale = max(float(b.abs().max()), 1.0)
        err = float((a - b).abs().max()) / scale
        assert err <= tol, f"{name}: {err:.2e}"
    for g in got:
        assert float(g[::3].abs().max()) == 0.0
    if degree == 0:
        assert float(got[0].abs().max()) == 0.0  # the DC term does not see the direction
    unused = got[2][:, (degree + 1) ** 2 - 1 :]
    assert unused.numel() == 0 or float(unused.abs().max()) == 0.0  # rows above the degree


def test_direction_edge_cases_match():
    """A Gaussian at the camera centre, one within 1e-13 of it, and one far away."""
    inputs = _inputs(3, torch.float64, seed=4)
    with torch.no_grad():
        inputs[0][0] = CAM
        inputs[0][1] = CAM + torch.tensor([1e-13, 0.0, -1e-13], dtype=torch.float64)
        inputs[0][2] = CAM + 1e7
    means, dc, rest = inputs
    weight = torch.ones(3, 3, dtype=torch.float64)
    ref = sh_to_rgb(3, torch.cat([dc, rest], 1), means - CAM)
    want = _grads(ref, inputs, weight)
    out = sh_colors_compiled(3, dc, rest, means, CAM)
    got = _grads(out, inputs, weight)
    torch.testing.assert_close(out, ref.detach(), rtol=1e-12, atol=1e-12)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


def test_gaussians_colors_use_it_on_cpu_and_keep_degree_zero_models_working():
    pts = torch.randn(50, 3, generator=torch.Generator().manual_seed(1))
    cols = torch.rand(50, 3, generator=torch.Generator().manual_seed(2))
    cam = Camera.look_at([0, -3, 0.5], [0, 0, 0], [0, 0, 1], Intrinsics(40, 40, 20, 20, 40, 40))
    for sh_degree in (0, 3):
        gs = Gaussians.from_points(pts, cols, sh_degree=sh_degree, radius=1.0)
        with torch.no_grad():
            gs.params["sh_rest"].normal_(0.0, 0.1)
        got = gs.colors(cam)
        assert got.grad_fn is not None and "CompiledSH" in type(got.grad_fn).__name__
        want = sh_to_rgb(sh_degree, gs.sh, gs.means - cam.center.float())
        torch.testing.assert_close(got, want, rtol=2e-6, atol=2e-6)
        if sh_degree == 0:  # a degree-0 model renders its DC colour: the input colours
            torch.testing.assert_close(got, cols, rtol=1e-5, atol=1e-5)


def test_bad_shapes_say_what_was_expected():
    means, dc, rest = _inputs(5, torch.float32, seed=0, rest_rows=3)
    with pytest.raises(ValueError, match="degree 2 needs 9 SH coefficients, got 4"):
        sh_colors_compiled(2, dc, rest, means, CAM)
    with pytest.raises(ValueError, match=r"sh_dc must be \(5, 1, 3\)"):
        sh_colors_compiled(1, dc[:4], rest, means, CAM)
    with pytest.raises(ValueError, match=r"SH degree must be in 0\.\.3"):
        sh_colors_compiled(4, dc, rest, means, CAM)


def test_threads_split_the_work_without_changing_it():
    from core.kernels.pool import set_kernel_threads

    means, dc, rest = _inputs(1001, torch.float32, seed=7)
    outs = []
    for threads in (1, 3):
        set_kernel_threads(threads)
        out = sh_colors_compiled(3, dc, rest, means, CAM)
        outs.append((out.detach(), *_grads(out, [means, dc, rest], torch.ones(1001, 3))))
    for a, b in zip(*outs, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("degree", [1, 3])
def test_gradients_match_finite_differences(degree: int):
    """Independent of the PyTorch path: torch.autograd.gradcheck in float64."""
    means, dc, rest = _inputs(6, torch.float64, seed=11)

    def colors(m: torch.Tensor, d: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        return sh_colors_compiled(degree, d, r, m, CAM)

    assert torch.autograd.gradcheck(colors, (means, dc, rest))


def test_no_gaussians():
    means, dc, rest = _inputs(0, torch.float32, seed=0)
    out = sh_colors_compiled(3, dc, rest, means, CAM)
    assert out.shape == (0, 3)
    out.sum().backward()
    assert means.grad is not None and means.grad.shape == (0, 3)
