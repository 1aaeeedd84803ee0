"""One-sided splats (core.render.orientation): sides learned from the views, culling."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from core.config import TrainConfig
from core.model.checkpoint import load_checkpoint, save_checkpoint
from core.model.trained import TrainedModel
from core.render.gaussians import Gaussians
from core.render.gbuffer import render_gbuffer
from core.render.orientation import (
    SEEN_COUNT,
    SEEN_DIR,
    add_orientation_state,
    facing,
    record_visibility,
)
from core.scene.cameras import Camera, Intrinsics
from core.scene.synthetic import make_scene
from core.scene.views import Scene
from core.training.optim import make_optimizers

from .test_silhouette import discs_on_the_sphere


@pytest.fixture(scope="module")
def sphere() -> Scene:
    return make_scene("sphere", "diffuse", n_train=16, n_test=0, size=64, samples=4)


def seen_from_every_view(g: Gaussians, scene: Scene) -> None:
    add_orientation_state(g)
    for v in scene.train:
        with torch.no_grad():
            gb, _ = render_gbuffer(g, v.camera, sh_degree=0, antialiased=True, lowpass=1 / 12)
        record_visibility(g, v.camera, gb.depth, gb.depth_valid)


def alpha_shift_px(g: Gaussians, scene: Scene, cull: bool) -> float:
    from scipy import ndimage

    shifts = []
    for v in scene.train:
        scale = facing(g, v.camera) if cull else None
        with torch.no_grad():
            gb, _ = render_gbuffer(
                g, v.camera, sh_degree=0, antialiased=True, lowpass=1 / 12, opacity_scale=scale
            )
        truth = v.mask.numpy()
        inside = truth > 0.5
        boundary = (inside ^ ndimage.binary_erosion(inside)).sum()
        shifts.append(float(gb.alpha.numpy().sum() - truth.sum()) / boundary)
    return float(np.mean(shifts))


def test_the_views_teach_each_disc_its_outside_and_culling_sharpens_silhouettes(sphere):
    g = discs_on_the_sphere()
    seen_from_every_view(g, sphere)
    mu, n = g.params["means"].detach(), g.normals().detach()
    seen = g.params[SEEN_DIR]
    learned = torch.sign((n * seen).sum(-1))
    truth = torch.sign((n * mu).sum(-1))  # discs on a sphere at the origin: outward
    counted = g.params[SEEN_COUNT] >= 3
    assert float(counted.float().mean()) > 0.95
    assert float((learned[counted] == truth[counted]).float().mean()) > 0.99
    # culling removes exactly discs whose outside faces away (never a front-facing one)
    cam = sphere.train[0].camera
    culled = facing(g, cam) == 0
    front = ((cam.center.float()[None] - mu) * (n * truth[:, None])).sum(-1) > 0
    assert int(culled.sum()) > 0.25 * len(mu)
    assert int((culled & front).sum()) == 0
    # the far side's tails no longer widen the silhouette (measured 0.40 → 0.09 px)
    two_sided, one_sided = alpha_shift_px(g, sphere, False), alpha_shift_px(g, sphere, True)
    assert one_sided < 0.2 and two_sided - one_sided > 0.2


def test_round_blobs_and_sheets_seen_from_both_sides_stay_two_sided(sphere):
    g = discs_on_the_sphere(2000)
    add_orientation_state(g)
    with torch.no_grad():
        mu = g.params["means"].detach()
        g.params[SEEN_DIR][:] = 10.0 * mu / mu.norm(dim=-1, keepdim=True)  # seen from outside...
        g.params[SEEN_COUNT][:] = 10.0
        g.params["log_scales"][:1000] = math.log(0.01)  # ...but the first half are round
    cam = sphere.train[0].camera
    culled = facing(g, cam) == 0
    assert not bool(culled[:1000].any()) and bool(culled[1000:].any())
    with torch.no_grad():  # a sheet seen as often from one side as from the other
        g.params[SEEN_DIR][:] = 0.0
    assert not bool((facing(g, cam) == 0).any())


def test_no_orientation_state_no_culling(sphere):
    g = discs_on_the_sphere(500)
    assert facing(g, sphere.train[0].camera) is None
    assert record_visibility(g, sphere.train[0].camera, torch.ones(64, 64), torch.ones(64, 64)) == 0


def test_orientation_state_is_untrained_and_survives_a_checkpoint(tmp_path: Path, sphere):
    g = discs_on_the_sphere(300)
    seen_from_every_view(g, sphere)
    assert not g.params[SEEN_DIR].requires_grad and not g.params[SEEN_COUNT].requires_grad
    assert SEEN_DIR not in make_optimizers(g, TrainConfig(), 1.0)
    save_checkpoint(tmp_path / "c.pt", g, {})
    back = load_checkpoint(tmp_path / "c.pt", "cpu").gaussians
    torch.testing.assert_close(back.params[SEEN_DIR], g.params[SEEN_DIR])
    assert not back.params[SEEN_COUNT].requires_grad
    # densification's row selection carries it to copies
    picked = back.index_select(torch.tensor([0, 0, 5]))
    torch.testing.assert_close(picked.params[SEEN_DIR][1], g.params[SEEN_DIR][0])


def test_a_trained_model_renders_one_sided(sphere):
    g = discs_on_the_sphere()
    seen_from_every_view(g, sphere)
    cams = [v.camera for v in sphere.train]
    model = TrainedModel(
        gaussians=g, envmap=None, config=TrainConfig(iterations=10), plan=None, iteration=10,
        device=torch.device("cpu"), backend="auto", cameras=cams,
    )  # fmt: skip
    # a camera inside the sphere sees only the inside of every disc: all culled
    inside = Camera.look_at(
        [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], Intrinsics(40, 40, 16, 16, 32, 32)
    )
    alpha = model.render(inside, ("alpha",)).gbuffer.alpha
    assert float(alpha.max()) < 0.05
    two_sided = TrainedModel(
        gaussians=g, envmap=None, config=TrainConfig(iterations=10, ablation={"one_sided": False}),
        plan=None, iteration=10, device=torch.device("cpu"), backend="auto", cameras=cams,
    )  # fmt: skip
    assert float(two_sided.render(inside, ("alpha",)).gbuffer.alpha.median()) > 0.9
