"""How far the silhouette points lie from the true surface, and whether their chords say so.

``core.training.silhouette`` puts each silhouette point in the middle of its ray's chord
through the visual hull. Where the hull hugs the object that middle is on the surface;
where the hull bridges a concavity it is in the air, and the silhouette term then holds
the surface there. This probe scores the points of a rendered scene against its
``gt_points.ply``: distance to the nearest true point, the share beyond ``--far``, the
share of bad ones among points whose nearest true point lies deep inside the true convex
hull, and the chord length of good against bad points (re-marched along each point's
ray in ``--step`` increments).

    python -m bench.silhouette_error ../shared/data/fandisk_copper ../shared/data/teapot_gold
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from bench.cd_breakdown import hull_depth
from core.evaluation.geometry import load_gt_points
from core.scene.formats import load_scene
from core.scene.views import Scene
from core.training.init_points import inside_hull
from core.training.silhouette import SilhouettePoints, silhouette_points

DEEP = 0.05  # "deep inside the hull": the bins bench.cd_breakdown reports from here on


def chord_lengths(
    pts: SilhouettePoints, scene: Scene, *, reach: float = 0.6, step: float = 0.005
) -> np.ndarray:
    """(M,) length of each point's ray chord through the visual hull, within ``reach``
    either side of the point (the same hull test as the points themselves)."""
    centres = torch.stack([scene.train[int(i)].camera.center for i in pts.source]).to(pts.points)
    d = pts.points - centres
    d = d / d.norm(dim=-1, keepdim=True)
    s = torch.arange(-reach, reach + 0.5 * step, step, dtype=torch.float64)
    out = np.empty(len(pts))
    for i in range(0, len(pts), 2048):
        sl = slice(i, i + 2048)
        q = pts.points[sl, None, :] + d[sl, None, :] * s[None, :, None]
        inside = inside_hull(q.reshape(-1, 3), scene, 0.9).reshape(q.shape[0], -1)
        out[sl] = inside.double().sum(1).numpy() * step
    return out


def score(root: Path, far: float) -> dict[str, float]:
    """The figures above for one scene."""
    scene = load_scene(root)
    gt = load_gt_points(root)
    if gt is None:
        raise SystemExit(f"{root}: needs gt_points.ply")
    pts = silhouette_points(scene)
    if pts is None:
        raise SystemExit(f"{root}: fewer than two masked views, no silhouette points")
    p = pts.points.numpy()
    dist, idx = cKDTree(gt["points"]).query(p)
    deep = hull_depth(gt["points"][idx], gt["points"]) >= DEEP
    bad = dist > far
    chord = chord_lengths(pts, scene)
    return {
        "points": len(p),
        "median_dist": float(np.median(dist)),
        "bad_share": float(bad.mean()),
        "bad_share_deep": float(bad[deep].mean()) if deep.any() else float("nan"),
        "chord_good": float(np.median(chord[~bad])) if (~bad).any() else float("nan"),
        "chord_bad": float(np.median(chord[bad])) if bad.any() else float("nan"),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("scenes", type=Path, nargs="+")
    ap.add_argument("--far", type=float, default=0.02, help="a point this far off is bad")
    args = ap.parse_args(argv)
    torch.set_grad_enabled(False)
    print(
        f"| scene | points | median distance | share > {args.far:g} | the same, deep "
        "(≥ 0.05 inside the hull) | median chord, good | median chord, bad |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for root in args.scenes:
        r = score(root, args.far)
        print(
            f"| {root.name} | {r['points']} | {r['median_dist']:.4f} | {r['bad_share']:.3f} | "
            f"{r['bad_share_deep']:.3f} | {r['chord_good']:.3f} | {r['chord_bad']:.3f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
