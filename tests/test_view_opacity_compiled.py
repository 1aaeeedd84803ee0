"""The compiled per-view opacity factors against the torch reference (facing × fade)."""

from __future__ import annotations

import math

import pytest
import torch

from core.render.gaussians import PARAM_SHAPES, Gaussians
from core.render.grazing import GRAZE_KEY, add_grazing_state
from core.render.orientation import SEEN_COUNT, SEEN_DIR, add_orientation_state
from core.render.view_opacity import view_opacity_scale
from core.scene.cameras import Camera, Intrinsics


def model(n: int, dtype: torch.dtype, seed: int = 0) -> Gaussians:
    """Random splats with orientation and grazing state spread across every branch:
    flat and round, seen by few and many views, agreeing and not, either side."""
    g = torch.Generator().manual_seed(seed)
    params = {k: torch.randn(n, *s, generator=g, dtype=dtype) for k, s in PARAM_SHAPES.items()}
    params["log_scales"] = torch.log(torch.rand(n, 3, generator=g, dtype=dtype) * 0.1 + 1e-4)
    gs = Gaussians(params, sh_degree=0)
    add_orientation_state(gs)
    add_grazing_state(gs)
    p = gs.params
    count = torch.randint(0, 8, (n,), generator=g).to(dtype)
    direction = torch.randn(n, 3, generator=g, dtype=dtype)
    agree = torch.rand(n, 1, generator=g, dtype=dtype)  # |sum| / count spans 0..1
    p[SEEN_DIR].data[:] = direction / direction.norm(dim=-1, keepdim=True) * agree * count[:, None]
    p[SEEN_COUNT].data[:] = count
    p[GRAZE_KEY].data[:] = torch.randn(n, generator=g, dtype=dtype) * 2
    return gs


def camera() -> Camera:
    return Camera.look_at([2.5, 0.7, 1.2], [0, 0, 0], [0, 0, 1], Intrinsics(60, 60, 32, 32, 64, 64))


@pytest.mark.parametrize("one_sided, grazing", [(True, True), (True, False), (False, True)])
def test_float64_matches_the_torch_reference(one_sided, grazing):
    g = model(20_000, torch.float64)
    cam = camera()
    ref = view_opacity_scale(g, cam, one_sided=one_sided, grazing=grazing, compiled=False)
    out = view_opacity_scale(g, cam, one_sided=one_sided, grazing=grazing, compiled=True)
    assert ref is not None and out is not None and out.dtype == torch.float64
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    if one_sided:  # every branch of the cull was taken
        culled = int((out == 0).sum())
        assert 0 < culled < out.numel() // 2


def test_float32_agrees_and_the_fade_keeps_its_gradient():
    g = model(20_000, torch.float32, seed=1)
    cam = camera()
    ref = view_opacity_scale(g, cam, one_sided=True, grazing=True, compiled=False)
    ref.sum().backward()
    grad_ref = g.params[GRAZE_KEY].grad.clone()
    g.params[GRAZE_KEY].grad = None
    out = view_opacity_scale(g, cam, one_sided=True, grazing=True, compiled=True)
    out.sum().backward()
    assert out.dtype == torch.float32
    # float32 against float64 arithmetic: a decision may flip only on a threshold
    assert int(((out == 0) != (ref == 0)).sum()) <= 2
    same = (out == 0) == (ref == 0)
    torch.testing.assert_close(out[same], ref[same], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(g.params[GRAZE_KEY].grad[same], grad_ref[same], rtol=1e-4, atol=1e-7)
    for key in ("means", "quats", "log_scales"):
        assert g.params[key].grad is None  # fading neither moves nor turns a splat


def test_without_state_or_switches_there_is_no_factor():
    g = model(10, torch.float32)
    cam = camera()
    assert view_opacity_scale(g, cam, one_sided=False, grazing=False, compiled=True) is None
    bare = Gaussians({k: v.detach().clone() for k, v in g.params.items() if k in PARAM_SHAPES}, 0)
    assert view_opacity_scale(bare, cam, one_sided=True, grazing=True, compiled=True) is None


def test_a_disc_seen_from_behind_is_culled_and_edge_on_fades():
    """The stated answers: a known flat disc facing +z, seen from -z, is culled; seen
    from 60° off its normal with k = 0.5 its fade is 1 − 0.5·(1 − cos 60°)² = 0.875."""
    params = {k: torch.zeros(1, *s, dtype=torch.float64) for k, s in PARAM_SHAPES.items()}
    params["quats"][0, 0] = 1.0
    params["log_scales"][0] = torch.log(torch.tensor([0.1, 0.1, 1e-4], dtype=torch.float64))
    g = Gaussians(params, 0)
    add_orientation_state(g)
    add_grazing_state(g)
    g.params[SEEN_DIR].data[:] = torch.tensor([[0.0, 0.0, 5.0]], dtype=torch.float64)
    g.params[SEEN_COUNT].data[:] = 5.0
    g.params[GRAZE_KEY].data[:] = 0.0
    intr = Intrinsics(10, 10, 5, 5, 10, 10)
    behind = Camera.look_at([0, 0, -3], [0, 0, 0], [0, 1, 0], intr)
    a = math.radians(60)
    oblique = Camera.look_at([3 * math.sin(a), 0, 3 * math.cos(a)], [0, 0, 0], [0, 1, 0], intr)
    for compiled in (True, False):
        back = view_opacity_scale(g, behind, one_sided=True, grazing=True, compiled=compiled)
        side = view_opacity_scale(g, oblique, one_sided=True, grazing=True, compiled=compiled)
        assert float(back[0].detach()) == 0.0
        assert float(side[0].detach()) == pytest.approx(0.875, abs=1e-12)
