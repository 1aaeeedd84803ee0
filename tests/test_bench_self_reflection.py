"""bench.self_reflection: which pixels of a mirror see the object itself."""

import numpy as np
import torch
import trimesh

from bench.self_reflection import self_reflecting
from core.scene.cameras import Camera, Intrinsics
from core.scene.groundtruth import GroundTruth
from core.scene.views import View

SIZE = 24


def _view_and_truth(mesh: trimesh.Trimesh) -> tuple[View, GroundTruth]:
    """A camera 3 above the origin looking down, and the mesh's true z-depth and
    camera-facing normals at its pixel centres (ray cast)."""
    cam = Camera.look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                         Intrinsics.from_fov_x(0.6, SIZE, SIZE))  # fmt: skip
    eye, rays = cam.world_rays(torch.float64)
    dirs = rays.reshape(-1, 3).numpy()
    origins = np.repeat(eye.numpy()[None], dirs.shape[0], axis=0)
    loc, ray, tri = mesh.ray.intersects_location(origins, dirs, multiple_hits=False)
    depth = np.zeros(dirs.shape[0])
    normal = np.zeros((dirs.shape[0], 3))
    depth[ray] = (loc - eye.numpy()) @ cam.forward.numpy()
    n = mesh.face_normals[tri]
    normal[ray] = n * -np.sign((n * dirs[ray]).sum(-1, keepdims=True))
    gt = GroundTruth(
        torch.from_numpy(depth.reshape(SIZE, SIZE)).float(),
        torch.from_numpy(normal.reshape(SIZE, SIZE, 3)).float(),
    )
    return View(cam, torch.zeros(SIZE, SIZE, 3)), gt


def _quads(*corners: list[list[float]]) -> trimesh.Trimesh:
    verts, faces = [], []
    for quad in corners:
        k = len(verts)
        verts += quad
        faces += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
    return trimesh.Trimesh(np.array(verts, float), np.array(faces), process=False)


def test_a_flat_mirror_facing_the_camera_reflects_nothing_of_itself() -> None:
    plane = _quads([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]])
    view, gt = _view_and_truth(plane)
    assert bool(gt.mask.all())
    assert not self_reflecting(view, gt, plane).any()


def test_each_wall_of_a_right_angled_groove_reflects_the_other() -> None:
    # z = |x|: a ray coming down onto one wall leaves it horizontally, into the other
    groove = _quads(
        [[0, -2, 0], [1.5, -2, 1.5], [1.5, 2, 1.5], [0, 2, 0]],
        [[-1.5, -2, 1.5], [0, -2, 0], [0, 2, 0], [-1.5, 2, 1.5]],
    )
    view, gt = _view_and_truth(groove)
    assert bool(gt.mask.all())
    assert self_reflecting(view, gt, groove).all()


def test_a_reflection_that_clears_the_shorter_wall_sees_no_object() -> None:
    # the left wall only rises to z = 0.3: a point of the right wall at x leaves it
    # horizontally at height x, so it sees the left wall where x < 0.3 and the sky above
    groove = _quads(
        [[0, -2, 0], [1.5, -2, 1.5], [1.5, 2, 1.5], [0, 2, 0]],
        [[-0.3, -2, 0.3], [0, -2, 0], [0, 2, 0], [-0.3, 2, 0.3]],
    )
    view, gt = _view_and_truth(groove)
    mine = self_reflecting(view, gt, groove)
    cam = view.camera
    x = cam.backproject(cam.pixel_centers(torch.float64), gt.depth.double())[..., 0].numpy()
    on = gt.mask.numpy()
    # the rays are not quite vertical (perspective): a margin either side of 0.3
    assert mine[on & (x < 0.25)].all()
    assert not mine[on & (x > 0.35)].any()
    assert (on & (x < 0.25)).sum() > 50 and (on & (x > 0.35)).sum() > 50
