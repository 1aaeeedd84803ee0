"""Losses: SSIM/L1, scale loss, depth-derived normals, single- and multi-view terms."""

from __future__ import annotations

import math

import pytest
import torch

from core.evaluation.ssim import ssim, ssim_reference
from core.render.depth_geometry import bilinear_lookup, normals_from_depth
from core.render.gbuffer import planar_depth
from core.scene.cameras import Camera, Intrinsics
from core.training.losses import (
    edge_weight,
    mask_loss,
    multi_view_loss,
    rgb_loss,
    scale_loss,
    single_view_loss,
)
from tests.helpers import identity_camera, rotmat_y


def test_ssim_identity_and_noise():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(24, 24, 3, generator=g)
    assert ssim(img, img).item() == torch.tensor(1.0).item()
    noisy = (img + 0.2 * torch.randn(24, 24, 3, generator=g)).clamp(0, 1)
    s = ssim(noisy, img).item()
    assert 0.0 < s < 0.95
    assert abs(ssim(img, noisy).item() - s) < 1e-6  # symmetric
    assert rgb_loss(img, img).item() == 0.0
    assert rgb_loss(noisy, img, 1.0).item() == (noisy - img).abs().mean().item()


def _ssim_by_hand(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """3DGS's SSIM written out independently of core: 11×11 Gaussian (σ 1.5), zero pad."""
    import torch.nn.functional as F

    x, y = img.permute(2, 0, 1)[None], ref.permute(2, 0, 1)[None]
    c = x.shape[1]
    t = torch.arange(11, dtype=img.dtype) - 5.0
    g = torch.exp(-(t**2) / 4.5)
    w = (torch.outer(g, g) / g.sum() ** 2).expand(c, 1, 11, 11).contiguous()

    def blur(m: torch.Tensor) -> torch.Tensor:
        return F.conv2d(m, w, padding=5, groups=c)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    num = (2 * mx * my + 1e-4) * (2 * sxy + 9e-4)
    return (num / ((mx**2 + my**2 + 1e-4) * (sxx + syy + 9e-4))).mean()


@pytest.mark.parametrize(("h", "w", "c"), [(24, 24, 3), (7, 13, 3), (31, 18, 1), (40, 33, 4)])
def test_separable_ssim_matches_the_2d_window(h: int, w: int, c: int):
    g = torch.Generator().manual_seed(h * w + c)
    ref = torch.rand(h, w, c, generator=g, dtype=torch.float64)
    img = (ref + 0.15 * torch.randn(h, w, c, generator=g, dtype=torch.float64)).clamp(0, 1)
    a = img.clone().requires_grad_(True)
    b = img.clone().requires_grad_(True)
    fast, plain = ssim(a, ref), _ssim_by_hand(b, ref)
    torch.testing.assert_close(ssim_reference(img, ref), plain.detach(), rtol=0, atol=1e-12)
    assert 0.1 < float(plain.detach()) < 0.99  # a scene where SSIM is informative
    torch.testing.assert_close(fast, plain, rtol=0, atol=1e-12)
    fast.backward()
    plain.backward()
    assert a.grad is not None and b.grad is not None
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-9, atol=1e-14)


def test_mask_loss_is_the_mean_coverage_beyond_the_mask():
    """max(α − mask, 0) averaged over every pixel: 0 on the mask itself (antialiased
    edge values included) and wherever coverage falls short of it; a halo costs its
    area, and the gradient lowers it, whatever colour it has."""
    mask = torch.zeros(8, 8)
    mask[2:6, 2:6] = 1.0
    mask[2:6, 6] = 0.25  # an antialiased edge column
    assert float(mask_loss(mask.clone(), mask)) == 0.0
    alpha = mask.clone()
    alpha[0, :] = 0.5  # halo: 8 px at 0.5 outside
    alpha[2:6, 6] = 0.75  # the edge column covered 0.5 beyond its coverage
    alpha[3, 3] = 0.0  # a hole inside: not this term's business
    alpha.requires_grad_(True)
    loss = mask_loss(alpha, mask)
    assert loss.item() == pytest.approx((8 * 0.5 + 4 * 0.5) / 64)
    loss.backward()
    assert bool((alpha.grad[0, :] > 0).all()) and bool((alpha.grad[2:6, 6] > 0).all())
    assert float(alpha.grad[3, 3]) == 0.0 and float(alpha.grad[4, 4]) == 0.0
    with pytest.raises(ValueError, match="differ"):
        mask_loss(torch.zeros(8, 8), torch.zeros(4, 4))


def test_scale_loss_is_mean_smallest_scale():
    s = torch.tensor([[1.0, 0.1, 2.0], [0.5, 0.5, 0.3]])
    assert math.isclose(scale_loss(s).item(), (0.1 + 0.3) / 2, rel_tol=1e-6)


