"""TSDF fusion and mesh extraction on exact depth maps of an analytic sphere."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.meshing.mesh import export_mesh
from core.meshing.tsdf import (
    HULL_MARGIN_PX,
    DepthFrame,
    extract_mesh,
    fuse_depth_frames,
    fusion_bounds,
    keep_largest_components,
)
from core.scene.synthetic import SPHERE_RADIUS, fibonacci_cameras, render_synthetic_view

SIZE = 32


@pytest.fixture(scope="module")
def sphere_frames() -> list[DepthFrame]:
    """Exact z-depth (pixel centres) and coverage of the r = 0.6 sphere from 12 views,
    masked the way rendered planar depths are (alpha > 0.5; empty where alpha ≈ 0)."""
    frames = []
    for cam in fibonacci_cameras(12, distance=3.0, size=SIZE):
        r = render_synthetic_view(cam, shape="sphere", kind="diffuse", samples=2)
        valid = (r.depth > 0) & (r.alpha > 0.5)
        frames.append(DepthFrame(cam, r.depth, valid, r.alpha < 0.05, r.rgb))
    return frames


def test_fused_sphere_is_within_a_voxel_of_the_true_radius(sphere_frames) -> None:
    vol, params = fuse_depth_frames(sphere_frames, center=torch.zeros(3), radius=2.0, resolution=40)
    # the box is tightened from the scene's radius 2 to the observed surface (+10% margin)
    assert max(h - lo for lo, h in zip(params.lo, params.hi, strict=True)) < 1.6
    assert params.trunc == pytest.approx(4 * params.voxel)
    mesh = extract_mesh(vol)
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(r - SPHERE_RADIUS).mean() < params.voxel
    assert np.abs(r - SPHERE_RADIUS).max() < 2 * params.voxel
    _, comp = keep_largest_components(mesh)
    assert comp["components"] == 1 and comp["faces_dropped"] == 0
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * SPHERE_RADIUS**3, rel=0.05)  # outward
    # colours come from the frames: the sphere's albedo varies, so the vertices do too
    vc = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(float)
    assert vc.std(axis=0).max() > 5


def test_explicit_voxel_and_truncation_are_used(sphere_frames) -> None:
    vol, params = fuse_depth_frames(sphere_frames, voxel=0.05, trunc=0.12)
    assert params.voxel == 0.05 and params.trunc == 0.12
    r = np.linalg.norm(extract_mesh(vol).vertices, axis=1)
    assert np.abs(r - SPHERE_RADIUS).mean() < 0.05


def test_carving_removes_a_floater_the_other_views_see_through(sphere_frames) -> None:
    """A blob of depth in two views, floating where the other views see background."""
    blob = torch.tensor([0.45, 0.45, 0.45], dtype=torch.float64)  # 0.18 off the sphere
    frames, hits = [], 0
    for f in sphere_frames:
        depth, valid = f.depth.clone(), f.valid.clone()
        uv, z = f.camera.project(blob[None])
        u, v = (int(x) for x in uv[0])
        if hits < 2 and 1 <= u < SIZE - 1 and 1 <= v < SIZE - 1 and not valid[v, u]:
            depth[v - 1 : v + 2, u - 1 : u + 2] = float(z[0])
            valid[v - 1 : v + 2, u - 1 : u + 2] = True
            hits += 1
        frames.append(DepthFrame(f.camera, depth, valid, f.empty & ~valid, f.color))
    assert hits == 2
    near_blob = []
    for carve in (False, True):
        vol, _ = fuse_depth_frames(frames, resolution=40, carve=carve)
        v = extract_mesh(vol).vertices
        near_blob.append(int((np.linalg.norm(v - blob.numpy(), axis=1) < 0.1).sum()))
    assert near_blob[0] > 0, "the floater should produce surface without carving"
    assert near_blob[1] == 0


def test_bounds_ignore_sparse_floaters(sphere_frames) -> None:
    frames = list(sphere_frames)
    f = frames[0]
    depth, valid = f.depth.clone(), f.valid.clone()
    depth[0, 0], valid[0, 0] = 10.0, True  # one pixel far behind the object
    frames[0] = DepthFrame(f.camera, depth, valid)
    lo, hi = fusion_bounds(frames)
    assert np.all(hi - lo < 1.6) and np.all(lo > -0.8) and np.all(hi < 0.8)


def test_components_and_export_round_trip(tmp_path) -> None:
    import trimesh

    big = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    small = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    small.apply_translation([0.9, 0, 0])
    both = trimesh.util.concatenate([big, small])
    both.visual.vertex_colors = np.tile([200, 100, 50, 255], (len(both.vertices), 1))
    kept, stats = keep_largest_components(both, keep_fraction=0.1)
    assert stats == {"components": 2, "kept": 1, "faces_dropped": len(small.faces)}
    assert len(kept.faces) == len(big.faces)
    paths = export_mesh(kept, tmp_path)
    assert [p.name for p in paths] == ["mesh.ply", "mesh.obj", "mesh.glb"]
    for p in paths:
        back = trimesh.load(p, force="mesh", process=False)
        assert len(back.faces) == len(big.faces), p.name
    ply = trimesh.load(paths[0], force="mesh", process=False)
    assert np.array_equal(np.asarray(ply.visual.vertex_colors)[0], [200, 100, 50, 255])


def test_vertex_colours_interpolate_trilinearly_from_the_band() -> None:
    """A colour field linear in position comes back exactly at any point whose 8
    neighbours are in the band; a point with no coloured neighbour gets weight 0."""
    from core.meshing.tsdf import TSDFVolume, VoxelGrid

    grid = VoxelGrid((0.0, 0.0, 0.0), 0.1, (6, 7, 8))
    all_ijk = torch.stack(torch.unravel_index(torch.arange(grid.count), grid.shape), -1)
    band = torch.arange(grid.count)[all_ijk[:, 0] != 3]  # a slab outside the band
    vol = TSDFVolume(grid, 0.3, band)
    ijk = torch.stack(torch.unravel_index(vol.index, grid.shape), -1).float()
    field = torch.stack([ijk[:, 0] / 5, ijk[:, 1] / 6, ijk[:, 2] / 7], -1)
    vol.color[:] = field
    vol.color_weight[:] = 1.0
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 1, (200, 3)) * (np.array(grid.shape) - 1)
    got = vol.vertex_colors(pts)
    flat = np.ravel_multi_index(np.floor(pts).astype(int).T, grid.shape)
    corners_in = np.ones(len(pts), bool)
    for d in np.ndindex(2, 2, 2):
        c = np.minimum(np.floor(pts).astype(int) + d, np.array(grid.shape) - 1)
        corners_in &= c[:, 0] != 3
    assert corners_in.sum() > 20 and flat.size == 200
    want = pts / (np.array(grid.shape) - 1)
    np.testing.assert_allclose(got[corners_in], want[corners_in], atol=1e-5)


def test_incidence_weight_is_the_cosine_between_ray_and_normal() -> None:
    from core.meshing.tsdf import MIN_INCIDENCE_WEIGHT, incidence_weight

    rays = torch.tensor([[[0.0, 0.0, 1.0]] * 5])  # (1, 5, 3)
    c60 = 0.5 * 3**0.5
    normal = torch.tensor(
        [[[0.0, 0.0, -2.0], [c60, 0.0, -0.5], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.3, 0.0]]]
    )
    got = incidence_weight(normal, rays)[0]
    # head-on (any length, either side), 60 degrees, edge-on, no normal, edge-on again
    want = [1.0, 0.5, MIN_INCIDENCE_WEIGHT, MIN_INCIDENCE_WEIGHT, MIN_INCIDENCE_WEIGHT]
    torch.testing.assert_close(got, torch.tensor(want), atol=1e-6, rtol=0)


def test_surface_observations_average_by_their_weight_and_carving_counts_one() -> None:
    """Voxels on the optical axis of one camera, fused from constant depth maps: each
    voxel's value is the weighted mean of (d - z) / trunc; a carving view adds +1 with
    weight 1 whatever its weight map says."""
    from core.meshing.tsdf import TSDFVolume, VoxelGrid
    from core.scene.cameras import Camera, Intrinsics

    cam = Camera.look_at([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                         Intrinsics(8.0, 8.0, 4.0, 4.0, 8, 8))  # fmt: skip
    grid = VoxelGrid((0.0, 0.0, 1.7), 0.05, (1, 1, 13))  # world z 1.7 .. 2.3: depth 3.3 .. 2.7
    trunc = 1.0
    z = 5.0 - grid.centers(torch.arange(grid.count))[:, 2].double()

    def frame(depth: float, weight: float, carve: bool = False) -> DepthFrame:
        full = torch.full((8, 8), depth)
        yes, no = torch.ones(8, 8, dtype=torch.bool), torch.zeros(8, 8, dtype=torch.bool)
        return DepthFrame(cam, full, no if carve else yes, yes if carve else no, None,
                          torch.full((8, 8), weight))  # fmt: skip

    vol = TSDFVolume(grid, trunc, torch.arange(grid.count))
    vol.integrate(frame(3.0, 1.0))
    vol.integrate(frame(3.1, 0.25))
    want = (1.0 * (3.0 - z) + 0.25 * (3.1 - z)) / 1.25 / trunc
    torch.testing.assert_close(vol.tsdf.double(), want, atol=1e-5, rtol=0)
    torch.testing.assert_close(vol.weight, torch.full((13,), 1.25))
    # the zero crossing sits at the weighted mean depth, 3.02, not the plain mean 3.05
    assert (vol.tsdf[z < 3.02 - 1e-6] > 0).all() and (vol.tsdf[z > 3.02 + 1e-6] < 0).all()

    vol.integrate(frame(0.0, 0.25, carve=True))  # no surface: the ray is free space
    torch.testing.assert_close(vol.tsdf.double(), (1.25 * want + 1.0) / 2.25, atol=1e-5, rtol=0)
    torch.testing.assert_close(vol.weight, torch.full((13,), 2.25))


def test_weighting_by_incidence_discounts_depth_noise_at_grazing_angles() -> None:
    """Depth noise whose spread grows as 1/cos toward the silhouette (an error across the
    pixel seen along the ray) roughens the fused sphere far less when each observation
    counts by its cosine (measured: the mean radius error above the exact depths' falls
    to ~15% of the unweighted one)."""
    from core.meshing.tsdf import incidence_weight

    gen = torch.Generator().manual_seed(0)
    views = []
    for cam in fibonacci_cameras(12, distance=3.0, size=SIZE):
        r = render_synthetic_view(cam, shape="sphere", kind="diffuse", samples=2)
        valid = (r.depth > 0) & (r.alpha > 0.5)
        normal_cam = r.normal.to(cam.R) @ cam.R.T
        w = incidence_weight(normal_cam, cam.camera_rays(normal_cam.dtype))
        noise = 0.01 * torch.randn(r.depth.shape, generator=gen) / w.clamp(min=0.2)
        views.append((cam, r, valid, w, torch.where(valid, noise, 0.0)))
    err = {}
    for noisy, weighted in ((False, False), (True, False), (True, True)):
        frames = []
        for cam, r, valid, w, noise in views:
            depth, weight = r.depth + noise * noisy, w if weighted else None
            frames.append(DepthFrame(cam, depth, valid, r.alpha < 0.05, None, weight))
        vol, _ = fuse_depth_frames(frames, center=torch.zeros(3), radius=2.0, resolution=40)
        radii = np.linalg.norm(extract_mesh(vol).vertices, axis=1)
        err[noisy, weighted] = float(np.abs(radii - SPHERE_RADIUS).mean())
    excess = {w: err[True, w] - err[False, False] for w in (False, True)}
    assert excess[False] > 0.01 * SPHERE_RADIUS / 40  # the noise does roughen the sphere
    assert excess[True] < 0.5 * excess[False], err


def test_depth_edges_mark_jumps_between_surfaces_not_slopes_or_silhouettes() -> None:
    from core.meshing.tsdf import EDGE_JUMP_PX, depth_edges

    focal = 100.0  # footprint at depth 2: 0.02
    depth = torch.full((6, 8), 2.0)
    depth[:, 4:] = 2.0 + 0.02 * (EDGE_JUMP_PX + 1)  # a step just over the jump
    valid = torch.ones(6, 8, dtype=torch.bool)
    valid[:, 0] = False  # background on the left: a silhouette, not an edge
    edges = depth_edges(depth, valid, focal)
    assert edges[:, 3:5].all() and not edges[:, :3].any() and not edges[:, 5:].any()

    ramp = 2.0 + 0.02 * torch.arange(8.0)[None].expand(6, 8)  # one footprint per pixel
    assert not depth_edges(ramp, torch.ones(6, 8, dtype=torch.bool), focal).any()


def test_observation_weight_is_incidence_times_the_minimum_on_edges() -> None:
    from core.meshing.tsdf import MIN_INCIDENCE_WEIGHT, observation_weight
    from core.scene.cameras import Camera, Intrinsics

    cam = Camera.look_at([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                         Intrinsics(100.0, 100.0, 4.0, 3.0, 8, 6))  # fmt: skip
    depth = torch.full((6, 8), 5.0)
    depth[:, 4:] = 6.0  # 20 footprints behind: an occlusion edge at columns 3-4
    valid = torch.ones(6, 8, dtype=torch.bool)
    rays = cam.camera_rays()
    normal = -rays  # every pixel head-on
    w = observation_weight(depth, valid, normal, cam)
    torch.testing.assert_close(w[:, [0, 1, 2, 5, 6, 7]], torch.ones(6, 6))
    torch.testing.assert_close(w[:, 3:5], torch.full((6, 2), MIN_INCIDENCE_WEIGHT))


def test_depth_between_pixel_centres_is_bilinear_on_a_surface_and_nearest_at_an_edge() -> None:
    from core.meshing.tsdf import interpolated_depth

    W, H, focal = 6, 5, 100.0
    jj, ii = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    plane = 2.0 + 0.01 * ii + 0.005 * jj  # a slanted plane, sampled at pixel centres
    valid = torch.ones(H * W, dtype=torch.bool)
    u = torch.tensor([0.5, 1.2, 2.75, 4.9, 0.1, 5.9])
    v = torch.tensor([0.5, 3.3, 1.6, 4.4, 0.2, 4.9])
    nearest = (v.floor() * W + u.floor()).long()
    got = interpolated_depth(plane.reshape(-1), valid, nearest, u, v, W, H, focal)
    # exact inside the centres' hull; the border half-pixel extrapolates nothing (clamped)
    want = 2.0 + 0.01 * u.clamp(0.5, W - 0.5) + 0.005 * v.clamp(0.5, H - 0.5)
    torch.testing.assert_close(got, want, atol=1e-6, rtol=0)

    step = plane.clone()
    step[:, 3:] += 1.0  # an occlusion edge between columns 2 and 3
    hole = valid.clone().reshape(H, W)
    hole[0, 0] = False
    got = interpolated_depth(step.reshape(-1), hole.reshape(-1), nearest, u, v, W, H, focal)
    at_edge = torch.tensor([False, False, True, False, True, False])  # (2.75, 1.6), (0.1, 0.2)
    torch.testing.assert_close(got[at_edge], step.reshape(-1)[nearest][at_edge])
    inside = (want + (u >= 3).float())[~at_edge]
    torch.testing.assert_close(got[~at_edge], inside, atol=1e-6, rtol=0)


def test_mask_hull_distance_and_the_bound_it_gives() -> None:
    """Distances are Euclidean to the nearest pixel a mask may hold; the bound is zero
    within half a pixel's diagonal of it, (d − margin)·z/(f·trunc) beyond, at most 1."""
    from core.meshing.tsdf import hull_bound, mask_hull_distance

    empty = torch.ones(5, 7, dtype=torch.bool)
    empty[2, 3] = False
    d = mask_hull_distance(empty)
    assert d[2, 3] == 0 and d[2, 5] == 2 and d[0, 1] == pytest.approx(8**0.5)
    assert torch.equal(mask_hull_distance(torch.ones(3, 3, dtype=torch.bool)), torch.zeros(3, 3))
    z = torch.tensor([2.0, 2.0, 2.0, 2.0])
    dist = torch.tensor([0.0, HULL_MARGIN_PX, HULL_MARGIN_PX + 1.0, 100.0])
    b = hull_bound(dist, z, focal=10.0, trunc=0.5)
    torch.testing.assert_close(b, torch.tensor([0.0, 0.0, 2.0 / (10.0 * 0.5), 1.0]))


