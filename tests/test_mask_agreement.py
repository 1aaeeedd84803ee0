"""core.training.mask_agreement and the plan's hull decision: the mesh is bounded by the
masks' hull only where the masks agree with each other."""

from __future__ import annotations

import torch

from core.config import config_from_dict
from core.scene.synthetic import make_scene
from core.training.mask_agreement import MAX_UNSUPPORTED, unsupported_rim_share
from core.training.planner import plan_scene


def _sphere(n_train: int = 16):  # type: ignore[no-untyped-def]
    return make_scene("sphere", "diffuse", n_train=n_train, n_test=1, size=48, samples=4)


def test_rendered_masks_agree_and_the_plan_bounds_meshes_by_their_hull() -> None:
    scene = _sphere()
    m = unsupported_rim_share(scene)
    assert m["share"] == 0.0 and m["views"] == 16 and m["rays"] > 16 * 50
    hull = plan_scene(scene, config_from_dict({})).hull
    assert hull.value is True and "agree" in hull.reason
    assert hull.evidence["share"] == 0.0


def test_masks_that_slip_disagree_and_the_plan_leaves_the_hull_off() -> None:
    """Every other mask moved 3 px sideways (a pose error or a segmentation slip): rays
    just inside those silhouettes, on the side they moved toward, leave the other views'
    masks before they reach the object."""
    scene = _sphere()
    for v in scene.train[::2]:
        assert v.mask is not None
        v.mask = torch.roll(v.mask, shifts=3, dims=1)
    m = unsupported_rim_share(scene)
    assert m["share"] > 5 * MAX_UNSUPPORTED
    hull = plan_scene(scene, config_from_dict({})).hull
    assert hull.value is False and "disagree" in hull.reason


def test_without_two_masks_there_is_nothing_to_compare_and_the_user_can_override() -> None:
    scene = _sphere(n_train=4)
    for v in scene.train[1:]:
        v.mask = None
    assert unsupported_rim_share(scene)["share"] is None
    assert plan_scene(scene, config_from_dict({})).hull.value is False
    agreeing = _sphere(n_train=4)
    off = plan_scene(agreeing, config_from_dict({"plan_overrides": {"hull": False}})).hull
    assert off.value is False and off.overridden and "set by the user" in off.reason


def test_mesh_commands_follow_the_plan_unless_told() -> None:
    """``--hull`` / ``--no-hull`` on glint mesh, eval and bench; neither: the plan's
    decision (None reaches mesh_model), and bench.md's command line says which."""
    from core.cli import _bench_command, build_parser

    p = build_parser()
    for cmd in (["mesh", "r"], ["eval", "r"], ["bench", "s", "--budget", "10"]):
        assert p.parse_args(cmd).hull is None
        assert p.parse_args([*cmd, "--hull"]).hull is True
        assert p.parse_args([*cmd, "--no-hull"]).hull is False
    bench = ["bench", "s", "--budget", "10"]
    assert "hull" not in _bench_command(p.parse_args(bench))
    assert _bench_command(p.parse_args([*bench, "--no-hull"])).endswith("--no-hull")
    for cmd in (["mesh", "r"], ["eval", "r"], bench):  # the mesher's oblique-pixel depth
        assert p.parse_args(cmd).grazing_blend is True
        assert p.parse_args([*cmd, "--no-grazing-blend"]).grazing_blend is False
    assert "--no-grazing-blend" not in _bench_command(p.parse_args(bench))
    assert _bench_command(p.parse_args([*bench, "--no-grazing-blend"])).endswith(
        "--no-grazing-blend"
    )


def test_bench_cli_prints_the_share_of_a_scene_on_disk(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from bench.mask_agreement import main
    from core.scene.formats.writers import write_blender

    write_blender(_sphere(n_train=6), tmp_path / "s")
    main([str(tmp_path / "s"), "--rays", "20"])
    row = capsys.readouterr().out.splitlines()[1].split()
    assert row[1:4] == ["6", "120", "0.0000"]
