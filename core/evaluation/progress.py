"""What a run measures about itself while it trains (one row of ``metrics.jsonl``).

Held-out image error always; geometry *error* when the scene ships ground truth (GT
depth and normal maps: per-pixel depth and normal error, from the same render as the
image error; ``gt_points.ply``: the Chamfer distance of the rendered surface points at
a few points of the run, see :func:`surface_points`). A real capture has no truth,
so only what can honestly be measured is recorded, under names that say so: the
*consistency* of the rendered depth with the rendered normals, and of a held-out
view's depth with its nearest training view's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from core.evaluation.geometry import (
    GEOMETRY_KEYS,
    SURFACE_ALPHA,
    frame_geometry_error,
    load_gt_points,
    nanmean,
)
from core.evaluation.metrics import normal_angle_error_deg, psnr, ssim_srgb
from core.model.frame import Frame
from core.model.trained import TrainedModel
from core.render.depth_geometry import bilinear_lookup, normals_from_depth, project_in_front
from core.scene.cameras import Camera
from core.scene.groundtruth import GroundTruth, load_ground_truth
from core.scene.views import View

# Chamfer probes at these fractions of the run (and at its end): evenly spaced in
# log time, five points in all.
CHAMFER_FRACTIONS = (1 / 16, 1 / 8, 1 / 4, 1 / 2)
PROBE_VIEWS = 16  # training views whose rendered depth is back-projected
PROBE_MAX_SCALE = 4.0  # small views are rendered up to this much larger for the probe
# Nearest-neighbour distances above this count as this (10× the F-score threshold, a
# tenth of the objects' unit radius): an early, cloudy model took 5 s to score without
# the bound, 0.3 s with it; converged models have no distance near it.
PROBE_MAX_DISTANCE = 0.1
PROBE_POINTS = 150_000  # surface points scored (glint eval: 1,000,000 on its mesh)
CONSISTENT_PX = 1.0  # forward-backward reprojection error counted as consistent


def depth_normal_consistency_deg(frame: Frame) -> float:
    """Mean angle between the rendered normals and the normals of the rendered depth
    (Eq. 10) over covered pixels: 0 for a surface whose depth and normals agree."""
    gb = frame.gbuffer
    depth, valid = frame.depth()
    valid = valid & (gb.alpha > SURFACE_ALPHA)
    n_depth, ok = normals_from_depth(depth, valid, frame.camera)
    return normal_angle_error_deg(gb.normal, n_depth, ok)


def reprojection_consistency(
    depth: Tensor, valid: Tensor, cam: Camera, depth_nb: Tensor, valid_nb: Tensor, cam_nb: Camera
) -> dict[str, float]:
    """Forward-backward reprojection of every valid pixel through a neighbour's depth
    (Eqs. 12-13): the median error in pixels and the fraction within 1 px, over pixels
    that land on the neighbour's surface (others are occluded or out of its view)."""
    idx = valid.reshape(-1).nonzero()[:, 0]
    if idx.numel() == 0:
        return {"median_px": math.nan, "within_1px": math.nan}
    W = depth.shape[1]
    dtype = depth.dtype
    uv = torch.stack([(idx % W).to(dtype) + 0.5, (idx // W).to(dtype) + 0.5], dim=-1)
    P = cam.backproject(uv, depth.reshape(-1)[idx])
    uv_n, _, front = project_in_front(cam_nb, P)
    d_n, inside = bilinear_lookup(depth_nb, uv_n)
    v_n, _ = bilinear_lookup(valid_nb.to(dtype), uv_n)
    ok = front & inside & (v_n > 0.999) & (d_n > 0)
    if not bool(ok.any()):
        return {"median_px": math.nan, "within_1px": math.nan}
    P2 = cam_nb.backproject(uv_n[ok], d_n[ok])
    back, _, front2 = project_in_front(cam, P2)
    err = (back - uv[ok]).norm(dim=-1)[front2]
    if err.numel() == 0:
        return {"median_px": math.nan, "within_1px": math.nan}
    return {
        "median_px": float(err.median()),
        "within_1px": float((err <= CONSISTENT_PX).float().mean()),
    }


def nearest_view(camera: Camera, candidates: Sequence[View]) -> int:
    """Index of the candidate whose viewing direction is closest to ``camera``'s."""
    f = camera.forward.double()
    dots = [float(f @ v.camera.forward.double()) for v in candidates]
    return int(np.argmax(dots))


class ProgressEvaluator:
    """Scores a live model on a few held-out views; geometry against truth when known."""

    def __init__(
        self,
        views: Sequence[View],
        train_views: Sequence[View],
        scene_root: str | Path | None,
        device: torch.device,
    ) -> None:
        self.views = list(views)
        self.train_views = list(train_views)
        self.device = device
        root = None if scene_root is None else Path(scene_root)
        self.gt: list[GroundTruth | None] = [load_ground_truth(root, v) for v in self.views]
        self.has_gt_maps = any(g is not None for g in self.gt)
        self.gt_points = load_gt_points(root)
        self._gt_tree: Any = None  # built at the first Chamfer probe, kept for the others
        self.targets = [v.image.to(device) for v in self.views]
        self.masks = [None if v.mask is None else v.mask.to(device) for v in self.views]
        self.neighbours = [nearest_view(v.camera, self.train_views) for v in self.views]

    @property
    def kind(self) -> str:
        """``error`` when geometry is scored against truth, else ``consistency``."""
        return "error" if self.has_gt_maps else "consistency"

    @torch.no_grad()
    def images_and_geometry(self, model: TrainedModel) -> dict[str, float]:
        """PSNR/SSIM and per-pixel geometry error (or consistency), one render per view."""
        bg = model.background
        ps, ss, dn, mv_med, mv_in = ([] for _ in range(5))
        errors: list[dict[str, float]] = []
        for i, v in enumerate(self.views):
            frame = model.render(v.camera, ("final", "depth", "normal"), background=bg)
            final = frame.image("final")
            view = View(v.camera, self.targets[i], self.masks[i], v.name, v.path)
            target = view.composited(bg)
            ps.append(psnr(final, target))
            ss.append(ssim_srgb(final, target))
            gt = self.gt[i]
            if gt is not None:
                errors.append(frame_geometry_error(frame, gt))
            elif not self.has_gt_maps:
                depth, valid = frame.depth()
                covered = valid & (frame.gbuffer.alpha > SURFACE_ALPHA)
                dn.append(depth_normal_consistency_deg(frame))
                nb = self.train_views[self.neighbours[i]]
                f_nb = model.render(nb.camera, ("depth",), background=bg)
                d_nb, v_nb = f_nb.depth()
                v_nb = v_nb & (f_nb.gbuffer.alpha > SURFACE_ALPHA)
                rc = reprojection_consistency(depth, covered, v.camera, d_nb, v_nb, nb.camera)
                mv_med.append(rc["median_px"])
                mv_in.append(rc["within_1px"])
        out = {"psnr": nanmean(ps), "ssim": nanmean(ss)}
        if self.has_gt_maps:
            for key in GEOMETRY_KEYS:
                out[key] = nanmean([e[key] for e in errors])
        else:
            out.update(
                depth_normal_consistency_deg=nanmean(dn),
                multiview_consistency_px=nanmean(mv_med),
                multiview_consistent_fraction=nanmean(mv_in),
            )
        return out

    def chamfer(self, model: TrainedModel) -> dict[str, Any] | None:
        """CD ×10² and F-score of the surface points the model renders, against
        ``gt_points`` (None without them); see :func:`surface_points`."""
        if self.gt_points is None:
            return None
        from core.evaluation.metrics import chamfer_distance

        t0 = time.perf_counter()
        pts = surface_points(model, self.train_views)
        if len(pts) == 0:
            return {"cd_x100": math.nan, "fscore": 0.0, "seconds": time.perf_counter() - t0}
        if self._gt_tree is None:
            from scipy.spatial import cKDTree

            self._gt_tree = cKDTree(self.gt_points["points"])
        res = chamfer_distance(
            pts, self.gt_points["points"], gt_tree=self._gt_tree, cap=PROBE_MAX_DISTANCE
        )
        return {
            "cd_x100": res["cd_x100"],
            "fscore": res["fscore"],
            "seconds": round(time.perf_counter() - t0, 3),
        }


@torch.no_grad()
def surface_points(
    model: TrainedModel,
    views: Sequence[View],
    *,
    max_views: int = PROBE_VIEWS,
    budget: int = PROBE_POINTS,
    seed: int = 0,
) -> np.ndarray:
    """World points of the surface the model renders: the depth it uses (Eq. 8, or Eq. 5
    in that ablation) back-projected from up to ``max_views`` evenly spread views,
    where coverage is above one half (and inside the mask), ``budget`` points in all.

    The quick stand-in for ``glint eval``'s TSDF mesh while training: one render per
    view and no fusion, so its cost does not grow with how noisy the surface still is
    (fusing an early, cloudy model took 30 s on teapot_gold against 2 s for this).
    """
    from core.meshing.mesh import model_depth_frame
    from core.meshing.tsdf import frame_points

    views = list(views)
    if len(views) > max_views:
        views = [views[i] for i in np.linspace(0, len(views) - 1, max_views).round().astype(int)]
    rng = np.random.default_rng(seed)
    per_view = max(1, budget // max(len(views), 1))
    # Too few points and the GT-to-prediction distances measure the sampling, not the
    # surface: views whose object covers fewer pixels than their share of the budget
    # are rendered larger (up to 4×). The object's coverage comes from the masks (a
    # quarter of the image without), not the model, so the protocol is the same at
    # every probe of a run, however cloudy the model still is.
    covered = [float(v.mask.sum()) if v.mask is not None else v.width * v.height / 4 for v in views]
    mean_covered = float(np.mean(covered)) if covered else 1.0
    scale = float(min(PROBE_MAX_SCALE, max(1.0, math.sqrt(per_view / max(mean_covered, 1.0)))))
    chunks = []
    for v in views:
        frame = model_depth_frame(model, v, color=None, scale=scale, weighted=False)
        p = frame_points(frame).cpu().numpy()
        if len(p) > per_view:
            p = p[rng.choice(len(p), per_view, replace=False)]
        chunks.append(p)
    return np.concatenate(chunks) if chunks else np.zeros((0, 3))
