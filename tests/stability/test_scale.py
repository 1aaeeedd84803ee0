"""Scene units: the same capture in millimetres, metres and kilometres (×1e-3, ×1, ×1e3).

Expected answers:

* rendering is unit-free: the same Gaussians and cameras scaled by k give the same
  final image, alpha and normals, and depth / k (before the fix, the fixed 0.01 near
  plane culled every Gaussian of the millimetre scene: an empty image);
* learning rates follow the scene radius: the position learning rate (initial, decayed
  and the one the trainer actually sets) is ∝ radius, every other rate is unit-free;
  densification's world-size thresholds (percent_dense split scale, world-size prune)
  are ∝ radius;
* a short training run is unit-free: after 30 iterations the ×1e-3 and ×1e3 runs
  hold the ×1 run's parameters scaled by k (before the fix the λ2 scale loss, a sum
  of world-unit scales, weighed 1e6× more in kilometres than in millimetres).
"""

from __future__ import annotations

import math

import pytest
import torch

from core.config import config_from_dict
from core.render.envmap import EnvMap
from core.render.gaussians import Gaussians
from core.render.gbuffer import render_gbuffer_tensors
from core.render.shading import deferred_shade
from core.scene.synthetic import fibonacci_cameras
from core.training.densify import DensifyStrategy
from core.training.optim import make_optimizers, means_lr
from core.training.trainer import Trainer
from tests.stability.common import BACKENDS, TINY_TRAIN, scaled_scene

UNITS = [1e-3, 1.0, 1e3]


def _scaled_camera(cam, k):
    from core.scene.cameras import Camera

    w2c = cam.world_to_cam.clone()
    w2c[:3, 3] *= k
    return Camera(cam.intrinsics, w2c, cam.name)


