"""Per-splat roughness (core.render.roughness): the optional state, its life through
densification, checkpoints, the plan and the trainer, the G-buffer channel, and what
the deferred pass does with it."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from core.config import TrainConfig, config_from_dict
from core.model.checkpoint import load_checkpoint, save_checkpoint
from core.model.plan import ScenePlan
from core.render import gbuffer as gbuffer_mod
from core.render.envmap import EnvMap
from core.render.envmap_mips import mip_sizes, roughness_to_lod, sample_cube_lod
from core.render.gaussians import Gaussians
from core.render.gbuffer import GBuffer, render_gbuffer
from core.render.roughness import (
    DEFAULT_INIT_ROUGHNESS,
    ROUGH_KEY,
    add_roughness_state,
    drop_roughness_state,
    has_roughness,
    roughness,
)
from core.render.shading import deferred_shade
from core.scene.cameras import Camera, Intrinsics
from core.scene.synthetic import make_scene
from core.training import trainer as trainer_mod
from core.training.densify import DensifyStrategy
from core.training.optim import make_optimizers
from core.training.planner import decide_envmap, plan_scene
from core.training.trainer import Trainer
from tests.helpers import identity_camera
from tests.test_densify import (
    BIG,
    HIGH_PX,
    LOW_PX,
    SMALL,
    H,
    W,
    config,
    fake_result,
    make_gaussians,
)

F64 = torch.float64
SPECULAR = {"excess": 0.05, "highlight_fraction": 0.2}  # decide_envmap: on
DIFFUSE = {"excess": 0.0, "highlight_fraction": 0.0}  # decide_envmap: off


# -- the state --------------------------------------------------------------------------


def test_add_drop_has():
    g = Gaussians.from_points(torch.randn(7, 3))
    assert not has_roughness(g) and roughness(g) is None
    drop_roughness_state(g)  # nothing to drop: no error
    add_roughness_state(g)
    assert has_roughness(g)
    p = g.params[ROUGH_KEY]
    assert isinstance(p, nn.Parameter) and p.requires_grad and p.shape == (7,)
    torch.testing.assert_close(roughness(g), torch.full((7,), DEFAULT_INIT_ROUGHNESS))
    # a second add keeps what was learned
    with torch.no_grad():
        p[0] = 2.0
    add_roughness_state(g, 0.9)
    assert g.params[ROUGH_KEY] is p and float(p.detach()[0]) == 2.0
    drop_roughness_state(g)
    assert not has_roughness(g) and ROUGH_KEY not in g.params
    add_roughness_state(g, 0.4)
    torch.testing.assert_close(roughness(g), torch.full((7,), 0.4))
    # roughness is differentiable in the logits
    roughness(g).sum().backward()
    assert g.params[ROUGH_KEY].grad is not None and (g.params[ROUGH_KEY].grad > 0).all()
    for bad in (0.0, 1.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="initial roughness"):
            add_roughness_state(Gaussians.from_points(torch.randn(2, 3)), bad)


def test_state_follows_dtype_and_device_and_trains():
    g = Gaussians.from_points(torch.randn(5, 3).double())
    add_roughness_state(g)
    assert g.params[ROUGH_KEY].dtype == g.params["means"].dtype
    cfg = TrainConfig(iterations=10, lr={"roughness": 0.02})
    opts = make_optimizers(g, cfg, 1.0)
    assert ROUGH_KEY in opts
    assert opts[ROUGH_KEY].param_groups[0]["params"][0] is g.params[ROUGH_KEY]
    assert opts[ROUGH_KEY].param_groups[0]["lr"] == pytest.approx(0.02)


def test_densification_carries_roughness_rows_and_its_optimizer():
    # rows: small+high → clone, small+low, big+high → split, big+low (tests/test_densify.py)
    g = make_gaussians([SMALL, SMALL, BIG, BIG])
    add_roughness_state(g)
    with torch.no_grad():
        g.params[ROUGH_KEY].copy_(torch.tensor([-1.0, -0.5, 0.5, 1.0]))
    before = g.params[ROUGH_KEY].detach().clone()
    opts = make_optimizers(g, TrainConfig(), 1.0)
    stats = DensifyStrategy(config(), scene_radius=1.0).step_post_backward(
        g, opts, fake_result([HIGH_PX, LOW_PX, HIGH_PX, LOW_PX]), 100, W, H
    )
    assert stats["cloned"] == 1 and stats["split"] == 1 and g.num == 6
    # kept originals [0, 1, 3], the clone of 0, the two children of 2
    assert torch.equal(g.params[ROUGH_KEY].detach(), before[[0, 1, 3, 0, 2, 2]])
    assert opts[ROUGH_KEY].param_groups[0]["params"][0] is g.params[ROUGH_KEY]
    assert roughness(g).shape == (6,)
    # and a prune drops the same rows as everything else
    with torch.no_grad():
        g.params["opacity_logits"][1] = -20.0
    s = DensifyStrategy(config(), scene_radius=1.0)
    s.step_post_backward(g, opts, fake_result([LOW_PX] * 6), 100, W, H)
    assert g.num == 5
    assert torch.equal(g.params[ROUGH_KEY].detach(), before[[0, 3, 0, 2, 2]])


def test_checkpoint_round_trip(tmp_path):
    g = Gaussians.from_points(torch.randn(9, 3))
    add_roughness_state(g, 0.3)
    with torch.no_grad():
        g.params[ROUGH_KEY].add_(torch.linspace(-1, 1, 9))
    back = load_checkpoint(save_checkpoint(tmp_path / "r.pt", g, {"iteration": 3}), "cpu")
    assert has_roughness(back.gaussians)
    assert torch.equal(back.gaussians.params[ROUGH_KEY], g.params[ROUGH_KEY].detach())
    plain = Gaussians.from_points(torch.randn(4, 3))
    back = load_checkpoint(save_checkpoint(tmp_path / "p.pt", plain, {}), "cpu")
    assert not has_roughness(back.gaussians)


# -- the plan ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_scene():
    return make_scene("sphere", "glossy", n_train=4, n_test=1, size=16, seed=1, samples=1)


def test_plan_roughness_waits_for_the_env_map_and_follows_it(small_scene):
    cfg = config_from_dict({})
    plan = plan_scene(small_scene, cfg)
    assert plan.roughness.pending and plan.roughness.value is True
    assert plan.roughness_possible(cfg)  # the state is there from the start
    decide_envmap(plan, dict(SPECULAR), cfg)
    assert plan.envmap.value is True
    assert not plan.roughness.pending and plan.roughness.value is True
    assert plan.roughness_possible(cfg)

    plan = plan_scene(small_scene, cfg)
    decide_envmap(plan, dict(DIFFUSE), cfg)
    assert plan.envmap.value is False
    assert not plan.roughness.pending and plan.roughness.value is False
    assert "no env map" in plan.roughness.reason and not plan.roughness_possible(cfg)
    assert plan.to_dict()["decisions"]["roughness"]["value"] is False


def test_plan_roughness_off_by_ablation_or_without_deferred_shading(small_scene):
    for ablation, words in (
        ({"roughness": False}, "ablation"),
        ({"deferred_shading": False}, "deferred shading"),
    ):
        cfg = config_from_dict({"ablation": ablation})
        plan = plan_scene(small_scene, cfg)
        assert plan.roughness.value is False and not plan.roughness.pending
        assert words in plan.roughness.reason
        decide_envmap(plan, dict(SPECULAR), cfg)  # a specular scene does not bring it back
        assert plan.roughness.value is False and not plan.roughness_possible(cfg)


def test_plan_override_wins(small_scene):
    cfg = config_from_dict({"plan_overrides": {"roughness": False}})
    plan = plan_scene(small_scene, cfg)
    decide_envmap(plan, dict(SPECULAR), cfg)
    assert plan.envmap.value is True
    assert plan.roughness.value is False and plan.roughness.overridden
    assert "set by the user" in plan.roughness.reason and not plan.roughness_possible(cfg)
    # ...and the other way round, over the ablation switch
    cfg = config_from_dict(
        {"ablation": {"roughness": False}, "plan_overrides": {"roughness": True}}
    )
    plan = plan_scene(small_scene, cfg)
    decide_envmap(plan, dict(SPECULAR), cfg)
    assert plan.roughness.value is True and plan.roughness_possible(cfg)
    with pytest.raises(Exception, match=r"plan_overrides\.roughness"):
        plan_scene(small_scene, config_from_dict({"plan_overrides": {"roughness": 2}}))


@pytest.mark.parametrize("envmap", [True, False])
def test_an_env_map_set_by_the_user_decides_roughness_at_once(small_scene, envmap):
    """With ``plan_overrides.envmap`` (every bench row with deferred shading) no probe runs:
    roughness must not stay 'pending' for the whole run."""
    cfg = config_from_dict({"plan_overrides": {"envmap": envmap}})
    plan = plan_scene(small_scene, cfg)
    assert not plan.roughness.pending and plan.roughness.value is envmap
    assert plan.roughness_possible(cfg) is envmap


def test_plans_from_before_roughness_load_with_it_off(small_scene):
    d = plan_scene(small_scene, config_from_dict({})).to_dict()
    del d["decisions"]["roughness"]
    old = ScenePlan.from_dict(d)
    assert old.roughness.value is False and not old.roughness_possible(config_from_dict({}))


# -- the trainer ------------------------------------------------------------------------

TINY = {"iterations": 40, "init_points": 150, "envmap_resolution": 8, "eval": {"views": 1}}


def _trainer(scene, tmp_path, **cfg) -> Trainer:
    t = Trainer(scene, config_from_dict({**TINY, **cfg}), tmp_path)
    t.setup(resume=False)
    return t


@pytest.mark.parametrize(("evidence", "kept"), [(SPECULAR, True), (DIFFUSE, False)])
def test_trainer_drops_roughness_when_the_plan_turns_it_off(
    small_scene, tmp_path, monkeypatch, evidence, kept
):
    t = _trainer(small_scene, tmp_path, init_roughness=0.2)
    assert has_roughness(t.gaussians) and ROUGH_KEY in t.optimizers
    torch.testing.assert_close(roughness(t.gaussians), torch.full((t.gaussians.num,), 0.2))
    monkeypatch.setattr(trainer_mod, "probe_view_dependence", lambda *a, **k: dict(evidence))
    t.iteration = t.marks.geometry_start
    t._maybe_plan_view_dependence()
    assert not t.plan.roughness.pending and t.plan.roughness.value is kept
    assert has_roughness(t.gaussians) is kept
    assert (ROUGH_KEY in t.optimizers) is kept
    assert (t.envmap is not None) is kept


@pytest.mark.parametrize(
    "cfg",
    [{"ablation": {"roughness": False}}, {"ablation": {"deferred_shading": False}},
     {"plan_overrides": {"roughness": False}}],
)  # fmt: skip
def test_trainer_without_roughness_has_no_state(small_scene, tmp_path, cfg):
    t = _trainer(small_scene, tmp_path, **cfg)
    assert not has_roughness(t.gaussians) and ROUGH_KEY not in t.optimizers


# -- the G-buffer -----------------------------------------------------------------------


def _splats(n: int = 12, seed: int = 0) -> tuple[Gaussians, Camera]:
    gen = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, 3, generator=gen) * torch.tensor([1.0, 1.0, 0.3]) + torch.tensor(
        [-0.5, -0.5, 3.0]
    )
    g = Gaussians.from_points(pts, radius=1.0)
    with torch.no_grad():
        g.params["opacity_logits"].fill_(2.0)
        g.params["refl_logits"].fill_(0.0)  # w_r = 0.5
    return g, identity_camera(24, dtype=torch.float32)


def _channels_splatted(monkeypatch) -> list[int]:
    seen: list[int] = []
    real = gbuffer_mod.rasterize

    def spy(*args, **kw):
        seen.append(int(args[4].shape[-1]))
        return real(*args, **kw)

    monkeypatch.setattr(gbuffer_mod, "rasterize", spy)
    return seen


def test_render_gbuffer_splats_roughness_only_when_asked_and_present(monkeypatch):
    seen = _channels_splatted(monkeypatch)
    g, cam = _splats()
    gb, _ = render_gbuffer(g, cam, sh_degree=0)
    assert seen == [9] and gb.roughness is None  # no state: 9 channels
    add_roughness_state(g, 0.3)
    gb, _ = render_gbuffer(g, cam, sh_degree=0, with_roughness=False)
    assert seen == [9, 9] and gb.roughness is None
    with torch.no_grad():  # the compiled features path too
        gb, _ = render_gbuffer(g, cam, sh_degree=0)
    assert seen == [9, 9, 10] and gb.roughness is not None
    gb, _ = render_gbuffer(g, cam, sh_degree=0)
    assert seen == [9, 9, 10, 10]
    # blended like w_r: premultiplied by coverage, so ρ = 0.3 everywhere reads 0.3 · alpha
    assert gb.roughness.shape == gb.alpha.shape and float(gb.alpha.detach().max()) > 0.5
    torch.testing.assert_close(gb.roughness, 0.3 * gb.alpha, rtol=1e-4, atol=1e-6)


# -- shading ----------------------------------------------------------------------------


def _gbuffer(rough: torch.Tensor | None, alpha: torch.Tensor) -> GBuffer:
    """A flat G-buffer facing an off-axis camera, normals varying across the image."""
    h, w = alpha.shape
    cam = Camera.look_at(
        [0.3, -0.2, 3.0], [0, 0, 0], [0, 1, 0], Intrinsics(20, 20, w / 2, h / 2, w, h)
    )
    jj, ii = torch.meshgrid(torch.linspace(-0.4, 0.4, h, dtype=F64),
                            torch.linspace(-0.4, 0.4, w, dtype=F64), indexing="ij")  # fmt: skip
    normal = torch.stack([ii, jj, -torch.ones_like(ii)], -1)
    normal = normal / normal.norm(dim=-1, keepdim=True) * alpha[..., None]
    z = torch.zeros(h, w, dtype=F64)
    return GBuffer(
        base=torch.full((h, w, 3), 0.1, dtype=F64) * alpha[..., None],
        normal=normal,
        plane_dist=z,
        w_r=0.8 * alpha,
        alpha=alpha,
        camera=cam,
        roughness=None if rough is None else rough * alpha,  # premultiplied, as splatted
    )


def _random_env(r: int = 16, seed: int = 3) -> EnvMap:
    env = EnvMap(resolution=r).double()
    with torch.no_grad():
        env.log_radiance.normal_(generator=torch.Generator().manual_seed(seed))
    return env


@pytest.mark.parametrize("coverage", [1.0, 0.4])
def test_specular_is_the_mirror_lookup_where_smooth_and_blurred_where_rough(coverage):
    h, w = 10, 12
    alpha = torch.full((h, w), coverage, dtype=F64)
    rho = torch.zeros(h, w, dtype=F64)
    rho[:, w // 2 :] = torch.linspace(0.2, 0.9, h, dtype=F64)[:, None]
    env = _random_env()
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=F64)
    mirror = deferred_shade(_gbuffer(None, alpha), env, bg, compiled=False)
    rough = deferred_shade(_gbuffer(rho, alpha), env, bg, compiled=False)
    smooth = rho == 0
    torch.testing.assert_close(rough.specular[smooth], mirror.specular[smooth], rtol=0, atol=1e-12)
    diff = (rough.specular - mirror.specular).abs().amax(-1)
    assert (diff[~smooth] > 1e-3).all(), diff[~smooth].min()
    torch.testing.assert_close(rough.base, mirror.base)
    torch.testing.assert_close(rough.reflected_dir, mirror.reflected_dir)
    # and it is the env map read at the LOD of the un-premultiplied ρ
    levels = len(mip_sizes(env.resolution))
    lod = roughness_to_lod(rho, env.resolution, levels)
    want = (0.8 * alpha)[..., None] * sample_cube_lod(env.texels(), mirror.reflected_dir, lod)
    torch.testing.assert_close(rough.specular, want)


def test_gradients_reach_rough_logits_through_deferred_shade():
    g, cam = _splats(seed=1)
    add_roughness_state(g, 0.3)
    with torch.no_grad():  # different roughness per splat
        g.params[ROUGH_KEY].copy_(torch.linspace(-2.0, 1.0, g.num))
    env = _random_env(8).float()
    gb, _ = render_gbuffer(g, cam, sh_degree=0)
    shade = deferred_shade(gb, env, torch.zeros(3))
    weights = torch.rand(shade.final.shape, generator=torch.Generator().manual_seed(0))
    (shade.final * weights).sum().backward()
    grad = g.params[ROUGH_KEY].grad
    assert grad is not None and torch.isfinite(grad).all()
    assert (grad != 0).sum() >= g.num // 2, grad
    assert env.log_radiance.grad is not None and torch.isfinite(env.log_radiance.grad).all()
    # a constant env map is the same at every level: roughness then changes nothing
    flat = EnvMap(resolution=8)
    g.params[ROUGH_KEY].grad = None
    gb, _ = render_gbuffer(g, cam, sh_degree=0)
    (deferred_shade(gb, flat, torch.zeros(3)).final * weights).sum().backward()
    assert g.params[ROUGH_KEY].grad.abs().max() < 1e-6 * max(1.0, grad.abs().max().item())


def test_init_roughness_default_matches_the_module():
    assert TrainConfig().init_roughness == DEFAULT_INIT_ROUGHNESS
    assert TrainConfig().ablation.roughness is True
    assert math.isclose(TrainConfig().lr.roughness, 0.01)
