"""Adaptive density control: selection, split sampling, pruning, cap, opacity reset, surgery."""

from __future__ import annotations

import io
import math

import pytest
import torch
from scipy.spatial.transform import Rotation
from torch import nn

from core.config import Densification, TrainConfig
from core.render.gaussians import PARAM_SHAPES, Gaussians, scalar_logit
from core.render.raster import RasterResult, rasterize
from core.render.rotations import normalize_quats, quat_to_rotmat
from core.training.densify import DensifyStrategy
from core.training.optim import make_optimizers
from tests.helpers import identity_camera

W = H = 100
HIGH_PX = 1e-5  # × W/2 = 5e-4 NDC ≥ 2e-4
LOW_PX = 1e-6  # 5e-5 NDC < 2e-4
SMALL = 0.005  # ≤ percent_dense · radius = 0.01 → clone
BIG = 0.05  # > 0.01 → split


def config(iterations: int = 30_000, **densify: object) -> TrainConfig:
    base = {"start": 0, "stop": 15_000, "interval": 100, "opacity_reset_interval": 3_000}
    base.update(densify)
    return TrainConfig(iterations=iterations, densify=Densification(**base))


def make_gaussians(
    scales: list[float] | list[list[float]],
    opacities: list[float] | None = None,
    quats: torch.Tensor | None = None,
    extra: bool = False,
) -> Gaussians:
    """Gaussians whose every parameter row is distinct, so row provenance is checkable."""
    n = len(scales)
    s = torch.tensor(scales, dtype=torch.float32)
    s = s[:, None].repeat(1, 3) if s.ndim == 1 else s
    ids = torch.arange(n, dtype=torch.float32)
    gen = torch.Generator().manual_seed(1)
    op = torch.tensor(opacities if opacities is not None else [0.5] * n)
    params = {
        "means": torch.randn(n, 3, generator=gen),
        "log_scales": s.log(),
        "quats": quats if quats is not None else normalize_quats(torch.randn(n, 4, generator=gen)),
        "opacity_logits": torch.logit(op),
        "sh_dc": ids[:, None, None] + torch.rand(n, 1, 3, generator=gen),
        "sh_rest": ids[:, None, None] + torch.rand(n, *PARAM_SHAPES["sh_rest"], generator=gen),
        "refl_logits": ids * 0.1 - 1.0,
    }
    if extra:
        params["extra_feat"] = ids[:, None] + torch.rand(n, 2, generator=gen)
    return Gaussians(params)


def fake_result(
    grad_px: list[float] | torch.Tensor, radii: list[int] | None = None
) -> RasterResult:
    """A render whose means2d gradient (pixel units, along x) is set by hand."""
    g = torch.as_tensor(grad_px, dtype=torch.float32)
    g = torch.stack([g, torch.zeros_like(g)], dim=1) if g.ndim == 1 else g
    n = g.shape[0]
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = g.clone()
    r = torch.as_tensor(radii if radii is not None else [1] * n, dtype=torch.int32)
    return RasterResult(torch.zeros(1, 1, 3), torch.zeros(1, 1), means2d, r, torch.ones(n), "fake")


def optimizers_for(g: Gaussians) -> dict[str, torch.optim.Optimizer]:
    return {k: torch.optim.Adam([p], lr=1e-2, eps=1e-15) for k, p in g.params.items()}


def adam_steps(g: Gaussians, opts: dict[str, torch.optim.Optimizer], n: int = 3) -> None:
    """A few real Adam steps so every moment buffer is populated and non-zero."""
    for i in range(n):
        loss = sum(((p - 0.1 * (i + 1)) ** 2).sum() for p in g.params.values())
        loss.backward()
        for opt in opts.values():
            opt.step()
            opt.zero_grad()


def assert_consistent(g: Gaussians, opts: dict[str, torch.optim.Optimizer]) -> None:
    for k, p in g.params.items():
        assert p.is_leaf and p.requires_grad and p.shape[0] == g.num
        held = opts[k].param_groups[0]["params"][0]
        assert held is p, k
        state = opts[k].state.get(p, {})
        for name in ("exp_avg", "exp_avg_sq"):
            if name in state:
                assert state[name].shape == p.shape, (k, name)


