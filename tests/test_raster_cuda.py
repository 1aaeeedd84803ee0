"""The gsplat ("cuda") backend against the reference rasteriser.

Two layers:

* On any machine (gsplat installed, no GPU): ``rasterize_gsplat`` runs with a PyTorch
  twin of ``gsplat.rasterization`` (``tests/gsplat_twin.py``) built from gsplat's own
  reference projection (``gsplat.cuda._torch_impl``) and this project's reference
  compositor. That checks
  everything this project owns — camera matrices in gsplat's layout, the per-axis and
  packed outputs mapped back to (N, …), gradients reaching every input and the
  screen-space gradient for densification — against ``backend="reference"``.
* On a CUDA machine: the real gsplat kernels, forward and gradients, on random scenes
  (several seeds, sizes and channel counts, Gaussians off-screen, behind the camera
  and needle-flat), and a short training run.
"""

from __future__ import annotations

import math

import pytest
import torch

from core.config import ConfigError, config_from_dict
from core.errors import BackendUnavailableError
from core.render.raster import (
    available_backends,
    covariances_from,
    rasterize,
    resolve_backend,
)
from core.render.raster.cuda import available, camera_matrices, rasterize_gsplat
from core.scene.cameras import Camera, Intrinsics
from tests.gsplat_twin import gsplat_twin

F64 = torch.float64
HAS_CUDA = torch.cuda.is_available() and "cuda" in available_backends("cuda")


def _camera(width: int, height: int, *, rotated: bool = False) -> Camera:
    """Off-centre principal point; ``rotated`` tilts the camera and moves it off-axis."""
    f = 0.9 * max(width, height)
    intr = Intrinsics(f, 1.1 * f, width / 2 + 0.7, height / 2 - 0.4, width, height)
    w2c = torch.eye(4, dtype=F64)
    if rotated:
        a = math.radians(12.0)
        w2c[:3, :3] = torch.tensor(
            [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]],
            dtype=F64,
        )
        w2c[:3, 3] = torch.tensor([0.3, -0.2, 0.4], dtype=F64)
    return Camera(intr, w2c, "test")


