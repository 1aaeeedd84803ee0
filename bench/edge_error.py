"""Where a run's held-out colour error lies around the silhouettes, and who paints it.

Issue 21: holding the surface on the truth (silhouette points) costs PSNR on some
objects, and the cost sits at the silhouettes. This measures it on the test views of a
scene with masks:

- the share of the squared colour error by distance to the GT silhouette (first pixel
  outside, 1–3 px outside, beyond; first pixel inside, 1–3 px inside, interior);
- for the first ring on each side, the error left when the render's own alpha is
  replaced by the mask (its colour kept): what stays is colour, the rest is alpha;
- with ``--splats``, the Gaussians whose footprints reach the first pixel outside:
  contribution-weighted quantiles of where their centres project (sub-pixel signed
  distance to the silhouette, + outside), their normal error against the GT surface,
  their angle to the view ray, their footprint's minor σ and effective opacity.

    python -m bench.edge_error RUN [RUN ...] --scene ../shared/data/spot_plastic [--splats]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from core.evaluation.geometry import load_gt_points
from core.model.trained import TrainedModel
from core.render.raster.projection import ALPHA_MIN, covariances_from, project_gaussians
from core.render.view_opacity import view_opacity_scale
from core.scene.formats import load_scene

RINGS = ("out 1", "out 1-3", "out >3", "in 1", "in 1-3", "in >3")
QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9)
SUBPIXEL = 8  # the silhouette is found on a mask upsampled this many times


def ring_masks(mask: np.ndarray) -> dict[str, np.ndarray]:
    """Pixels by distance to the silhouette (inside = coverage ≥ 0.5)."""
    inside = mask >= 0.5
    d_out = ndimage.distance_transform_edt(~inside)
    d_in = ndimage.distance_transform_edt(inside)
    return {
        "out 1": (d_out > 0) & (d_out <= 1.01),
        "out 1-3": (d_out > 1.01) & (d_out <= 3),
        "out >3": d_out > 3,
        "in 1": (d_in > 0) & (d_in <= 1.01),
        "in 1-3": (d_in > 1.01) & (d_in <= 3),
        "in >3": d_in > 3,
    }


def signed_edge_distance(mask: np.ndarray) -> np.ndarray:
    """Signed distance (px, + outside) to the 0.5 contour of the coverage, on a grid
    SUBPIXEL times finer (bilinear coverage is exact for a box-filtered straight edge)."""
    h, w = mask.shape
    # fine cell centres (i + 0.5)/SUBPIXEL in pixels, i.e. index (i + 0.5)/SUBPIXEL - 0.5
    ys = (np.arange(h * SUBPIXEL) + 0.5) / SUBPIXEL - 0.5
    xs = (np.arange(w * SUBPIXEL) + 0.5) / SUBPIXEL - 0.5
    grid = np.stack(np.meshgrid(ys, xs, indexing="ij"))
    big = ndimage.map_coordinates(mask.astype(np.float64), grid, order=1, mode="nearest") >= 0.5
    d = ndimage.distance_transform_edt(~big) - ndimage.distance_transform_edt(big)
    return d / SUBPIXEL


def error_split(model: TrainedModel, views) -> dict:
    bg = model.background.cpu().double().numpy()
    share = dict.fromkeys(RINGS, 0.0)
    alpha_only = {"out 1": [0.0, 0.0], "in 1": [0.0, 0.0]}
    halo: list[np.ndarray] = []
    total, count = 0.0, 0
    for v in views:
        frame = model.render(v.camera, ("final",))
        img = frame.image("final").cpu().double().numpy()
        alpha = frame.gbuffer.alpha.cpu().double().numpy()[..., None]
        gt = v.composited(model.background.cpu()).double().numpy()
        cov = v.mask.double().numpy()
        err = ((img - gt) ** 2).sum(-1)
        colour = (img - (1 - alpha) * bg) / np.maximum(alpha, 1e-3)
        swapped = colour * cov[..., None] + (1 - cov[..., None]) * bg
        err_gt_alpha = ((swapped - gt) ** 2).sum(-1)
        rings = ring_masks(cov)
        for k, r in rings.items():
            share[k] += float(err[r].sum())
        for k, acc in alpha_only.items():
            acc[0] += float(err[rings[k]].sum())
            acc[1] += float(err_gt_alpha[rings[k]].sum())
        halo.append((alpha[..., 0] - cov)[rings["out 1"]])
        total += float(err.sum())
        count += err.size * 3
    return {
        "psnr_pooled": float(10 * np.log10(count / total)),
        "share": {k: v / total for k, v in share.items()},
        "colour_part": {k: (v[1] / v[0] if v[0] else float("nan")) for k, v in alpha_only.items()},
        "halo_alpha": float(np.concatenate(halo).mean()),
    }


def _weighted_quantiles(x: np.ndarray, w: np.ndarray) -> list[float]:
    order = np.argsort(x)
    c = np.cumsum(w[order]) / w.sum()
    return [float(x[order][min(np.searchsorted(c, q), len(x) - 1)]) for q in QUANTILES]


@torch.no_grad()
def halo_splats(model: TrainedModel, views, root: Path) -> dict:
    """Contribution-weighted description of the Gaussians painting the first outer
    ring (contributions without transmittance: the halo's alpha is small)."""
    g, phase = model.gaussians, model.phase
    mu = g.params["means"].detach().double().cpu()
    covs = covariances_from(g.unit_quats.detach().double().cpu(), g.scales.detach().double().cpu())
    op = g.opacities.detach().double().cpu().reshape(-1)
    normals = g.normals().detach().double().cpu()
    gt = load_gt_points(root)
    gt_normal = None
    if gt is not None and "normals" in gt:
        _, nearest = cKDTree(gt["points"]).query(mu.numpy(), k=1)
        gt_normal = torch.from_numpy(gt["normals"][nearest])
    cols: dict[str, list[np.ndarray]] = {k: [] for k in ("w", "edge", "ray", "sigma", "op", "nerr")}
    ring_pixels = 0
    for v in views:
        cov = v.mask.double().numpy()
        ring = ring_masks(cov)["out 1"]
        ring_pixels += int(ring.sum())
        proj = project_gaussians(mu, covs, v.camera, eps2d=phase.lowpass)
        o = op * (proj.compensation if phase.antialiased else 1.0)
        scale = view_opacity_scale(g, v.camera, one_sided=phase.one_sided, grazing=phase.grazing)
        if scale is not None:
            o = o * scale.detach().double().cpu().reshape(-1)
        ids = ((proj.radii > 0) & (o > ALPHA_MIN)).nonzero()[:, 0]
        ys, xs = np.nonzero(ring)
        pix = torch.from_numpy(np.stack([xs + 0.5, ys + 0.5], -1))
        d = pix[None] - proj.means2d[ids][:, None]
        a, b, c = proj.conics[ids].unbind(-1)
        q = a[:, None] * d[..., 0] ** 2 + 2 * b[:, None] * d[..., 0] * d[..., 1]
        q = q + c[:, None] * d[..., 1] ** 2
        w = (o[ids, None] * torch.exp(-0.5 * q)).clamp(max=0.99)
        contrib = torch.where(w > ALPHA_MIN, w, torch.zeros_like(w)).sum(1)
        keep = contrib > 1e-3
        ids, contrib = ids[keep], contrib[keep]
        sd = signed_edge_distance(cov)
        uv = (proj.means2d[ids].numpy() * SUBPIXEL).astype(int)
        uv[:, 0] = uv[:, 0].clip(0, sd.shape[1] - 1)
        uv[:, 1] = uv[:, 1].clip(0, sd.shape[0] - 1)
        ray = mu[ids] - v.camera.center.double()[None]
        ray = ray / ray.norm(dim=-1, keepdim=True)
        cols["w"].append(contrib.numpy())
        cols["edge"].append(sd[uv[:, 1], uv[:, 0]])
        cos_ray = (normals[ids] * ray).sum(-1).abs().clamp(max=1)
        cols["ray"].append(torch.rad2deg(torch.arccos(cos_ray)))
        cols["sigma"].append(torch.linalg.eigvalsh(proj.cov2d[ids])[:, 0].clamp_min(0).sqrt())
        cols["op"].append(o[ids].numpy())
        if gt_normal is not None:
            cosn = (normals[ids] * gt_normal[ids]).sum(-1).abs().clamp(max=1)
            cols["nerr"].append(torch.rad2deg(torch.arccos(cosn)))
    arr = {k: np.concatenate([np.asarray(x) for x in v]) for k, v in cols.items() if v}
    w = arr.pop("w")
    out = {"contributors_per_ring_pixel": len(w) / max(1, ring_pixels)}
    names = {"edge": "centre to silhouette (px, + out)", "ray": "normal to view ray (°)",
             "sigma": "footprint minor σ (px)", "op": "effective opacity",
             "nerr": "normal error (°)"}  # fmt: skip
    for k, x in arr.items():
        out[names[k]] = _weighted_quantiles(np.asarray(x, dtype=np.float64), w)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--scene", required=True, help="scene folder with masks (and gt_points.ply)")
    ap.add_argument("--splats", action="store_true", help="also describe the halo's Gaussians")
    a = ap.parse_args()
    torch.set_num_threads(1)
    root = Path(a.scene)
    views = [v for v in load_scene(root).test if v.mask is not None]
    if not views:
        raise SystemExit(f"{root}: no test view has a mask")
    for run in a.runs:
        model = TrainedModel.open(run)
        s = error_split(model, views)
        print(f"{run}: pooled PSNR {s['psnr_pooled']:.2f} dB, halo alpha {s['halo_alpha']:+.3f}")
        shares = ", ".join(f"{k} {v:.2f}" for k, v in s["share"].items())
        print(f"  share of squared error: {shares}")
        print("  colour part (error left with GT alpha): " + ", ".join(
            f"{k} {v:.2f}" for k, v in s["colour_part"].items()))  # fmt: skip
        if a.splats:
            for k, q in halo_splats(model, views, root).items():
                print(f"  {k}: {q if isinstance(q, float) else [round(x, 3) for x in q]}")


if __name__ == "__main__":
    main()
