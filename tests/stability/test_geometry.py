"""Extreme geometry: grazing planes, the near plane, cameras inside Gaussians, footprints
of 1e-4 px and 1e4 px, and reprojection through a neighbour's focal plane.

Expected answers are stated per test; in short: planar depth is the exact ray–plane
depth where |cos(N, r̃)| > MIN_COS and a masked 0 (no gradient) where the plane is
grazing (up to 89.999°); Gaussians behind or on the camera draw nothing; one that
straddles the near plane is drawn if its centre is in front and culled otherwise; a
camera inside a Gaussian sees a uniform veil of its opacity; and every forward value
and gradient is finite.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.render.gbuffer import (
    MIN_ALPHA,
    MIN_COS,
    NEAR_FRACTION,
    near_plane,
    planar_depth,
    render_gbuffer_tensors,
)
from core.render.raster import rasterize
from core.scene.cameras import Camera, Intrinsics
from core.training.losses import multi_view_loss
from tests.stability.common import BACKENDS, all_finite, camera, quat_axis_angle, rotmat

DTYPES = [torch.float32, torch.float64]


def _flat(deg: float, dtype, center=(0.05, -0.03, 2.0), scale=(0.6, 0.5, 0.0), opacity=0.95):
    """One flat Gaussian tilted by ``deg`` about y: (tensors..., unit normal (1, 3))."""
    q = quat_axis_angle((0.0, 1.0, 0.0), deg, dtype)
    normal = (rotmat(q) @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))[None].to(dtype)
    return (
        torch.tensor([center], dtype=dtype),
        q,
        torch.tensor([scale], dtype=dtype),
        torch.tensor([opacity], dtype=dtype),
        torch.tensor([[0.2, 0.4, 0.6]], dtype=dtype),
        normal,
        torch.tensor([0.3], dtype=dtype),
    )


def _gbuffer_with_grads(tensors, cam, backend):
    leaves = [t.detach().clone().requires_grad_(True) for t in tensors]
    gb, res = render_gbuffer_tensors(*leaves, cam, backend=backend)
    loss = gb.depth.sum() + gb.normal.sum() + gb.plane_dist.sum() + gb.center_depth.sum()
    loss = loss + gb.base.sum() + gb.alpha.sum()
    grads = torch.autograd.grad(loss, leaves, allow_unused=True) if loss.requires_grad else []
    return gb, res, grads


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    deg=st.one_of(st.floats(0.0, 89.999), st.sampled_from([80.0, 87.0, 88.0, 89.9, 89.999])),
    dtype=st.sampled_from(DTYPES),
    backend=st.sampled_from(BACKENDS),
)
def test_grazing_planes_exact_or_masked(deg, dtype, backend):
    """Tilt 0–89.999°: where |cos| clearly exceeds MIN_COS the planar depth is the exact
    ray–plane depth (relative error < 1e-4); where it is clearly below, the pixel is
    masked (depth exactly 0). Nothing is Inf/NaN, gradients included."""
    cam = camera(24, f=24.0)
    tensors = _flat(deg, dtype)
    gb, _, grads = _gbuffer_with_grads(tensors, cam, backend)
    assert all_finite(gb.depth, gb.normal, gb.plane_dist, gb.center_depth, gb.base, gb.alpha)
    assert all_finite(*grads), "gradients must be finite at every tilt"
    means, normal = tensors[0], tensors[5]
    rays = cam.camera_rays(torch.float64)
    n = normal[0].double()
    ndotr = rays @ n
    truth = (n @ means[0].double()) / ndotr
    cos = ndotr.abs() / rays.norm(dim=-1)
    covered = gb.alpha > MIN_ALPHA
    v = gb.depth_valid
    assert torch.all(covered[v]), "a valid depth needs coverage"
    assert not torch.any(v & (cos < MIN_COS * 0.999)), "grazing pixels must be masked"
    must = covered & (cos > MIN_COS * 1.001) & (truth > 0)
    assert torch.all(v[must]), "non-grazing covered pixels must have a depth"
    assert torch.all(gb.depth[~v] == 0), "masked pixels hold depth 0"
    if bool(v.any()):
        rel = ((gb.depth[v].double() - truth[v]) / truth[v]).abs().max().item()
        assert rel < 1e-4, f"planar depth off by {rel:.2e} at tilt {deg}°"


@settings(max_examples=60, deadline=None)
@given(
    scale=st.sampled_from([0.0, 1e-45, 1e-38, 1e-30, 1e-20, 1e-6, 1.0, 1e10, 1e30]),
    cos_target=st.floats(0.0, 1.0),
    alpha=st.sampled_from([0.0, 0.01, 0.05, 0.051, 0.5, 1.0]),
    dtype=st.sampled_from(DTYPES),
)
def test_planar_depth_never_inf_or_nan(scale, cos_target, alpha, dtype):
    """Eq. 8 on arbitrary blended normals (length 0 to 1e30, any angle down to N·r̃ = 0):
    depth is finite and ≥ 0, invalid pixels hold 0, and the gradient is finite."""
    cam = camera(8)
    s = math.sqrt(max(0.0, 1.0 - cos_target**2))
    n_dir = torch.tensor([s, 0.0, -cos_target], dtype=dtype)
    normal = (n_dir * scale).expand(8, 8, 3).clone().requires_grad_(True)
    plane = torch.full((8, 8), -2.0 * scale * max(cos_target, 1e-3), dtype=dtype)
    plane.requires_grad_(True)
    depth, valid = planar_depth(normal, plane, torch.full((8, 8), alpha, dtype=dtype), cam)
    assert all_finite(depth) and bool((depth >= 0).all())
    assert bool((depth[~valid] == 0).all())
    if alpha <= MIN_ALPHA or scale == 0.0:
        assert not bool(valid.any()), "no coverage or no normal: no depth"
    depth.sum().backward()
    assert all_finite(normal.grad, plane.grad)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussian_behind_camera_draws_nothing(backend):
    """Centre behind the camera (z = −1, large enough to reach in front): culled, the
    image is exactly 0 and gradients (if any) are finite."""
    cam = camera()
    means = torch.tensor([[0.0, 0.0, -1.0]], requires_grad=True)
    scales = torch.tensor([[2.0, 2.0, 2.0]], requires_grad=True)
    res = rasterize(
        means, torch.tensor([[1.0, 0, 0, 0]]), scales, torch.tensor([0.9]), torch.ones(1, 3), cam,
        backend=backend,
    )  # fmt: skip
    assert int(res.radii[0]) == 0
    assert float(res.alpha.detach().abs().max()) == 0.0
    assert float(res.features.detach().abs().max()) == 0.0


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_gaussian_straddling_near_plane(backend, dtype):
    """A unit Gaussian whose centre sits just in front of the near plane (z = near·1.001)
    is drawn with finite values and gradients; just behind it (z = near·0.999) it is
    culled. The EWA footprint of the first is huge (J ∝ 1/z) but finite."""
    cam = camera()
    near = 0.01
    for z, drawn in ((near * 1.001, True), (near * 0.999, False)):
        means = torch.tensor([[0.0, 0.0, z]], dtype=dtype, requires_grad=True)
        scales = torch.tensor([[1.0, 1.0, 1.0]], dtype=dtype, requires_grad=True)
        res = rasterize(
            means, torch.tensor([[1.0, 0, 0, 0]], dtype=dtype), scales,
            torch.tensor([0.5], dtype=dtype), torch.ones(1, 3, dtype=dtype), cam,
            backend=backend, near=near,
        )  # fmt: skip
        assert (int(res.radii[0]) > 0) == drawn, f"z = {z}: expected drawn={drawn}"
        assert all_finite(res.features, res.alpha)
        if drawn:
            assert float(res.alpha.detach().min()) == pytest.approx(0.5, abs=1e-3)
            res.features.sum().backward()
            assert all_finite(means.grad, scales.grad)


def test_near_plane_is_relative_to_the_view():
    """The default near plane is NEAR_FRACTION × the median positive depth (unit-free);
    with nothing in front of the camera it is a harmless positive constant."""
    z = torch.tensor([-5.0, 2.0, 3.0, 4.0, float("nan")])
    assert near_plane(z) == pytest.approx(NEAR_FRACTION * 3.0)
    assert near_plane(z * 1e-3) == pytest.approx(NEAR_FRACTION * 3e-3)
    assert near_plane(torch.tensor([-1.0, -2.0])) > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_camera_inside_gaussian_sees_uniform_veil(backend):
    """Camera inside a huge Gaussian (centre 0.5 ahead, σ = 50): every pixel gets alpha ≈
    its opacity 0.3 (the footprint is ~2400 px σ), finite values and gradients. With the
    centre behind or exactly at the camera the Gaussian is culled (3DGS's rule)."""
    cam = camera()
    for z, drawn in ((0.5, True), (0.0, False), (-0.5, False)):
        means = torch.tensor([[0.0, 0.0, z]], requires_grad=True)
        scales = torch.tensor([[50.0, 50.0, 50.0]], requires_grad=True)
        res = rasterize(
            means, torch.tensor([[1.0, 0, 0, 0]]), scales, torch.tensor([0.3]),
            torch.ones(1, 3), cam, backend=backend,
        )  # fmt: skip
        assert all_finite(res.features, res.alpha)
        if drawn:
            torch.testing.assert_close(
                res.alpha, torch.full_like(res.alpha, 0.3), atol=1e-4, rtol=0
            )
            res.alpha.sum().backward()
            assert all_finite(means.grad, scales.grad)
        else:
            assert float(res.alpha.detach().abs().max()) == 0.0


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_footprints_1e_minus_4_and_1e4_pixels(backend, dtype):
    """σ = 1e-4 px: the low-pass makes it a ~0.55 px blob, 3σ radius ≤ 3 px, alpha at the
    centre pixel o·exp(−½·d²/0.3), gradient w.r.t. the mean finite and non-zero.
    σ = 1e4 px: alpha is the opacity over the whole 24 px image (to 1e-5)."""
    cam = camera()
    f = cam.intrinsics.fx
    z = 3.0
    for sigma_px in (1e-4, 1e4):
        s = sigma_px * z / f
        # the centre lands on a pixel centre (12.5, 12.5) so the centre pixel has d = 0
        means = torch.tensor([[0.5 * z / f, 0.5 * z / f, z]], dtype=dtype, requires_grad=True)
        scales = torch.tensor([[s, s, s]], dtype=dtype, requires_grad=True)
        res = rasterize(
            means, torch.tensor([[1.0, 0, 0, 0]], dtype=dtype), scales,
            torch.tensor([0.8], dtype=dtype), torch.ones(1, 3, dtype=dtype), cam, backend=backend,
        )  # fmt: skip
        assert all_finite(res.features, res.alpha)
        a = res.alpha.detach()
        if sigma_px < 1:
            assert 0 < int(res.radii[0]) <= 3
            assert float(a[12, 12]) == pytest.approx(0.8, rel=1e-4)
            assert float(a[12, 13]) == pytest.approx(0.8 * math.exp(-0.5 / 0.3), rel=1e-3)
            assert float(a[0, 0]) == 0.0
        else:
            torch.testing.assert_close(a, torch.full_like(a, 0.8), atol=1e-5, rtol=0)
        res.features.sum().backward()
        assert all_finite(means.grad, scales.grad)
        if sigma_px < 1:
            assert float(means.grad.abs().sum()) > 0


def _plane_depth(cam: Camera, n: torch.Tensor, c: float) -> torch.Tensor:
    """z-depth of the plane n·X = c through every pixel of ``cam`` (float64)."""
    dirs = cam.camera_rays(torch.float64) @ cam.R  # R^T r̃
    return (c - n @ cam.center) / (dirs @ n)


@pytest.mark.parametrize("dtype", DTYPES)
def test_multi_view_point_on_neighbour_focal_plane(dtype):
    """A reference pixel whose 3D point lies exactly on the neighbour's focal plane
    (z_nb = 0) is excluded, and the loss gradient stays finite (before the fix:
    x/0 = inf in the projection, and its masked-out gradient 0·∞ = NaN)."""
    intr = Intrinsics(24.0, 24.0, 12.5, 12.5, 24, 24)
    ref = Camera(intr, torch.eye(4, dtype=torch.float64))
    R = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    eye = torch.tensor([-3.0, 0.0, 2.0], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    nb = Camera(intr, w2c)  # looks along +x; its focal plane is world x = −3
    n = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    d_ref = _plane_depth(ref, n, 2.0).to(dtype)
    d_ref[:, 0] = 6.0  # pixel column 0 has x/z = −0.5 exactly: the point is (−3, y, 6)
    d_ref.requires_grad_(True)
    d_nb = _plane_depth(nb, n, 2.0).to(dtype)
    ones = torch.ones(24, 24, dtype=torch.bool)
    loss, stats = multi_view_loss(d_ref, ones, ref, d_nb.clamp_min(0), d_nb > 0, nb)
    assert stats["kept"] > 100, "the consistent plane must be kept"
    assert math.isfinite(float(loss.detach()))
    loss.backward()
    assert all_finite(d_ref.grad), "gradient must be finite (no 0·inf)"
    assert float(d_ref.grad[:, 0].abs().max()) == 0.0, "the focal-plane pixels are excluded"


@settings(max_examples=25, deadline=None)
@given(
    yaw=st.floats(-179.0, 179.0),
    baseline=st.sampled_from([0.0, 1e-9, 0.5, 3.0]),
    depth_kind=st.sampled_from(["plane", "zeros", "huge", "tiny"]),
    dtype=st.sampled_from(DTYPES),
)
def test_multi_view_loss_finite_for_any_pair(yaw, baseline, depth_kind, dtype):
    """Any neighbour pose (turned up to ±179°, baseline 0 to 3) and any depth map (a
    plane, all 0, 1e30, 1e-30): loss and gradient finite, loss ≥ 0."""
    intr = Intrinsics(16.0, 16.0, 8.0, 8.0, 16, 16)
    ref = Camera(intr, torch.eye(4, dtype=torch.float64))
    q = quat_axis_angle((0.0, 1.0, 0.0), yaw)
    R = rotmat(q)
    eye = torch.tensor([baseline, 0.0, 0.0], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R.T
    w2c[:3, 3] = -R.T @ eye
    nb = Camera(intr, w2c)
    fill = {"zeros": 0.0, "huge": 1e30, "tiny": 1e-30}
    if depth_kind == "plane":
        d_ref = _plane_depth(ref, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 3.0)
        d_nb = _plane_depth(nb, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 3.0)
    else:
        d_ref = torch.full((16, 16), fill[depth_kind], dtype=torch.float64)
        d_nb = d_ref.clone()
    d_ref = d_ref.to(dtype).requires_grad_(True)
    d_nb = d_nb.to(dtype)
    loss, _ = multi_view_loss(d_ref, d_ref.detach() > 0, ref, d_nb, d_nb > 0, nb)
    assert math.isfinite(float(loss.detach())) and float(loss.detach()) >= 0
    if loss.requires_grad:
        loss.backward()
        assert d_ref.grad is None or all_finite(d_ref.grad)
