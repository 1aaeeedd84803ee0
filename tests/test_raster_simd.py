"""The SIMD compositing kernels (forward, backward) against the reference and numba.

The kernel's only intended difference from the exact kernels is its polynomial exp
(about 2 float32 ulps), so outputs and gradients must agree to float32 rounding on
random scenes
with the edge cases of test_raster_cpu: image sizes that are not tile multiples,
Gaussians off-screen and behind the camera, needle-flat ones, the 0.99 clamp, early
termination, degenerate conics and NaN inputs. Every vector width the source can
build for (16, 8, 4 lanes on x86) is checked, and the dispatch must keep every call
that needs a gradient or float64 on the exact kernel.
"""

from __future__ import annotations

import ctypes
import platform

import numpy as np
import pytest
import torch

from core.kernels import native_build
from core.render.raster import (
    bin_gaussians,
    covariances_from,
    cpu_simd,
    project_gaussians,
    rasterize,
)
from core.render.raster.cpu import _Setup, rasterize_cpu
from core.render.raster.projection import T_MIN, Projected
from core.render.raster.reference import rasterize_reference
from tests.test_raster_cpu import _camera, _scene

F32 = torch.float32

pytestmark = pytest.mark.skipif(
    cpu_simd.why_unavailable() is not None,
    reason=f"SIMD kernel not built here: {cpu_simd.why_unavailable()}",
)


def _projected(scene, cam):
    means, quats, scales, op, feats = scene
    proj = project_gaussians(means, covariances_from(quats, scales), cam)
    bins = bin_gaussians(proj.means2d, proj.depths, proj.radii, cam.width, cam.height)
    return proj, op * proj.compensation, feats, bins


def _all_three(proj, op, feats, bins, w, h):
    """(SIMD, numba, reference) outputs of one composite, without gradients."""
    with torch.no_grad():
        simd = rasterize_cpu(proj, op, feats, bins, w, h, simd=True)
        exact = rasterize_cpu(proj, op, feats, bins, w, h, simd=False)
        ref = rasterize_reference(proj, op, feats, bins, w, h)
    return simd, exact, ref


def _assert_close(got, want, tol: float = 2e-6) -> None:
    torch.testing.assert_close(got[0], want[0], rtol=0, atol=tol)
    torch.testing.assert_close(got[1], want[1], rtol=0, atol=tol)


@pytest.mark.parametrize(
    ("seed", "size", "channels", "flat"),
    [
        (0, (37, 29), 3, False),
        (1, (32, 32), 1, True),
        (2, (20, 41), 9, True),
        (3, (70, 45), 17, False),
    ],
)
def test_matches_numba_and_reference(seed, size, channels, flat):
    cam = _camera(*size)
    scene = _scene(300, seed, channels, F32, flat=flat)
    proj, op, feats, bins = _projected(scene, cam)
    simd, exact, ref = _all_three(proj, op, feats, bins, *size)
    assert float(ref[1].mean()) > 0.2  # the scene covers the image: the test can fail
    assert simd[0].dtype == F32 and simd[0].shape == (size[1], size[0], channels)
    _assert_close(simd, exact)
    _assert_close(simd, ref, tol=1e-5)


@pytest.mark.parametrize("seed", [4, 5])
def test_early_termination_and_clamp(seed):
    cam = _camera(35, 27)
    scene = _scene(400, seed, 3, F32, opacity=(0.9, 1.0))
    scene[2][:60] *= 4.0
    scene[3][:60] = 1.0  # alpha clamps at 0.99 near these centres
    proj, op, feats, bins = _projected(scene, cam)
    simd, exact, ref = _all_three(proj, op, feats, bins, 35, 27)
    T = 1.0 - simd[1]
    assert bool((T >= T_MIN * (1 - 1e-5)).all()) and int((T < 1e-2).sum()) > 100
    _assert_close(simd, exact)
    _assert_close(simd, ref, tol=1e-5)