def _ray_miss_distance(cam, points: torch.Tensor) -> torch.Tensor:
    """How far the ray from ``cam`` through each point passes from the origin."""
    o = cam.center.to(torch.float64)
    ray = torch.nn.functional.normalize(points.to(torch.float64) - o, dim=-1)
    return torch.linalg.cross(ray, -o[None].expand_as(ray), dim=-1).norm(dim=-1)


def _sphere_frames_with_mask(mask_radius: float, small_views: set[int]) -> list[DepthFrame]:
    """The r = 0.6 sphere's exact depths from 12 views, masked as model_depth_frame does:
    views in ``small_views`` with the mask of a sphere of ``mask_radius`` (what they see
    through), the rest with the sphere's own."""
    from core.meshing.tsdf import mask_hull_distance

    frames = []
    for i, cam in enumerate(fibonacci_cameras(12, distance=3.0, size=SIZE)):
        r = render_synthetic_view(cam, shape="sphere", kind="diffuse", samples=2)
        empty = r.alpha < 0.05
        if i in small_views:
            uv = cam.pixel_centers(torch.float64).reshape(-1, 2)
            far = cam.backproject(uv, torch.ones(uv.shape[0], dtype=torch.float64))
            empty = (_ray_miss_distance(cam, far) > mask_radius).reshape(SIZE, SIZE)
        valid = (r.depth > 0) & (r.alpha > 0.5) & ~empty
        frames.append(DepthFrame(cam, r.depth, valid, empty, None, None, mask_hull_distance(empty)))
    return frames


