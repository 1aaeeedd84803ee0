"""core.training.view_coverage, the plan's oblique_depth decision and the depth that
L_single reads where it is on (core.render.depth_geometry.oblique_depth)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch

from core.config import config_from_dict
from core.render.depth_geometry import OBLIQUE_DEPTH_COS, oblique_depth
from core.scene.cameras import Camera, Intrinsics
from core.scene.synthetic import make_scene
from core.training.planner import MAX_UNFACED, plan_scene
from core.training.view_coverage import fibonacci_directions, unfaced_share

ORIGIN = torch.zeros(3, dtype=torch.float64)


def test_directions_are_unit_and_spread_evenly() -> None:
    d = fibonacci_directions(2000)
    assert d.shape == (2000, 3)
    assert torch.allclose(d.norm(dim=-1), torch.ones(2000, dtype=torch.float64))
    # a cap of half-angle 60° holds a quarter of the sphere's area
    cap = (d @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) > 0.5).double().mean()
    assert abs(float(cap) - 0.25) < 0.005


def test_unfaced_share_states_the_geometry() -> None:
    """A sphere of views faces every side; one view faces a 60° cap (a quarter of the
    sphere), so three quarters go unfaced; views over the whole upper hemisphere, down
    to the horizon, face everything above 60° below it: (1 - sin 60°) / 2 unfaced."""
    dirs = fibonacci_directions(3000)
    assert unfaced_share(3.0 * fibonacci_directions(64), ORIGIN) == 0.0
    one = torch.tensor([[0.0, 0.0, 4.0]], dtype=torch.float64)
    assert abs(unfaced_share(one, ORIGIN) - 0.75) < 0.005
    upper = 4.0 * dirs[dirs[:, 2] >= 0]
    expected = (1.0 - math.sin(math.radians(60.0))) / 2.0
    assert abs(unfaced_share(upper, ORIGIN) - expected) < 0.005
    # the target matters: the same views seen from a point far below them face less
    assert unfaced_share(upper, torch.tensor([0.0, 0.0, -50.0])) > 0.7


def _scene_with_views(n: int, upper_only: bool):  # type: ignore[no-untyped-def]
    scene = make_scene("sphere", "diffuse", n_train=n, n_test=1, size=24, samples=1)
    if upper_only:
        intr = Intrinsics.from_fov_x(0.7, 24, 24)
        for v, d in zip(scene.train, fibonacci_directions(2 * n)[:n], strict=True):
            v.camera = Camera.look_at((3.0 * d).tolist(), [0.0, 0.0, 0.0], [0, 0, 1], intr)
    return scene


def test_the_plan_turns_oblique_depth_on_only_where_a_side_goes_unfaced() -> None:
    around = plan_scene(_scene_with_views(32, upper_only=False), config_from_dict({}))
    dec = around.oblique_depth
    assert dec.value is False and dec.evidence["unfaced_share"] <= MAX_UNFACED
    above = _scene_with_views(32, upper_only=True)
    dec = plan_scene(above, config_from_dict({})).oblique_depth
    assert dec.value is True and dec.evidence["unfaced_share"] > 0.05
    assert "face no training view" in dec.reason
    # the ablations and the user's override win
    for ablation in ({"oblique_depth": False}, {"planar_depth": False}, {"facing_depth": False}):
        cfg = config_from_dict({"ablation": ablation})
        assert plan_scene(above, cfg).oblique_depth.value is False
    off = config_from_dict({"plan_overrides": {"oblique_depth": False}})
    dec = plan_scene(above, off).oblique_depth
    assert dec.value is False and dec.overridden and "set by the user" in dec.reason


def test_oblique_depth_keeps_facing_pixels_and_reads_centre_depth_edge_on() -> None:
    """A 1×5 strip of pixels along the optical axis' row, the surface normal tilted so
    that |cos θ| is 1, 0.5 (the facing limit), 0.4, 0.3 and 0.1 with the ray: the facing
    pixels keep Eq. 8's depth, 0.4 is halfway to Eq. 5's, 0.3 is Eq. 5's, and 0.1 (84°
    from face-on, beyond OBLIQUE_DEPTH_MAX_DEG) leaves the loss."""
    intr = Intrinsics(fx=1000.0, fy=1000.0, cx=2.5, cy=0.5, width=5, height=1)
    cam = Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], intr)
    rays = cam.camera_rays(torch.float64, torch.device("cpu"))[0]
    rays = rays / rays.norm(dim=-1, keepdim=True)
    normals = []
    for c, r in zip((1.0, 0.5, 0.4, 0.3, 0.1), rays, strict=True):
        side = torch.linalg.cross(r, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
        side = side / side.norm()
        normals.append(c * r + math.sqrt(1.0 - c * c) * side)
    gb = SimpleNamespace(
        normal=torch.stack(normals)[None], center_depth=torch.full((1, 5), 2.0, dtype=torch.float64)
    )
    planar = torch.full((1, 5), 3.0, dtype=torch.float64)
    valid = torch.ones(1, 5, dtype=torch.bool)
    depth, used = oblique_depth(gb, planar, valid, cam)  # type: ignore[arg-type]
    lo, hi = OBLIQUE_DEPTH_COS
    assert hi == math.cos(math.radians(60.0)) and lo == 0.3
    assert torch.allclose(depth[0], torch.tensor([3.0, 3.0, 2.5, 2.0, 2.0], dtype=torch.float64))
    assert used[0].tolist() == [True, True, True, True, False]
    # pixels outside the given valid set stay out and keep their depth
    depth, used = oblique_depth(gb, planar, torch.zeros_like(valid), cam)  # type: ignore[arg-type]
    assert not used.any() and torch.equal(depth, planar)
