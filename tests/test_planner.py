"""The scene plan: measured decisions, recorded evidence, user overrides."""

from __future__ import annotations

import json

import pytest

from core.config import ConfigError, config_from_dict
from core.scene.cameras import Camera, Intrinsics
from core.scene.synthetic import make_scene
from core.training.planner import auto_envmap_resolution, find_neighbours, plan_scene
from core.training.trainer import Trainer


def _phase1_plan(scene, tmp_path, **overrides):
    """Train just through the RGB phase and return the plan decided at its end."""
    cfg = config_from_dict(
        {
            "iterations": 3000,  # RGB phase ends at 300
            "init_points": 1500,
            "envmap_resolution": 8,
            "eval": {"every": 1000, "views": 1},
            **overrides,
        }
    )
    t = Trainer(scene, cfg, tmp_path, should_stop=lambda: not t.plan.envmap.pending)
    t.setup(resume=False)
    t.train()
    return t, json.loads((tmp_path / "plan.json").read_text())


@pytest.mark.parametrize(("kind", "expect"), [("diffuse", False), ("mirror", True)])
def test_planner_turns_envmap_off_for_diffuse_and_on_for_mirror(kind, expect, tmp_path):
    scene = make_scene("sphere", kind, n_train=32, n_test=1, size=32, seed=3, samples=2)
    t, plan = _phase1_plan(scene, tmp_path)
    env = plan["decisions"]["envmap"]
    assert env["value"] is expect, env
    assert env["evidence"]["pairs"] > 0 and env["evidence"]["pixels"] > 100
    if expect:
        assert t.envmap is not None and "envmap" in t.optimizers
    else:
        # Left out means not built and never computed.
        assert t.envmap is None and "envmap" not in t.optimizers
        assert plan["decisions"]["sh_degree"]["value"] == 0
        assert not t.current_phase(2999).envmap


def test_user_override_wins_and_is_recorded(tmp_path):
    scene = make_scene("sphere", "diffuse", n_train=32, n_test=1, size=32, seed=3, samples=2)
    _, plan = _phase1_plan(scene, tmp_path, plan_overrides={"envmap": True})
    env = plan["decisions"]["envmap"]
    assert env["value"] is True and env["overridden"] and "set by the user" in env["reason"]


def test_invalid_override_is_a_config_error():
    scene = make_scene("sphere", "diffuse", n_train=4, n_test=1, size=16, samples=1)
    with pytest.raises(ConfigError, match=r"plan_overrides\.bogus"):
        plan_scene(scene, config_from_dict({"plan_overrides": {"bogus": True}}))
    with pytest.raises(ConfigError, match=r"plan_overrides\.sh_degree"):
        plan_scene(scene, config_from_dict({"plan_overrides": {"sh_degree": 7}}))


def test_neighbours_respect_angle_and_baseline():
    intr = Intrinsics(20, 20, 10, 10, 20, 20)
    cams = [
        Camera.look_at([3.0, 0, 0], [0, 0, 0], [0, 0, 1], intr),
        Camera.look_at([0, 3.0, 0], [0, 0, 0], [0, 0, 1], intr),  # 90° away
        Camera.look_at([3.0, 0.5, 0], [0, 0, 0], [0, 0, 1], intr),  # ~9.5° from the first
        Camera.look_at([3.0, 0, 0], [0, 0, 0], [0, 0, 1], intr),  # same pose as the first
    ]
    nb = find_neighbours(cams, 30.0, 1e-3)
    assert nb[0][0] == 2 and nb[2][0] in (0, 3)
    assert nb[1][0] is None  # nothing within 30°
    assert nb[3][0] == 2  # the identical camera is no neighbour: no parallax


def test_no_neighbours_turns_multi_view_off_and_says_why():
    scene = make_scene("sphere", "diffuse", n_train=4, n_test=1, size=16, samples=1)
    plan = plan_scene(scene, config_from_dict({}))
    assert plan.multi_view.value is False and "no view has a neighbour" in plan.multi_view.reason
    assert all(plan.neighbour_of(i) is None for i in range(4))
    assert plan.background.value == "masked"


