"""G-buffer and planar depth (Eq. 8) on analytic single-plane cases."""

from __future__ import annotations

import pytest
import torch

from core.render.gbuffer import MIN_ALPHA, MIN_COS, planar_depth, render_gbuffer_tensors
from tests.helpers import identity_camera, rot_y, rotmat_y


def _flat_gaussian(deg: float, dtype, center=(0.05, -0.03, 2.0), opacity=0.95):
    means = torch.tensor([center], dtype=dtype)
    quats = rot_y(deg, dtype)
    scales = torch.tensor([[0.4, 0.3, 1e-7]], dtype=dtype)
    op = torch.tensor([opacity], dtype=dtype)
    colors = torch.tensor([[0.2, 0.4, 0.6]], dtype=dtype)
    normal = (rotmat_y(deg, dtype) @ torch.tensor([0.0, 0.0, 1.0], dtype=dtype))[None]
    w_r = torch.tensor([0.3], dtype=dtype)
    return means, quats, scales, op, colors, normal, w_r


def _analytic(cam, means, normal, dtype):
    """z-depth of the ray–plane intersection and |cos(ray, normal)| per pixel."""
    rays = cam.camera_rays(dtype)
    n = normal[0]
    ndotr = rays @ n
    depth = (n @ means[0]) / ndotr
    cos = ndotr.abs() / rays.norm(dim=-1)
    return depth, cos


@pytest.mark.parametrize("deg", [0.0, 60.0])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_planar_depth_is_exact_ray_plane_depth(deg, dtype):
    cam = identity_camera(48)
    means, quats, scales, op, colors, normal, w_r = _flat_gaussian(deg, dtype)
    gb, _ = render_gbuffer_tensors(
        means, quats, scales, op, colors, normal, w_r, cam, backend="reference"
    )
    truth, cos = _analytic(cam, means, normal, dtype)
    covered = gb.alpha > MIN_ALPHA
    assert covered.sum() > 50
    assert torch.equal(gb.depth_valid, covered & (cos > MIN_COS))
    v = gb.depth_valid
    rel = ((gb.depth[v] - truth[v]) / truth[v]).abs().max().item()
    assert rel < 1e-4
    # Normal channel: the camera-facing plane normal, times alpha.
    n_unit = gb.normal[v] / gb.alpha[v, None]
    torch.testing.assert_close(n_unit, (-normal).expand_as(n_unit), rtol=1e-4, atol=1e-4)
    assert torch.all(gb.depth[~v] == 0)


def test_center_depth_eq5_is_biased_on_tilted_plane():
    dtype = torch.float64
    cam = identity_camera(48)
    means, quats, scales, op, colors, normal, w_r = _flat_gaussian(60.0, dtype)
    gb, _ = render_gbuffer_tensors(
        means, quats, scales, op, colors, normal, w_r, cam, backend="reference"
    )
    truth, _ = _analytic(cam, means, normal, dtype)
    v = gb.depth_valid
    # Eq. 5 gives the centre's z everywhere: off by far more than Eq. 8's 1e-4.
    torch.testing.assert_close(gb.center_depth[v], torch.full_like(truth[v], 2.0))
    bias = ((gb.center_depth[v] - truth[v]) / truth[v]).abs().max().item()
    assert bias > 0.05


def test_grazing_plane_is_masked_not_inf():
    dtype = torch.float32
    cam = identity_camera(32)
    means, quats, scales, op, colors, normal, w_r = _flat_gaussian(
        89.0, dtype, center=(0.0, 0.0, 2.0)
    )
    for t in (means, quats, scales, op):
        t.requires_grad_(True)
    gb, _ = render_gbuffer_tensors(
        means, quats, scales, op, colors, normal, w_r, cam, backend="reference"
    )
    covered = gb.alpha > MIN_ALPHA
    assert covered.any()
    assert not gb.depth_valid[covered].any()  # every covered pixel is grazing: masked
    assert torch.isfinite(gb.depth).all() and torch.isfinite(gb.center_depth).all()
    (gb.depth.sum() + gb.normal.sum() + gb.alpha.sum()).backward()
    for t in (means, quats, scales, op):
        assert torch.isfinite(t.grad).all()


def test_planar_depth_guard_on_zero_normals():
    cam = identity_camera(8)
    normal = torch.zeros(8, 8, 3, requires_grad=True)
    plane = torch.full((8, 8), -2.0, requires_grad=True)
    alpha = torch.ones(8, 8)
    depth, valid = planar_depth(normal, plane, alpha, cam)
    assert not valid.any() and torch.equal(depth, torch.zeros(8, 8))
    depth.sum().backward()
    assert torch.isfinite(normal.grad).all() and torch.isfinite(plane.grad).all()