def test_degenerate_and_nan_inputs_match_numba():
    # Non positive-definite conics (evaluated without culling), opacities at 1/255,
    # above 1, huge and infinite (alpha = inf · exp(power) is NaN where exp underflows),
    # NaN opacity, NaN centre, NaN conic: each kernel must skip or keep them alike.
    g = torch.Generator().manual_seed(13)
    n, W, H = 60, 45, 33
    means2d = torch.rand(n, 2, generator=g) * torch.tensor([W, H], dtype=F32)
    conics = torch.stack(
        [torch.rand(n, generator=g) * 0.3 + 0.02, (torch.rand(n, generator=g) - 0.5) * 0.05,
         torch.rand(n, generator=g) * 0.3 + 0.02], dim=-1,
    )  # fmt: skip
    conics[:4, 1] = 0.5  # saddle: power > 0 on part of the tile
    conics[4:6, 0] = -0.01
    conics[6, :] = 0.0  # power 0 everywhere
    conics[7, 2] = float("nan")
    op = torch.rand(n, generator=g) * 0.8 + 0.1
    op[8] = 1 / 255
    op[9] = float("nan")
    means2d[10, 0] = float("nan")
    op[11], op[12], op[13] = 5.0, 1e36, float("inf")
    conics[12:14, 1] = 0.0  # huge/infinite opacity with and without culling
    conics[13, 0] = -0.02
    feats = torch.rand(n, 5, generator=g)
    depths = torch.rand(n, generator=g) + 1.0
    radii = torch.full((n,), 9, dtype=torch.int64)
    bins = bin_gaussians(means2d, depths, radii, W, H)
    proj = Projected(means2d, conics, depths, radii, torch.zeros(n, 2, 2))
    simd, exact, ref = _all_three(proj, op, feats, bins, W, H)
    assert bool(torch.isfinite(simd[0]).all())
    _assert_close(simd, exact)
    _assert_close(simd, ref, tol=1e-5)


def test_viewer_sized_frame_matches_numba():
    cam = _camera(256, 192)
    scene = _scene(20000, 21, 9, F32, flat=True)
    proj, op, feats, bins = _projected(scene, cam)
    with torch.no_grad():
        simd = rasterize_cpu(proj, op, feats, bins, 256, 192, simd=True)
        exact = rasterize_cpu(proj, op, feats, bins, 256, 192, simd=False)
    # Pixels integrate hundreds of Gaussians: rounding differences add up a little.
    _assert_close(simd, exact, tol=2e-5)
    assert float((simd[0] - exact[0]).abs().mean()) < 1e-7


def _native_widths() -> list[tuple[str, ...]]:
    """Builds that force narrower vectors on this x86 machine (16, 8 and 4 lanes), and
    the lane sums older compilers (no ``__builtin_shufflevector``) build instead."""
    fallback = ("-DGLINT_NO_SHUFFLEVECTOR",)
    if platform.machine() not in ("x86_64", "AMD64"):
        return [(), fallback]
    return [(), ("-mno-avx512f",), ("-mno-avx512f", "-mno-avx"), fallback]


@pytest.mark.parametrize("flags", _native_widths(), ids=lambda f: " ".join(f) or "native")
def test_every_vector_width_gives_the_same_frame(flags):
    lib = cpu_simd.library(flags)
    assert lib is not None, native_build.why_unavailable(cpu_simd.SOURCE, flags)
    cam = _camera(83, 61)
    scene = _scene(800, 30, 6, F32)
    proj, op, feats, bins = _projected(scene, cam)
    with torch.no_grad():
        exact = rasterize_cpu(proj, op, feats, bins, 83, 61, simd=False)
    setup = _Setup(proj.means2d, proj.conics, op, feats, bins, 83, 61, F32)
    out_feat = np.zeros((61, 83, 6), np.float32)
    out_T = np.ones((61, 83), np.float32)
    cpu_simd.composite(setup.args(), 2, out_feat, out_T, lib=lib)
    _assert_close((torch.from_numpy(out_feat), 1 - torch.from_numpy(out_T)), exact)


