"""Training never writes NaN/Inf into its parameters, optimizer state or checkpoints.

Runs are tiny (24×24 images, 30 iterations, every phase, densification on). Expected
answers:

* learning rates 10× too high, and images that are all one colour: the run finishes,
  every parameter, Adam moment, the environment map and the checkpoint are finite, every
  recorded loss is finite, and each metrics row carries ``skipped_steps``;
* a NaN pixel in one training image (a loader would refuse it; memory can still hold
  it): every step on that view is skipped by the guard and counted, exactly, in
  ``skipped_steps`` (trainer and metrics.jsonl); the other views train normally;
* a finite gradient whose square overflows (|g| > √max) is skipped like a NaN one
  (before the fix it reached Adam, whose second moment became Inf: the parameter
  froze and the next checkpoint refused to save).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
import torch

import core.training.trainer as trainer_mod
from core.config import config_from_dict
from core.model.checkpoint import load_checkpoint
from core.outputs.report import read_metrics
from core.scene.views import View
from core.training.trainer import Trainer
from tests.stability.common import BACKENDS, TINY_TRAIN, all_finite, replace_views


def _finite_tree(obj: Any) -> bool:
    if isinstance(obj, torch.Tensor):
        return not obj.is_floating_point() or all_finite(obj)
    if isinstance(obj, dict):
        return all(_finite_tree(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return all(_finite_tree(v) for v in obj)
    if isinstance(obj, float):
        return math.isfinite(obj)
    return True


def _run(scene, out: Path, **overrides) -> Trainer:
    cfg = config_from_dict({**TINY_TRAIN, "backend": BACKENDS[-1], **overrides})
    t = Trainer(scene, cfg, out)
    t.setup(resume=False)
    t.train()
    return t


def _assert_clean(t: Trainer, out: Path) -> None:
    """Parameters, optimizer moments, env map, checkpoint and metrics are all finite."""
    for name, p in t.gaussians.params.items():
        assert all_finite(p), f"parameter {name} holds NaN/Inf"
    for name, o in t.optimizers.items():
        assert _finite_tree(o.state_dict()["state"]), f"optimizer {name} state holds NaN/Inf"
    if t.envmap is not None:
        assert all_finite(t.envmap.log_radiance)
    ck = load_checkpoint(out / "checkpoint.pt")
    assert all(all_finite(p) for p in ck.gaussians.params.values())
    assert _finite_tree(ck.extra["optimizers"])
    rows = read_metrics(out / "metrics.jsonl")
    assert rows and rows[-1]["iteration"] == t.iteration
    for row in rows:
        assert "skipped_steps" in row
        assert all(math.isfinite(v) for v in row["loss"].values()), row["loss"]
        assert not math.isnan(row["psnr"])
    assert rows[-1]["skipped_steps"] == t.skipped_steps


def test_learning_rate_10x_too_high(sphere_48, tmp_path):
    """Every learning rate ×10: finishes with finite parameters, state and checkpoint."""
    lr = {k: 10.0 * v for k, v in config_from_dict({}).lr.model_dump().items()}
    t = _run(sphere_48, tmp_path, lr=lr)
    assert t.iteration == TINY_TRAIN["iterations"]
    _assert_clean(t, tmp_path)


@pytest.mark.parametrize("colour,masked", [(0.5, True), (1.0, False)])
def test_images_all_one_colour(sphere_48, tmp_path, colour, masked):
    """Flat grey images with masks, and flat white ones without (SSIM's variances are 0,
    colour variation across views is 0): finite run, finite checkpoint."""

    def flat(v: View) -> View:
        return View(v.camera, torch.full_like(v.image, colour), v.mask if masked else None, v.name)

    scene = replace_views(
        sphere_48, [flat(v) for v in sphere_48.train], [flat(v) for v in sphere_48.test]
    )
    t = _run(scene, tmp_path)
    _assert_clean(t, tmp_path)


def test_nan_pixel_view_is_skipped_and_recorded(sphere_48, tmp_path, monkeypatch):
    """One training image with a NaN pixel: exactly the steps drawn on it are skipped."""
    bad = 5
    train = list(sphere_48.train)
    img = train[bad].image.clone()
    img[3, 4, 1] = float("nan")
    train[bad] = View(train[bad].camera, img, train[bad].mask, train[bad].name)
    scene = replace_views(sphere_48, train)
    picks: list[int] = []
    original = Trainer._next_view

    def spy(self: Trainer) -> int:
        i = original(self)
        picks.append(i)
        return i

    monkeypatch.setattr(Trainer, "_next_view", spy)
    # 60 iterations: one pass over the 48 views and part of a second, so the bad view is drawn.
    t = _run(scene, tmp_path, iterations=60)
    expected = picks.count(bad)
    assert expected >= 1
    assert t.skipped_steps == expected, f"skipped {t.skipped_steps}, NaN view drawn {expected}×"
    _assert_clean(t, tmp_path)


def test_overflowing_gradient_is_skipped(sphere_48, tmp_path, monkeypatch):
    """A loss spike of 1e30 at one step (finite loss, finite gradients whose squares
    overflow float32): that step is skipped and recorded, nothing non-finite is kept,
    and every checkpoint saves."""
    real = trainer_mod.rgb_loss
    calls = {"n": 0}

    def spiky(*args, **kwargs):
        calls["n"] += 1
        out = real(*args, **kwargs)
        return out * 1e30 if calls["n"] == 12 else out

    monkeypatch.setattr(trainer_mod, "rgb_loss", spiky)
    t = _run(sphere_48, tmp_path)
    assert t.skipped_steps == 1
    _assert_clean(t, tmp_path)


@pytest.mark.parametrize(
    ("bad", "usable"),
    [(0.5, True), (-3.0e19, False), (3.0e19, False), (float("-inf"), False),
     (float("inf"), False), (float("nan"), False), (-1.0e19, True)],
)  # fmt: skip
def test_gradient_ratio_is_max_abs_over_sqrt_max(bad, usable):
    """The guard's ratio per parameter is max|g| / √(float max): a gradient is usable
    below 1 only. Negative overflow counts as much as positive (the ratio is taken from
    min and max, without an |g| buffer); NaN compares False."""
    from types import SimpleNamespace

    a = torch.nn.Parameter(torch.zeros(40, 15, 3))
    b = torch.nn.Parameter(torch.zeros(7))
    a.grad = torch.linspace(-0.25, 0.125, a.numel()).reshape(a.shape)
    b.grad = torch.zeros(7)
    b.grad[3] = bad
    empty = torch.nn.Parameter(torch.zeros(0))
    empty.grad = torch.zeros(0)
    opt = torch.optim.Adam([a, b, empty])
    ratios = trainer_mod.Trainer._gradient_ratios(SimpleNamespace(optimizers={"x": opt}))
    assert len(ratios) == 2  # the empty gradient is skipped
    limit = math.sqrt(torch.finfo(torch.float32).max)
    assert float(ratios[0]) == pytest.approx(0.25 / limit)
    assert (float(ratios[1]) < 1.0) is usable
    if usable:
        assert float(ratios[1]) == pytest.approx(abs(bad) / limit)
