"""The compiled deferred shading kernel against the PyTorch path it replaces."""

from __future__ import annotations

import pytest
import torch

from core.kernels.pool import set_kernel_threads
from core.render.envmap import EnvMap, texel_directions
from core.render.gbuffer import GBuffer
from core.render.shading import deferred_shade
from core.render.shading_compiled import can_shade_compiled
from core.scene.cameras import Camera, Intrinsics


def _camera(w: int = 40, h: int = 31) -> Camera:
    intr = Intrinsics(37.0, 41.0, 0.5 * w + 1.7, 0.5 * h - 2.3, w, h)
    return Camera.look_at([1.5, -2.0, 0.9], [0.1, 0.0, -0.05], [0, 0, 1], intr)


def _env(res: int, dtype: torch.dtype, seed: int) -> EnvMap:
    g = torch.Generator().manual_seed(seed)
    env = EnvMap(res).to(dtype)
    d = texel_directions(res, dtype)
    noise = torch.rand(6, res, res, 3, generator=g, dtype=dtype)
    env.set_texels(0.2 + d.abs() + 2.0 * noise)  # sharp texel-to-texel changes, HDR
    env.requires_grad_(False)
    return env


def _gbuffer(cam: Camera, dtype: torch.dtype, seed: int) -> GBuffer:
    g = torch.Generator().manual_seed(seed)
    h, w = cam.height, cam.width
    normal = torch.randn(h, w, 3, generator=g, dtype=dtype)
    normal[:3] *= 1e-20  # blended normals that cancelled: shrink to 0, reflect the view ray
    normal[3, :5] = 0.0
    # Normals along the cube axes and the diagonals: face ties and edges.
    axes = torch.tensor([[1, 0, 0], [0, -1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 1]], dtype=dtype)
    normal[4, : len(axes)] = axes @ cam.R.to(dtype).T
    alpha = torch.rand(h, w, generator=g, dtype=dtype)
    alpha[5] = 0.0
    z = torch.zeros(h, w, dtype=dtype)
    return GBuffer(
        base=torch.rand(h, w, 3, generator=g, dtype=dtype) * alpha[..., None],
        normal=normal,
        plane_dist=z,
        w_r=torch.rand(h, w, generator=g, dtype=dtype) * alpha,
        alpha=alpha,
        camera=cam,
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed,res", [(0, 1), (1, 4), (2, 16)])
def test_compiled_shading_matches_the_pytorch_path(dtype, seed, res):
    set_kernel_threads(3)  # rows split over workers (reset after each test)
    cam = _camera()
    gb = _gbuffer(cam, dtype, seed)
    env = _env(res, dtype, seed)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    with torch.no_grad():
        assert can_shade_compiled((gb.base, gb.normal, gb.w_r, gb.alpha), env)
        got = deferred_shade(gb, env, bg)
        want = deferred_shade(gb, env, bg, compiled=False)
    # float64 intermediates vs the PyTorch path's own dtype: float32 differs by rounding.
    tol = dict(rtol=2e-5, atol=2e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    for name in ("final", "specular", "reflected_dir"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        torch.testing.assert_close(a, b, **tol, msg=name)
    assert torch.isfinite(got.final).all()


def test_degenerate_directions_give_zero_radiance_as_in_pytorch():
    """NaN normals: no radiance from the env map (the PyTorch lookup returns 0 there)."""
    cam = _camera(8, 6)
    gb = _gbuffer(cam, torch.float32, 3)
    gb.normal[2, 2] = float("nan")
    env = _env(4, torch.float32, 3)
    bg = torch.zeros(3)
    with torch.no_grad():
        got = deferred_shade(gb, env, bg)
        want = deferred_shade(gb, env, bg, compiled=False)
    assert float(got.specular[2, 2].abs().max()) == 0.0
    torch.testing.assert_close(got.specular, want.specular, rtol=2e-5, atol=2e-5)
    torch.testing.assert_close(got.final, want.final, rtol=2e-5, atol=2e-5, equal_nan=True)


def test_gradients_keep_the_differentiable_path():
    """Training shades with gradients: the kernel must step aside, or nothing would learn."""
    cam = _camera(8, 6)
    gb = _gbuffer(cam, torch.float32, 4)
    env = _env(4, torch.float32, 4)
    env.requires_grad_(True)
    tensors = (gb.base, gb.normal, gb.w_r, gb.alpha)
    assert not can_shade_compiled(tensors, env)
    out = deferred_shade(gb, env, torch.zeros(3))
    out.final.sum().backward()
    assert env.log_radiance.grad is not None and float(env.log_radiance.grad.abs().sum()) > 0
    with torch.no_grad():
        assert can_shade_compiled(tensors, env)