# -- schedule ---------------------------------------------------------------------------


def test_marks_are_scaled_and_reset_fires_on_schedule() -> None:
    s = DensifyStrategy(config(iterations=3_000, start=500), scene_radius=1.0)
    # The interval (views averaged per step) is not scaled: it stays 100 here...
    assert (s.start, s.stop, s.interval, s.reset_every) == (50, 1500, 100, 1000)
    refine = [i for i in range(3_000) if s.is_refine_step(i)]
    assert refine[0] == 100 and refine[-1] == 1400 and len(refine) == 14
    # ...and shrinks only so that a very short run still densifies about ten times.
    short = DensifyStrategy(config(iterations=600, start=500), scene_radius=1.0)
    assert short.interval == (short.stop - short.start) // 10
    # ...but never below 10 views: a 20-iteration run does not densify at all.
    tiny = DensifyStrategy(config(iterations=20, start=0), scene_radius=1.0)
    assert tiny.interval == 10 and not any(tiny.is_refine_step(i) for i in range(20))
    # gsplat 1.5.3 writes `step % every == 0 & step > 0`, which is always False.
    # Resets are never closer than MIN_RESET_INTERVAL (the scaled 300 would starve opacity).
    assert [i for i in range(3_000) if s.is_reset_step(i)] == [1000]
    full = DensifyStrategy(config(iterations=30_000, start=500), scene_radius=1.0)
    assert [i for i in range(30_000) if full.is_reset_step(i)] == [3000, 6000, 9000, 12000]
    off = DensifyStrategy(config(opacity_reset_interval=0), scene_radius=1.0)
    assert off.reset_every == 0 and not any(off.is_reset_step(i) for i in range(0, 15_000, 100))
    assert not off.size_pruning(14_000)


# -- accumulation -----------------------------------------------------------------------


def test_gradient_accumulated_in_ndc_units_for_visible_only() -> None:
    g = make_gaussians([SMALL] * 3)
    s = DensifyStrategy(config(), scene_radius=1.0)
    grad = torch.tensor([[1e-5, 0.0], [0.0, 1e-5], [1e-5, 1e-5]])
    for _ in range(2):
        res = fake_result(grad, radii=[10, 40, 0])
        s.step_pre_backward(res)
        stats = s.step_post_backward(g, optimizers_for(g), res, 1, width=200, height=100)
        assert stats == {"cloned": 0, "split": 0, "pruned": 0, "reset": 0, "n": 3}
    assert s.grad2d is not None and s.count is not None and s.max_radii is not None
    torch.testing.assert_close(s.grad2d, torch.tensor([2e-3, 1e-3, 0.0]))  # x·W/2, y·H/2
    assert s.count.tolist() == [2, 2, 0]
    torch.testing.assert_close(s.max_radii, torch.tensor([0.05, 0.2, 0.0]))  # / max(W, H)


def test_real_render_gradient_reaches_accumulators() -> None:
    cam = identity_camera(24, dtype=torch.float32)
    pts = torch.tensor([[0.0, 0.0, 3.0], [0.3, -0.2, 4.0], [0.0, 0.0, -3.0]])  # last: behind
    g = Gaussians.from_points(pts, radius=1.0)
    res = rasterize(g.means, g.unit_quats, g.scales, g.opacities, torch.ones(3, 1), cam)
    s = DensifyStrategy(config(), scene_radius=1.0)
    s.step_pre_backward(res)
    xs = torch.arange(cam.width, dtype=torch.float32)
    (res.features[..., 0] * xs).sum().backward()  # not translation invariant
    s.step_post_backward(g, make_optimizers(g, TrainConfig(), 1.0), res, 1, cam.width, cam.height)
    assert s.grad2d is not None and s.count is not None
    assert s.count.tolist() == [1, 1, 0]
    assert (s.grad2d[:2] > 0).all() and s.grad2d[2] == 0


def test_missing_pre_backward_is_an_error() -> None:
    g = make_gaussians([SMALL])
    res = fake_result([HIGH_PX])
    res.means2d.grad = None
    with pytest.raises(RuntimeError, match="step_pre_backward"):
        DensifyStrategy(config(), 1.0).step_post_backward(g, {}, res, 1, W, H)


