"""Held-out colour error by viewing angle (issue 21): does the reflection fall short at grazing?

Eq. 9 gives each splat one reflection strength w_r for every angle; a real coat
(dielectric: plastic, lacquer) reflects ~4% face-on and far more near grazing
(Fresnel). If that matters, the render is too dark (signed error < 0) where the true
surface is seen edge-on, and the shortfall grows with 1 − cos θ. For every test view,
over pixels inside the GT mask at least ``--inset`` pixels from its silhouette (so the
alpha halo does not enter), this bins the signed and squared colour error by
cos θ = |n_gt · ray| and reports the blended w_r and specular colour per bin, and the
error of the model's own depth (Eq. 8, or Eq. 5 for that ablation) against the GT depth
where both have one: Eq. 8's depth d = D / (N·r̃) turns a normal error into a depth error
that grows toward grazing, which a capture that sees some parts only edge-on exposes.

    python -m bench.angle_error RUN --scene ../shared/data/spot_plastic
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from bench.trained_run import open_run_and_scene, run_scene_parser
from core.model.trained import TrainedModel
from core.scene.groundtruth import load_ground_truth

COS_BINS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0001)


def measure(model: TrainedModel, scene, root: Path, inset: float) -> dict:
    names = ("cos", "err", "wr", "spec", "gt", "derr")
    cols: dict[str, list[np.ndarray]] = {k: [] for k in names}
    for v in scene.test:
        gt = load_ground_truth(root, v)
        if gt is None:
            continue
        f = model.render(v.camera, ("final", "specular", "depth"))
        img = f.image("final").cpu().double().numpy()
        ref = v.composited(model.background.cpu()).double().numpy()
        spec = f.image("specular").cpu().double().numpy()
        wr = f.gbuffer.w_r.cpu().double().numpy()
        mask = gt.mask.numpy()
        keep = ndimage.distance_transform_edt(mask) > inset
        depth, valid = f.depth()
        d = depth.detach().cpu().double().numpy()
        derr = np.where(valid.cpu().numpy() & mask, d - gt.depth.double().numpy(), np.nan)
        rays = v.camera.camera_rays(torch.float64, "cpu") @ v.camera.R.to(torch.float64)
        rays = rays / rays.norm(dim=-1, keepdim=True)
        n = gt.normal_world.double()
        cos = (n * rays).sum(-1).abs().numpy()
        cols["cos"].append(cos[keep])
        cols["err"].append((img - ref)[keep])
        cols["gt"].append(ref[keep])
        cols["spec"].append(spec[keep])
        cols["wr"].append(wr[keep])
        cols["derr"].append(derr[keep])
    cos, err, gtc, spec, wr, derr = (np.concatenate(cols[k]) for k in names)
    bins = bin_by_cos(cos, err, gtc, wr, spec, derr)
    return {"pixels": int(cos.size), "inset_px": inset, "by_cos": bins}


def bin_by_cos(
    cos: np.ndarray,
    err: np.ndarray,
    gt: np.ndarray,
    wr: np.ndarray,
    spec: np.ndarray,
    depth_err: np.ndarray | None = None,
) -> list[dict]:
    """Per bin of ``cos`` (M,): share of pixels and of squared error, PSNR, mean signed
    error, GT level, w_r and specular; ``err``, ``gt``, ``spec`` are (M, 3). With
    ``depth_err`` (M,; NaN where either depth is missing): its median signed and mean
    absolute value (None in a bin without depths)."""
    sq = (err**2).mean(-1)
    total = float(sq.sum()) or 1.0
    bins = []
    for lo, hi in itertools.pairwise(COS_BINS):
        s = (cos >= lo) & (cos < hi)
        if not s.any():
            continue
        row = {
            "cos": f"[{lo:g}, {min(hi, 1):g})",
            "pixel_share": float(s.mean()),
            "sq_error_share": float(sq[s].sum() / total),
            "psnr": float(-10 * np.log10(max(sq[s].mean(), 1e-12))),
            "signed_error": float(err[s].mean()),
            "gt_level": float(gt[s].mean()),
            "w_r": float(wr[s].mean()),
            "specular": float(spec[s].mean()),
        }
        if depth_err is not None:
            de = depth_err[s][np.isfinite(depth_err[s])]
            row["depth_signed_median"] = float(np.median(de)) if de.size else None
            row["depth_abs_mean"] = float(np.abs(de).mean()) if de.size else None
        bins.append(row)
    return bins


def main(argv: list[str] | None = None) -> None:
    ap = run_scene_parser(__doc__)
    ap.add_argument("--inset", type=float, default=1.5, help="pixels from the silhouette left out")
    args = ap.parse_args(argv)
    model, scene = open_run_and_scene(args)
    print(json.dumps(measure(model, scene, args.scene, args.inset), indent=2))


if __name__ == "__main__":
    main()
