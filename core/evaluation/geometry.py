"""Geometry against ground truth: rendered normals and depth vs GT maps, meshes vs GT points.

The paper scores geometry on meshes (Chamfer distance ×10², F-score; Tables 1, 3);
the per-pixel normal and depth errors are cheaper and say where a surface is wrong.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from core.evaluation import DEFAULT_CHAMFER_POINTS
from core.evaluation.metrics import depth_error, normal_angle_error_deg
from core.model.frame import Frame
from core.model.trained import TrainedModel
from core.scene.groundtruth import GroundTruth, load_ground_truth
from core.scene.views import View

if TYPE_CHECKING:
    import trimesh

SURFACE_ALPHA = 0.5  # pixels the model covers at least this much are scored
# per-view errors against GT maps, averaged over views (depth_bias: median signed error)
GEOMETRY_KEYS = ("normal_error_deg", "depth_abs_error", "depth_rel_error", "depth_bias")


def nanmean(xs: Sequence[float]) -> float:
    """Mean of the values that are not NaN (NaN when none is)."""
    kept = [x for x in xs if not math.isnan(x)]
    return float(np.mean(kept)) if kept else math.nan


def frame_geometry_error(frame: Frame, gt: GroundTruth) -> dict[str, float]:
    """Normal angle (°) and depth error (abs, rel) of one render against its GT maps,
    over the pixels both cover (the model at least SURFACE_ALPHA)."""
    depth, valid = frame.depth()
    mask = gt.mask.to(depth.device) & valid & (frame.gbuffer.alpha > SURFACE_ALPHA)
    n_world = frame.world_normals()
    de = depth_error(depth, gt.depth.to(depth), mask)
    return {
        "normal_error_deg": normal_angle_error_deg(n_world, gt.normal_world.to(n_world), mask),
        "depth_abs_error": de["abs"],
        "depth_rel_error": de["rel"],
        "depth_bias": de["signed_median"],
    }


@torch.no_grad()
def geometry_errors(
    model: TrainedModel, views: Sequence[View], scene_root: str | Path | None
) -> dict[str, Any] | None:
    """Mean normal angle and depth error vs the GT maps over pixels both cover, or
    None when the scene ships no GT maps."""
    if scene_root is None:
        return None
    per_view = []
    for v in views:
        gt = load_ground_truth(Path(scene_root), v)
        if gt is not None:
            per_view.append(frame_geometry_error(model.render(v.camera, ("depth", "normal")), gt))
    if not per_view:
        return None
    out: dict[str, Any] = {"views": len(per_view)}
    for key in GEOMETRY_KEYS:
        out[key] = nanmean([e[key] for e in per_view])
    return out


def load_gt_points(scene_root: Path | None) -> dict[str, np.ndarray] | None:
    """``gt_points.ply`` (points, normals) and ``gt_points_seen.npy`` when present."""
    if scene_root is None or not (Path(scene_root) / "gt_points.ply").is_file():
        return None
    from plyfile import PlyData

    root = Path(scene_root)
    v = PlyData.read(str(root / "gt_points.ply"))["vertex"]
    out = {"points": np.stack([np.asarray(v[k], dtype=np.float64) for k in "xyz"], 1)}
    names = {p.name for p in v.properties}
    if {"nx", "ny", "nz"} <= names:
        out["normals"] = np.stack(
            [np.asarray(v[k], dtype=np.float64) for k in ("nx", "ny", "nz")], 1
        )
    seen = root / "gt_points_seen.npy"
    if seen.is_file():
        out["seen"] = np.load(seen).astype(bool)
    return out


def chamfer_floor_x100(scene_root: Path | None, n_points: int) -> float | None:
    """The CD ×10² a perfect surface scores against this scene's GT points with
    ``n_points`` predicted points (``meta.json:gt.chamfer_sampling_floor_x100``), or
    None when the scene does not state it for that count."""
    if scene_root is None:
        return None
    meta = Path(scene_root) / "meta.json"
    if not meta.is_file():
        return None
    try:
        floors = json.loads(meta.read_text()).get("gt", {}).get("chamfer_sampling_floor_x100")
    except (json.JSONDecodeError, AttributeError):
        return None
    if not isinstance(floors, dict):
        return None
    if n_points % 1_000_000 == 0:
        key = f"pred_{n_points // 1_000_000}M_points"
    else:
        key = f"pred_{n_points // 1000}k_points"
    value = floors.get(key)
    return float(value) if isinstance(value, int | float) else None


def mesh_chamfer(
    mesh: trimesh.Trimesh,
    gt: dict[str, np.ndarray],
    *,
    n_points: int = DEFAULT_CHAMFER_POINTS,
    seed: int = 0,
) -> dict[str, Any]:
    """CD, F-score (all and seen GT) and normal consistency of a mesh vs GT points."""
    from core.evaluation.metrics import chamfer_distance, sample_surface

    pts, face = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.faces), n_points, seed)
    normals = np.asarray(mesh.face_normals)[face] if len(face) else None
    res = chamfer_distance(
        pts,
        gt["points"],
        gt_seen=gt.get("seen"),
        pred_normals=normals,
        gt_normals=gt.get("normals"),
    )
    res["sampled"] = n_points
    return res
