"""Where a mesh's Chamfer distance comes from (issue 36): which side, which parts, how far.

CD = (d(P→G) + d(G→P)) / 2 says how wrong a mesh is, not where. This splits it:

- **accuracy** (mesh → truth) and **completeness** (truth → mesh) apart, each with its
  percentiles and the share of its mean that the points beyond a distance carry (a
  tail of floaters or missing parts, against an offset everywhere);
- the **signed offset** of mesh points along the nearest true normal (+ = outside the
  true surface): a median near the mean says a uniform shell, a median near zero with
  a large mean says local faults;
- both directions over the true surface split into **creases** (true normals within
  ``--crease-radius`` differ by more than ``--crease-deg``), **flat/smooth** parts and
  parts **no training view saw**.

    python -m bench.cd_breakdown MESH.ply --scene ../shared/data/fandisk_copper
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from core.evaluation.geometry import load_gt_points
from core.evaluation.metrics import sample_surface

TAILS = (0.01, 0.02, 0.05)


def crease_mask(points: np.ndarray, normals: np.ndarray, radius: float, deg: float) -> np.ndarray:
    """(N,) bool: some true normal within ``radius`` turns more than ``deg`` from this one."""
    tree = cKDTree(points)
    cos = np.cos(np.radians(deg))
    out = np.zeros(len(points), dtype=bool)
    for start in range(0, len(points), 20000):
        sl = slice(start, start + 20000)
        _, idx = tree.query(points[sl], k=64, distance_upper_bound=radius)
        idx = np.where(idx >= len(points), np.arange(start, start + len(idx))[:, None], idx)
        dots = np.einsum("nkc,nc->nk", normals[idx], normals[sl])
        out[sl] = dots.min(axis=1) < cos
    return out


def summarise(d: np.ndarray) -> dict[str, float]:
    """Mean, percentiles and the share of the mean carried by each tail."""
    total = float(d.sum()) or 1.0
    out = {"n": int(d.size), "mean_x100": 100 * float(d.mean()) if d.size else float("nan")}
    for q in (50, 90, 99):
        out[f"p{q}_x100"] = 100 * float(np.percentile(d, q)) if d.size else float("nan")
    for t in TAILS:
        out[f"share_beyond_{t}"] = float(d[d > t].sum()) / total
    return out


def breakdown(
    mesh_points: np.ndarray,
    gt: dict[str, np.ndarray],
    *,
    crease_radius: float,
    crease_deg: float,
) -> dict[str, object]:
    """The split described in the module docstring, as one JSON-able dict."""
    G, N = gt["points"], gt["normals"]
    d_pg, i_pg = cKDTree(G).query(mesh_points, workers=-1)
    d_gp, _ = cKDTree(mesh_points).query(G, workers=-1)
    signed = np.einsum("nc,nc->n", mesh_points - G[i_pg], N[i_pg])
    crease = crease_mask(G, N, crease_radius, crease_deg)
    seen = gt.get("seen", np.ones(len(G), dtype=bool))
    parts = {"crease": crease & seen, "smooth": ~crease & seen, "unseen": ~seen}
    out: dict[str, object] = {
        "cd_x100": 50 * float(d_pg.mean() + d_gp.mean()),
        "accuracy": summarise(d_pg),
        "completeness": summarise(d_gp),
        "signed_offset_x100": {
            "mean": 100 * float(signed.mean()),
            "median": 100 * float(np.median(signed)),
            "outside_share": float((signed > 0).mean()),
        },
    }
    for name, m in parts.items():
        pm = m[i_pg]  # mesh points whose nearest true point lies in this part
        out[name] = {
            "gt_share": float(m.mean()),
            "completeness_x100": 100 * float(d_gp[m].mean()) if m.any() else float("nan"),
            "accuracy_x100": 100 * float(d_pg[pm].mean()) if pm.any() else float("nan"),
            "signed_median_x100": 100 * float(np.median(signed[pm])) if pm.any() else float("nan"),
            "cd_share": float(d_gp[m].sum() + d_pg[pm].sum()) / float(d_gp.sum() + d_pg.sum()),
        }
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("mesh", type=Path, help="mesh file (PLY/OBJ/GLB)")
    ap.add_argument("--scene", type=Path, required=True, help="scene folder with gt_points.ply")
    ap.add_argument("--points", type=int, default=200_000, help="points sampled on the mesh")
    ap.add_argument("--crease-radius", type=float, default=0.02)
    ap.add_argument("--crease-deg", type=float, default=30.0)
    args = ap.parse_args(argv)
    import trimesh

    gt = load_gt_points(args.scene)
    if gt is None or "normals" not in gt:
        raise SystemExit(f"{args.scene}: needs gt_points.ply with normals")
    mesh = trimesh.load(args.mesh, force="mesh")
    pts, _ = sample_surface(mesh.vertices, mesh.faces, args.points)
    res = breakdown(pts, gt, crease_radius=args.crease_radius, crease_deg=args.crease_deg)
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
