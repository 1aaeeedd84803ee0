"""The held-out scene generator (bench/render_unseen.py) reproduces the dev data's layout:
its cameras, its pixel rays and z-depth, its shapes' orientation and frame, the points
it calls seen. The Mitsuba render itself runs where mitsuba is installed."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from bench.render_unseen import (
    CAMERA_ANGLE_X,
    PRESETS,
    SHAPES,
    TEST_PHASE,
    chamfer_x100,
    fibonacci_cameras,
    normalize,
    pixel_rays,
    seen_by,
)

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "teapot_gold"


def test_cameras_sit_on_the_sphere_looking_at_the_origin_with_z_up() -> None:
    for c2w in fibonacci_cameras(64, 0.0) + fibonacci_cameras(16, TEST_PHASE):
        rot, eye = c2w[:3, :3], c2w[:3, 3]
        assert np.allclose(rot.T @ rot, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(1.0)
        assert np.linalg.norm(eye) == pytest.approx(4.0)
        assert np.allclose(-rot[:, 2], -eye / 4.0)  # looks down its -Z at the origin
        assert rot[2, 0] == pytest.approx(0.0, abs=1e-12)  # no roll: +X stays level
        assert rot[2, 1] >= 0.0  # +Y up in the image


def test_upper_cameras_cover_the_upper_half_evenly_and_never_the_underside() -> None:
    train = fibonacci_cameras(64, 0.0, upper=True)
    heights = np.array([c2w[2, 3] / 4.0 for c2w in train])
    assert heights.min() > 0.0 and heights.max() < 1.0  # none below the equator, none at the pole
    # evenly in z (equal areas of the hemisphere): half the views above z = 0.5
    assert int((heights > 0.5).sum()) == 32
    for c2w in train + fibonacci_cameras(16, TEST_PHASE, upper=True):
        rot, eye = c2w[:3, :3], c2w[:3, 3]
        assert np.linalg.norm(eye) == pytest.approx(4.0)
        assert np.allclose(-rot[:, 2], -eye / 4.0)


@pytest.mark.skipif(not SHARED.is_dir(), reason="needs ../shared/data")
@pytest.mark.parametrize(("split", "n", "phase"), [("train", 64, 0.0), ("test", 16, TEST_PHASE)])
def test_cameras_are_the_dev_datas(split: str, n: int, phase: float) -> None:
    doc = json.loads((SHARED / f"transforms_{split}.json").read_text())
    assert doc["camera_angle_x"] == pytest.approx(CAMERA_ANGLE_X)
    for frame, mine in zip(doc["frames"], fibonacci_cameras(n, phase), strict=True):
        assert np.allclose(np.array(frame["transform_matrix"]), mine, atol=1e-9)


def test_pixel_rays_have_unit_camera_depth_and_the_centre_ray_meets_the_origin() -> None:
    c2w = fibonacci_cameras(16, 0.0)[5]
    size = 8
    origins, dirs = pixel_rays(c2w, size)
    forward = -c2w[:3, 2]
    assert np.allclose(dirs @ forward, 1.0)  # hit distance along d is the z-depth
    # The image centre lies between the four middle pixels; their mean ray is forward.
    mid = dirs.reshape(size, size, 3)[3:5, 3:5].reshape(-1, 3).mean(0)
    assert np.allclose(mid / np.linalg.norm(mid), forward)
    assert np.allclose(origins[0] + 4.0 * forward, 0.0, atol=1e-12)
    # Row 0 is the top of the image, column 0 its left.
    up, right = c2w[:3, 1], c2w[:3, 0]
    first = dirs.reshape(size, size, 3)[0, 0]
    assert first @ up > 0 and first @ right < 0


@pytest.mark.parametrize("shape", sorted(SHAPES))
def test_shapes_are_closed_outward_and_fill_the_unit_sphere(shape: str) -> None:
    mesh, matrix = normalize(SHAPES[shape]())
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    radius = np.linalg.norm(mesh.vertices, axis=1).max()
    assert radius == pytest.approx(1.0, abs=1e-6)
    assert matrix.shape == (4, 4)


def test_every_preset_names_a_shape_and_a_dev_light() -> None:
    for spec in PRESETS.values():
        assert spec["shape"] in SHAPES
        assert spec["envmap"] in ("courtyard", "forest", "studio")
        assert 0.0 < spec["material"]["alpha"] <= 1.0


def test_seen_counts_the_visible_side_only() -> None:
    c2w = fibonacci_cameras(16, 0.0)[7]
    size = 32
    forward, eye = -c2w[:3, 2], c2w[:3, 3]
    depth = np.full((size, size), 4.0)  # a wall through the origin, facing the camera
    front = eye + 3.9 * forward  # in front of the wall: seen
    behind = eye + 4.5 * forward  # behind it, more than a footprint: hidden
    beside = eye + 4.0 * forward + 10.0 * c2w[:3, 0]  # out of the frame
    seen = seen_by(np.stack([front, behind, beside]), [c2w], [depth], size)
    assert seen.tolist() == [True, False, False]
    # A point on the wall itself is seen (the tolerance is about a pixel footprint).
    f = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    on = eye + (4.0 + 1.0 / f) * forward
    assert seen_by(on[None], [c2w], [depth], size).tolist() == [True]


def test_chamfer_is_zero_on_itself_and_the_mean_of_both_ways() -> None:
    a = np.random.default_rng(0).normal(size=(50, 3))
    assert chamfer_x100(a, a) == 0.0
    b = a + np.array([0.01, 0.0, 0.0])
    assert chamfer_x100(a, b) == pytest.approx(1.0, rel=1e-6)


def test_a_tiny_scene_renders_in_the_dev_layout(tmp_path: Path) -> None:
    pytest.importorskip("mitsuba")
    if not SHARED.is_dir():
        pytest.skip("needs ../shared/data for the env map")
    from bench.render_unseen import render_scene

    out = tmp_path / "tiny"
    meta = render_scene(
        out, "trefoil_aluminium", SHARED.parent, size=16, n_train=2, n_test=1, spp=4,
        variant="scalar_rgb",
    )  # fmt: skip
    for rel in ("train/r_0.png", "test/r_0.png", "train_gt/r_1_depth.exr", "gt_points.ply"):
        assert (out / rel).is_file(), rel
    assert meta["envmap"]["scale"] > 0
    assert json.loads((out / "meta.json").read_text())["spec"]["preset"] == "trefoil_aluminium"
