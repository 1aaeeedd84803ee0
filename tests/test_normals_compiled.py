"""Compiled Eq. 6 normals against the torch path: values and quaternion gradients."""

from __future__ import annotations

import math

import pytest
import torch

from core.render.gaussians import PARAM_SHAPES, Gaussians


def model(n: int, dtype: torch.dtype, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    params = {k: torch.randn(n, *s, generator=g, dtype=dtype) for k, s in PARAM_SHAPES.items()}
    params["quats"][:3] = torch.tensor([[0, 0, 0, 0], [1e-14, 0, 0, 0], [0, 0, 3, 0]], dtype=dtype)
    params["log_scales"][3:6] = torch.tensor([[1, 1, 1], [2, 0, 0], [0, 3, 0]], dtype=dtype)  # ties
    return Gaussians(params, sh_degree=0)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_matches_the_torch_normals_and_their_gradient(dtype, tol):
    g = model(20_000, dtype)
    grad_out = torch.randn(20_000, 3, dtype=dtype)
    got = {}
    for compiled in (False, True):
        g.params["quats"].grad = None
        n = g.normals(compiled=compiled)
        (n * grad_out).sum().backward()
        got[compiled] = (n.detach(), g.params["quats"].grad.clone())
        assert g.params["log_scales"].grad is None  # the axis choice has no gradient
    for a, b in zip(got[False], got[True], strict=True):
        torch.testing.assert_close(b, a, rtol=tol, atol=tol)
    assert float(got[True][1][:2].abs().sum()) == 0.0  # degenerate quaternions: none


def test_stated_answers():
    """The identity's smallest axis is that axis; 90° about z turns x onto y."""
    params = {k: torch.zeros(2, *s, dtype=torch.float64) for k, s in PARAM_SHAPES.items()}
    params["quats"][0] = torch.tensor([1.0, 0, 0, 0])
    params["quats"][1] = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    params["log_scales"][0] = torch.tensor([0.0, 0.0, -5.0])
    params["log_scales"][1] = torch.tensor([-5.0, 0.0, 0.0])
    n = Gaussians(params, 0).normals(compiled=True).detach()
    torch.testing.assert_close(n, torch.tensor([[0.0, 0, 1], [0, 1, 0]], dtype=torch.float64))


def test_gradcheck():
    g = model(6, torch.float64, seed=2)
    s = g.params["log_scales"].detach()
    from core.render.normals_compiled import normals_compiled

    q = g.params["quats"].detach()[3:].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: normals_compiled(x, s[3:]), (q,))
