"""The compiled reflected directions and LOD (training's deferred shading) against the
torch path, values and gradients, and a whole shaded frame both ways."""

from __future__ import annotations

import pytest
import torch

from core.kernels.pool import set_kernel_threads
from core.render.envmap import EnvMap
from core.render.envmap_mips import lod_scale, mip_sizes
from core.render.gbuffer import GBuffer
from core.render.reflection_compiled import reflection_and_lod
from core.render.shading import deferred_shade, pixel_lod, reflect, world_normals
from core.scene.cameras import Camera, Intrinsics

RES = 16  # env map face size


def _buffers(dtype: torch.dtype, seed: int = 0):
    """A (24, 32) G-buffer's blended channels as strided views of one (H, W, 6) pass,
    with the awkward pixels: zero and tiny normals, no coverage, ρ above alpha."""
    g = torch.Generator().manual_seed(seed)
    cam = Camera.look_at(
        [1.5, -3.0, 1.0], [0, 0, 0], [0, 0, 1], Intrinsics(30, 28, 15.2, 12.7, 32, 24)
    )
    raw = torch.empty(24, 32, 6, dtype=dtype)
    raw[..., :3] = torch.randn(24, 32, 3, generator=g, dtype=dtype)
    raw[..., 3] = torch.rand(24, 32, generator=g, dtype=dtype)  # alpha
    raw[..., 4] = torch.rand(24, 32, generator=g, dtype=dtype) * raw[..., 3] * 1.1  # ρ·alpha
    raw[..., 5] = torch.rand(24, 32, generator=g, dtype=dtype)  # w_r
    raw[0, :4, :3] = 0.0  # zero normal: the reflection is the view ray
    raw[1, :4, :3] = 1e-14  # below safe_normalize's floor
    raw[2, :4, 3] = 0.0  # uncovered
    raw[3, :4, 3] = 1e-7  # below pixel_roughness's threshold
    return cam, raw


def _torch_path(normal, rough, alpha, cam):
    _, view = cam.world_rays(dtype=normal.dtype)
    nw = world_normals(
        GBuffer(base=normal, normal=normal, plane_dist=alpha, w_r=alpha, alpha=alpha, camera=cam)
    )
    refl = reflect(view, nw)
    return refl, pixel_lod(rough, alpha, RES)


@pytest.mark.parametrize("holes", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_directions_lod_and_gradients_match_torch(dtype, holes):
    """``holes``: pixels no gradient reaches (skipped by the backward), and pixels only
    the LOD's gradient reaches (not skipped)."""
    set_kernel_threads(2)
    cam, raw = _buffers(dtype)
    leaves = [raw.clone().requires_grad_(True) for _ in range(2)]
    outs = []
    for k, leaf in enumerate(leaves):
        normal, alpha, rough = leaf[..., :3], leaf[..., 3], leaf[..., 4]
        if k == 0:
            top = len(mip_sizes(RES)) - 1
            outs.append(reflection_and_lod(normal, rough, alpha, cam, lod_scale(RES), top))
        else:
            outs.append(_torch_path(normal, rough, alpha, cam))
    (refl_c, lod_c), (refl_t, lod_t) = outs
    tol = dict(rtol=1e-5, atol=2e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(refl_c, refl_t, **tol)
    torch.testing.assert_close(lod_c, lod_t, **tol)
    assert (lod_c > 0).any() and (lod_c == len(mip_sizes(RES)) - 1).any()  # some clamp at the top
    g = torch.Generator().manual_seed(5)
    g_refl = torch.randn(refl_c.shape, generator=g, dtype=dtype)
    g_lod = torch.randn(lod_c.shape, generator=g, dtype=dtype)
    if holes:
        g_refl[:, ::2] = 0.0
        g_lod[:, ::4] = 0.0  # every other hole has the LOD's gradient only
    for refl, lod in outs:
        ((refl * g_refl).sum() + (lod * g_lod).sum()).backward()
    grad_c, grad_t = leaves[0].grad, leaves[1].grad
    # the tiny-normal row has gradients of ~1e12 in both: compare it relatively
    torch.testing.assert_close(
        grad_c[1], grad_t[1], rtol=1e-4 if dtype == torch.float32 else 1e-9, atol=0
    )
    keep = torch.ones(24, dtype=torch.bool)
    keep[1] = False
    torch.testing.assert_close(grad_c[keep][..., :5], grad_t[keep][..., :5], **tol)
    assert not grad_c[..., 5].any()  # w_r is not an input


def test_without_roughness_only_directions_come_back():
    cam, raw = _buffers(torch.float64, 1)
    leaf = raw.clone().requires_grad_(True)
    refl, lod = reflection_and_lod(leaf[..., :3], None, leaf[..., 3], cam, lod_scale(RES), 3.0)
    assert lod is None
    refl.sum().backward()
    assert leaf.grad[..., :3].abs().sum() > 0 and not leaf.grad[..., 3:].any()


@pytest.mark.parametrize("with_roughness", [False, True])
def test_training_frame_shades_as_the_torch_path(with_roughness):
    """deferred_shade with gradients (a training step): final image and the gradients
    of every G-buffer channel and of the env map equal the torch path's."""
    cam, raw = _buffers(torch.float64, 2)
    envs, leaves, finals = [], [], []
    for compiled in (True, False):
        env = EnvMap(RES).to(torch.float64)
        leaf = raw.clone().requires_grad_(True)
        base = leaf[..., :3].abs() * 0.3
        gb = GBuffer(
            base=base, normal=leaf[..., :3], plane_dist=leaf[..., 3], w_r=leaf[..., 5],
            alpha=leaf[..., 3], camera=cam, roughness=leaf[..., 4] if with_roughness else None,
        )  # fmt: skip
        out = deferred_shade(
            gb, env, torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64), compiled=compiled
        )
        (
            out.final
            * torch.linspace(-1, 1, out.final.numel(), dtype=torch.float64).reshape(out.final.shape)
        ).sum().backward()
        envs.append(env)
        leaves.append(leaf)
        finals.append(out.final.detach())
    torch.testing.assert_close(finals[0], finals[1], rtol=1e-10, atol=1e-10)
    keep = torch.ones(24, dtype=torch.bool)
    keep[1] = False  # tiny normals: ~1e12 gradients, compared relatively above
    torch.testing.assert_close(leaves[0].grad[keep], leaves[1].grad[keep], rtol=1e-8, atol=1e-8)
    ga, gb_ = (next(e.parameters()).grad for e in envs)
    torch.testing.assert_close(ga, gb_, rtol=1e-9, atol=1e-9)
