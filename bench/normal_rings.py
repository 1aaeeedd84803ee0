"""Where a run's normal error lies: by distance to the silhouette, and which way it leans.

The run record's normal error is the mean angle between the rendered normal map and the
scene's true one over the pixels both cover. The true map is point-sampled at each
pixel centre (the data README), the render blends every splat whose footprint reaches
the pixel. This splits the same error over the rings of ``bench.edge_error`` (first
pixel inside the silhouette, 1–3 px inside, the interior) and reports, per ring, the
mean of (rendered − true normal) · (direction to the camera): positive means the
rendered normals lean toward the viewer.

    python -m bench.normal_rings RUN [RUN ...] --scene ../shared/data/teapot_gold
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from bench.edge_error import RINGS, ring_masks
from core.evaluation.geometry import SURFACE_ALPHA
from core.model.trained import TrainedModel
from core.scene.formats import load_scene
from core.scene.groundtruth import load_ground_truth


@torch.no_grad()
def normal_rings(model: TrainedModel, root: Path) -> dict:
    """Pooled angle error and facing bias of the test views, in total and per ring."""
    angle = {k: [] for k in RINGS}
    lean = {k: [] for k in RINGS}
    for v in load_scene(root).test:
        gt = load_ground_truth(root, v)
        if gt is None or v.mask is None:
            continue
        frame = model.render(v.camera, ("depth", "normal"))
        _, valid = frame.depth()
        covered = (gt.mask & valid & (frame.gbuffer.alpha > SURFACE_ALPHA)).numpy()
        n = F.normalize(frame.world_normals().double(), dim=-1)
        g = F.normalize(gt.normal_world.double(), dim=-1)
        deg = torch.rad2deg(torch.acos((n * g).sum(-1).clamp(-1, 1))).numpy()
        world_rays = v.camera.camera_rays(torch.float64) @ v.camera.R.double()
        rays = F.normalize(world_rays, dim=-1)
        bias = (((g - n) * rays).sum(-1)).numpy()  # (n − g)·(−ray)
        for k, ring in ring_masks(v.mask.double().numpy()).items():
            sel = ring & covered
            angle[k].append(deg[sel])
            lean[k].append(bias[sel])
    every = np.concatenate([a for k in RINGS for a in angle[k]])
    if every.size == 0:
        raise SystemExit(f"{root}: no test view with a mask and true normals")
    out: dict = {"mean_deg": float(every.mean()), "median_deg": float(np.median(every))}
    for k in RINGS:
        a, b = np.concatenate(angle[k]), np.concatenate(lean[k])
        if a.size:
            out[k] = {
                "pixels": a.size / every.size,
                "mean_deg": float(a.mean()),
                "error_share": float(a.sum() / every.sum()),
                "lean": float(b.mean()),
            }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--scene", type=Path, required=True)
    args = ap.parse_args()
    for run in args.runs:
        r = normal_rings(TrainedModel.open(run), args.scene)
        print(f"{run}: mean {r['mean_deg']:.2f}°, median {r['median_deg']:.2f}°")
        for k in RINGS:
            if k in r:
                s = r[k]
                print(
                    f"  {k:8s} pixels {s['pixels']:.3f}  mean {s['mean_deg']:5.2f}°  "
                    f"share of the error {s['error_share']:.3f}  lean to camera {s['lean']:+.4f}"
                )


if __name__ == "__main__":
    main()
