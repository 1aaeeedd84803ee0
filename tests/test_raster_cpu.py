"""The compiled "cpu" backend against the reference rasteriser (the oracle).

Forward outputs and the gradients of every rasteriser input (and of the screen-space
means) must match the reference's autograd, on random scenes that exercise the edge
cases: image sizes that are not tile multiples, Gaussians off-screen and behind the
camera, needle-flat Gaussians, opacities that hit the 0.99 clamp and early termination.
"""

from __future__ import annotations

import pytest
import torch

from core.render.raster import (
    BACKENDS,
    available_backends,
    bin_gaussians,
    covariances_from,
    project_gaussians,
    rasterize,
    resolve_backend,
)
from core.render.raster.cpu import CpuComposite, available
from core.render.raster.projection import ALPHA_MAX, T_MIN, Projected
from core.render.raster.reference import rasterize_reference
from core.scene.cameras import Camera, Intrinsics

F64 = torch.float64


def _camera(width: int, height: int) -> Camera:
    """Camera at the origin looking down +z with an off-centre principal point."""
    f = 0.9 * max(width, height)
    intr = Intrinsics(f, 1.1 * f, width / 2 + 0.7, height / 2 - 0.4, width, height)
    return Camera(intr, torch.eye(4, dtype=F64), "test")