# -- grow ----------------------------------------------------------------------------------


def test_clone_vs_split_selection_and_every_key_carried() -> None:
    # rows: small+high → clone, small+low, big+high → split, big+low
    g = make_gaussians([SMALL, SMALL, BIG, BIG], extra=True)
    before = {k: p.detach().clone() for k, p in g.params.items()}
    params_obj = g.params
    opts = optimizers_for(g)
    s = DensifyStrategy(config(), scene_radius=1.0)
    res = fake_result([HIGH_PX, LOW_PX, HIGH_PX, LOW_PX])
    stats = s.step_post_backward(g, opts, res, 100, W, H)
    assert stats == {"cloned": 1, "split": 1, "pruned": 0, "reset": 0, "n": 6}
    assert g.params is params_obj  # updated in place
    assert g.num == 6 and set(g.params) == set(before)
    # Layout: kept originals [0, 1, 3], the clone of 0, then the two children of 2.
    for k, new in g.params.items():
        new = new.detach()
        torch.testing.assert_close(new[:4], before[k][[0, 1, 3, 0]], msg=k)
        if k == "log_scales":
            expected = before[k][[2, 2]] - math.log(1.6)
            torch.testing.assert_close(new[4:], expected, msg=k)
        elif k == "means":
            assert not torch.equal(new[4], before[k][2]) and not torch.equal(new[4], new[5])
        else:
            torch.testing.assert_close(new[4:], before[k][[2, 2]], msg=k)
    assert_consistent(g, opts)


def test_split_makes_two_children_with_shrunk_scales() -> None:
    g = make_gaussians([BIG], extra=True)
    before = {k: p.detach().clone() for k, p in g.params.items()}
    stats = DensifyStrategy(config(), 1.0).step_post_backward(
        g, optimizers_for(g), fake_result([HIGH_PX]), 100, W, H
    )
    assert stats["split"] == 1 and stats["cloned"] == 0 and g.num == 2
    torch.testing.assert_close(g.scales.detach(), torch.full((2, 3), BIG / 1.6), rtol=1e-5, atol=0)
    assert not torch.equal(g.means[0], g.means[1])
    for k in ("quats", "opacity_logits", "sh_dc", "sh_rest", "refl_logits", "extra_feat"):
        torch.testing.assert_close(g.params[k].detach(), before[k].expand_as(g.params[k]), msg=k)


def test_split_samples_follow_parent_covariance() -> None:
    n = 3000
    rot = Rotation.from_rotvec([0.4, -0.9, 0.6])
    x, y, z, w = rot.as_quat()
    quats = torch.tensor([[w, x, y, z]], dtype=torch.float32).repeat(n, 1)
    scales = [[0.3, 0.1, 0.02]] * n
    g = make_gaussians(scales, quats=quats)
    g.params["means"].data[:] = torch.tensor([1.0, -2.0, 0.5])
    cfg = config(max_gaussians=10 * n)
    DensifyStrategy(cfg, 1.0).step_post_backward(
        g, optimizers_for(g), fake_result([HIGH_PX] * n), 100, W, H
    )
    assert g.num == 2 * n
    d = g.means.detach() - torch.tensor([1.0, -2.0, 0.5])
    R = quat_to_rotmat(quats[:1])[0]
    local = d @ R / torch.tensor([0.3, 0.1, 0.02])  # Rᵀ d / s ~ N(0, I)
    assert local.mean(0).abs().max() < 0.08
    cov = local.T @ local / local.shape[0]
    torch.testing.assert_close(cov, torch.eye(3), atol=0.1, rtol=0)
    # Same in world space: the sample covariance is the parent's Σ.
    sigma = R @ torch.diag(torch.tensor([0.3, 0.1, 0.02]) ** 2) @ R.T
    torch.testing.assert_close(d.T @ d / d.shape[0], sigma, atol=0.1 * 0.09, rtol=0)


