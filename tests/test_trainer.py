"""The trainer end to end on tiny generated scenes: phases, outputs, resume, cancel."""

from __future__ import annotations

import itertools
import json

import pytest
import torch

from core.config import config_from_dict
from core.model.checkpoint import load_checkpoint
from core.outputs.report import read_metrics
from core.scene.synthetic import make_scene
from core.training.run import train_scene
from core.training.trainer import Trainer

TINY = {
    "iterations": 40,
    "init_points": 300,
    "envmap_resolution": 8,
    "checkpoint_every": 10,
    "eval": {"every": 10, "views": 2},
    "densify": {"max_gaussians": 1500},
}


@pytest.fixture(scope="module")
def tiny_scene():
    return make_scene("sphere", "glossy", n_train=24, n_test=2, size=24, seed=1, samples=2)


def _params(t: Trainer) -> dict[str, torch.Tensor]:
    return {k: p.detach().clone() for k, p in t.gaussians.params.items()}


def test_full_run_writes_every_output(tiny_scene, tmp_path):
    # 120 iterations: at 24 px each densification step costs antialiased splatting ~1 dB
    # (split Gaussians shrink towards the low-pass and fade), recovered ~40 steps later,
    # and the silhouette points hold the surface out where the splats are still round
    # blobs that overhang it (end of the run: 19.1 dB after 80 iterations, 23.6 after 120).
    cfg = config_from_dict({**TINY, "iterations": 120})
    result, _ = train_scene(tiny_scene, tmp_path, cfg)
    assert result.status == "succeeded" and result.iteration == 120
    for name in (
        "checkpoint.pt",
        "point_cloud.ply",
        "plan.json",
        "metrics.jsonl",
        "report.md",
        "error_vs_time.png",
        "config.json",
    ):
        assert (tmp_path / name).is_file(), name
    rows = read_metrics(tmp_path / "metrics.jsonl")
    its = [r["iteration"] for r in rows]
    assert its == sorted(set(its)) and its[0] == 0 and its[-1] == 120
    assert all(r["wall_time"] >= 0 for r in rows)
    assert {r["phase"] for r in rows} >= {"rgb", "multiview"}
    assert rows[-1]["psnr"] > rows[0]["psnr"]
    renders = {p.name for p in (tmp_path / "renders").glob("*.png")}
    for ch in ("final", "base", "specular", "normal", "depth", "w_r", "roughness", "alpha"):
        assert any(n.endswith(f"_{ch}.png") for n in renders), ch
    plan = json.loads((tmp_path / "plan.json").read_text())
    assert set(plan["decisions"]) == {
        "envmap",
        "envmap_resolution",
        "sh_degree",
        "multi_view",
        "background",
        "mesh",
        "silhouette",
        "roughness",
        "hull",
        "oblique_depth",
    }
    assert plan["decisions"]["oblique_depth"]["value"] is False  # a sphere of views
    assert not plan["decisions"]["envmap"]["pending"]
    # roughness is decided with the env map: on with it, off without it
    rough = plan["decisions"]["roughness"]
    assert not rough["pending"] and rough["value"] is plan["decisions"]["envmap"]["value"]
    # the scene has alpha: silhouette points were found and counted
    sil = plan["decisions"]["silhouette"]
    assert sil["value"] is True and sil["evidence"]["points"] > 0
    report = (tmp_path / "report.md").read_text()
    assert "error_vs_time.png" in report
    assert all(f"| {r['iteration']} |" in report for r in rows)  # a table row per evaluation


class _CrashError(RuntimeError):
    pass