def _model(seed: int = 3) -> Gaussians:
    """60 flattened Gaussians scattered in a ball of radius 0.6 about the origin."""
    g = Gaussians.random([0.0, 0.0, 0.0], 0.6, 60, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        g.params["quats"].copy_(torch.randn(60, 4, generator=gen))
        g.params["log_scales"][:, 2] -= 6.0  # flat: smallest scale 1/400 of the others
        g.params["opacity_logits"].fill_(1.5)
        g.params["refl_logits"].fill_(0.0)
    return g


def _render(g: Gaussians, cam, k: float, backend: str):
    env = EnvMap(8)
    gb, _ = render_gbuffer_tensors(
        g.means.detach() * k,
        g.unit_quats.detach(),
        g.scales.detach() * k,
        g.opacities.detach(),
        g.colors(_scaled_camera(cam, 1.0), 0).detach(),
        g.normals().detach(),
        g.w_r.detach(),
        _scaled_camera(cam, k),
        backend=backend,
    )
    shade = deferred_shade(gb, env, torch.ones(3))
    return gb, shade


@pytest.mark.parametrize("backend", BACKENDS)
def test_rendering_is_unit_free(backend):
    """mm / m / km: final image and alpha equal to 1e-5, normals to 1e-4, depth / k and
    centre depth / k equal to 1e-5 relative, the same pixels valid."""
    g = _model()
    for cam in fibonacci_cameras(3, distance=3.0, size=24):
        gb1, sh1 = _render(g, cam, 1.0, backend)
        assert float(gb1.alpha.max()) > 0.5, "the reference view must see the model"
        for k in (1e-3, 1e3):
            gbk, shk = _render(g, cam, k, backend)
            torch.testing.assert_close(gbk.alpha, gb1.alpha, atol=1e-5, rtol=0)
            torch.testing.assert_close(shk.final, sh1.final, atol=1e-5, rtol=0)
            torch.testing.assert_close(gbk.normal, gb1.normal, atol=1e-4, rtol=0)
            assert torch.equal(gbk.depth_valid, gb1.depth_valid), f"k={k}: valid pixels differ"
            v = gb1.depth_valid
            torch.testing.assert_close(gbk.depth[v] / k, gb1.depth[v], rtol=1e-5, atol=0)
            torch.testing.assert_close(gbk.center_depth / k, gb1.center_depth, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("k", UNITS)
def test_learning_rates_and_thresholds_follow_the_radius(k):
    """Position lr (initial, decayed, and what a trainer sets) and densification's world
    thresholds are ∝ radius; every other learning rate is the same in every unit."""
    cfg = config_from_dict({"iterations": 100})
    radius = 0.6
    g = Gaussians.random([0.0, 0.0, 0.0], radius * k, 10)
    opts = make_optimizers(g, cfg, radius * k)
    ref = make_optimizers(Gaussians.random([0.0, 0.0, 0.0], radius, 10), cfg, radius)
    for name, opt in opts.items():
        want = ref[name].param_groups[0]["lr"] * (k if name == "means" else 1.0)
        assert opt.param_groups[0]["lr"] == pytest.approx(want, rel=1e-12), name
    for it in (0, 50, 100):
        assert means_lr(cfg, it, radius * k) == pytest.approx(k * means_lr(cfg, it, radius))
    d, d1 = DensifyStrategy(cfg, radius * k), DensifyStrategy(cfg, radius)
    assert d.split_scale == pytest.approx(k * d1.split_scale)
    assert d.world_max_scale == pytest.approx(k * d1.world_max_scale)
    assert d.grad_threshold == d1.grad_threshold  # NDC units: unit-free


def _train(scene, tmp_path, name: str, extra: dict | None = None) -> Trainer:
    cfg = config_from_dict({**TINY_TRAIN, "backend": BACKENDS[-1], **(extra or {})})
    t = Trainer(scene, cfg, tmp_path / name)
    t.setup(resume=False)
    t.train()
    return t


# (splat order, tolerance on means / k in radii, on log-scales and opacity logits). Plane
# order sorts each pixel's splats by where their planes meet its ray: the splats of one
# smooth surface meet it at nearly the same depth, so float32 rounding of the scaled means
# swaps some near-ties, and a swap moves the pixel's colour by α_a α_b (c_a − c_b)
# (measured in mm: means 2.3e-4 of the radius, opacity logits 6.8e-3). A unit bug (a
# constant in world units) moves them by percents of the radius.
ORDERS = [("centre", 1e-4, 1e-3), ("auto", 1e-3, 2e-2)]


@pytest.mark.parametrize(("order", "mean_tol", "tol"), ORDERS, ids=[o[0] for o in ORDERS])
def test_training_is_unit_free(sphere_48, tmp_path, order: str, mean_tol: float, tol: float):
    """30 iterations in mm, m and km (all phases, densification, multi-view loss on): the
    same Gaussian count, means / k equal to ``mean_tol`` of the radius, log-scales − log k
    and opacity logits equal to ``tol``, the position lr set by the trainer ∝ k."""
    mv = {"plan_overrides": {"multi_view": True}, "splat_order": order}
    runs = {k: _train(scaled_scene(sphere_48, k), tmp_path, f"k{k:g}", mv) for k in UNITS}
    ref = runs[1.0]
    assert ref.plan.multi_view.value, "the multi-view loss must be part of this run"
    lr1 = ref.optimizers["means"].param_groups[0]["lr"]
    p1 = {n: p.detach() for n, p in ref.gaussians.params.items()}
    r = sphere_48.radius
    for k in (1e-3, 1e3):
        t = runs[k]
        assert t.skipped_steps == 0
        assert t.optimizers["means"].param_groups[0]["lr"] == pytest.approx(k * lr1, rel=1e-9)
        assert t.gaussians.num == ref.gaussians.num, f"k={k}: densification differs"
        pk = {n: p.detach() for n, p in t.gaussians.params.items()}
        dm = float(((pk["means"] / k - p1["means"]).abs().max()) / r)
        ds = float((pk["log_scales"] - math.log(k) - p1["log_scales"]).abs().max())
        do = float((pk["opacity_logits"] - p1["opacity_logits"]).abs().max())
        assert dm < mean_tol, f"k={k}: means differ by {dm:.2e} of the radius"
        assert ds < tol, f"k={k}: log-scales differ by {ds:.2e}"
        assert do < tol, f"k={k}: opacity logits differ by {do:.2e}"