@pytest.mark.parametrize("flags", _native_widths(), ids=lambda f: " ".join(f) or "native")
def test_every_vector_width_gives_the_same_gradients(flags):
    """The backward at 16, 8 and 4 lanes a vector against numba's float64 backward."""
    lib = cpu_simd.library(flags)
    assert lib is not None, native_build.why_unavailable(cpu_simd.SOURCE, flags)
    W, H, C = 83, 61, 5
    scene = _scene(600, 31, C, F32, flat=True)
    proj, op, feats, bins = _projected(scene, _camera(W, H))
    _, want = _train(proj, op, feats, bins, W, H, simd=False)
    setup = _Setup(proj.means2d, proj.conics, op, feats, bins, W, H, F32)
    comp = cpu_simd.SimdComposite(setup.args(), W, H, lib)
    out_feat, out_T = np.zeros((H, W, C), np.float32), np.ones((H, W), np.float32)
    last = np.zeros((H, W), np.int32)
    comp.forward(2, out_feat, out_T, last)
    gen = torch.Generator().manual_seed(3)  # the weights _train puts on (features, alpha)
    wf = torch.randn(H, W, C, generator=gen).numpy()
    wa = torch.randn(H, W, generator=gen).numpy()
    gbuf = np.zeros((2, comp.n, 6 + C), np.float64)
    comp.backward(2, out_T, last, wf, wa, gbuf)
    g = torch.from_numpy(gbuf.sum(0)).float()
    got = [g[:, 0:2], g[:, 2:5], g[:, 5], g[:, 6:]]
    _assert_grads(got, want)


def test_thread_count_does_not_change_the_frame():
    cam = _camera(50, 38)
    scene = _scene(300, 12, 4, F32)
    proj, op, feats, bins = _projected(scene, cam)
    setup = _Setup(proj.means2d, proj.conics, op, feats, bins, 50, 38, F32)
    outs = []
    for threads in (1, 3):
        f, t = np.zeros((38, 50, 4), np.float32), np.ones((38, 50), np.float32)
        cpu_simd.composite(setup.args(), threads, f, t)
        outs.append((f, t))
    assert np.array_equal(outs[0][0], outs[1][0]) and np.array_equal(outs[0][1], outs[1][1])


def test_dispatch_float32_to_simd_float64_to_numba(monkeypatch):
    calls = []
    real = cpu_simd.composite
    monkeypatch.setattr(cpu_simd, "composite", lambda *a, **k: (calls.append(1), real(*a, **k)))
    cam = _camera(30, 20)
    scene = _scene(80, 3, 3, F32)
    with torch.no_grad():
        r = rasterize(*scene, cam, backend="cpu")
    assert len(calls) == 1 and r.features.grad_fn is None
    backs = []
    real_back = cpu_simd.SimdComposite.backward
    monkeypatch.setattr(
        cpu_simd.SimdComposite, "backward", lambda *a: (backs.append(1), real_back(*a))[1]
    )
    params = [t.clone().requires_grad_(True) for t in scene]
    r = rasterize(*params, cam, backend="cpu")  # training: the SIMD pair, via autograd
    assert len(calls) == 1 and r.features.grad_fn is not None
    r.features.sum().backward()
    assert len(backs) == 1 and params[4].grad is not None
    r = rasterize(*[t.double().requires_grad_() for t in scene], cam, backend="cpu")
    r.features.sum().backward()  # float64: numba, both ways
    assert len(calls) == 1 and len(backs) == 1
    with torch.no_grad():
        proj, op, feats, bins = _projected(scene, cam)
        with pytest.raises(RuntimeError, match="does not apply"):
            rasterize_cpu(proj, op.double(), feats, bins, 30, 20, simd=True)
        small = bin_gaussians(proj.means2d, proj.depths, proj.radii, 30, 20, tile_size=8)
        rasterize_cpu(proj, op, feats, small, 30, 20)  # 8-px tiles: numba
        assert len(calls) == 1


def _screen_space(means2d, conics, op, feats, w, h):
    n = means2d.shape[0]
    depths = torch.linspace(1.0, 2.0, n)
    radii = torch.full((n,), max(w, h), dtype=torch.int64)
    bins = bin_gaussians(means2d, depths, radii, w, h)
    return Projected(means2d, conics, depths, radii, torch.zeros(n, 2, 2)), op, feats, bins