def test_resume_after_crash_matches_uninterrupted_run(tiny_scene, tmp_path):
    """A run killed after its checkpoint at 20 and resumed ends like one never stopped."""
    cfg = config_from_dict(TINY)
    ref = Trainer(tiny_scene, cfg, tmp_path / "ref")
    ref.setup(resume=False)
    ref.train()

    def crash_after_20(event):
        if event["type"] == "checkpoint" and event["iteration"] == 20:
            raise _CrashError

    t1 = Trainer(tiny_scene, cfg, tmp_path / "run", on_event=crash_after_20)
    t1.setup(resume=False)
    with pytest.raises(_CrashError):
        t1.train()
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt").extra["iteration"] == 20
    resumed_at = []
    t2 = Trainer(
        tiny_scene,
        cfg,
        tmp_path / "run",
        on_event=lambda e: resumed_at.append(e["iteration"]) if e["type"] == "resumed" else None,
    )
    t2.setup(resume=True)
    result = t2.train()
    assert resumed_at == [20] and result.iteration == 40
    rows = read_metrics(tmp_path / "run" / "metrics.jsonl")
    its = [r["iteration"] for r in rows]
    assert its == sorted(set(its)), "metrics rows duplicated or out of order after resume"
    a, b = _params(ref), _params(t2)
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].shape == b[k].shape, k
        torch.testing.assert_close(b[k], a[k], rtol=1e-4, atol=1e-5, msg=k)
    assert abs(result.last_metrics["psnr"] - ref.last_eval["psnr"]) < 0.05


def test_cancel_keeps_a_checkpoint_and_resume_finishes(tiny_scene, tmp_path):
    cfg = config_from_dict(TINY)
    t = Trainer(tiny_scene, cfg, tmp_path, should_stop=lambda: t.iteration >= 7)
    t.setup(resume=False)
    r = t.train()
    assert r.status == "cancelled" and r.iteration == 7
    assert load_checkpoint(tmp_path / "checkpoint.pt").extra["iteration"] == 7
    t2 = Trainer(tiny_scene, cfg, tmp_path)
    t2.setup(resume=True)
    assert t2.train().iteration == 40


def test_nan_guard_skips_bad_steps(tiny_scene, tmp_path, monkeypatch):
    import core.training.trainer as tr

    cfg = config_from_dict({**TINY, "iterations": 12})
    real = tr.rgb_loss
    calls = {"n": 0}

    def sometimes_nan(img, ref, w):
        calls["n"] += 1
        loss = real(img, ref, w)
        return loss * float("nan") if calls["n"] % 3 == 0 else loss

    monkeypatch.setattr(tr, "rgb_loss", sometimes_nan)
    t = Trainer(tiny_scene, cfg, tmp_path)
    t.setup(resume=False)
    r = t.train()
    assert r.iteration == 12 and t.skipped_steps == 4
    for k, p in t.gaussians.params.items():
        assert torch.isfinite(p).all(), k
    assert read_metrics(tmp_path / "metrics.jsonl")[-1]["skipped_steps"] == 4


def test_a_step_reads_back_from_the_device_once(tiny_scene, tmp_path):
    """Every host read of a tensor (``.item()``, ``float(t)``, ``bool(t)``, ``.tolist()``)
    is a sync on a GPU. The trainer's own bookkeeping in a step, the NaN guard over
    every gradient and the loss values it returns, makes one read (it made one per
    parameter and per loss term, plus the loss check: 11 a step here)."""
    import sys

    from torch.overrides import TorchFunctionMode

    reads = {"item", "tolist", "__float__", "__bool__", "__int__", "__index__", "numpy"}
    dispatch = ("torch/_tensor.py", "torch/overrides.py")

    class StepReads(TorchFunctionMode):
        count = 0

        def __torch_function__(self, func, types, args=(), kwargs=None):
            if getattr(func, "__name__", "") in reads:
                frame = sys._getframe(1)
                while frame is not None and frame.f_code.co_filename.endswith(dispatch):
                    frame = frame.f_back
                code = frame.f_code if frame is not None else None
                # the view order is drawn from a CPU generator: no device involved
                if code and code.co_filename.endswith("core/training/trainer.py"):
                    StepReads.count += code.co_name != "_next_view"
            return func(*args, **(kwargs or {}))

    t = Trainer(tiny_scene, config_from_dict({**TINY, "iterations": 40}), tmp_path)
    t.setup(resume=False)
    t.step()
    with StepReads():
        for _ in range(4):
            losses = t.step()
    assert StepReads.count == 4
    terms = [v for k, v in losses.items() if k != "total" and not k.startswith("densify_")]
    assert losses["total"] == pytest.approx(sum(terms))