def test_the_masks_hull_bounds_a_surface_the_depths_put_outside_it() -> None:
    """Ten views' depths put the surface at r = 0.6; two views' masks allow only r = 0.55
    (a membrane across a hole that only those views see through, a slab thicker than a
    thin part): carving is outvoted and leaves surface outside those masks, the hull
    distance keeps every vertex within them (to a voxel and the margin)."""
    small = {0, 6}
    frames = _sphere_frames_with_mask(0.55, small)
    cams = [f.camera for f in frames]
    excess = {}
    for hull in (False, True):
        vol, params = fuse_depth_frames(
            frames, center=torch.zeros(3), radius=2.0, resolution=40, hull=hull
        )
        v = torch.as_tensor(extract_mesh(vol).vertices)
        excess[hull] = max(float((_ray_miss_distance(cams[i], v) - 0.55).max()) for i in small)
    footprint = 3.0 / cams[0].intrinsics.fx  # the margin at the sphere's depth, about
    assert excess[False] > 0.03, excess
    assert excess[True] < params.voxel + HULL_MARGIN_PX * footprint, excess


def test_a_true_mask_leaves_the_surface_where_the_depths_put_it() -> None:
    """With masks of the sphere itself the hull bounds nothing the depths did not already
    say: the mesh is as close to the sphere as the one without it."""
    frames = _sphere_frames_with_mask(0.6, set())
    radius = {}
    for hull in (False, True):
        vol, _ = fuse_depth_frames(
            frames, center=torch.zeros(3), radius=2.0, resolution=40, hull=hull
        )
        radius[hull] = np.linalg.norm(extract_mesh(vol).vertices, axis=1)
    err = {h: np.abs(r - SPHERE_RADIUS) for h, r in radius.items()}
    # beside the rim a voxel's bound may exceed its projective distance (which only
    # underestimates there), moving a crossing by a fraction of a voxel, never out
    assert abs(err[True].mean() - err[False].mean()) < 1e-3, (err[True].mean(), err[False].mean())
    assert err[True].max() <= err[False].max() + 1e-3