def _tuned(seed, n, k_lo, k_span, offsets, value, channels):
    """Isotropic Gaussians whose o·exp(power) at one pixel each (offset by ``offsets``
    from the centre's pixel) lies within ±5e-7 relative of ``value``."""
    g = torch.Generator().manual_seed(seed)
    W, H = 64, 48
    means2d = torch.rand(n, 2, generator=g) * torch.tensor([W, H], dtype=F32)
    k = torch.rand(n, generator=g) * k_span + k_lo
    conics = torch.stack([k, torch.zeros(n), k], dim=-1)
    target = means2d.floor() + 0.5 + torch.randint(*offsets, (n, 2), generator=g)
    d2 = ((target - means2d) ** 2).sum(-1).double()
    rel = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 1e-6
    op = (value * (1 + rel) / torch.exp(-0.5 * k.double() * d2)).float()
    feats = torch.rand(n, channels, generator=g) + 0.5
    return (*_screen_space(means2d, conics, op, feats, W, H), W, H)


def test_alphas_at_the_cutoff_decide_as_the_exact_kernel():
    # Each Gaussian's opacity puts one pixel's alpha within a few ulps of 1/255, where
    # the vector exp (2 ulps off) alone could decide differently: a whole 1/255 of
    # colour. Such lanes take libm's expf, so every decision matches numba's.
    *scene, W, H = _tuned(5, 400, 0.05, 0.2, (-3, 4), 1 / 255, 3)
    simd, exact, ref = _all_three(*scene, W, H)
    _assert_close(simd, exact)
    _assert_close(simd, ref, tol=1e-5)


@pytest.mark.parametrize("opacity", [1e36, float("inf")])
def test_huge_opacities_follow_libm(opacity):
    # o · exp(power) with o = 1e36 still reaches 1/255 at power ≈ -88, below the
    # vector exp's range; an infinite o gives alpha 0.99 until expf underflows to 0
    # (inf · 0 = NaN: skipped). One Gaussian, wide enough that both happen on screen.
    W, H = 64, 48
    means2d = torch.tensor([[30.3, 24.7]])
    conics = torch.tensor([[0.8, 0.05, 0.9]])
    op = torch.tensor([opacity])
    feats = torch.tensor([[1.0, 0.5]])
    simd, exact, ref = _all_three(*_screen_space(means2d, conics, op, feats, W, H), W, H)
    covered = float(simd[1].gt(0).float().mean())
    assert 0.2 < covered < 0.95  # the cut-off ring lies inside the image
    _assert_close(simd, exact)
    _assert_close(simd, ref, tol=1e-5)


def test_prebuilt_levels_give_the_same_frame(tmp_path):
    # The variants an image ships (python -m core.kernels.native_build --prebuild), each run
    # where this CPU supports it.
    if not native_build._levels():
        pytest.skip(f"no prebuilt levels for {platform.machine()}")
    native_build.prebuild(tmp_path, (cpu_simd.SOURCE,))
    cam = _camera(83, 61)
    scene = _scene(800, 31, 6, F32, flat=True)
    proj, op, feats, bins = _projected(scene, cam)
    with torch.no_grad():
        exact = rasterize_cpu(proj, op, feats, bins, 83, 61, simd=False)
    setup = _Setup(proj.means2d, proj.conics, op, feats, bins, 83, 61, F32)
    ran = 0
    for level, needs in native_build._levels():
        if not needs <= native_build._cpu_flags():
            continue
        lib = ctypes.CDLL(str(tmp_path / native_build._prebuilt_name(cpu_simd.SOURCE, level)))
        cpu_simd._set_signatures(lib)
        out_feat = np.zeros((61, 83, 6), np.float32)
        out_T = np.ones((61, 83), np.float32)
        cpu_simd.composite(setup.args(), 2, out_feat, out_T, lib=lib)
        _assert_close((torch.from_numpy(out_feat), 1 - torch.from_numpy(out_T)), exact)
        ran += 1
    assert ran >= 1


def _train(proj, op, feats, bins, w, h, simd, seed=3):
    """Forward + backward of a weighted sum through the CPU composite alone."""
    leaves = [t.detach().clone().requires_grad_(True) for t in (proj.means2d, proj.conics,
                                                               op, feats)]  # fmt: skip
    p = Projected(leaves[0], leaves[1], proj.depths, proj.radii, proj.cov2d)
    f, a = rasterize_cpu(p, leaves[2], leaves[3], bins, w, h, simd=simd)
    gen = torch.Generator().manual_seed(seed)
    wf = torch.randn(f.shape, generator=gen)
    wa = torch.randn(a.shape, generator=gen)
    ((f * wf).sum() + (a * wa).sum()).backward()
    return (f.detach(), a.detach()), [t.grad for t in leaves]