def test_gradient_is_averaged_over_views() -> None:
    g = make_gaussians([SMALL])
    s = DensifyStrategy(config(), 1.0)
    opts = optimizers_for(g)
    # One high view among 10: mean 0.1 × 5e-4 NDC < threshold → no clone.
    for it in range(91, 101):
        grad = [HIGH_PX] if it == 91 else [0.0]
        stats = s.step_post_backward(g, opts, fake_result(grad), it, W, H)
    assert stats["cloned"] == 0 and g.num == 1
    # Accumulators restart after each refinement step.
    assert s.count is not None and s.count.tolist() == [0]


def test_cap_keeps_largest_gradients() -> None:
    g = make_gaussians([SMALL] * 6)
    g.params["refl_logits"].data[:] = torch.arange(6.0)
    grads = [2e-5, 9e-5, 1e-6, 5e-5, 3e-5, 7e-5]
    cfg = config(max_gaussians=8)
    stats = DensifyStrategy(cfg, 1.0).step_post_backward(
        g, optimizers_for(g), fake_result(grads), 100, W, H
    )
    assert stats["cloned"] == 2 and g.num == 8
    assert g.params["refl_logits"][6:].tolist() == [1.0, 5.0]  # largest two, index order


def test_cap_enforced_when_already_above() -> None:
    op = [0.9, 0.02, 0.8, 0.03, 0.7, 0.5]
    g = make_gaussians([SMALL] * 6, opacities=op)
    cfg = config(max_gaussians=4)
    stats = DensifyStrategy(cfg, 1.0).step_post_backward(
        g, optimizers_for(g), fake_result([HIGH_PX] * 6), 100, W, H
    )
    assert stats["cloned"] == 0 and stats["pruned"] == 2 and g.num == 4
    torch.testing.assert_close(g.opacities.detach(), torch.tensor([0.9, 0.8, 0.7, 0.5]))


# -- prune ---------------------------------------------------------------------------------


def test_prune_low_opacity() -> None:
    g = make_gaussians([SMALL] * 4, opacities=[0.5, 0.001, 0.2, 0.004])
    opts = optimizers_for(g)
    stats = DensifyStrategy(config(), 1.0).step_post_backward(
        g, opts, fake_result([LOW_PX] * 4), 100, W, H
    )
    assert stats == {"cloned": 0, "split": 0, "pruned": 2, "reset": 0, "n": 2}
    torch.testing.assert_close(g.opacities.detach(), torch.tensor([0.5, 0.2]))
    assert_consistent(g, opts)


def test_clone_of_transparent_gaussian_is_pruned_too() -> None:
    g = make_gaussians([SMALL, SMALL], opacities=[0.5, 0.001])
    stats = DensifyStrategy(config(), 1.0).step_post_backward(
        g, optimizers_for(g), fake_result([HIGH_PX] * 2), 100, W, H
    )
    assert (stats["cloned"], stats["pruned"], stats["n"]) == (2, 2, 2)
    torch.testing.assert_close(g.opacities.detach(), torch.tensor([0.5, 0.5]))


@pytest.mark.parametrize("it, pruned", [(2_000, 0), (3_100, 2)])
def test_size_pruning_only_after_first_reset(it: int, pruned: int) -> None:
    # rows: normal, too big on screen (radius 50 px = 0.5 of 100), too big in the world
    g = make_gaussians([SMALL, SMALL, 0.5])
    s = DensifyStrategy(config(), scene_radius=1.0)
    opts = optimizers_for(g)
    s.step_post_backward(g, opts, fake_result([0.0] * 3, radii=[5, 50, 5]), it - 1, W, H)
    stats = s.step_post_backward(g, opts, fake_result([0.0] * 3, radii=[5, 2, 5]), it, W, H)
    assert stats["pruned"] == pruned and g.num == 3 - pruned
    if pruned:
        assert g.scales.max().item() == pytest.approx(SMALL)


# -- opacity reset ---------------------------------------------------------------------------


