"""Splats proposed behind the rendered surface at an opacity reset
(core.training.seed_behind, DensifyStrategy.append, Trainer._add_splats)."""

from __future__ import annotations

import pytest
import torch

from core.config import config_from_dict
from core.scene.synthetic import SPHERE_RADIUS, make_scene
from core.training.densify import RESET_OPACITY
from core.training.init_points import inside_hull
from core.training.seed_behind import MARGIN_PX, hidden_everywhere, propose_behind, view_errors
from core.training.trainer import Trainer

TINY = {
    "iterations": 120,
    "init_points": 300,
    "envmap_resolution": 8,
    "densify": {"max_gaussians": 1500, "seed_behind": 0.2},
}


@pytest.fixture(scope="module")
def scene():
    return make_scene("sphere", "glossy", n_train=16, n_test=1, size=24, seed=1, samples=2)


@pytest.fixture()
def trainer(scene, tmp_path):
    t = Trainer(scene, config_from_dict(TINY), tmp_path)
    t.setup(resume=False)
    for _ in range(15):
        t.step()
    return t


def test_proposals_lie_inside_the_hull_behind_the_rendered_surface(trainer) -> None:
    scene = trainer.scene
    P, C = propose_behind(trainer.model, scene, 200, torch.Generator().manual_seed(0))
    assert P.shape[1] == 3 and C.shape == P.shape and 0 < P.shape[0] <= 200
    # inside the masks' hull, but for the half-step jitter at its far side
    assert float(inside_hull(P, scene, 0.9).float().mean()) > 0.9
    # behind the rendered surface of some view by the margin: none in front of every view
    errors = view_errors(trainer.model, scene.train)
    behind = torch.zeros(P.shape[0], dtype=torch.bool)
    for v, (_, depth) in zip(scene.train, errors, strict=True):
        uv, z = v.camera.project(P)
        px = uv.floor().long()
        ok = (px[:, 0] >= 0) & (px[:, 0] < v.width) & (px[:, 1] >= 0) & (px[:, 1] < v.height)
        idx = px[:, 1].clamp(0, v.height - 1) * v.width + px[:, 0].clamp(0, v.width - 1)
        d = depth[idx]
        behind |= ok & (z >= d * (1 + 0.5 * MARGIN_PX / v.camera.intrinsics.fx))
    assert bool(behind.all())


def test_the_worst_pixels_are_chosen(trainer) -> None:
    scene = trainer.scene
    errors = view_errors(trainer.model, scene.train)
    pooled = torch.cat([e for e, _ in errors])
    cut = float(torch.quantile(pooled[~torch.isnan(pooled)], 0.5))
    P, _ = propose_behind(trainer.model, scene, 10_000, torch.Generator().manual_seed(1),
                          quantile=0.5)  # fmt: skip
    few, _ = propose_behind(trainer.model, scene, 10_000, torch.Generator().manual_seed(1),
                            quantile=0.95)  # fmt: skip
    n_above = int((pooled > cut).sum())
    # every ray through a pixel above the cut is a candidate, one point each at most
    assert few.shape[0] < P.shape[0] <= n_above


def test_nothing_to_propose(trainer) -> None:
    gen = torch.Generator().manual_seed(0)
    assert propose_behind(trainer.model, trainer.scene, 0, gen) is None


def test_new_splats_join_at_the_reset_opacity_with_fresh_moments(trainer) -> None:
    t = trainer
    n0 = t.gaussians.num
    old_means = t.gaussians.params["means"].detach().clone()
    opt = t.optimizers["means"]
    old_m = opt.state[opt.param_groups[0]["params"][0]]["exp_avg"].clone()
    P, C = propose_behind(t.model, t.scene, 50, torch.Generator().manual_seed(0))
    k = t._add_splats(P, C)
    assert k == P.shape[0] and t.gaussians.num == n0 + k
    p = t.gaussians.params
    assert torch.equal(p["means"][:n0], old_means)
    assert torch.allclose(p["means"][n0:].double(), P.to(p["means"].device).double(), atol=1e-5)
    opacity = torch.sigmoid(p["opacity_logits"][n0:])
    assert torch.allclose(opacity, torch.full_like(opacity, RESET_OPACITY), rtol=1e-4)
    m = opt.state[opt.param_groups[0]["params"][0]]["exp_avg"]
    assert torch.equal(m[:n0], old_m) and not bool(m[n0:].any())
    # and training goes on with them
    for _ in range(3):
        t.step()
    assert t.gaussians.num >= n0


def test_append_refuses_rows_without_every_key(trainer) -> None:
    t = trainer
    values = {"means": torch.zeros(2, 3)}
    with pytest.raises(ValueError, match="keys"):
        t.strategy.append(t.gaussians, t.optimizers, values)


def test_a_run_seeds_at_its_opacity_reset(scene, tmp_path) -> None:
    t = Trainer(scene, config_from_dict(TINY), tmp_path)
    t.setup(resume=False)
    t.strategy.reset_every = 20  # resets at 20 and 40 (densification stops at 60)
    seeded = []
    for _ in range(41):
        out = t.step()
        seeded.append(out.get("densify_seeded", 0.0))
    assert seeded[20] > 0 and seeded[40] > 0
    assert sum(1 for s in seeded if s > 0) == 2


def test_hidden_everywhere_is_behind_the_surface_in_every_view(scene) -> None:
    # every view's rendered depth: a wall at the sphere's nearest point
    depths = [
        torch.full((v.height * v.width,), float(v.camera.center.norm()) - SPHERE_RADIUS)
        for v in scene.train
    ]
    pts = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # the sphere's centre: behind its surface from every side
            [0.0, 0.0, 1.5 * SPHERE_RADIUS],  # outside it: in front of it from above
        ],
        dtype=torch.float64,
    )
    assert hidden_everywhere(pts, scene.train, depths).tolist() == [True, False]
    # a point in no view's frame (behind the one camera): nothing says it is hidden
    v = scene.train[0]
    behind_camera = (2 * v.camera.center)[None]
    assert hidden_everywhere(behind_camera, [v], depths[:1]).tolist() == [False]
    # where a view rendered no surface, nothing hides the centre from it
    depths[3] = torch.full_like(depths[3], float("inf"))
    assert hidden_everywhere(pts, scene.train, depths).tolist() == [False, False]


def test_remove_keeps_the_others_and_their_moments(trainer) -> None:
    t = trainer
    n0 = t.gaussians.num
    opt = t.optimizers["means"]
    m0 = opt.state[opt.param_groups[0]["params"][0]]["exp_avg"].clone()
    means0 = t.gaussians.params["means"].detach().clone()
    drop = torch.zeros(n0, dtype=torch.bool)
    drop[[0, 5, 7]] = True
    assert t.strategy.remove(t.gaussians, t.optimizers, drop) == 3
    assert t.gaussians.num == n0 - 3
    assert torch.equal(t.gaussians.params["means"], means0[~drop])
    assert torch.equal(opt.state[opt.param_groups[0]["params"][0]]["exp_avg"], m0[~drop])
    with pytest.raises(ValueError, match="shape"):
        t.strategy.remove(t.gaussians, t.optimizers, drop)
    t.step()
