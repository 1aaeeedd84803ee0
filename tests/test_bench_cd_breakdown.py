"""bench.cd_breakdown: which side of the truth a mesh lies on, and where its error sits."""

import numpy as np
import trimesh

from bench.cd_breakdown import breakdown, crease_mask
from core.evaluation.metrics import sample_surface


def _box_truth(n: int = 40_000) -> dict[str, np.ndarray]:
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    pts, face = sample_surface(box.vertices, box.faces, n, seed=1)
    return {"points": pts, "normals": np.asarray(box.face_normals)[face]}


def test_a_shell_outside_the_truth_reads_as_a_positive_offset_everywhere() -> None:
    gt = _box_truth()
    big = trimesh.creation.box(extents=(1.04, 1.04, 1.04))  # every face 0.02 outside
    pts, _ = sample_surface(big.vertices, big.faces, 40_000, seed=2)
    res = breakdown(pts, gt, crease_radius=0.05, crease_deg=30.0)
    off = res["signed_offset_x100"]
    assert abs(off["median"] - 2.0) < 0.05
    assert off["outside_share"] > 0.99
    assert 1.9 < res["accuracy"]["p50_x100"] < 2.1
    # a uniform shell has no tail: nothing lies 0.05 off
    assert res["accuracy"]["share_beyond_0.05"] == 0.0


def test_the_true_surface_scores_its_sampling_floor_with_no_side() -> None:
    gt = _box_truth()
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    pts, _ = sample_surface(box.vertices, box.faces, 40_000, seed=3)
    res = breakdown(pts, gt, crease_radius=0.05, crease_deg=30.0)
    assert res["cd_x100"] < 1.0  # the sampling floor of 40k points on area 6
    assert abs(res["signed_offset_x100"]["median"]) < 1e-6


def _notched_box_truth(rng: np.random.Generator, n: int = 60_000) -> dict[str, np.ndarray]:
    """Points on a unit box with a groove 0.4 wide and 0.2 deep along y in its top face."""
    gt = _box_truth(n)
    p, nrm = gt["points"], gt["normals"]
    keep = ~((p[:, 2] > 0.499) & (np.abs(p[:, 0]) < 0.2))  # the top face over the groove
    m = n // 12
    floor = np.c_[rng.uniform(-0.2, 0.2, m), rng.uniform(-0.5, 0.5, m), np.full(m, 0.3)]
    walls = []
    for side in (-1.0, 1.0):
        walls.append(
            np.c_[np.full(m, 0.2 * side), rng.uniform(-0.5, 0.5, m), rng.uniform(0.3, 0.5, m)]
        )
    pts = np.concatenate([p[keep], floor, *walls])
    up, wl, wr = (
        np.tile([0, 0, 1.0], (m, 1)),
        np.tile([1.0, 0, 0], (m, 1)),
        np.tile([-1.0, 0, 0], (m, 1)),
    )
    return {"points": pts, "normals": np.concatenate([nrm[keep], up, wl, wr])}


def test_a_filled_notch_shows_as_missing_truth_in_the_notch() -> None:
    """A box with a groove, reconstructed as the full box (the groove filled, as a
    visual hull fills a concavity): the truth inside the groove is far from the mesh, and
    the mesh over the groove lies outside the truth."""
    gt = _notched_box_truth(np.random.default_rng(4))
    full = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    pred, _ = sample_surface(full.vertices, full.faces, 60_000, seed=5)
    res = breakdown(pred, gt, crease_radius=0.05, crease_deg=30.0)
    # the lid over the groove sits outside (its nearest true points are partly the walls'
    # tops, at a sideways offset, so the mean is less than the groove's share × depth)
    assert res["signed_offset_x100"]["mean"] > 0.2
    assert res["completeness"]["p99_x100"] > 10.0  # the groove's floor is ~0.2 away
    # the error is a tail (the groove), not a shell
    assert res["completeness"]["share_beyond_0.05"] > 0.5
    assert res["completeness"]["p50_x100"] < 1.0


def test_crease_mask_marks_the_edges_of_a_box_and_not_its_faces() -> None:
    gt = _box_truth()
    mask = crease_mask(gt["points"], gt["normals"], radius=0.05, deg=30.0)
    dist_to_edge = np.sort(0.5 - np.abs(gt["points"]), axis=1)[:, 1]  # 2nd-nearest face
    assert mask[dist_to_edge < 0.02].mean() > 0.95
    assert not mask[dist_to_edge > 0.1].any()


def test_hull_depth_is_the_distance_to_the_convex_hull_inside_and_negative_outside() -> None:
    from bench.cd_breakdown import hull_depth

    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    pts = np.array([[0.5, 0.5, 0.5], [0.5, 0.5, 0.9], [0.5, 0.5, 1.2]])
    np.testing.assert_allclose(hull_depth(pts, corners), [0.5, 0.1, -0.2], atol=1e-12)


def test_the_groove_lands_in_the_deeper_hull_bin() -> None:
    """The groove's floor lies 0.2 inside the convex hull: its truth is what the filled
    lid misses, while the truth on the hull is covered."""
    gt = _notched_box_truth(np.random.default_rng(6))
    full = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    pred, _ = sample_surface(full.vertices, full.faces, 60_000, seed=7)
    res = breakdown(pred, gt, crease_radius=0.05, crease_deg=30.0)
    on_hull, floor = res["hull depth < 0.01"], res["hull depth >= 0.15"]
    assert floor["completeness_x100"] > 10 * on_hull["completeness_x100"]
    assert floor["completeness_x100"] > 15.0  # the floor is 0.2 below the lid


def test_the_plot_draws_the_groove_as_what_the_mesh_misses(tmp_path) -> None:
    """--plot: the filled groove's truth is what is drawn as missed, and its share of the
    completeness error is most of it; a mesh of the true surface misses nothing."""
    from bench.cd_breakdown import plot_missed

    gt = _notched_box_truth(np.random.default_rng(8))
    full = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    pred, _ = sample_surface(full.vertices, full.faces, 60_000, seed=9)
    out = plot_missed(pred, gt["points"], tmp_path / "missed.png", beyond=0.05)
    in_groove = (np.abs(gt["points"][:, 0]) < 0.2) & (gt["points"][:, 2] < 0.45)
    assert abs(out["missed_share"] - in_groove.mean()) < 0.35 * in_groove.mean()
    assert out["missed_completeness_share"] > 0.6
    png = (tmp_path / "missed.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    true = plot_missed(gt["points"], gt["points"], tmp_path / "none.png", beyond=0.05)
    assert true["missed_share"] == 0.0


def test_the_plot_options_are_checked_before_any_work(tmp_path, capsys) -> None:
    import pytest

    from bench.cd_breakdown import main

    for argv, says in (
        (["m.ply", "--scene", str(tmp_path), "--beyond", "0"], "--beyond must be a positive"),
        (["m.ply", "--scene", str(tmp_path), "--plot", str(tmp_path / "no" / "p.png")],
         "does not exist"),
    ):  # fmt: skip
        with pytest.raises(SystemExit):
            main(argv)
        assert says in capsys.readouterr().err
