"""What the meshing protocol scores on a perfect depth: the floor under every mesh CD.

``glint eval`` fuses the training views' rendered depth into a TSDF (``core.meshing``),
extracts a mesh and samples it. This script fuses the scene's *true* depth maps
(``train_gt/``) with the grid and truncation a run's mesh used (its ``mesh.json``) and
scores the mesh against ``gt_points.ply`` as ``glint eval`` does (observations
weighted by the true normals' incidence, as the rendered normals weight a run's): what the protocol
gives a perfect depth. The GT maps are antialiased, so a pixel on an occlusion edge or
the silhouette holds a mix of two surfaces' depths (fused as is, those pixels build
skirts: teapot_gold 0.64 instead of 0.37); pixels whose 3×3 neighbourhood leaves the
mask or spans a depth jump above ``--jump`` pixel footprints (depth / focal length)
are left out (so are surfaces steeper than ~70° to the view, which others see
head-on). Beside it: the point-sampling floor from the scene's ``meta.json``.

    python -m bench.tsdf_floor ../shared/data/teapot_gold [--run runs/x] [--points 200000]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
import torch.nn.functional as F

from core.evaluation.geometry import chamfer_floor_x100, load_gt_points, mesh_chamfer
from core.meshing.tsdf import (
    MASK_EMPTY,
    DepthFrame,
    extract_mesh,
    fuse_depth_frames,
    incidence_weight,
    keep_largest_components,
)
from core.scene.formats import load_scene
from core.scene.groundtruth import load_ground_truth
from core.scene.views import Scene

COVERED = 0.999


def gt_frames(scene: Scene, root: Path, jump_px: float) -> list[DepthFrame]:
    """The training views' true depth without mixed pixels (see the module docstring)."""
    frames = []
    for v in scene.train:
        gt = load_ground_truth(root, v)
        if gt is None:
            raise SystemExit(f"{root}: no GT depth map for training view {v.name!r}")
        mask = v.mask if v.mask is not None else (gt.depth > 0).float()
        valid = (gt.depth > 0) & torch.isfinite(gt.depth) & (mask > COVERED)
        d = torch.where(valid, gt.depth, torch.full_like(gt.depth, torch.inf))[None, None]
        spread = F.max_pool2d(d, 3, 1, 1) + F.max_pool2d(-d, 3, 1, 1)
        footprint = gt.depth / float(v.camera.intrinsics.fx)
        valid = valid & (spread[0, 0] < jump_px * footprint)
        normal_cam = gt.normal_world.to(v.camera.R) @ v.camera.R.T
        weight = incidence_weight(normal_cam, v.camera.camera_rays(normal_cam.dtype))
        frames.append(DepthFrame(v.camera, gt.depth, valid, mask < MASK_EMPTY, None, weight))
    return frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--run", type=Path, help="a run whose mesh.json sets grid and truncation")
    ap.add_argument("--points", type=int, default=200_000, help="points sampled on the mesh")
    ap.add_argument("--jump", type=float, default=2.5, help="depth jump, pixel footprints")
    a = ap.parse_args()
    torch.set_num_threads(1)
    scene = load_scene(a.scene)
    gt = load_gt_points(a.scene)
    if gt is None:
        raise SystemExit(f"{a.scene}: no gt_points.ply")
    kw: dict = {"center": scene.center, "radius": float(scene.radius)}
    if a.run is not None:
        fusion = json.loads((a.run / "mesh.json").read_text())["fusion"]
        kw.update(voxel=fusion["voxel"], trunc=fusion["trunc"])
    vol, params = fuse_depth_frames(gt_frames(scene, a.scene, a.jump), **kw)
    mesh, _ = keep_largest_components(extract_mesh(vol), 0.1)
    res = mesh_chamfer(mesh, gt, n_points=a.points)
    floor = chamfer_floor_x100(a.scene, a.points)
    print(
        f"{a.scene.name}: GT depth through the TSDF (voxel {params.voxel:.5f}, trunc "
        f"{params.trunc:.5f}, {len(mesh.faces)} faces): CD×10² {res['cd_x100']:.3f}, "
        f"F@0.01 {res['fscore']:.3f}; point-sampling floor at {a.points} points: "
        f"{'–' if floor is None else f'{floor:.3f}'}"
    )


if __name__ == "__main__":
    main()