def test_resuming_a_finished_run_records_its_last_row_once(tiny_scene, tmp_path):
    """A runner killed after the last evaluation but before the job was marked done is
    resumed on a run whose last row exists: it must not be written again."""
    cfg = config_from_dict({**TINY, "iterations": 20})
    t = Trainer(tiny_scene, cfg, tmp_path)
    t.setup(resume=False)
    t.train()
    again = Trainer(tiny_scene, cfg, tmp_path)
    again.setup(resume=True)
    assert again.train().iteration == 20
    its = [r["iteration"] for r in read_metrics(tmp_path / "metrics.jsonl")]
    assert its == sorted(set(its)) and its[-1] == 20


@pytest.mark.parametrize("facing", [True, False])
def test_depth_losses_use_only_pixels_facing_the_view(tiny_scene, tmp_path, monkeypatch, facing):
    """With ablation.facing_depth, L_single and L_multi see only pixels whose rendered
    normal is within DEPTH_FACING_DEG of the ray (Eq. 8's depth is ill-conditioned
    edge-on); without it, every covered pixel, grazing ones included."""
    import core.training.trainer as tr
    from core.render.depth_geometry import facing_view

    seen: dict[str, list] = {"single": [], "multi": []}
    real_single, real_multi = tr.single_view_loss, tr.multi_view_loss

    def single(normal, depth, valid, camera, weight=None, **kw):
        seen["single"].append((valid.clone(), facing_view(normal, camera)))
        return real_single(normal, depth, valid, camera, weight, **kw)

    def multi(depth_ref, valid_ref, *args, **kw):
        seen["multi"].append(valid_ref.clone())
        return real_multi(depth_ref, valid_ref, *args, **kw)

    monkeypatch.setattr(tr, "single_view_loss", single)
    monkeypatch.setattr(tr, "multi_view_loss", multi)
    cfg = config_from_dict({
        **TINY, "iterations": 40, "ablation": {"facing_depth": facing},
        "loss": {"multiview_max_angle_deg": 90.0},  # 24 views: give each a neighbour
        "plan_overrides": {"multi_view": True},  # a masked scene's plan drops L_multi
    })  # fmt: skip
    t = Trainer(tiny_scene, cfg, tmp_path)
    t.setup(resume=False)
    t.train()
    assert seen["single"] and seen["multi"]
    grazing = 0
    for valid, faces in seen["single"]:
        grazing += int((valid & ~faces).sum())
        if facing:
            assert not bool((valid & ~faces).any())
    # a sphere always shows a rim seen edge-on: the switch has something to leave out
    assert (grazing == 0) if facing else (grazing > 0)


def test_planned_oblique_depth_widens_l_single_to_80_degrees(tiny_scene, tmp_path, monkeypatch):
    """With the plan's oblique_depth on (here by override: a sphere of views plans it
    off), L_single also reads pixels 60-80° from face-on, never beyond, and the pixels
    facing the view keep Eq. 8's depth."""
    import core.training.trainer as tr
    from core.render.depth_geometry import OBLIQUE_DEPTH_MAX_DEG, facing_view

    seen: list[tuple] = []
    real_single, real_oblique = tr.single_view_loss, tr.oblique_depth

    def oblique(gb, planar, valid, camera):
        depth, used = real_oblique(gb, planar, valid, camera)
        faces = facing_view(gb.normal, camera)
        same = bool(torch.equal(depth[faces & valid], planar[faces & valid]))
        seen.append(
            (used.clone(), faces, facing_view(gb.normal, camera, OBLIQUE_DEPTH_MAX_DEG), same)
        )
        return depth, used

    def single(normal, depth, valid, camera, weight=None, **kw):
        assert seen and torch.equal(valid, seen[-1][0])  # L_single reads what oblique gave
        return real_single(normal, depth, valid, camera, weight, **kw)

    monkeypatch.setattr(tr, "oblique_depth", oblique)
    monkeypatch.setattr(tr, "single_view_loss", single)
    cfg = config_from_dict({**TINY, "plan_overrides": {"oblique_depth": True}})
    t = Trainer(tiny_scene, cfg, tmp_path)
    t.setup(resume=False)
    t.train()
    assert t.plan.oblique_depth.value is True and seen
    oblique_pixels = 0
    for used, faces, within, same in seen:
        assert same and not bool((used & ~within).any())
        oblique_pixels += int((used & ~faces).sum())
    assert oblique_pixels > 0  # the sphere's rim: pixels the facing rule leaves out
    planned = plan_of(tmp_path)
    assert planned["oblique_depth"]["value"] is True and planned["oblique_depth"]["overridden"]