def _scene(n: int, seed: int, channels: int, *, flat: bool = False) -> list[torch.Tensor]:
    """Random Gaussians around z = 3: some behind the camera, some off-screen."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=F64) * torch.tensor([0.6, 0.5, 0.8], dtype=F64)
    means[:, 2] += 3.0
    means[: n // 10, 2] = -1.0 - torch.rand(n // 10, generator=g, dtype=F64)
    means[n // 10 : n // 5, 0] += 2.5
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    scales = torch.rand(n, 3, generator=g, dtype=F64) * 0.12 + 0.02
    if flat:
        scales[:, 2] = 1e-7
    opac = torch.rand(n, generator=g, dtype=F64) * 0.7 + 0.2
    feats = torch.rand(n, channels, generator=g, dtype=F64) * 2 - 0.5
    return [t.float() for t in (means, quats, scales, opac, feats)]


def _run(fn, scene, cam, weights):
    params = [t.clone().requires_grad_(True) for t in scene]
    r = fn(*params, cam)
    r.means2d.retain_grad()
    w_feat, w_alpha = weights
    loss = (r.features * w_feat).sum() + (r.alpha * w_alpha).sum()
    loss.backward()
    grads = dict(
        zip(("means", "quats", "scales", "opac", "feats"), [p.grad for p in params], strict=True)
    )
    grads["means2d"] = r.screen_grad(scene[0].shape[0])
    return r, grads


def _weights(cam: Camera, channels: int, seed: int, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    w_feat = torch.randn(cam.height, cam.width, channels, generator=g)
    w_alpha = torch.randn(cam.height, cam.width, generator=g)
    return w_feat.to(device), w_alpha.to(device)


def _assert_close_rel(got: torch.Tensor, want: torch.Tensor, name: str, tol: float) -> None:
    """Max error relative to the largest reference magnitude (robust to scale)."""
    got, want = got.detach(), want.detach()
    scale = max(float(want.abs().max()), 1e-12)
    err = float((got.float() - want.float()).abs().max()) / scale
    assert err <= tol, f"{name}: max error {err:.2e} of the largest value (tolerance {tol:.0e})"


# -- selection and errors (any machine) ----------------------------------------------
def test_cuda_unavailable_on_cpu_says_why():
    reason = available(torch.device("cpu"))
    assert reason is not None and "CUDA device" in reason
    assert "cuda" not in available_backends("cpu")
    assert resolve_backend("auto", "cpu") in ("cpu", "reference")
    with pytest.raises(BackendUnavailableError, match="'cuda' is unavailable: it needs a CUDA"):
        resolve_backend("cuda", "cpu")


def test_absgrad_needs_the_cuda_backend():
    cam = _camera(16, 16)
    means, quats, scales, opac, feats = _scene(10, 0, 3)
    with pytest.raises(BackendUnavailableError, match="absgrad"):
        rasterize(means, quats, scales, opac, feats, cam, backend="reference", absgrad=True)
    from core.training.trainer import check_runnable

    cfg = config_from_dict({"backend": "cpu", "densify": {"absgrad": True}})
    with pytest.raises(ConfigError, match=r"densify\.absgrad"):
        check_runnable(cfg)
    assert check_runnable(config_from_dict({})) == torch.device("cpu")  # off: nothing to check


def test_camera_matrices_in_gsplat_layout():
    cam = _camera(40, 30, rotated=True)
    viewmats, Ks = camera_matrices(cam, torch.float32, torch.device("cpu"))
    assert viewmats.shape == (1, 4, 4) and Ks.shape == (1, 3, 3)
    p_world = torch.tensor([0.2, -0.1, 3.0], dtype=F64)
    p_cam = cam.R @ p_world + cam.t
    uv = Ks[0].double() @ (viewmats[0, :3, :3].double() @ p_world + viewmats[0, :3, 3].double())
    uv = uv[:2] / uv[2]
    intr = cam.intrinsics
    want = torch.stack(
        [intr.fx * p_cam[0] / p_cam[2] + intr.cx, intr.fy * p_cam[1] / p_cam[2] + intr.cy]
    )
    torch.testing.assert_close(uv, want, rtol=1e-6, atol=1e-4)


# -- the adapter through gsplat's PyTorch twin (any machine with gsplat) --------------
@pytest.mark.parametrize(
    ("seed", "size", "channels", "flat", "packed", "rotated"),
    [
        (0, (37, 29), 3, False, True, False),
        (1, (32, 32), 9, True, False, True),
        (2, (20, 41), 13, False, True, True),
    ],
)
def test_adapter_matches_reference_through_gsplat_twin(seed, size, channels, flat, packed, rotated):
    pytest.importorskip("gsplat")
    cam = _camera(*size, rotated=rotated)
    scene = _scene(260, seed, channels, flat=flat)
    weights = _weights(cam, channels, seed)

    def via_twin(m, q, s, o, f, c):
        return rasterize_gsplat(m, q, s, o, f, c, packed=packed, impl=gsplat_twin)

    def via_reference(m, q, s, o, f, c):
        return rasterize(m, q, s, o, f, c, backend="reference")

    r_tw, g_tw = _run(via_twin, scene, cam, weights)
    r_ref, g_ref = _run(via_reference, scene, cam, weights)
    assert r_tw.backend == "cuda" and (r_tw.gaussian_ids is not None) == packed
    assert float(r_ref.alpha.detach().mean()) > 0.2  # the scene covers the image: the test can fail
    assert r_tw.features.shape == r_ref.features.shape and r_tw.alpha.shape == r_ref.alpha.shape
    # Visibility agrees up to the radius rule at the screen border (3σ vs 3.33σ per axis).
    vis_tw, vis_ref = r_tw.radii > 0, r_ref.radii > 0
    assert int((vis_tw != vis_ref).sum()) <= len(scene[0]) // 30
    torch.testing.assert_close(
        r_tw.depths[vis_ref & vis_tw], r_ref.depths.detach()[vis_ref & vis_tw]
    )
    _assert_close_rel(r_tw.features, r_ref.features.detach(), "features", 2e-3)
    _assert_close_rel(r_tw.alpha, r_ref.alpha.detach(), "alpha", 2e-3)
    for name in ("means", "quats", "scales", "opac", "feats", "means2d"):
        _assert_close_rel(g_tw[name], g_ref[name], name, 2e-2)


def test_antialiased_mode_matches_reference():
    pytest.importorskip("gsplat")
    cam = _camera(30, 26, rotated=True)
    scene = _scene(200, 6, 5, flat=True)
    r_tw = rasterize_gsplat(*scene, cam, antialiased=True, impl=gsplat_twin)
    r_ref = rasterize(*scene, cam, backend="reference", antialiased=True)
    r_classic = rasterize(*scene, cam, backend="reference")
    _assert_close_rel(r_tw.alpha, r_ref.alpha, "alpha", 2e-3)
    _assert_close_rel(r_tw.features, r_ref.features, "features", 2e-3)
    assert float((r_classic.alpha - r_ref.alpha).abs().max()) > 1e-2  # the mode matters


def test_full_covariance_goes_through_covars():
    pytest.importorskip("gsplat")
    cam = _camera(24, 24)
    means, quats, scales, opac, feats = _scene(80, 3, 4)
    covs = covariances_from(quats, scales)
    r_cov = rasterize_gsplat(
        means, None, None, opac, feats, cam, covariances=covs, impl=gsplat_twin
    )
    r_qs = rasterize_gsplat(means, quats, scales, opac, feats, cam, impl=gsplat_twin)
    torch.testing.assert_close(r_cov.features, r_qs.features, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="quats and scales, or covariances"):
        rasterize_gsplat(means, None, None, opac, feats, cam, impl=gsplat_twin)


def test_screen_grad_scatters_packed_rows():
    from core.render.raster import RasterResult

    m2d = torch.zeros(3, 2, requires_grad=True)
    (m2d * torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])).sum().backward()
    ids = torch.tensor([4, 0, 2])
    r = RasterResult(
        torch.zeros(1, 1, 1), torch.zeros(1, 1), m2d, torch.zeros(5), torch.zeros(5), "x", ids
    )
    g = r.screen_grad(5)
    assert g is not None
    torch.testing.assert_close(g, torch.tensor([[3.0, 4.0], [0, 0], [5, 6], [0, 0], [1, 2]]))
    assert r.screen_grad(5, absolute=True) is None  # no absgrad computed


# -- the real kernels (CUDA machines) --------------------------------------------------
needs_cuda = pytest.mark.skipif(
    not HAS_CUDA, reason="needs a CUDA device and gsplat (extra 'cuda')"
)


@needs_cuda
@pytest.mark.parametrize(
    ("seed", "size", "channels", "flat", "packed", "aa"),
    [
        (0, (37, 29), 3, False, True, False),
        (1, (64, 48), 9, True, True, True),
        (2, (20, 41), 13, False, False, False),
        (3, (128, 96), 8, True, False, True),
    ],
)
def test_cuda_matches_reference(seed, size, channels, flat, packed, aa):
    cam = _camera(*size, rotated=seed % 2 == 1)
    scene = [t.cuda() for t in _scene(300, seed, channels, flat=flat)]
    weights = _weights(cam, channels, seed, "cuda")

    def via_cuda(m, q, s, o, f, c):
        return rasterize_gsplat(m, q, s, o, f, c, packed=packed, antialiased=aa)

    def via_reference(m, q, s, o, f, c):
        return rasterize(m, q, s, o, f, c, backend="reference", antialiased=aa)

    r_cu, g_cu = _run(via_cuda, scene, cam, weights)
    r_ref, g_ref = _run(via_reference, scene, cam, weights)
    assert r_cu.backend == "cuda"
    assert float(r_ref.alpha.mean()) > 0.1  # the scene covers the image (seed 3: 0.18)
    # gsplat clamps alpha at 0.999 (reference 0.99) and bins with its own radii.
    _assert_close_rel(r_cu.features, r_ref.features.detach(), "features", 5e-3)
    _assert_close_rel(r_cu.alpha, r_ref.alpha.detach(), "alpha", 5e-3)
    for name in ("means", "quats", "scales", "opac", "feats", "means2d"):
        _assert_close_rel(g_cu[name], g_ref[name], name, 5e-2)


@needs_cuda
def test_cuda_absgrad_is_filled():
    cam = _camera(48, 48)
    params = [t.cuda().requires_grad_(True) for t in _scene(200, 5, 8)]
    r = rasterize(*params, cam, backend="cuda", absgrad=True)
    r.means2d.retain_grad()
    (r.features.sum() + r.alpha.sum()).backward()
    g, ga = r.screen_grad(200), r.screen_grad(200, absolute=True)
    assert g is not None and ga is not None
    assert bool((ga.abs() + 1e-6 >= g.abs()).all())  # Σ|g| ≥ |Σ g|


@pytest.mark.parametrize(
    ("device", "backend"),
    [
        ("cpu", "cpu"),  # the same test body everywhere, so it is known to work
        pytest.param("cuda", "cuda", marks=needs_cuda),
    ],
)
def test_short_training_run(device, backend, tmp_path):
    from core.scene.synthetic import make_sphere_scene
    from core.training.run import train_scene

    scene = make_sphere_scene("glossy", n_train=8, n_test=2, size=48, samples=2)
    cfg = config_from_dict(
        {
            "iterations": 90,
            "device": device,
            "backend": backend,
            "init_points": 500,
            "envmap_resolution": 8,
            "eval": {"every": 45, "views": 2},
        }
    )
    result, _ = train_scene(scene, tmp_path / "run", cfg)
    assert result.status == "succeeded" and result.iteration == 90
    assert math.isfinite(result.last_metrics["psnr"]) and result.last_metrics["psnr"] > 12
