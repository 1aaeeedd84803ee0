"""Initial points on the visual hull (core.training.init_points)."""

from __future__ import annotations

import pytest

from core.scene.synthetic import SPHERE_RADIUS, make_scene
from core.training.init_points import visual_hull_points


def test_hull_points_lie_on_the_hull_not_a_marching_step_inside() -> None:
    scene = make_scene("sphere", "diffuse", n_train=16, n_test=0, size=48, samples=2)
    scene.radius = 1.3  # loaders' bounds are loose: rays start well outside the object
    pts, cols = visual_hull_points(scene, 2000)
    assert pts.shape == (2000, 3) and cols.shape == (2000, 3)
    off = pts.norm(dim=-1) - SPHERE_RADIUS
    # the hull of 16 views encloses the sphere: points on or just outside it
    assert float(off.quantile(0.05)) > -0.004
    assert 0.0 < float(off.median()) < 0.01
    # the marching step alone (2.6 / 64 here) leaves them half a step inside on average
    coarse, _ = visual_hull_points(scene, 2000, bisections=0)
    coarse_off = coarse.norm(dim=-1) - SPHERE_RADIUS
    assert float(coarse_off.quantile(0.25)) < -0.01


def test_no_masks_no_hull() -> None:
    scene = make_scene("sphere", "diffuse", n_train=4, n_test=0, size=16, samples=1)
    for v in scene.train:
        v.mask = None
    assert visual_hull_points(scene, 100) is None


def test_a_share_of_the_points_starts_inside_the_hull() -> None:
    scene = make_scene("sphere", "diffuse", n_train=16, n_test=0, size=48, samples=2)
    scene.radius = 1.3
    step = 2 * 1.3 / 63  # the march's step through the bounding sphere
    pts, cols = visual_hull_points(scene, 2000, volume_fraction=0.3)
    assert pts.shape == (2000, 3) and cols.shape == (2000, 3)
    off = pts.norm(dim=-1) - SPHERE_RADIUS
    surface, _ = visual_hull_points(scene, 2000)
    surface_off = surface.norm(dim=-1) - SPHERE_RADIUS
    assert float(surface_off.min()) > -0.02
    # no further out than the hull's surface but for the inside samples' half-step jitter
    assert float(off.max()) < float(surface_off.max()) + step / 2
    # about 30% drawn along their rays' chords (a few of those land near the surface)
    deep = float((off < -0.05).float().mean())
    assert 0.2 < deep < 0.32
    # inside points reach deep: the sphere's chords pass near its centre
    assert float(off.min()) < -0.7 * SPHERE_RADIUS


def test_volume_fraction_out_of_range_is_refused() -> None:
    scene = make_scene("sphere", "diffuse", n_train=4, n_test=0, size=16, samples=1)
    with pytest.raises(ValueError, match="volume_fraction"):
        visual_hull_points(scene, 100, volume_fraction=1.5)