def plan_of(run) -> dict:  # type: ignore[no-untyped-def]
    return json.loads((run / "plan.json").read_text())["decisions"]


@pytest.mark.parametrize("held", [True, False])
def test_silhouette_term_reads_the_planar_depth_with_normals_held(
    tiny_scene, tmp_path, monkeypatch, held
):
    """ablation.silhouette_holds_normals: the silhouette term gets Eq. 8's depth values
    through the held-normal channels (its gradient cannot turn a splat), L_single the
    plain one; switched off, both read the very same tensor."""
    import core.training.trainer as tr

    seen: list[tuple] = []
    real = tr.single_view_loss

    def single(normal, depth, valid, camera, weight=None, **kw):
        seen.append(("single", depth))
        return real(normal, depth, valid, camera, weight, **kw)

    monkeypatch.setattr(tr, "single_view_loss", single)
    cfg = config_from_dict({
        **TINY, "iterations": 40, "ablation": {"silhouette_holds_normals": held},
    })  # fmt: skip
    t = Trainer(tiny_scene, cfg, tmp_path)
    t.setup(resume=False)
    assert t.silhouette is not None
    real_sil = t.silhouette.__call__

    class Spy:
        def __call__(self, vi, camera, depth, valid):
            seen.append(("silhouette", depth))
            return real_sil(vi, camera, depth, valid)

    t.silhouette = Spy()
    t.train()
    pairs = [
        (a[1], b[1])
        for a, b in itertools.pairwise(seen)
        if (a[0], b[0]) == ("single", "silhouette")
    ]
    assert pairs
    for plain, sil in pairs:
        torch.testing.assert_close(sil, plain, rtol=1e-5, atol=1e-6)
        assert (sil is plain) != held


@pytest.mark.parametrize("case", ["masked", "unmasked", "switched off"])
def test_mask_term_is_the_coverage_error_of_masked_views_only(
    tiny_scene, tmp_path, monkeypatch, case
):
    """loss.mask weighs mean |alpha − mask| of the trained view; a capture without masks,
    or ablation.mask_coverage off, has no such term (and pays nothing for it)."""
    from dataclasses import replace

    import core.training.trainer as tr
    from core.training.losses import mask_loss

    scene = tiny_scene
    if case == "unmasked":
        scene = replace(scene, train=[replace(v, mask=None) for v in scene.train])
    cfg = config_from_dict({
        **TINY, "iterations": 10, "loss": {"mask": 2.0},
        "ablation": {"mask_coverage": case != "switched off"},
    })  # fmt: skip
    t = Trainer(scene, cfg, tmp_path)
    t.setup(resume=False)
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []

    def spy(alpha, mask):
        seen.append((alpha.detach().clone(), mask))
        return mask_loss(alpha, mask)

    monkeypatch.setattr(tr, "mask_loss", spy)
    losses = t.step()
    if case == "masked":
        assert len(seen) == 1
        alpha, mask = seen[0]
        assert losses["mask"] == pytest.approx(2.0 * float(mask_loss(alpha, mask)), rel=1e-5)
        assert losses["mask"] > 0
    else:
        assert not seen and "mask" not in losses
