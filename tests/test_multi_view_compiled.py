"""L_multi's compiled round trip against the torch definition: value, stats, gradients."""

from __future__ import annotations

import pytest
import torch

from core.training.losses import multi_view_loss

from .test_losses import _plane_depth_world, _two_views


def depths(dtype: torch.dtype, seed: int = 0):
    """A tilted plane seen from two views, the neighbour's depth bumped and partly
    occluded (errors above the 1 px cut), holes in both valid masks."""
    g = torch.Generator().manual_seed(seed)
    ref, nb = _two_views()
    n = torch.tensor([0.2, 0.1, -1.0], dtype=torch.float64)
    n = n / n.norm()
    p = torch.zeros(3, dtype=torch.float64)
    d_ref = _plane_depth_world(ref, n, p).to(dtype)
    d_nb = _plane_depth_world(nb, n, p) * (1 + 0.01 * torch.rand(32, 32, generator=g))
    d_nb[20:, :8] *= 0.7  # an occluder: those pixels fail the 1 px test
    v_ref = torch.rand(32, 32, generator=g) > 0.1
    v_nb = torch.rand(32, 32, generator=g) > 0.1
    return ref, nb, d_ref, d_nb.to(dtype), v_ref, v_nb


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("n_pixels", [None, 300])
def test_matches_the_torch_loss(dtype, tol, weighted, n_pixels):
    ref, nb, d_ref, d_nb, v_ref, v_nb = depths(dtype)
    out = {}
    for compiled in (False, True):
        a = d_ref.clone().requires_grad_(True)
        b = d_nb.clone().requires_grad_(True)
        loss, stats = multi_view_loss(
            a, v_ref, ref, b, v_nb, nb, n_pixels=n_pixels, error_weighting=weighted,
            generator=torch.Generator().manual_seed(3), compiled=compiled,
        )  # fmt: skip
        loss.backward()
        out[compiled] = (loss.detach(), a.grad, b.grad, stats)
    (l0, ga0, gb0, s0), (l1, ga1, gb1, s1) = out[False], out[True]
    assert s1 == s0 and 0 < s1["kept"] < s1["pixels"]
    torch.testing.assert_close(l1, l0, rtol=tol, atol=tol)
    torch.testing.assert_close(ga1, ga0, rtol=tol, atol=tol)
    torch.testing.assert_close(gb1, gb0, rtol=tol, atol=tol)
    assert float(gb1.abs().sum()) > 0 and float(ga1.abs().sum()) > 0


def test_nothing_kept_gives_zero_and_no_gradient():
    ref, nb, d_ref, d_nb, v_ref, v_nb = depths(torch.float32)
    a = d_ref.clone().requires_grad_(True)
    b = (d_nb * 3).requires_grad_(True)
    loss, stats = multi_view_loss(a, v_ref, ref, b, v_nb, nb, compiled=True)
    loss.backward()
    assert stats["kept"] == 0.0 and float(loss.detach()) == 0.0
    assert float(a.grad.abs().sum()) == 0.0
