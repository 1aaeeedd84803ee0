"""bench.mask_iou: a mesh drawn into the held-out views, against their masks."""

import pytest
import trimesh

from bench.mask_iou import mask_agreement, mesh_coverage
from core.scene.cameras import Camera, Intrinsics
from core.scene.synthetic import SPHERE_RADIUS, make_scene


def test_coverage_of_one_triangle_is_its_area_in_pixels() -> None:
    intr = Intrinsics(40.0, 40.0, 16.0, 16.0, 32, 32)
    cam = Camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], intr)
    # a right triangle in the plane z = 0, 1.6 wide: 16 pixels on a side at f / z = 10
    tri = trimesh.Trimesh([[-0.8, -0.8, 0.0], [0.8, -0.8, 0.0], [-0.8, 0.8, 0.0]], [[0, 1, 2]])
    cov = mesh_coverage(tri, cam, supersample=8)
    assert cov.sum() == pytest.approx(16 * 16 / 2, rel=0.04)
    assert cov.max() == 1.0 and cov.min() == 0.0


def test_the_true_sphere_agrees_with_the_masks_and_a_wrong_one_does_not() -> None:
    scene = make_scene("sphere", "diffuse", n_train=2, n_test=4, size=48, samples=4)
    true = trimesh.creation.icosphere(subdivisions=4, radius=SPHERE_RADIUS)
    ok = mask_agreement(true, scene)
    assert ok.views == 4
    assert ok.iou > 0.97 and ok.missing < 0.02 and ok.extra < 0.02
    # a sphere 10% smaller leaves out about 1 − 0.9² of each disc (perspective aside)
    small = mask_agreement(
        trimesh.creation.icosphere(subdivisions=4, radius=0.9 * SPHERE_RADIUS), scene
    )
    assert small.missing == pytest.approx(0.19, abs=0.04) and small.extra < 0.01
    big = mask_agreement(
        trimesh.creation.icosphere(subdivisions=4, radius=1.1 * SPHERE_RADIUS), scene
    )
    assert big.extra == pytest.approx(0.21, abs=0.05) and big.missing < 0.01
    assert big.iou < ok.iou and small.iou < ok.iou


def test_a_scene_without_test_masks_is_refused() -> None:
    scene = make_scene("sphere", "diffuse", n_train=2, n_test=1, size=16, samples=1)
    for v in scene.test:
        v.mask = None
    with pytest.raises(ValueError, match="no test view has a mask"):
        mask_agreement(trimesh.creation.icosphere(), scene)