def test_gbuffer_gradients_match_finite_differences():
    dtype = torch.float64
    cam = identity_camera(10, f=12.0)
    g = torch.Generator().manual_seed(4)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.05, 2.2], [-0.1, 0.0, 2.4]], dtype=dtype)
    quats = torch.randn(3, 4, generator=g, dtype=dtype) * 0.2 + torch.tensor(
        [1.0, 0, 0, 0], dtype=dtype
    )
    scales = torch.tensor([[0.3, 0.25, 1e-3], [0.2, 0.3, 1e-3], [0.3, 0.3, 1e-3]], dtype=dtype)
    op = torch.tensor([0.6, 0.5, 0.7], dtype=dtype)
    colors = torch.rand(3, 3, generator=g, dtype=dtype)
    w_r = torch.rand(3, generator=g, dtype=dtype)
    wts = torch.rand(10, 10, 6, generator=g, dtype=dtype)

    def f(means, quats, op, colors, w_r):
        from core.render.rotations import normalize_quats, quat_to_rotmat

        normals = quat_to_rotmat(normalize_quats(quats))[:, :, 2]
        gb, _ = render_gbuffer_tensors(
            means, quats, scales, op, colors, normals, w_r, cam, backend="reference"
        )
        return (
            (gb.depth * wts[..., 0]).sum()
            + (gb.base * wts[..., 1:4]).sum()
            + (gb.w_r * wts[..., 4]).sum()
            + (gb.normal[..., 2] * wts[..., 5]).sum()
        )

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, op, colors, w_r)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_two_views_sharing_one_normals_tensor_match_computing_them_per_view():
    """The trainer computes Eq. 6 normals once per step for both views and their opacity
    factors; the images and the gradients are those of computing them per render."""
    from bench.common import bench_camera
    from bench.train_step import make_gaussians, neighbour_camera
    from core.render.gbuffer import render_gbuffer

    cam = bench_camera(24)
    cams = (cam, neighbour_camera(cam, 25.0))

    def loss_and_grads(shared: bool):
        gs = make_gaussians(400, torch.device("cpu"), seed=3)
        normals = gs.normals() if shared else None
        total = 0.0
        for c in cams:
            gb, _ = render_gbuffer(gs, c, sh_degree=1, backend="cpu", normals=normals)
            total = total + (gb.normal * gb.base).sum() + gb.plane_dist.square().sum()
        total.backward()
        return total.detach(), {
            k: p.grad.clone() for k, p in gs.params.items() if p.grad is not None
        }

    once, grads_once = loss_and_grads(shared=True)
    per_view, grads_per_view = loss_and_grads(shared=False)
    torch.testing.assert_close(once, per_view, rtol=0, atol=0)  # same forward, bit for bit
    assert grads_once.keys() == grads_per_view.keys() and "quats" in grads_once
    for k in grads_once:
        torch.testing.assert_close(grads_once[k], grads_per_view[k], rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_a_geometry_only_pass_is_the_full_pass_without_colour(backend):
    """The neighbour view of a training step splats normal, D and centre z only: those
    buffers, the depth and every gradient a depth loss sends equal the full pass's."""
    from core.render.gbuffer import render_gbuffer
    from core.scene.cameras import Camera, Intrinsics

    from .test_silhouette import discs_on_the_sphere

    g = discs_on_the_sphere(3000)
    cam = Camera.look_at([0.3, 0.4, 2.5], [0, 0, 0], [0, 1, 0], Intrinsics(60, 60, 24, 24, 48, 48))
    out = {}
    for geometry_only in (False, True):
        for p in g.params.values():
            p.grad = None
        gb, _ = render_gbuffer(g, cam, sh_degree=0, backend=backend, with_roughness=False,
                               geometry_only=geometry_only)  # fmt: skip
        loss = (gb.depth * gb.depth_valid).sum() + gb.center_depth.sum() + gb.normal.square().sum()
        loss.backward()
        grads = {k: p.grad.clone() for k, p in g.params.items() if p.grad is not None}
        out[geometry_only] = (gb, grads)
    (full, g_full), (geo, g_geo) = out[False], out[True]
    for name in ("normal", "plane_dist", "alpha", "z_blend", "depth", "center_depth"):
        torch.testing.assert_close(getattr(geo, name), getattr(full, name), rtol=1e-6, atol=1e-7)
    assert torch.equal(geo.depth_valid, full.depth_valid)
    assert float(geo.base.abs().sum()) == 0.0 and float(geo.w_r.abs().sum()) == 0.0
    assert set(g_geo) <= set(g_full)  # colour parameters get no gradient
    for k, v in g_geo.items():  # float32 sums in another order: rounding only
        torch.testing.assert_close(v, g_full[k], rtol=1e-3, atol=1e-5, msg=k)


def test_held_normal_depth_moves_the_plane_and_never_turns_it():
    """``held_plane``: the same Eq. 8 depth, whose gradient reaches the centre along the
    normal and neither the normal nor the opacity. For one splat d = n·μ / (n·r̃), so
    ∂d/∂μ = n / (n·r̃) per pixel, and n·μ does not depend on how opaque it is."""
    dtype = torch.float64
    cam = identity_camera(32)
    means, quats, scales, op, colors, normal, w_r = _flat_gaussian(30.0, dtype)
    for t in (means, op, normal):
        t.requires_grad_(True)
    gb, _ = render_gbuffer_tensors(
        means, quats, scales, op, colors, normal, w_r, cam, backend="reference", held_plane=True
    )
    v = gb.depth_valid
    assert v.sum() > 50
    torch.testing.assert_close(gb.depth_normals_held[v], gb.depth[v], rtol=1e-12, atol=1e-12)
    g_means, g_op, g_normal = torch.autograd.grad(
        gb.depth_normals_held[v].sum(), (means, op, normal), allow_unused=True, retain_graph=True
    )
    assert g_normal is None or torch.count_nonzero(g_normal) == 0
    assert g_op is None or g_op.abs().max() < 1e-12
    n_cam = -normal.detach()[0]  # facing the camera
    expected = (n_cam / (cam.camera_rays(dtype)[v] @ n_cam)[:, None]).sum(0)
    torch.testing.assert_close(g_means[0], expected, rtol=1e-9, atol=1e-9)
    # the plain depth's gradient does turn the normal
    (g_plain,) = torch.autograd.grad(gb.depth[v].sum(), (normal,))
    assert g_plain.abs().max() > 1e-3


def test_the_layouts_groups_start_at_its_offsets() -> None:
    from core.render.gbuffer_compiled import FeatureLayout

    for geometry_only in (False, True):
        for roughness in (False, True):
            for held in (False, True):
                lay = FeatureLayout(geometry_only, roughness, held)
                starts, col = {}, 0
                for name, width in lay.groups():
                    starts[name], col = col, col + width
                assert col == lay.channels
                assert (starts["normal"], starts["plane_dist"], starts["z_blend"]) == (
                    lay.normal,
                    lay.plane,
                    lay.z,
                )
                if roughness:
                    assert starts["roughness"] == lay.z + 1
                if held:
                    assert starts["normal_held"] == lay.held_start
                if geometry_only or held:
                    with pytest.raises(ValueError, match="read for its depth"):
                        lay.columns_without_depth()
                    continue
                # a pass without depth: the same groups less D and z, from those columns
                cols = lay.columns_without_depth()
                lean = lay.groups(depth=False)
                assert [g for g in lay.groups() if g[0] not in ("plane_dist", "z_blend")] == lean
                assert len(cols) == sum(w for _, w in lean) == lay.channels - 2
                kept = [c for name, w in lay.groups() for c in range(starts[name], starts[name] + w)
                        if name not in ("plane_dist", "z_blend")]  # fmt: skip
                assert cols == kept


def test_the_channel_split_passes_back_only_the_fields_a_loss_reads() -> None:
    """split_channels hands each field's gradient back as one concatenation, zeros
    where a field was not read: the same gradient slicing gives."""
    from core.render.gbuffer import split_channels
    from core.render.gbuffer_compiled import FeatureLayout

    for lay in (FeatureLayout(), FeatureLayout(True), FeatureLayout(False, True, True)):
        feats = torch.randn(5, 4, lay.channels, dtype=torch.float64, requires_grad=True)
        fields = split_channels(feats, lay)
        assert list(fields) == [name for name, _ in lay.groups()]
        loss = fields["normal"].square().sum() + 3.0 * fields["z_blend"].sum()
        (got,) = torch.autograd.grad(loss, feats)
        want = torch.zeros_like(feats)
        want[..., lay.normal : lay.normal + 3] = (
            2.0 * feats.detach()[..., lay.normal : lay.normal + 3]
        )
        want[..., lay.z] = 3.0
        assert torch.equal(got, want)
        assert torch.autograd.gradcheck(
            lambda f, lay=lay: tuple(split_channels(f, lay).values()), (feats,)
        )
