"""Ground-truth depth and normal maps of the rendered dev scenes (train_gt/, test_gt/).

Layout (../shared/data/README.md): ``{split}_gt/r_{i}_depth.exr`` z-depth (0 = no
surface) and ``{split}_gt/r_{i}_normal.exr`` world-space unit normals (0 = none).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from core.scene.imageio import read_image_array
from core.scene.views import View


@dataclass
class GroundTruth:
    depth: Tensor  # (H, W) z-depth, 0 = no surface
    normal_world: Tensor  # (H, W, 3)

    @property
    def mask(self) -> Tensor:
        return self.depth > 0


def gt_paths(root: Path, view: View) -> tuple[Path, Path] | None:
    """Where the GT maps of a Blender-format view would be, if they exist."""
    if view.path is None:
        return None
    rel = Path(view.name) if view.name else view.path.relative_to(root).with_suffix("")
    split, stem = rel.parent.name, rel.name
    d = root / f"{split}_gt" / f"{stem}_depth.exr"
    n = root / f"{split}_gt" / f"{stem}_normal.exr"
    return (d, n) if d.is_file() and n.is_file() else None


def load_ground_truth(root: Path | None, view: View) -> GroundTruth | None:
    """GT maps resized (nearest) to the view's resolution, or None when absent."""
    if root is None:
        return None
    paths = gt_paths(Path(root), view)
    if paths is None:
        return None
    d, _ = read_image_array(paths[0])
    n, _ = read_image_array(paths[1])
    depth = torch.from_numpy(d[..., 0].copy())
    normal = torch.from_numpy(n[..., :3].copy())
    H, W = view.height, view.width
    if depth.shape != (H, W):
        depth = F.interpolate(depth[None, None], size=(H, W), mode="nearest")[0, 0]
        normal = F.interpolate(normal.permute(2, 0, 1)[None], size=(H, W), mode="nearest")[0]
        normal = normal.permute(1, 2, 0)
    return GroundTruth(depth, normal)


def write_gt_points(path: str | Path, points: np.ndarray, normals: np.ndarray) -> Path:
    """``gt_points.ply`` as the dev data ships it: binary little-endian float
    ``x y z nx ny nz`` (what ``core.evaluation.geometry.load_gt_points`` reads)."""
    from plyfile import PlyData, PlyElement

    data = np.empty(len(points), dtype=[(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz")])
    for i, k in enumerate("xyz"):
        data[k] = points[:, i]
        data["n" + k] = normals[:, i]
    PlyData([PlyElement.describe(data, "vertex")], byte_order="<").write(str(path))
    return Path(path)