def _scene(
    n: int,
    seed: int,
    channels: int,
    dtype: torch.dtype = F64,
    *,
    opacity: tuple[float, float] = (0.2, 0.9),
    flat: bool = False,
) -> list[torch.Tensor]:
    """Random Gaussians around z = 3: some off-screen, some behind the camera."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=F64) * torch.tensor([0.6, 0.5, 0.8], dtype=F64)
    means[:, 2] += 3.0
    means[: n // 10, 2] = -1.0 - torch.rand(n // 10, generator=g, dtype=F64)  # behind
    means[n // 10 : n // 5, 0] += 2.5  # mostly off-screen to the right
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = torch.rand(n, 3, generator=g, dtype=F64) * 0.12 + 0.02
    if flat:
        scales[:, 2] = 1e-7  # needle-flat, as PGSR-DR drives them
    lo, hi = opacity
    op = torch.rand(n, generator=g, dtype=F64) * (hi - lo) + lo
    feats = torch.rand(n, channels, generator=g, dtype=F64) * 2 - 0.5
    return [t.to(dtype) for t in (means, quats, scales, op, feats)]


def _run(backend: str, scene, cam: Camera, weights, tile_size: int = 16):
    """Forward, then backward of a weighted sum; returns outputs and all gradients."""
    params = [t.clone().requires_grad_(True) for t in scene]
    r = rasterize(*params, cam, backend=backend, tile_size=tile_size)
    r.means2d.retain_grad()
    w_feat, w_alpha = weights
    loss = (r.features * w_feat.to(r.features.dtype)).sum()
    loss = loss + (r.alpha * w_alpha.to(r.alpha.dtype)).sum()
    loss.backward()
    grads = {
        name: p.grad
        for name, p in zip(("means", "quats", "scales", "opac", "feats"), params, strict=True)
    }
    grads["means2d"] = r.means2d.grad
    return r, grads


def _weights(cam: Camera, channels: int, seed: int = 7):
    g = torch.Generator().manual_seed(seed)
    w_feat = torch.randn(cam.height, cam.width, channels, generator=g, dtype=F64)
    w_alpha = torch.randn(cam.height, cam.width, generator=g, dtype=F64)
    return w_feat, w_alpha


def _assert_grads_close(got: dict, want: dict, rtol: float, atol_rel: float) -> None:
    for name, ref in want.items():
        scale = float(ref.abs().max()) if ref.numel() else 1.0
        torch.testing.assert_close(
            got[name],
            ref,
            rtol=rtol,
            atol=atol_rel * max(scale, 1.0),
            msg=lambda m, n=name: f"{n}: {m}",
        )


@pytest.mark.parametrize(
    ("seed", "size", "channels", "flat"),
    [
        (0, (37, 29), 3, False),
        (1, (32, 32), 1, True),
        (2, (20, 41), 13, True),
    ],
)
def test_forward_and_gradients_match_reference_float64(seed, size, channels, flat):
    cam = _camera(*size)
    scene = _scene(120, seed, channels, flat=flat)
    weights = _weights(cam, channels, seed)
    r_cpu, g_cpu = _run("cpu", scene, cam, weights)
    r_ref, g_ref = _run("reference", scene, cam, weights)
    assert r_cpu.backend == "cpu"
    assert float(r_ref.alpha.detach().mean()) > 0.2  # the scene covers the image: the test can fail
    torch.testing.assert_close(r_cpu.features, r_ref.features, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(r_cpu.alpha, r_ref.alpha, rtol=1e-9, atol=1e-10)
    _assert_grads_close(g_cpu, g_ref, rtol=1e-8, atol_rel=1e-9)


@pytest.mark.parametrize("seed", [4, 5])
def test_early_termination_and_alpha_clamp_float64(seed):
    # Dense, nearly opaque Gaussians: most pixels terminate early and many centres
    # are clamped at alpha = 0.99 (o·exp(power) > 0.99).
    cam = _camera(35, 27)
    scene = _scene(220, seed, 3, opacity=(0.9, 1.0))
    scene[2][:40] *= 4.0  # wide enough that some pixel centre sits near the peak
    scene[3][:40] = 1.0
    weights = _weights(cam, 3, seed)
    r_cpu, g_cpu = _run("cpu", scene, cam, weights, tile_size=8)
    r_ref, g_ref = _run("reference", scene, cam, weights, tile_size=8)
    T = 1.0 - r_ref.alpha.detach()
    # Pixels end with T in [1e-4, 1e-2) when the next Gaussian (alpha ≤ 0.99) was cut.
    assert bool((T >= T_MIN).all()) and int((T < 1e-2).sum()) > 100
    proj = project_gaussians(scene[0], covariances_from(scene[1], scene[2]), cam)
    d = cam.pixel_centers(F64).reshape(-1, 1, 2) - proj.means2d.detach()[None]
    a, b, c = proj.conics.detach().unbind(-1)
    power = -0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) - b * d[..., 0] * d[..., 1]
    vis = proj.radii > 0
    assert bool((scene[3] * torch.exp(power) > ALPHA_MAX)[:, vis].any())  # clamp hit
    torch.testing.assert_close(r_cpu.features, r_ref.features, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(r_cpu.alpha, r_ref.alpha, rtol=1e-9, atol=1e-10)
    _assert_grads_close(g_cpu, g_ref, rtol=1e-8, atol_rel=1e-9)


@pytest.mark.parametrize(("seed", "channels"), [(6, 3), (7, 8)])
def test_float32_matches_reference(seed, channels):
    cam = _camera(40, 33)
    scene = _scene(200, seed, channels, torch.float32, flat=seed % 2 == 1)
    weights = _weights(cam, channels, seed)
    r_cpu, g_cpu = _run("cpu", scene, cam, weights)
    r_ref, g_ref = _run("reference", scene, cam, weights)
    assert r_cpu.features.dtype == torch.float32 and r_cpu.alpha.dtype == torch.float32
    torch.testing.assert_close(r_cpu.features, r_ref.features, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(r_cpu.alpha, r_ref.alpha, rtol=1e-5, atol=1e-5)
    for name in g_ref:
        assert g_cpu[name].dtype == torch.float32
    _assert_grads_close(g_cpu, g_ref, rtol=1e-4, atol_rel=1e-4)


@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["numba f64", "f32 (SIMD where built)"])
def test_pixels_no_loss_reads_walk_nothing(dtype):
    """A loss that reads scattered pixels (some their features, some their alpha): the
    backward skips the rest, and the gradients are still the reference's."""
    cam = _camera(40, 33)
    scene = _scene(200, 8, 4, dtype)
    w_feat, w_alpha = _weights(cam, 4, 8)
    g = torch.Generator().manual_seed(1)
    w_feat = w_feat * (torch.rand(33, 40, generator=g) < 0.3)[..., None]
    w_alpha = w_alpha * (torch.rand(33, 40, generator=g) < 0.3)
    _, g_cpu = _run("cpu", scene, cam, (w_feat, w_alpha))
    _, g_ref = _run("reference", scene, cam, (w_feat, w_alpha))
    if dtype == F64:
        _assert_grads_close(g_cpu, g_ref, rtol=1e-8, atol_rel=1e-9)
    else:
        _assert_grads_close(g_cpu, g_ref, rtol=1e-4, atol_rel=1e-4)