def _bloated_sphere_frames(depth_radius: float, true_radius: float) -> list[DepthFrame]:
    """12 views whose depths show a sphere of ``depth_radius`` (a model thicker than the
    object) and whose masks show the true sphere of ``true_radius``."""
    from core.meshing.tsdf import mask_hull_distance

    frames = []
    for cam in fibonacci_cameras(12, distance=3.0, size=SIZE):
        uv = cam.pixel_centers(torch.float64).reshape(-1, 2)
        o = cam.center.to(torch.float64)
        d = cam.backproject(uv, torch.ones(uv.shape[0], dtype=torch.float64)) - o
        dn = d / d.norm(dim=-1, keepdim=True)
        b = (dn * o).sum(-1)
        disc = b * b - (o * o).sum() + depth_radius**2
        t = -b - disc.clamp_min(0).sqrt()  # distance along the unit ray to the near side
        z = (t / d.norm(dim=-1)).reshape(SIZE, SIZE)  # z-depth (d has z = 1)
        hit = (disc > 0).reshape(SIZE, SIZE)
        empty = (_ray_miss_distance(cam, o + dn) > true_radius).reshape(SIZE, SIZE)
        depth = torch.where(hit, z, torch.zeros_like(z)).float()
        frames.append(
            DepthFrame(cam, depth, hit & ~empty, empty, None, None, mask_hull_distance(empty))
        )
    return frames