def _assert_grads(got, want, rtol=1e-4, atol_rel=1e-5):
    for name, g, r in zip(("means2d", "conics", "opacities", "features"), got, want, strict=True):
        scale = max(float(r.abs().max()), 1.0)
        torch.testing.assert_close(g, r, rtol=rtol, atol=atol_rel * scale,
                                   msg=lambda m, n=name: f"{n}: {m}")  # fmt: skip


@pytest.mark.parametrize(
    ("seed", "size", "channels", "flat", "opacity"),
    [
        (0, (37, 29), 3, False, (0.2, 0.9)),
        (1, (32, 32), 1, True, (0.2, 0.9)),
        (2, (50, 41), 9, True, (0.2, 0.9)),
        (3, (45, 38), 17, False, (0.9, 1.0)),  # early termination and the 0.99 clamp
    ],
)
def test_training_gradients_match_numba_and_reference(seed, size, channels, flat, opacity):
    cam = _camera(*size)
    scene = _scene(300, seed, channels, F32, flat=flat, opacity=opacity)
    if opacity[0] > 0.5:
        scene[2][:60] *= 4.0
        scene[3][:60] = 1.0
    proj, op, feats, bins = _projected(scene, cam)
    out_s, g_s = _train(proj, op, feats, bins, *size, simd=True)
    out_n, g_n = _train(proj, op, feats, bins, *size, simd=False)
    _assert_close(out_s, out_n)
    _assert_grads(g_s, g_n)
    # and against the reference's autograd, in float64
    leaves = [t.detach().double().requires_grad_(True) for t in (proj.means2d, proj.conics,
                                                                op, feats)]  # fmt: skip
    p = Projected(leaves[0], leaves[1], proj.depths, proj.radii, proj.cov2d)
    f, a = rasterize_reference(p, leaves[2], leaves[3], bins, *size)
    gen = torch.Generator().manual_seed(3)
    wf = torch.randn(f.shape, generator=gen)
    wa = torch.randn(a.shape, generator=gen)
    ((f * wf.double()).sum() + (a * wa.double()).sum()).backward()
    _assert_grads(g_s, [t.grad.float() for t in leaves], rtol=1e-3, atol_rel=1e-4)


def test_float32_backward_state_holds_over_hundreds_of_faint_layers():
    """The SIMD backward keeps T and the suffix sum in float32 (3DGS's CUDA kernel does
    too), rebuilding T_before = T_after / (1 - alpha) once per layer. Stacks of ~600
    faint splats (alpha 0.01-0.02 per layer, so T falls through 1e-4 only after
    hundreds of layers) must still give the float64 reference's gradients."""
    g = torch.Generator().manual_seed(21)
    n, W, H = 1800, 32, 32
    means2d = torch.rand(n, 2, generator=g) * 8 + 12  # all on the middle tiles
    k = torch.rand(n, generator=g) * 0.01 + 0.01  # wide: every splat covers every pixel
    conics = torch.stack([k, torch.zeros(n), k], dim=-1)
    op = torch.rand(n, generator=g) * 0.01 + 0.01
    feats = torch.rand(n, 5, generator=g)
    proj, op, feats, bins = _screen_space(means2d, conics, op, feats, W, H)
    out_s, g_s = _train(proj, op, feats, bins, W, H, simd=True)
    out_n, g_n = _train(proj, op, feats, bins, W, H, simd=False)
    assert float(out_s[1][8:24, 8:24].min()) > 0.99  # deep stacks: the middle is covered
    _assert_close(out_s, out_n, tol=1e-5)
    _assert_grads(g_s, g_n)