def test_many_channels_and_partial_requires_grad():
    cam = _camera(24, 18)
    scene = _scene(60, 8, 37)
    w = _weights(cam, 37)
    feats_cpu = scene[4].clone().requires_grad_(True)
    feats_ref = scene[4].clone().requires_grad_(True)
    r_cpu = rasterize(*scene[:4], feats_cpu, cam, backend="cpu")
    r_ref = rasterize(*scene[:4], feats_ref, cam, backend="reference")
    torch.testing.assert_close(r_cpu.features, r_ref.features, rtol=1e-9, atol=1e-10)
    (r_cpu.features * w[0]).sum().backward()
    (r_ref.features * w[0]).sum().backward()
    torch.testing.assert_close(feats_cpu.grad, feats_ref.grad, rtol=1e-9, atol=1e-10)


def test_gradcheck_tiny_float64():
    # The autograd.Function alone, with the bins fixed: means2d, conics, o, features.
    cam = _camera(11, 9)
    means, quats, scales, op, feats = _scene(5, 10, 3)
    means = means.clone()
    means[:, 2] = means[:, 2].abs() + 2.0
    means[:, :2] *= 0.3
    proj = project_gaussians(means, covariances_from(quats, scales), cam)
    bins = bin_gaussians(proj.means2d, proj.depths, proj.radii, 11, 9, tile_size=4)
    w = _weights(cam, 3, 4)

    def f(m2, con, o, fe):
        out, alpha = CpuComposite.apply(m2, con, o, fe, bins, 11, 9)
        return (out * w[0]).sum() + (alpha * w[1]).sum()

    inputs = [
        t.detach().clone().requires_grad_(True) for t in (proj.means2d, proj.conics, op, feats)
    ]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_degenerate_footprints_match_reference():
    # Screen-space inputs the projection never makes but the composite must still
    # treat like the reference: non positive-definite conics (evaluated without
    # culling), opacities at/below 1/255, an infinite opacity (alpha clamps to 0.99).
    g = torch.Generator().manual_seed(13)
    n, W, H = 40, 30, 22
    means2d = torch.rand(n, 2, generator=g, dtype=F64) * torch.tensor([W, H], dtype=F64)
    conics = torch.stack(
        [
            torch.rand(n, generator=g, dtype=F64) * 0.3 + 0.02,
            (torch.rand(n, generator=g, dtype=F64) - 0.5) * 0.05,
            torch.rand(n, generator=g, dtype=F64) * 0.3 + 0.02,
        ],
        dim=-1,
    )
    conics[:4, 1] = 0.5  # det < 0: a saddle, power > 0 on part of the tile
    conics[4:6, 0] = -0.01  # a < 0
    conics[6, :] = 0.0  # flat: power 0 everywhere
    op = torch.rand(n, generator=g, dtype=F64) * 0.8 + 0.1
    op[7] = 1 / 255 - 1e-12
    op[8] = 1 / 255
    op[9] = float("inf")
    feats = torch.rand(n, 3, generator=g, dtype=F64)
    depths = torch.rand(n, generator=g, dtype=F64) + 1.0
    radii = torch.full((n,), 7, dtype=torch.int64)
    bins = bin_gaussians(means2d, depths, radii, W, H, tile_size=8)
    proj = Projected(means2d, conics, depths, radii, torch.zeros(n, 2, 2, dtype=F64))
    f_ref, a_ref = rasterize_reference(proj, op, feats, bins, W, H)
    f_cpu, a_cpu = CpuComposite.apply(means2d, conics, op, feats, bins, W, H)
    torch.testing.assert_close(f_cpu, f_ref, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(a_cpu, a_ref, rtol=1e-9, atol=1e-10)
    # Gradients, without the infinite opacity.
    op[9] = 0.5
    leaves = [t.clone().requires_grad_(True) for t in (means2d, conics, op, feats)]
    leaves_ref = [t.clone().requires_grad_(True) for t in (means2d, conics, op, feats)]
    w = _weights(_camera(W, H), 3, 14)
    f, a = CpuComposite.apply(*leaves, bins, W, H)
    ((f * w[0]).sum() + (a * w[1]).sum()).backward()
    proj_ref = Projected(leaves_ref[0], leaves_ref[1], depths, radii, proj.cov2d)
    f, a = rasterize_reference(proj_ref, leaves_ref[2], leaves_ref[3], bins, W, H)
    ((f * w[0]).sum() + (a * w[1]).sum()).backward()
    for got, want in zip(leaves, leaves_ref, strict=True):
        torch.testing.assert_close(got.grad, want.grad, rtol=1e-8, atol=1e-9)


def test_backward_refuses_inputs_modified_in_place():
    cam = _camera(16, 16)
    means, quats, scales, op, feats = _scene(20, 15, 2)
    proj = project_gaussians(means, covariances_from(quats, scales), cam)
    bins = bin_gaussians(proj.means2d, proj.depths, proj.radii, 16, 16)
    op = op.clone().requires_grad_(True)
    m2 = proj.means2d.detach().clone().requires_grad_(True)
    f, _ = CpuComposite.apply(m2, proj.conics.detach(), op, feats, bins, 16, 16)
    with torch.no_grad():
        op.mul_(0.5)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        f.sum().backward()


def test_empty_scenes():
    cam = _camera(19, 17)
    feats = torch.zeros(0, 4, dtype=F64, requires_grad=True)
    empty = [torch.zeros(0, k, dtype=F64) for k in (3, 4, 3)]
    r = rasterize(*empty, torch.zeros(0, dtype=F64), feats, cam, backend="cpu")
    assert r.features.shape == (17, 19, 4) and r.alpha.shape == (17, 19)
    assert r.features.abs().max() == 0 and r.alpha.abs().max() == 0
    # Everything culled (behind the camera): zero output, zero gradients.
    means, quats, scales, op, feats = _scene(10, 11, 2)
    means = means.clone()
    means[:, 2] = -2.0
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, op, feats)]
    r = rasterize(*params, cam, backend="cpu")
    (r.features.sum() + r.alpha.sum()).backward()
    assert r.alpha.abs().max() == 0
    assert all(p.grad is None or p.grad.abs().max() == 0 for p in params)


