"""Signed depth error of a trained run against the scene's GT depth maps (issue 21).

Where does the rendered depth sit relative to the true surface? For every view of a
split: signed error (rendered − GT z-depth) of the planar depth (Eq. 8) and of the
blended centre depth (Eq. 5), over pixels the GT and the model both cover, as mean
and median, binned by the pixel's distance to the GT silhouette. Then the Gaussians
themselves: the signed distance of their centres to the GT surface (nearest GT
point, along its outward normal), weighted by opacity. A rendered depth behind the
surface with centres on it is a rendering bias; centres inside is an optimisation one.

    python -m bench.depth_bias runs/x --gt ../shared/data/teapot_gold [--split test]
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from core.evaluation.geometry import load_gt_points
from core.model.trained import TrainedModel
from core.render.gbuffer import MIN_ALPHA
from core.scene.formats import load_scene
from core.scene.groundtruth import load_ground_truth

EDGE_BINS = (0.0, 1.5, 3.0, 6.0, 12.0, np.inf)  # pixels to the GT silhouette


def _stats(x: np.ndarray) -> dict[str, float]:
    if x.size == 0:
        return {"n": 0, "mean": float("nan"), "median": float("nan"), "mad": float("nan")}
    return {
        "n": int(x.size),
        "mean": float(x.mean()),
        "median": float(np.median(x)),
        "mad": float(np.median(np.abs(x))),
    }


def depth_errors(model: TrainedModel, scene, root: Path, split: str) -> dict:
    views = scene.test if split == "test" else scene.train
    planar: list[np.ndarray] = []
    center: list[np.ndarray] = []
    edge: list[np.ndarray] = []
    for v in views:
        gt = load_ground_truth(root, v)
        if gt is None:
            continue
        f = model.render(v.camera, ("depth",))
        gb = f.gbuffer
        d_p, ok_p = gb.depth.cpu(), gb.depth_valid.cpu()
        d_c = gb.center_depth.cpu()
        alpha = gb.alpha.cpu()
        gmask = gt.mask.numpy()
        dist = ndimage.distance_transform_edt(gmask)
        m = gmask & ok_p.numpy() & (alpha.numpy() > 0.5)
        g = gt.depth.numpy()
        planar.append((d_p.numpy() - g)[m])
        mc = gmask & (alpha.numpy() > max(MIN_ALPHA, 0.5))
        center.append((d_c.numpy() - g)[m & mc])
        edge.append(dist[m])
    p, e = np.concatenate(planar), np.concatenate(edge)
    out = {"planar": _stats(p), "center": _stats(np.concatenate(center)), "by_edge": []}
    for lo, hi in itertools.pairwise(EDGE_BINS):
        sel = (e > lo) & (e <= hi)
        out["by_edge"].append({"px": f"({lo:g}, {hi:g}]", "planar": _stats(p[sel])})
    return out


def centre_offsets(model: TrainedModel, root: Path) -> dict:
    gt = load_gt_points(root)
    if gt is None or "normals" not in gt:
        return {}
    tree = cKDTree(gt["points"])
    g = model.gaussians
    mu = g.params["means"].detach().double().cpu().numpy()
    op = g.opacities.detach().double().cpu().numpy().reshape(-1)
    dist, idx = tree.query(mu, k=1)
    sd = ((mu - gt["points"][idx]) * gt["normals"][idx]).sum(-1)
    near = dist < 0.05
    w = op[near]
    s = sd[near]
    order = np.argsort(s)
    cw = np.cumsum(w[order]) / w.sum()
    return {
        "gaussians": int(mu.shape[0]),
        "near_surface": int(near.sum()),
        "opacity_weighted_mean": float((w * s).sum() / w.sum()),
        "opacity_weighted_median": float(s[order][np.searchsorted(cw, 0.5)]),
        "unweighted_median": float(np.median(s)),
        "smallest_scale_median": float(g.scales.detach().min(dim=-1).values.median().cpu()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--gt", required=True, help="scene folder with *_gt/ maps")
    ap.add_argument("--split", default="test", choices=("test", "train"))
    ap.add_argument("--json", help="write the figures here too")
    a = ap.parse_args()
    torch.set_num_threads(1)
    root = Path(a.gt)
    model = TrainedModel.open(a.run)
    scene = load_scene(root)
    res = {
        "run": a.run,
        "iteration": model.iteration,
        "depth": depth_errors(model, scene, root, a.split),
        "centres": centre_offsets(model, root),
    }
    d = res["depth"]
    print(f"{a.run} (iteration {model.iteration}), {a.split} views; signed error = rendered − GT")
    for k in ("planar", "center"):
        s = d[k]
        print(f"  {k:7s} mean {s['mean']:+.5f}  median {s['median']:+.5f}  |med| {s['mad']:.5f}")
    for row in d["by_edge"]:
        s = row["planar"]
        print(f"  planar, {row['px']:>12s} px from edge: n={s['n']:6d} median {s['median']:+.5f}")
    print("  centres:", json.dumps(res["centres"]))
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
