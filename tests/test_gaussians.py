"""Gaussians: accessors, Eq. 6 normals, covariance, construction, selection."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from core.render.gaussians import PARAM_SHAPES, SCALE_RANGE, Gaussians
from core.render.rotations import normalize_quats
from core.render.sh import C0, C1, sh_to_rgb
from core.scene.cameras import Camera, Intrinsics
from core.scene.views import Scene

INTR = Intrinsics(50.0, 50.0, 16.0, 16.0, 32, 32)


def make(
    means: list[list[float]],
    scales: list[list[float]],
    quats_wxyz: list[list[float]],
) -> Gaussians:
    n = len(means)
    params = {
        "means": torch.tensor(means, dtype=torch.float32),
        "log_scales": torch.tensor(scales, dtype=torch.float32).log(),
        "quats": torch.tensor(quats_wxyz, dtype=torch.float32),
        "opacity_logits": torch.zeros(n),
        "sh_dc": torch.zeros(n, 1, 3),
        "sh_rest": torch.zeros(n, 15, 3),
        "refl_logits": torch.zeros(n),
    }
    return Gaussians(params)


def scipy_quat_wxyz(rot: Rotation) -> list[float]:
    x, y, z, w = rot.as_quat()
    return [float(w), float(x), float(y), float(z)]


def random_gaussians(n: int = 20, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    params = {k: torch.randn(n, *shape, generator=g) for k, shape in PARAM_SHAPES.items()}
    return Gaussians(params)


def test_rotation_matches_scipy_and_ignores_quat_length() -> None:
    rots = Rotation.random(8, random_state=0)
    q = torch.tensor([scipy_quat_wxyz(r) for r in rots], dtype=torch.float32)
    g = make([[0, 0, 0]] * 8, [[1, 1, 1]] * 8, (q * 3.7).tolist())
    torch.testing.assert_close(
        g.rotations, torch.tensor(rots.as_matrix(), dtype=torch.float32), atol=1e-6, rtol=0
    )
    torch.testing.assert_close(g.unit_quats.norm(dim=1), torch.ones(8))


def test_normal_is_rotated_third_axis() -> None:
    rot = Rotation.from_rotvec([0.3, -1.1, 0.7])
    g = make([[0.0, 0.0, 0.0]], [[1.0, 2.0, 0.01]], [scipy_quat_wxyz(rot)])
    expected = torch.tensor(rot.apply([0.0, 0.0, 1.0]), dtype=torch.float32)
    torch.testing.assert_close(g.normals()[0], expected, atol=1e-6, rtol=0)
    assert g.min_axis().item() == 2


def test_normal_follows_smallest_scale_axis() -> None:
    rot = Rotation.from_euler("xyz", [20, 40, -65], degrees=True)
    q = scipy_quat_wxyz(rot)
    scales = [[0.01, 1.0, 2.0], [1.0, 0.02, 2.0], [3.0, 2.0, 0.5]]
    g = make([[0, 0, 0]] * 3, scales, [q] * 3)
    R = rot.as_matrix()
    expected = torch.tensor(np.stack([R[:, 0], R[:, 1], R[:, 2]]), dtype=torch.float32)
    torch.testing.assert_close(g.normals(), expected, atol=1e-6, rtol=0)
    # Not the row (the paper's "R_i[k, :]" is the row of Rᵀ): the rotation is not symmetric.
    assert not torch.allclose(g.normals()[0], torch.tensor(R[0], dtype=torch.float32), atol=1e-3)


def test_normal_is_eigenvector_of_smallest_covariance_eigenvalue() -> None:
    g = random_gaussians(50, seed=1)
    evals, evecs = torch.linalg.eigh(g.covariances.double())
    n = g.normals().double()
    smallest = evecs[:, :, 0]
    assert torch.allclose(
        (smallest * n).sum(1).abs(), torch.ones(50, dtype=torch.float64), atol=1e-4
    )
    s2 = g.scales.double().pow(2).sort(dim=1).values
    torch.testing.assert_close(evals, s2, rtol=1e-4, atol=1e-6)


def test_covariance_is_R_S2_Rt() -> None:
    rot = Rotation.from_rotvec([0.9, 0.2, -0.4])
    s = [1.0, 2.0, 0.01]
    g = make([[1, 2, 3]], [s], [scipy_quat_wxyz(rot)])
    R = rot.as_matrix()
    expected = R @ np.diag(np.square(s)) @ R.T
    torch.testing.assert_close(
        g.covariances[0], torch.tensor(expected, dtype=torch.float32), atol=1e-5, rtol=1e-5
    )


def test_normals_toward_camera_from_both_sides() -> None:
    # Normal along +z; Gaussian at the origin.
    g = make([[0.0, 0.0, 0.0]], [[1.0, 1.0, 0.01]], [[1.0, 0.0, 0.0, 0.0]])
    above = Camera.look_at([0.0, 0.0, 5.0], [0, 0, 0], [0, 1, 0], INTR)
    below = Camera.look_at([0.0, 0.0, -5.0], [0, 0, 0], [0, 1, 0], INTR)
    oblique = Camera.look_at([3.0, 1.0, -0.5], [0, 0, 0], [0, 0, 1], INTR)
    torch.testing.assert_close(g.normals_toward(above)[0], torch.tensor([0.0, 0.0, 1.0]))
    torch.testing.assert_close(g.normals_toward(below)[0], torch.tensor([0.0, 0.0, -1.0]))
    torch.testing.assert_close(g.normals_toward(oblique)[0], torch.tensor([0.0, 0.0, -1.0]))
    # Flipped Gaussians (rotated by π about x) give the same oriented result.
    flipped = make([[0.0, 0.0, 0.0]], [[1.0, 1.0, 0.01]], [[0.0, 1.0, 0.0, 0.0]])
    torch.testing.assert_close(flipped.normals()[0], torch.tensor([0.0, 0.0, -1.0]))
    torch.testing.assert_close(flipped.normals_toward(above)[0], torch.tensor([0.0, 0.0, 1.0]))


def test_normals_toward_many_random() -> None:
    g = random_gaussians(200, seed=2)
    cam = Camera.look_at([4.0, -3.0, 2.0], [0, 0, 0], [0, 0, 1], INTR)
    n = g.normals_toward(cam)
    c = cam.center.float()
    assert torch.all((n * (c - g.means)).sum(1) >= 0)
    torch.testing.assert_close(n.abs(), g.normals().abs())


def test_zero_quaternion_is_identity_with_finite_gradients() -> None:
    g = make([[0, 0, 0], [1, 0, 0]], [[1.0, 2.0, 0.01]] * 2, [[0, 0, 0, 0], [0.5, 0, 0, 0]])
    torch.testing.assert_close(g.rotations[0], torch.eye(3))
    torch.testing.assert_close(g.rotations[1], torch.eye(3))
    torch.testing.assert_close(g.normals()[0], torch.tensor([0.0, 0.0, 1.0]))
    loss = g.normals().sum() + g.covariances.sum() + g.unit_quats.sum()
    loss.backward()
    grad = g.params["quats"].grad
    assert grad is not None and torch.isfinite(grad).all()
    # Tiny but non-zero quaternions still normalise to unit length.
    q = normalize_quats(torch.tensor([[1e-9, 0.0, 1e-9, 0.0]]))
    torch.testing.assert_close(q.norm(dim=1), torch.ones(1))


def test_accessors_apply_constraints() -> None:
    g = random_gaussians(10, seed=3)
    p = g.params
    torch.testing.assert_close(g.scales, p["log_scales"].exp())
    torch.testing.assert_close(g.opacities, torch.sigmoid(p["opacity_logits"]))
    torch.testing.assert_close(g.w_r, torch.sigmoid(p["refl_logits"]))
    assert g.sh.shape == (10, 16, 3)
    torch.testing.assert_close(g.sh[:, 0], p["sh_dc"][:, 0])
    assert g.num == len(g) == 10
    assert g.device == torch.device("cpu")
    assert isinstance(g.params, torch.nn.ParameterDict)
    assert all(v.requires_grad for v in g.params.values())


def test_colors_use_direction_from_camera_to_mean() -> None:
    g = make([[0.0, 0.0, 0.0]], [[1.0, 1.0, 1.0]], [[1.0, 0.0, 0.0, 0.0]])
    with torch.no_grad():
        g.params["sh_dc"][0, 0] = torch.tensor([0.1, 0.2, 0.3]) / C0
        g.params["sh_rest"][0, 1] = torch.tensor([1.0, 0.0, -1.0])  # Y_1 z-term
    cam = Camera.look_at([0.0, 0.0, -4.0], [0, 0, 0], [0, 1, 0], INTR)  # direction +z
    col = g.colors(cam, degree=1)
    torch.testing.assert_close(col[0], torch.tensor([0.6 + C1, 0.7, max(0.8 - C1, 0.0)]))
    # Degree 0 ignores view dependence.
    torch.testing.assert_close(g.colors(cam, degree=0)[0], torch.tensor([0.6, 0.7, 0.8]))
    # From the other side the lobe flips.
    cam2 = Camera.look_at([0.0, 0.0, 4.0], [0, 0, 0], [0, 1, 0], INTR)
    torch.testing.assert_close(g.colors(cam2, degree=3)[0], torch.tensor([0.6 - C1, 0.7, 0.8 + C1]))
    # Matches the generic SH evaluation for random Gaussians.
    r = random_gaussians(30, seed=4)
    expected = sh_to_rgb(3, r.sh, r.means - cam.center.float())
    torch.testing.assert_close(r.colors(cam), expected)


def test_from_points_scale_matches_grid_spacing() -> None:
    for d in (0.05, 3.0):
        ax = torch.arange(8, dtype=torch.float64) * d
        pts = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
        g = Gaussians.from_points(pts, torch.rand(pts.shape[0], 3))
        torch.testing.assert_close(g.scales, torch.full((512, 3), d, dtype=torch.float32))
        torch.testing.assert_close(g.unit_quats, torch.tensor([[1.0, 0, 0, 0]]).expand(512, 4))
        torch.testing.assert_close(g.opacities, torch.full((512,), 0.1))
        assert g.sh_degree == 3
        assert torch.all(g.params["sh_rest"] == 0)


def test_from_points_colors_and_init_values() -> None:
    pts = torch.rand(50, 3)
    cols = torch.rand(50, 3)
    g = Gaussians.from_points(pts, cols, init_opacity=0.3, init_refl=0.2, sh_degree=1)
    torch.testing.assert_close(g.params["sh_dc"][:, 0] * C0 + 0.5, cols)
    torch.testing.assert_close(g.opacities, torch.full((50,), 0.3))
    torch.testing.assert_close(g.w_r, torch.full((50,), 0.2))
    assert g.sh_degree == 1
    u8 = Gaussians.from_points(pts, (cols * 255).round().to(torch.uint8))
    rgb = u8.sh[:, 0] * C0 + 0.5
    torch.testing.assert_close(rgb, (cols * 255).round() / 255, atol=1e-6, rtol=0)
    with pytest.raises(ValueError):
        Gaussians.from_points(pts, cols, init_opacity=1.0)
    with pytest.raises(ValueError):
        Gaussians.from_points(pts[:, :2], None)


def test_from_points_scale_is_clamped_and_finite() -> None:
    # Duplicates (distance 0) and a far outlier.
    pts = torch.tensor([[0.0, 0, 0]] * 4 + [[0.1, 0, 0], [100.0, 0, 0]])
    g = Gaussians.from_points(pts, None, radius=1.0)
    s = g.scales[:, 0]
    assert torch.isfinite(g.params["log_scales"]).all()
    assert s.min().item() == pytest.approx(SCALE_RANGE[0], rel=1e-5)
    assert s.max().item() == pytest.approx(SCALE_RANGE[1], rel=1e-5)
    one = Gaussians.from_points(torch.tensor([[1.0, 2.0, 3.0]]), None, radius=2.0)
    assert one.scales[0, 0].item() == pytest.approx(SCALE_RANGE[1] * 2.0, rel=1e-5)


def test_random_is_deterministic_and_in_ball() -> None:
    center = [1.0, -2.0, 0.5]
    a = Gaussians.random(center, 2.0, 2000, seed=7)
    b = Gaussians.random(center, 2.0, 2000, seed=7)
    c = Gaussians.random(center, 2.0, 2000, seed=8)
    assert all(torch.equal(a.params[k], b.params[k]) for k in a.params)
    assert not torch.equal(a.means, c.means)
    r = (a.means - torch.tensor(center)).norm(dim=1)
    assert r.max().item() <= 2.0 + 1e-5
    # Uniform in the ball: the fraction inside half the radius is 1/8.
    assert (r < 1.0).float().mean().item() == pytest.approx(1 / 8, abs=0.03)
    rgb = a.sh[:, 0] * C0 + 0.5
    assert rgb.min() >= 0 and rgb.max() <= 1 and rgb.std() > 0.2


def test_from_scene_uses_points_or_random() -> None:
    pts = torch.rand(30, 3, dtype=torch.float64)
    cols = torch.rand(30, 3)
    sc = Scene([], [], torch.zeros(3, dtype=torch.float64), 1.5, "test", None, pts, cols)
    g = Gaussians.from_scene(sc)
    assert g.num == 30
    torch.testing.assert_close(g.means, pts.float())
    sc.points = None
    r = Gaussians.from_scene(sc, n_random=123, seed=1)
    assert r.num == 123
    assert r.means.norm(dim=1).max().item() <= 1.5 + 1e-5


def test_constructor_validates_shapes() -> None:
    good = {k: v.detach() for k, v in random_gaussians(4).params.items()}
    bad = dict(good, sh_rest=torch.zeros(4, 8, 3))
    with pytest.raises(ValueError, match="sh_rest"):
        Gaussians(bad)
    missing = {k: v for k, v in good.items() if k != "refl_logits"}
    with pytest.raises(ValueError, match="refl_logits"):
        Gaussians(missing)
    with pytest.raises(ValueError, match="foo"):
        Gaussians(dict(good, foo=torch.zeros(5)))


def test_index_select_and_cat_carry_every_parameter() -> None:
    g = random_gaussians(10, seed=5)
    extra = dict(g.params.items())
    extra["feature"] = torch.nn.Parameter(torch.arange(20.0).reshape(10, 2))
    g = Gaussians(extra, sh_degree=2)
    mask = torch.zeros(10, dtype=torch.bool)
    mask[[1, 4, 7]] = True
    sel = g.index_select(mask)
    same = g.index_select(torch.tensor([1, 4, 7]))
    assert sel.num == 3 and sel.sh_degree == 2
    for k in g.params:
        assert torch.equal(sel.params[k], g.params[k][mask].detach())
        assert torch.equal(same.params[k], sel.params[k])
        assert sel.params[k].is_leaf and sel.params[k].requires_grad
    both = sel.cat(g)
    assert both.num == 13
    assert set(both.params.keys()) == set(g.params.keys())
    for k in g.params:
        assert torch.equal(both.params[k][3:], g.params[k].detach())
    with pytest.raises(ValueError):
        both.cat(random_gaussians(2))
    with pytest.raises(ValueError):
        g.index_select(torch.ones(3, dtype=torch.bool))


def test_clone_detach_to_are_independent() -> None:
    g = random_gaussians(5)
    c = g.clone()
    d = g.detach()
    assert g.to("cpu") is g  # already there: no copy, like Tensor.to
    assert all(c.params[k].requires_grad for k in c.params)
    assert not any(d.params[k].requires_grad for k in d.params)
    with torch.no_grad():
        g.params["means"].add_(1.0)
    for other in (c, d):
        assert not torch.equal(other.means, g.means)
    state = g.state_dict()
    back = Gaussians.from_state_dict(state)
    assert all(torch.equal(back.params[k], g.params[k]) for k in g.params)


def test_gradients_flow_to_all_parameters() -> None:
    g = random_gaussians(8, seed=6)
    cam = Camera.look_at([0.0, 0.0, -6.0], [0, 0, 0], [0, 1, 0], INTR)
    loss = (
        g.colors(cam).sum()
        + g.normals_toward(cam).sum()
        + g.covariances.sum()
        + g.opacities.sum()
        + g.w_r.sum()
    )
    loss.backward()
    for k, p in g.params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all(), k
        assert p.grad.abs().sum() > 0, k


def test_default_random_count_is_fast() -> None:
    import time

    t = time.perf_counter()
    g = Gaussians.random([0, 0, 0], 1.0, 100_000)
    assert g.num == 100_000
    assert time.perf_counter() - t < 5.0
    assert math.isfinite(g.scales.mean().item())