def test_training_backward_is_deterministic_across_threads():
    cam = _camera(50, 38)
    scene = _scene(300, 12, 4, F32, flat=True)
    proj, op, feats, bins = _projected(scene, cam)
    from core.kernels.pool import set_kernel_threads

    set_kernel_threads(1)
    out1, g1 = _train(proj, op, feats, bins, 50, 38, simd=True)
    set_kernel_threads(3)
    out3, g3 = _train(proj, op, feats, bins, 50, 38, simd=True)
    assert torch.equal(out1[0], out3[0]) and torch.equal(out1[1], out3[1])
    _assert_grads(g3, g1, rtol=1e-12, atol_rel=1e-12)


def test_training_huge_opacity_and_nan_inputs_match_numba():
    g = torch.Generator().manual_seed(17)
    n, W, H = 50, 40, 30
    means2d = torch.rand(n, 2, generator=g) * torch.tensor([W, H], dtype=F32)
    k = torch.rand(n, generator=g) * 0.3 + 0.05
    conics = torch.stack([k, (torch.rand(n, generator=g) - 0.5) * 0.02, k * 1.3], dim=-1)
    op = torch.rand(n, generator=g) * 0.8 + 0.1
    conics[0, 1] = 0.5  # saddle (no culling)
    op[1], op[2] = 1e36, float("nan")
    means2d[3, 1] = float("nan")
    feats = torch.rand(n, 4, generator=g)
    proj, op, feats, bins = _screen_space(means2d, conics, op, feats, W, H)
    out_s, g_s = _train(proj, op, feats, bins, W, H, simd=True)
    out_n, g_n = _train(proj, op, feats, bins, W, H, simd=False)
    _assert_close(out_s, out_n)
    for gs, gn in zip(g_s, g_n, strict=True):  # NaN inputs give NaN gradients alike
        assert torch.equal(gs.isnan(), gn.isnan())
    _assert_grads([t.nan_to_num() for t in g_s], [t.nan_to_num() for t in g_n])


def test_training_clamp_decisions_match_numba():
    # o · exp(power) within a few ulps of the 0.99 clamp at one pixel per Gaussian:
    # a clamped pixel passes no gradient to o or the footprint, so a flipped decision
    # would change those gradients by that pixel's whole share. The pixel is 6-9 px
    # out, so that exp(power) is far from 1 where the vector exp and libm's differ
    # (opacities above 1 are valid rasteriser inputs).
    *scene, W, H = _tuned(8, 120, 0.03, 0.05, (6, 10), 0.99, 3)
    out_s, g_s = _train(*scene, W, H, simd=True)
    out_n, g_n = _train(*scene, W, H, simd=False)
    _assert_close(out_s, out_n)
    _assert_grads(g_s, g_n)


def test_kernel_entry_points_reject_mismatched_arrays():
    cam = _camera(40, 24)
    scene = _scene(50, 4, 3, F32)
    proj, op, feats, bins = _projected(scene, cam)
    setup = _Setup(proj.means2d, proj.conics, op, feats, bins, 40, 24, F32)
    with pytest.raises(ValueError, match="do not cover a 57x24 image"):
        cpu_simd.SimdComposite(setup.args(), 41 + 16, 24)
    with pytest.raises(ValueError, match="out_feat must be C-contiguous float32"):
        cpu_simd.composite(setup.args(), 1, np.zeros((24, 40, 3)), np.ones((24, 40), np.float32))
    k = cpu_simd.SimdComposite(setup.args(), 40, 24)
    with pytest.raises(ValueError, match=r"out_T must have shape \(24, 40\)"):
        k.forward(1, np.zeros((24, 40, 3), np.float32), np.ones((40, 24), np.float32))
    T, last = np.ones((24, 40), np.float32), np.zeros((24, 40), np.int32)
    gbuf = np.zeros((1, 50, 9))
    with pytest.raises(ValueError, match=r"grad_feat must have shape \(24, 40, 3\)"):
        k.backward(1, T, last, np.zeros((24, 40, 2), np.float32), T, gbuf)
    with pytest.raises(ValueError, match="last must be C-contiguous int32"):
        k.backward(1, T, last.astype(np.int64), np.zeros((24, 40, 3), np.float32), T, gbuf)
    with pytest.raises(ValueError, match=r"gbuf must have shape \(2, 50, 9\)"):
        k.backward(2, T, last, np.zeros((24, 40, 3), np.float32), T, gbuf)