def test_opacity_reset_clamps_and_restarts_moments() -> None:
    cfg = config(iterations=30_000, prune_opacity=0.0)
    g = make_gaussians([SMALL] * 3, opacities=[0.9, 0.5, 0.003])
    opts = optimizers_for(g)
    adam_steps(g, opts)
    g.params["opacity_logits"].data[:] = torch.logit(torch.tensor([0.9, 0.5, 0.003]))
    opa = g.params["opacity_logits"]
    steps = {k: opts[k].state[p]["step"].item() for k, p in g.params.items()}
    means_m = opts["means"].state[g.params["means"]]["exp_avg"].clone()
    s = DensifyStrategy(cfg, 1.0)
    assert s.step_post_backward(g, opts, fake_result([0.0] * 3), 2999, W, H)["reset"] == 0
    torch.testing.assert_close(g.opacities[0].detach(), torch.tensor(0.9))
    stats = s.step_post_backward(g, opts, fake_result([0.0] * 3), 3000, W, H)
    assert stats["reset"] == 1 and g.num == 3
    assert g.params["opacity_logits"] is opa  # edited in place
    torch.testing.assert_close(g.opacities.detach(), torch.tensor([0.01, 0.01, 0.003]))
    st = opts["opacity_logits"].state[opa]
    assert st["exp_avg"].abs().sum() == 0 and st["exp_avg_sq"].abs().sum() == 0
    assert {k: opts[k].state[p]["step"].item() for k, p in g.params.items()} == steps
    torch.testing.assert_close(opts["means"].state[g.params["means"]]["exp_avg"], means_m)
    # No reset at the stop mark (15000 is a multiple of 3000) nor after it.
    g.params["opacity_logits"].data[:] = 2.0
    for it in (15_000, 18_000):
        assert s.step_post_backward(g, opts, fake_result([0.0] * 3), it, W, H)["reset"] == 0
    assert (g.params["opacity_logits"] == 2.0).all()


def test_reset_value_matches_logit() -> None:
    g = make_gaussians([SMALL], opacities=[0.7])
    s = DensifyStrategy(config(), 1.0)
    s.step_post_backward(g, {}, fake_result([0.0]), 3_000, W, H)
    assert g.params["opacity_logits"].item() == pytest.approx(scalar_logit(0.01), abs=1e-6)


# -- optimizer surgery ---------------------------------------------------------------------


def test_optimizer_state_remapped_and_step_works() -> None:
    # rows: clone, keep, split, prune (opacity), keep
    g = make_gaussians([SMALL, SMALL, BIG, SMALL, BIG], opacities=[0.5, 0.5, 0.5, 0.001, 0.5])
    opts = make_optimizers(g, TrainConfig(), scene_radius=1.0)
    adam_steps(g, opts)
    g.params["opacity_logits"].data[3] = scalar_logit(0.001)
    old = {k: {n: opts[k].state[p][n].clone() for n in ("exp_avg", "exp_avg_sq", "step")}
           for k, p in g.params.items()}  # fmt: skip
    s = DensifyStrategy(config(), scene_radius=1.0)
    res = fake_result([HIGH_PX, LOW_PX, HIGH_PX, LOW_PX, LOW_PX])
    stats = s.step_post_backward(g, opts, res, 100, W, H)
    assert stats == {"cloned": 1, "split": 1, "pruned": 1, "reset": 0, "n": 6}
    assert_consistent(g, opts)
    src = [0, 1, 4]  # kept originals, then clone + 2 children (new: zero moments)
    for k, p in g.params.items():
        st = opts[k].state[p]
        assert st["step"] == old[k]["step"]
        for name in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(st[name][:3], old[k][name][src], msg=f"{k}.{name}")
            assert st[name][3:].abs().sum() == 0, f"{k}.{name} new rows"
    before = {k: p.detach().clone() for k, p in g.params.items()}
    adam_steps(g, opts, n=1)
    for k, p in g.params.items():
        assert not torch.equal(p.detach(), before[k]), k


def test_pending_grads_carried_for_a_step_right_after() -> None:
    g = make_gaussians([SMALL, SMALL], opacities=[0.5, 0.001])
    opts = optimizers_for(g)
    for p in g.params.values():
        p.grad = torch.ones_like(p)
    DensifyStrategy(config(), 1.0).step_post_backward(
        g, opts, fake_result([HIGH_PX, LOW_PX]), 100, W, H
    )
    assert g.num == 2  # row 0 kept + its clone; row 1 pruned
    for p in g.params.values():
        assert p.grad is not None and p.grad.shape == p.shape
        assert (p.grad[0] == 1).all() and (p.grad[1] == 0).all()
    for opt in opts.values():
        opt.step()