def test_results_do_not_depend_on_thread_count():
    cam = _camera(50, 38)
    scene = _scene(300, 12, 4)
    weights = _weights(cam, 4)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        r1, g1 = _run("cpu", scene, cam, weights)
        torch.set_num_threads(3)
        r3, g3 = _run("cpu", scene, cam, weights)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(r1.features, r3.features) and torch.equal(r1.alpha, r3.alpha)
    _assert_grads_close(g3, g1, rtol=1e-12, atol_rel=1e-12)


def test_registration_and_availability():
    assert "cpu" in BACKENDS and "cpu" in available_backends("cpu")
    assert resolve_backend("auto", "cpu") == "cpu"
    assert available(torch.device("cpu")) is None
    reason = available(torch.device("cuda", 0))
    assert reason is not None and "CPU tensors only" in reason and "cuda:0" in reason


def test_the_backward_reduction_adds_workers_in_order_and_rounds_once():
    """``_reduce_split_range`` (the compositing backward's last pass) gives what adding
    the workers' float64 buffers in order and converting each slice gave, bit for bit."""
    import numpy as np

    from core.render.raster.cpu import _reduce_split_range

    rng = np.random.default_rng(3)
    n, n_ch = 257, 5
    for workers in (1, 2, 3):
        gbuf = rng.standard_normal((workers, n, 6 + n_ch)) * 10.0 ** rng.integers(-8, 8, (1, n, 1))
        want = gbuf[0].copy()
        for w in range(1, workers):
            np.add(want, gbuf[w], out=want)
        for dtype in (np.float32, np.float64):
            parts = [np.empty((n, k), dtype) for k in (2, 3, 1, n_ch)]
            _reduce_split_range(0, n, gbuf, *parts)
            ref = torch.from_numpy(want)
            slices = (ref[:, 0:2], ref[:, 2:5], ref[:, 5:6], ref[:, 6:])
            for got, exp in zip(parts, slices, strict=True):
                assert torch.equal(torch.from_numpy(got), exp.to(torch.from_numpy(got).dtype))