def _plane_depth(cam: Camera, n: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    rays = cam.camera_rays(torch.float64)
    return (n @ point) / (rays @ n)


def test_normals_from_depth_recover_tilted_plane():
    cam = identity_camera(32)
    n = rotmat_y(35.0) @ torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    depth = _plane_depth(cam, n, torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64))
    valid = torch.ones(32, 32, dtype=torch.bool)
    N, ok = normals_from_depth(depth, valid, cam)
    assert ok[1:-1, 1:-1].all() and not ok[0].any() and not ok[:, -1].any()
    torch.testing.assert_close(N[ok], n.expand(int(ok.sum()), 3), atol=1e-9, rtol=0)
    # Holes in the depth invalidate their neighbours too.
    valid[10, 10] = False
    _, ok2 = normals_from_depth(depth, valid, cam)
    assert not ok2[10, 11] and not ok2[11, 10] and ok2[12, 12]


def _occlusion_step(cam: Camera) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Left half: a plane tilted 35° about y at depth ~3; right half: a wall at depth 6
    facing the camera. Returns (depth, left normal, right normal)."""
    n_front = rotmat_y(35.0) @ torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    n_back = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    front = _plane_depth(cam, n_front, torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64))
    back = torch.full_like(front, 6.0)
    depth = front.clone()
    depth[:, 16:] = back[:, 16:]
    return depth, n_front, n_back


def test_same_surface_normals_across_a_depth_jump():
    """At a self-occlusion edge the central difference mixes both surfaces (its normal is
    neither's); one-sided differences give each side's own normal, and on a smooth plane
    they change nothing."""
    cam = identity_camera(32)
    depth, n_front, n_back = _occlusion_step(cam)
    valid = torch.ones(32, 32, dtype=torch.bool)
    central, ok = normals_from_depth(depth, valid, cam)
    same, ok_same = normals_from_depth(depth, valid, cam, jump_ratio=2.0)
    assert torch.equal(ok, ok_same)
    rows = slice(1, 31)
    for col, n_true in ((15, n_front), (16, n_back)):
        cos_central = (central[rows, col] @ n_true).min().item()
        cos_same = (same[rows, col] @ n_true).min().item()
        assert cos_central < math.cos(math.radians(30))  # the mixed normal is far off
        assert cos_same > 1 - 1e-9  # the pixel's own surface exactly
    # Away from the jump (and on a plane seen whole) nothing changes.
    torch.testing.assert_close(same[rows, 2:14], central[rows, 2:14], atol=0, rtol=0)
    plane = _plane_depth(cam, n_front, torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64))
    a, _ = normals_from_depth(plane, valid, cam)
    b, _ = normals_from_depth(plane, valid, cam, jump_ratio=2.0)
    torch.testing.assert_close(a, b, atol=0, rtol=0)


def test_same_surface_normals_on_a_sphere_match_central_differences():
    """A smooth curved surface (no jump) keeps its central differences: the switch must
    not cost accuracy where Eq. 10 is right."""
    cam = identity_camera(48)
    rays = cam.camera_rays(torch.float64)
    c, r = torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64), 1.6
    b = rays @ c
    disc = b**2 - (rays * rays).sum(-1) * (c @ c - r * r)
    hit = disc > 0
    depth = torch.where(hit, (b - disc.clamp_min(0).sqrt()) / (rays * rays).sum(-1), 0.0)
    a, ok = normals_from_depth(depth, hit, cam)
    s, _ = normals_from_depth(depth, hit, cam, jump_ratio=2.0)
    # Where the sphere is seen at up to ~60° the steps agree within 2×.
    P = depth[..., None] * rays
    n_true = (P - c) / r
    facing = hit & ((n_true * -P).sum(-1) / P.norm(dim=-1) > 0.5) & ok
    assert int(facing.sum()) > 300
    torch.testing.assert_close(s[facing], a[facing], atol=0, rtol=0)


def test_single_view_loss_same_surface_at_an_occlusion_edge():
    """Rendered normals that are right on both sides of an occlusion edge: the central
    target penalises them at the edge, the same-surface target does not."""
    cam = identity_camera(32)
    depth, n_front, n_back = _occlusion_step(cam)
    rendered = torch.empty(32, 32, 3, dtype=torch.float64)
    rendered[:, :16] = n_front
    rendered[:, 16:] = n_back
    valid = torch.ones(32, 32, dtype=torch.bool)
    assert single_view_loss(rendered, depth, valid, cam).item() > 1e-3
    assert single_view_loss(rendered, depth, valid, cam, same_surface=True).item() < 1e-12


def test_single_view_loss_zero_when_consistent_one_when_perpendicular():
    cam = identity_camera(16)
    n = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    depth = torch.full((16, 16), 2.0, dtype=torch.float64)
    valid = torch.ones(16, 16, dtype=torch.bool)
    rendered = n.expand(16, 16, 3) * 0.7  # blended normals are not unit length
    assert single_view_loss(rendered, depth, valid, cam).item() < 1e-12
    perp = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).expand(16, 16, 3)
    assert abs(single_view_loss(perp, depth, valid, cam).item() - 1.0) < 1e-12
    none = torch.zeros(16, 16, dtype=torch.bool)
    assert single_view_loss(rendered, depth, none, cam).item() == 0.0


def test_bilinear_lookup():
    img = torch.arange(20, dtype=torch.float64).reshape(4, 5)
    uv = torch.tensor(
        [[0.5, 0.5], [1.5, 0.5], [1.0, 1.0], [4.5, 3.5], [4.6, 1.0], [float("nan"), 1.0]]
    )
    v, inside = bilinear_lookup(img, uv.double())
    assert inside.tolist() == [True, True, True, True, False, False]
    torch.testing.assert_close(v[:4], torch.tensor([0.0, 1.0, 3.0, 19.0], dtype=torch.float64))


def _two_views():
    intr = Intrinsics(30.0, 30.0, 16.3, 15.8, 32, 32)
    ref = Camera.look_at([0.0, 0.0, -4.0], [0, 0, 0], [0, -1, 0], intr, "ref")
    eye = torch.tensor([math.sin(math.radians(20)) * 4, 0.0, -math.cos(math.radians(20)) * 4])
    nb = Camera.look_at(eye, [0, 0, 0], [0, -1, 0], intr, "nb")
    return ref, nb


def _plane_depth_world(cam: Camera, n_world: torch.Tensor, p_world: torch.Tensor) -> torch.Tensor:
    n_cam = cam.R @ n_world
    p_cam = cam.R @ p_world + cam.t
    return _plane_depth(cam, n_cam, p_cam)


def test_multi_view_loss_zero_on_consistent_depths_and_positive_otherwise():
    ref, nb = _two_views()
    n = torch.tensor([0.2, 0.1, -1.0], dtype=torch.float64)
    n = n / n.norm()
    p = torch.zeros(3, dtype=torch.float64)
    d_ref = _plane_depth_world(ref, n, p)
    d_nb = _plane_depth_world(nb, n, p)
    ones = torch.ones(32, 32, dtype=torch.bool)
    loss, stats = multi_view_loss(d_ref, ones, ref, d_nb, ones, nb)
    # Not exactly 0: depth of a tilted plane is not bilinear in (u, v) (1/depth is).
    assert loss.item() < 1e-3 and stats["kept"] > 500
    # A neighbour depth off by 2% gives a sub-pixel error that counts...
    loss2, st2 = multi_view_loss(d_ref, ones, ref, d_nb * 1.02, ones, nb)
    assert loss2.item() > 0.05 and st2["kept"] > 0.5 * stats["kept"]
    # ...while a gross error (> 1 px everywhere) is excluded, not averaged in.
    loss3, st3 = multi_view_loss(d_ref, ones, ref, d_nb * 1.5, ones, nb)
    assert st3["kept"] < 0.05 * stats["kept"]
    assert loss3.item() <= 1.0


def test_multi_view_loss_gradients_finite_and_flow_to_both_depths():
    ref, nb = _two_views()
    n = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    d_ref = _plane_depth_world(ref, n, torch.zeros(3, dtype=torch.float64)).requires_grad_(True)
    d_nb = (_plane_depth_world(nb, n, torch.zeros(3, dtype=torch.float64)) * 1.01).requires_grad_(
        True
    )
    ones = torch.ones(32, 32, dtype=torch.bool)
    loss, _ = multi_view_loss(
        d_ref, ones, ref, d_nb, ones, nb, n_pixels=200, generator=torch.Generator().manual_seed(0)
    )
    loss.backward()
    assert torch.isfinite(d_ref.grad).all() and torch.isfinite(d_nb.grad).all()
    assert d_ref.grad.abs().sum() > 0 and d_nb.grad.abs().sum() > 0


def test_edge_weight_is_zero_on_edges_and_one_on_flat_regions():
    img = torch.zeros(16, 16, 3)
    img[:, 8:] = 1.0  # a vertical step between columns 7 and 8
    w = edge_weight(img)
    assert w.shape == (16, 16)
    assert torch.all(w[1:-1, 7:9] == 0.0)  # both columns next to the step
    assert torch.all(w[1:-1, 1:6] == 1.0) and torch.all(w[1:-1, 10:15] == 1.0)
    assert torch.all(w[0] == 0) and torch.all(w[:, -1] == 0)  # borders have no gradient
    flat = edge_weight(torch.full((8, 8, 3), 0.3))
    assert torch.all(flat[1:-1, 1:-1] == 1.0)


def test_single_view_loss_weight_masks_pixels():
    cam = identity_camera(16, 16)
    depth = torch.full((16, 16), 2.0)
    ones = torch.ones(16, 16, dtype=torch.bool)
    perpendicular = torch.zeros(16, 16, 3)
    perpendicular[..., 0] = 1.0  # the plane faces -z; this normal is at 90°
    assert abs(single_view_loss(perpendicular, depth, ones, cam).item() - 1.0) < 1e-5
    zero_w = torch.zeros(16, 16)
    assert single_view_loss(perpendicular, depth, ones, cam, zero_w).item() == 0.0
    half = torch.full((16, 16), 0.5)
    assert abs(single_view_loss(perpendicular, depth, ones, cam, half).item() - 0.5) < 1e-5


def test_multi_view_error_weighting_is_pgsrs_exp_weight():
    ref, nb = _two_views()
    n = torch.tensor([0.2, 0.1, -1.0], dtype=torch.float64)
    n = n / n.norm()
    d_ref = _plane_depth_world(ref, n, torch.zeros(3, dtype=torch.float64))
    d_nb = _plane_depth_world(nb, n, torch.zeros(3, dtype=torch.float64)) * 1.02
    ones = torch.ones(32, 32, dtype=torch.bool)
    plain, st = multi_view_loss(d_ref, ones, ref, d_nb, ones, nb)
    weighted, st2 = multi_view_loss(d_ref, ones, ref, d_nb, ones, nb, error_weighting=True)
    assert st == st2 and 0 < weighted.item() < plain.item()
    # exp(-e)·e ≥ e·exp(-1) for e ≤ 1 px, so the weighted mean stays above that bound.
    assert weighted.item() >= plain.item() * math.exp(-1.0) - 1e-12


def test_facing_view_by_angle_to_the_pixel_ray():
    from core.render.depth_geometry import DEPTH_FACING_DEG, facing_view

    cam = identity_camera(8)
    rays = cam.camera_rays(torch.float64)
    r = rays / rays.norm(dim=-1, keepdim=True)
    # a unit vector perpendicular to each ray, to tilt the normal away from it
    perp = torch.linalg.cross(r, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand_as(r))
    perp = perp / perp.norm(dim=-1, keepdim=True)

    def tilted(deg: float, scale: float = 1.0) -> torch.Tensor:
        a = math.radians(deg)
        return scale * (-math.cos(a) * r + math.sin(a) * perp)

    assert DEPTH_FACING_DEG == 60.0
    assert facing_view(tilted(0.0), cam).all()
    assert facing_view(tilted(59.0, 0.3), cam).all()  # blended normals are not unit
    assert facing_view(-tilted(59.0), cam).all()  # either side
    assert not facing_view(tilted(61.0), cam).any()
    assert not facing_view(tilted(90.0), cam).any()
    assert not facing_view(torch.zeros(8, 8, 3, dtype=torch.float64), cam).any()
    assert facing_view(tilted(70.0), cam, max_deg=75.0).all()


def test_single_view_loss_on_eq8_depth_cannot_see_a_wrong_normal():
    """Eq. 8 puts every pixel's depth on the plane (N, D) it was computed from, so with
    N and D constant over the image the depth-derived normals are N itself and L_single
    is zero, however wrong N is: on the planar depth L_single is a smoothness prior on
    (N, D), not a check of N against the splats' centres. The same wrong N against the
    depth of the true surface costs 1 − cos (docs/benchmarks.md, issue 36: handing
    L_single the centre depth instead did not improve the normals)."""
    cam = identity_camera(24)
    true_n = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    wrong_n = rotmat_y(30.0) @ true_n
    centre = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    valid = torch.ones(24, 24, dtype=torch.bool)
    rendered = wrong_n.expand(24, 24, 3)
    eq8 = planar_depth(
        rendered, torch.full((24, 24), float(wrong_n @ centre), dtype=torch.float64),
        torch.ones(24, 24, dtype=torch.float64), cam, compiled=False,
    )[0]  # fmt: skip
    assert single_view_loss(rendered, eq8, valid, cam).item() < 1e-12
    surface = _plane_depth(cam, true_n, centre)
    expected = 1.0 - math.cos(math.radians(30.0))
    assert abs(single_view_loss(rendered, surface, valid, cam).item() - expected) < 1e-9