def test_stale_optimizer_is_detected() -> None:
    g = make_gaussians([SMALL])
    opts = optimizers_for(g)
    opts["sh_rest"] = torch.optim.Adam([nn.Parameter(torch.zeros(1, 15, 3))])
    params = dict(g.params.items())
    with pytest.raises(ValueError, match="sh_rest"):
        DensifyStrategy(config(), 1.0).step_post_backward(
            g, opts, fake_result([HIGH_PX]), 100, W, H
        )
    assert all(g.params[k] is p for k, p in params.items()) and g.num == 1  # untouched


def test_disabled_does_nothing() -> None:
    g = make_gaussians([BIG, SMALL], opacities=[0.5, 0.001])
    s = DensifyStrategy(config(enabled=False), 1.0)
    for it in (100, 3_000):
        stats = s.step_post_backward(g, {}, fake_result([HIGH_PX] * 2), it, W, H)
        assert stats == {"cloned": 0, "split": 0, "pruned": 0, "reset": 0, "n": 2}
    assert s.grad2d is None


# -- checkpointing -------------------------------------------------------------------------


def test_state_dict_round_trip_resumes_exactly() -> None:
    def views(s: DensifyStrategy, g: Gaussians, opts: dict, its: range) -> list[dict]:
        gen = torch.Generator().manual_seed(its.start)
        out = []
        for it in its:
            grad = torch.rand(g.num, generator=gen) * 2 * HIGH_PX
            radii = torch.randint(0, 20, (g.num,), generator=gen).tolist()
            out.append(s.step_post_backward(g, opts, fake_result(grad, radii), it, W, H))
        return out

    base = make_gaussians([SMALL, BIG, SMALL, BIG, 0.02, 0.004])
    g1 = base.clone()
    o1 = optimizers_for(g1)
    s1 = DensifyStrategy(config(), 1.0)
    first = views(s1, g1, o1, range(181, 221))  # refinement at 200, stats pending after
    assert sum(x["split"] for x in first) > 0  # the split RNG has advanced
    buf = io.BytesIO()
    torch.save(s1.state_dict(), buf)
    buf.seek(0)
    state = torch.load(buf, weights_only=True)

    g2, g3 = g1.clone(), g1.clone()
    o2, o3 = optimizers_for(g2), optimizers_for(g3)
    s2 = DensifyStrategy(config(), 1.0)
    s2.load_state_dict(state)
    for name in ("grad2d", "count", "max_radii"):
        assert torch.equal(getattr(s1, name), getattr(s2, name)), name
    s3 = DensifyStrategy(config(), 1.0)  # not restored: must diverge (the test can fail)
    stats1 = views(s1, g1, o1, range(221, 421))  # refinements at 300, 400
    stats2 = views(s2, g2, o2, range(221, 421))
    views(s3, g3, o3, range(221, 421))
    assert stats1 == stats2 and sum(x["split"] for x in stats1) > 0
    for k in g1.params:
        assert torch.equal(g1.params[k], g2.params[k]), k
    assert g3.num != g1.num or not torch.equal(g3.params["means"], g1.params["means"])


def test_loaded_state_must_match_the_set() -> None:
    s = DensifyStrategy(config(), 1.0)
    g = make_gaussians([SMALL] * 3)
    s.step_post_backward(g, {}, fake_result([0.0] * 3), 1, W, H)
    other = DensifyStrategy(config(), 1.0)
    other.load_state_dict(s.state_dict())
    g4 = make_gaussians([SMALL] * 4)
    with pytest.raises(ValueError, match="rows"):
        other.step_post_backward(g4, {}, fake_result([0.0] * 4), 2, W, H)


def test_load_rejects_bad_state() -> None:
    s = DensifyStrategy(config(), 1.0)
    with pytest.raises(ValueError, match="version"):
        s.load_state_dict({"version": 99})
    bad = s.state_dict() | {"grad2d": torch.zeros(3), "count": None, "max_radii": None}
    with pytest.raises(ValueError, match="all present"):
        s.load_state_dict(bad)