def test_masked_capture_drops_multi_view_unless_something_else_must_pin_it():
    """Every view masked and silhouette points on: L_multi off, with the reason and the
    way back; one unmasked view, no silhouette points or the user's override: on."""
    scene = make_scene("sphere", "glossy", n_train=16, n_test=1, size=16, samples=1)

    def plan(**extra):
        wide = {"loss": {"multiview_max_angle_deg": 90.0}}  # 16 views: give each a neighbour
        return plan_scene(scene, config_from_dict({**wide, **extra}))

    masked = plan()
    assert masked.silhouette.value is True and masked.multi_view.value is False
    assert "silhouette points pin the surface" in masked.multi_view.reason
    assert "plan_overrides.multi_view=true" in masked.multi_view.reason
    assert masked.multi_view.evidence["views_with_neighbour"] == 16
    assert all(masked.neighbour_of(i) is None for i in range(16))  # nothing rendered for it
    forced = plan(plan_overrides={"multi_view": True})
    assert forced.multi_view.value is True and forced.multi_view.overridden
    assert forced.neighbour_of(0) is not None
    assert plan(plan_overrides={"silhouette": False}).multi_view.value is True
    assert plan(loss={"silhouette": 0, "multiview_max_angle_deg": 90.0}).multi_view.value
    scene.train[3].mask = None  # one view without a mask: the masks do not pin it all
    partly = plan()
    assert partly.silhouette.value is True and partly.multi_view.value is True


def test_auto_envmap_resolution_follows_focal_length():
    # The paper's 128 at f ≈ 1111 px (800-px NeRF-synthetic), then scaled with f.
    assert auto_envmap_resolution(1111.1) == 128
    assert auto_envmap_resolution(177.8) == 32  # the dev scenes at 128 px
    assert auto_envmap_resolution(88.9) == 16  # ... and at 64 px
    assert auto_envmap_resolution(10.0) == 8 and auto_envmap_resolution(5000.0) == 128
    assert auto_envmap_resolution(float("nan")) == 128


def test_plan_records_envmap_resolution_and_config_wins(tmp_path):
    scene = make_scene("sphere", "mirror", n_train=8, n_test=1, size=32, samples=1)
    f = scene.train[0].camera.intrinsics.fx
    auto = plan_scene(scene, config_from_dict({}))
    d = auto.to_dict()["decisions"]["envmap_resolution"]
    assert d["value"] == auto_envmap_resolution(f)
    assert d["evidence"]["median_focal_px"] == pytest.approx(f)
    fixed = plan_scene(scene, config_from_dict({"envmap_resolution": 24}))
    assert fixed.envmap_resolution.value == 24 and "config" in fixed.envmap_resolution.reason
    cfg = config_from_dict({"iterations": 10, "init_points": 200, "envmap_resolution": 12})
    t = Trainer(scene, cfg, tmp_path)
    t.setup(resume=False)
    assert t.envmap is not None and t.envmap.resolution == 12


def test_a_plan_with_a_decision_this_version_does_not_know_still_opens():
    """A run planned by a later version (one more decision in plan.json) opens here: the
    unknown decision is dropped, the rest read as written."""
    from core.model.plan import ScenePlan

    scene = make_scene("sphere", "diffuse", n_train=4, n_test=1, size=16, samples=1)
    d = plan_scene(scene, config_from_dict({})).to_dict()
    d["decisions"]["later_part"] = {"value": True, "reason": "from a later version"}
    back = ScenePlan.from_dict(json.loads(json.dumps(d)))
    assert back.to_dict() == json.loads(
        json.dumps(plan_scene(scene, config_from_dict({})).to_dict())
    )


def test_a_resumed_run_keeps_its_plan_without_planning_again(tmp_path, monkeypatch):
    """Resume reads the checkpoint's plan: planning (which measures the masks) is not
    repeated and thrown away; a bad override still fails when the trainer is built."""
    import core.training.trainer as trainer_mod

    scene = make_scene("sphere", "mirror", n_train=8, n_test=1, size=24, samples=1)
    cfg = config_from_dict({"iterations": 6, "init_points": 200, "envmap_resolution": 8})
    t = Trainer(scene, cfg, tmp_path)
    t.setup(resume=False)
    t.train()
    written = t.plan.to_dict()

    def no_planning(*_a, **_k):
        raise AssertionError("a resumed run planned its scene again")

    monkeypatch.setattr(trainer_mod, "plan_scene", no_planning)
    again = Trainer(scene, cfg, tmp_path)
    again.setup(resume=True)
    assert again.iteration == 6 and again.plan.to_dict() == written
    with pytest.raises(ConfigError, match=r"plan_overrides\.bogus"):
        Trainer(scene, config_from_dict({"plan_overrides": {"bogus": True}}), tmp_path / "b")
