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
  parts **no training view saw**;
- and by **concavity**: how deep each true point lies inside the convex hull of the
  true surface (0 on the hull; a visual hull cannot see deeper than that, so this is
  where only shading and multi-view terms can put the surface). With ``--run``, the
  same bins for the run's rendered depth on the test views (signed, − = in front of the
  truth), which says whether the splats or the mesh fusion put a surface there. With
  ``--plot F.png``, a picture of the true points the mesh misses (three axis views).

    python -m bench.cd_breakdown MESH.ply --scene ../shared/data/fandisk_copper [--run RUN]
"""

from __future__ import annotations

import argparse
import itertools
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from core.evaluation.geometry import SURFACE_ALPHA, load_gt_points
from core.evaluation.metrics import sample_surface

TAILS = (0.01, 0.02, 0.05)
HULL_BINS = (-np.inf, 0.01, 0.05, 0.15, np.inf)  # depth inside the true convex hull


def hull_depth(points: np.ndarray, hull_of: np.ndarray) -> np.ndarray:
    """(N,) distance of each point inside the convex hull of ``hull_of`` to its boundary
    (negative outside)."""
    from scipy.spatial import ConvexHull

    eq = ConvexHull(hull_of).equations  # outward normals n and offsets b: n·x + b ≤ 0 inside
    step = max(1, 20_000_000 // len(eq))  # a smooth hull has tens of thousands of facets
    out = np.empty(len(points))
    for i in range(0, len(points), step):
        out[i : i + step] = -(points[i : i + step] @ eq[:, :3].T + eq[:, 3]).max(axis=1)
    return out


def hull_bins(depth: np.ndarray) -> Iterator[tuple[str, np.ndarray]]:
    """(label, mask) of each HULL_BINS bin over ``depth`` (from :func:`hull_depth`)."""
    for lo, hi in itertools.pairwise(HULL_BINS):
        if not np.isfinite(lo):
            label = f"< {hi:g}"
        else:
            label = f"[{lo:g}, {hi:g})" if np.isfinite(hi) else f">= {lo:g}"
        yield label, (depth >= lo) & (depth < hi)


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
    for label, m in hull_bins(hull_depth(G, G)):
        parts[f"hull depth {label}"] = m
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


def rendered_depth_by_hull_depth(
    run: Path, scene_root: Path, gt_points: np.ndarray
) -> dict[str, dict[str, float]]:
    """Signed error (rendered − true z-depth) of the run's depth on the test views, over
    pixels both cover, binned by how deep the true surface point lies in the hull."""
    import torch

    from core.model.trained import TrainedModel
    from core.scene.formats import load_scene
    from core.scene.groundtruth import load_ground_truth

    torch.set_grad_enabled(False)
    model, scene = TrainedModel.open(run), load_scene(scene_root)
    errs: list[np.ndarray] = []
    depths: list[np.ndarray] = []
    for v in scene.test:
        gt = load_ground_truth(scene_root, v)
        if gt is None:
            continue
        frame = model.render(v.camera, ("depth",))
        d, valid = frame.depth()
        idx = (gt.mask & valid & (frame.gbuffer.alpha > SURFACE_ALPHA)).reshape(-1).nonzero()[:, 0]
        uv = torch.stack([(idx % v.width).double() + 0.5, (idx // v.width).double() + 0.5], -1)
        z_true = gt.depth.reshape(-1)[idx].double()
        depths.append(hull_depth(v.camera.backproject(uv, z_true).numpy(), gt_points))
        errs.append((d.reshape(-1)[idx].double() - z_true).numpy())
    if not errs:
        raise SystemExit(f"{scene_root}: no GT depth maps for the test views")
    e, dep = np.concatenate(errs), np.concatenate(depths)
    out = {}
    for label, sel in hull_bins(dep):
        out[label] = {
            "pixels": int(sel.sum()),
            "signed_median": float(np.median(e[sel])) if sel.any() else float("nan"),
            "mean_abs": float(np.abs(e[sel]).mean()) if sel.any() else float("nan"),
        }
    return out


def plot_missed(
    mesh_points: np.ndarray, gt_points: np.ndarray, path: Path, *, beyond: float = 0.015
) -> dict[str, float]:
    """Draw where the mesh misses the truth: the true points farther than ``beyond`` from
    the mesh, coloured by that distance, over the whole object in grey, seen along each
    axis (x–y, x–z, y–z). A number says how much; the picture says which part. Returns the
    share of true points drawn and the share of the completeness they carry."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d, _ = cKDTree(mesh_points).query(gt_points, workers=-1)
    far = d > beyond
    rest = np.flatnonzero(~far)[:: max(1, int((~far).sum()) // 20_000)]
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2), constrained_layout=True)
    sc = None
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2)), strict=True):
        ax.scatter(gt_points[rest, i], gt_points[rest, j], s=0.3, c="0.8", linewidths=0)
        order = np.flatnonzero(far)[np.argsort(d[far])]  # farthest drawn last, on top
        sc = ax.scatter(gt_points[order, i], gt_points[order, j], s=1.0, c=d[order],
                        cmap="inferno", vmin=beyond, vmax=max(4 * beyond, float(d.max())),
                        linewidths=0)  # fmt: skip
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[i])
        ax.set_ylabel("xyz"[j])
    share = float(far.mean())
    carried = float(d[far].sum() / max(d.sum(), 1e-30))
    fig.suptitle(
        f"true points farther than {beyond:g} from the mesh: {share:.1%} of them, "
        f"{carried:.0%} of the completeness error"
    )
    if sc is not None:
        fig.colorbar(sc, ax=axes, shrink=0.8, label="distance to the mesh")
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return {"missed_share": share, "missed_completeness_share": carried}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("mesh", type=Path, help="mesh file (PLY/OBJ/GLB)")
    ap.add_argument("--scene", type=Path, required=True, help="scene folder with gt_points.ply")
    ap.add_argument("--points", type=int, default=200_000, help="points sampled on the mesh")
    ap.add_argument("--crease-radius", type=float, default=0.02)
    ap.add_argument("--crease-deg", type=float, default=30.0)
    ap.add_argument("--run", type=Path, help="run folder: also bin its rendered test depth")
    ap.add_argument("--plot", type=Path, help="PNG: where the mesh misses the truth (three views)")
    ap.add_argument("--beyond", type=float, default=0.015, help="what --plot calls missed")
    args = ap.parse_args(argv)
    if not args.beyond > 0:
        ap.error(f"--beyond must be a positive distance, got {args.beyond}")
    if args.plot is not None and not args.plot.parent.is_dir():
        ap.error(f"--plot: folder {args.plot.parent} does not exist")
    import trimesh

    gt = load_gt_points(args.scene)
    if gt is None or "normals" not in gt:
        raise SystemExit(f"{args.scene}: needs gt_points.ply with normals")
    mesh = trimesh.load(args.mesh, force="mesh")
    pts, _ = sample_surface(mesh.vertices, mesh.faces, args.points)
    res = breakdown(pts, gt, crease_radius=args.crease_radius, crease_deg=args.crease_deg)
    if args.run is not None:
        res["rendered_depth_by_hull_depth"] = rendered_depth_by_hull_depth(
            args.run, args.scene, gt["points"]
        )
    if args.plot is not None:
        res["plot"] = {"file": str(args.plot), "beyond": args.beyond,
                       **plot_missed(pts, gt["points"], args.plot, beyond=args.beyond)}  # fmt: skip
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