def test_the_hull_closes_a_surface_the_depths_put_beyond_the_band(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A model 0.2 thicker than the object all round (a slab over a thin part, lego's
    base plate; carving off, so that every view's depths put the band behind the model's
    surface inside, as the views that face a slab do): the masks lift every band voxel,
    and the band holds nothing of the true surface. The closure gives the voxels behind
    the lifted ones an inside where every mask may hold them, so the mesh closes on the
    masks' hull (the sphere) instead of vanishing."""
    import core.meshing.tsdf as tsdf

    frames = _bloated_sphere_frames(0.8, SPHERE_RADIUS)

    def mesh():  # type: ignore[no-untyped-def]
        vol, params = fuse_depth_frames(
            frames, center=torch.zeros(3), radius=2.0, resolution=80, carve=False, hull=True
        )
        assert params.trunc + params.voxel < 0.8 - SPHERE_RADIUS  # the band misses the truth
        return extract_mesh(vol)

    closed = mesh()
    r = np.linalg.norm(closed.vertices, axis=1)
    assert abs(float(np.median(r)) - SPHERE_RADIUS) < 0.05  # on the hull: within a voxel
    dirs = closed.vertices / r[:, None]
    probes = np.stack([np.asarray(c.center) for c in fibonacci_cameras(50, distance=1.0, size=4)])
    assert float((probes @ dirs.T).max(axis=1).min()) > 0.95  # no direction left open
    monkeypatch.setattr(tsdf.TSDFVolume, "_closure", lambda self, idx, lifted: None)
    assert len(mesh().vertices) < len(closed.vertices) / 10  # without it: next to nothing
