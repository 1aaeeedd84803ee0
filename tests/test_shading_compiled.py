"""The compiled deferred shading kernel against the PyTorch path it replaces."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from core.kernels.pool import set_kernel_threads
from core.render import shading_compiled
from core.render.envmap import EnvMap, texel_directions
from core.render.envmap_mips import mip_sizes, roughness_to_lod
from core.render.gbuffer import GBuffer
from core.render.shading import deferred_shade, pixel_lod, pixel_roughness
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


def _assert_same_shading(got, want, dtype) -> None:
    """Compiled vs PyTorch shading: float64 intermediates vs the PyTorch path's own dtype,
    so float32 differs by rounding."""
    tol = dict(rtol=2e-5, atol=2e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    for name in ("final", "specular", "reflected_dir"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        torch.testing.assert_close(a, b, **tol, msg=name)
    assert torch.isfinite(got.final).all()


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
    _assert_same_shading(got, want, dtype)


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


def _integer_lod_neighbours(res: int, dtype: torch.dtype) -> list[float]:
    """ρ values whose LOD (``roughness_to_lod``, in ``dtype``) sits just below and at or
    above every interior integer level: the kernel's level switch, both sides."""
    levels = len(mip_sizes(res))
    eps = torch.finfo(dtype).eps
    out = []
    for k in range(1, levels - 1):
        rho = math.sqrt(math.sqrt(4.0**k - 1.0) / (4.0 * res / (0.5 * math.pi)))
        cand = torch.tensor(rho, dtype=dtype) * (1.0 + eps * torch.arange(-64, 65, dtype=dtype))
        lod = roughness_to_lod(cand, res, levels)
        below, above = cand[lod < k], cand[lod >= k]
        out += [float(below.max()), float(above.min())]
    return out


def _rough_gbuffer(cam: Camera, dtype: torch.dtype, seed: int, res: int) -> GBuffer:
    """``_gbuffer`` with a blended roughness: ρ spanning [0, 1] (more of it near 0, where
    the LOD changes fastest), row 5 uncovered, row 6 fully covered with ρ = 0 (LOD 0),
    ρ = 1 and above (clamped: the top level) and the integer-LOD neighbours, row 7 at
    coverages around the 1e-6 cut."""
    g = torch.Generator().manual_seed(seed + 100)
    gb = _gbuffer(cam, dtype, seed)
    h, w = cam.height, cam.width
    alpha = gb.alpha.clone()
    rho = torch.rand(h, w, generator=g, dtype=dtype).square()
    special = [0.0, 1.0, 1.5, 0.0, *_integer_lod_neighbours(res, dtype)]
    alpha[6, : len(special)] = 1.0
    rho[6, : len(special)] = torch.tensor(special, dtype=dtype)
    alpha[7, :4] = torch.tensor([1e-7, 1e-6, 2e-6, 1e-5], dtype=dtype)
    rho[7, :4] = 0.5
    rough = rho * alpha
    rough[5] = 0.3  # uncovered: ignored (ρ = 0) whatever the channel holds
    w_r = torch.rand(h, w, generator=g, dtype=dtype) * alpha
    return dataclasses.replace(gb, alpha=alpha, w_r=w_r, roughness=rough)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed,res", [(0, 1), (1, 4), (2, 16), (3, 12), (4, 5), (5, 6)])
def test_compiled_shading_with_roughness_matches_the_pytorch_path(dtype, seed, res):
    """Mip levels 16-8-4-2-1, 12-6-3 and 6-3 (an odd size ends the chain), 5 and 1 (one
    level): the compiled trilinear lookup against ``sample_cube_lod``."""
    set_kernel_threads(3)
    cam = _camera()
    gb = _rough_gbuffer(cam, dtype, seed, res)
    env = _env(res, dtype, seed)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    levels = len(mip_sizes(res))
    lod = pixel_lod(gb.roughness, gb.alpha, res)
    assert (lod[6, :3] == torch.tensor([0.0, levels - 1, levels - 1], dtype=dtype)).all()
    if levels > 2:  # LODs just below and at/above every interior integer level
        near = lod[6, 4 : 4 + 2 * (levels - 2)]
        assert torch.allclose(near, near.round(), atol=1e-5) and (near.frac() != 0).any()
    with torch.no_grad():
        assert can_shade_compiled((gb.base, gb.normal, gb.w_r, gb.alpha, gb.roughness), env)
        got = deferred_shade(gb, env, bg)
        want = deferred_shade(gb, env, bg, compiled=False)
        sharp = deferred_shade(dataclasses.replace(gb, roughness=None), env, bg)
    _assert_same_shading(got, want, dtype)
    # The roughness is read: where the LOD is above 0 the lookup is not the sharp one.
    blurred = (lod > 0.5) & (gb.w_r > 0.05)
    if levels > 1:
        diff = (got.specular - sharp.specular).abs().amax(dim=-1)
        assert (diff[blurred] > 1e-3).float().mean() > 0.5
    # Where ρ is 0 (uncovered, ρ = 0, coverage below the cut) it is the sharp one, exactly.
    zero = pixel_roughness(gb.roughness, gb.alpha) == 0
    assert zero[5].all() and zero[7, :2].all() and (levels == 1 or not zero[7, 2:4].any())
    assert torch.equal(got.specular[zero], sharp.specular[zero])


def test_roughness_gradient_keeps_the_differentiable_path():
    """A roughness that wants a gradient (training) sends the frame to PyTorch."""
    cam = _camera(12, 9)
    gb = _rough_gbuffer(cam, torch.float32, 6, 8)
    env = _env(8, torch.float32, 6)
    rough = gb.roughness.clone().requires_grad_(True)
    gb = dataclasses.replace(gb, roughness=rough)
    out = deferred_shade(gb, env, torch.zeros(3))
    out.final.sum().backward()
    assert rough.grad is not None and float(rough.grad.abs().sum()) > 0


def test_without_roughness_the_kernel_is_the_sharp_one(monkeypatch):
    """No roughness: no mip chain is built, and the result is bit for bit the one a zero
    roughness gives (level 0 alone, which is the lookup the kernel had before roughness)."""
    set_kernel_threads(2)
    cam = _camera()
    gb = _rough_gbuffer(cam, torch.float32, 7, 16)
    env = _env(16, torch.float32, 7)
    bg = torch.tensor([0.2, 0.5, 0.9])
    mirror = dataclasses.replace(gb, roughness=torch.zeros_like(gb.alpha))
    with torch.no_grad():
        want = deferred_shade(mirror, env, bg)

        sharp_only = shading_compiled.packed_cube_levels

        def no_chain(texels, mips):
            assert not mips, "a G-buffer without roughness built the mip chain"
            return sharp_only(texels, mips)

        monkeypatch.setattr(shading_compiled, "packed_cube_levels", no_chain)
        got = deferred_shade(dataclasses.replace(gb, roughness=None), env, bg)
    for name in ("final", "specular", "reflected_dir"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name
