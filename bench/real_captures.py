"""Held-out image metrics of a run on a real capture, inside the object mask (issue 23).

    python -m bench.real_captures RUN [RUN ...] [--scene DIR] [--json OUT.json]

``glint eval`` scores the render against the photo composited over the background
with the mask, so on a masked capture every background pixel counts as a perfect
match once the model renders the background colour there. This reports, per run,
on every held-out view (the run's scene's test split, at the run's resolution):

* ``psnr`` / ``ssim``: what ``glint eval`` reports (whole composited image);
* ``psnr_mask`` / ``ssim_mask``: over the pixels where the mask is > 0.5 only
  (SSIM: the 3DGS 11×11 Gaussian SSIM map averaged over those pixels);
* ``alpha_iou``: intersection over union of the rendered alpha (> 0.5) and the
  held-out mask (> 0.5): how well the model's silhouette matches the object's.

Without masks only ``psnr`` / ``ssim`` are given. Prints one Markdown row per run.
``--figure OUT.png``: the first run's first two held-out views side by side: the
photo (composited with its mask), the render, its normals and its alpha.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from core.evaluation.metrics import psnr, ssim_srgb, to_display
from core.model.run_folder import open_run


def ssim_map(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """(H, W) SSIM map, 3DGS's 11×11 Gaussian window (σ 1.5), zero padding, channel mean."""
    x, y = img.permute(2, 0, 1)[None], ref.permute(2, 0, 1)[None]
    c = x.shape[1]
    g = torch.exp(-((torch.arange(11, dtype=x.dtype) - 5) ** 2) / (2 * 1.5**2))
    g = (g / g.sum())[None, :]
    w = (g.T @ g).expand(c, 1, 11, 11).contiguous()

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, w, padding=5, groups=c)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
    return m[0].mean(0)


@torch.no_grad()
def figure(run: Path, path: Path, scene_dir: Path | None = None, views: int = 2) -> Path:
    """Rows of photo | render | normal | alpha for the first held-out views (sRGB PNG)."""
    from core.scene.imageio import write_image

    model, scene = open_run(run, scene_dir)
    bg = model.background
    rows = []
    for v in (scene.test or scene.train)[:views]:
        frame = model.render(v.camera, ("final", "normal", "alpha"), background=bg)
        tiles = [v.composited(bg.cpu())] + [
            frame.image(c).cpu()[..., :3] for c in ("final", "normal", "alpha")
        ]
        rows.append(torch.cat(tiles, dim=1))
    return write_image(path, torch.cat(rows, dim=0))


@torch.no_grad()
def score_run(run: Path, scene_dir: Path | None = None) -> dict[str, Any]:
    model, scene = open_run(run, scene_dir)
    views = scene.test or scene.train
    bg = model.background
    rows = []
    for v in views:
        frame = model.render(v.camera, ("final", "alpha"), background=bg)
        final = frame.image("final").cpu()
        target = v.composited(bg.cpu())
        row: dict[str, Any] = {
            "view": v.name,
            "psnr": psnr(final, target),
            "ssim": ssim_srgb(final, target),
        }
        if v.mask is not None:
            inside = v.mask > 0.5
            a, b = to_display(final), to_display(target)
            mse = float(((a - b) ** 2)[inside].mean())
            row["psnr_mask"] = math.inf if mse == 0 else -10 * math.log10(mse)
            row["ssim_mask"] = float(ssim_map(a, b)[inside].mean())
            alpha = frame.image("alpha").cpu()
            alpha = alpha[..., 0] if alpha.ndim == 3 else alpha
            pred = alpha > 0.5
            union = int((pred | inside).sum())
            row["alpha_iou"] = int((pred & inside).sum()) / union if union else 1.0
        rows.append(row)
    keys = [k for k in rows[0] if k != "view"]
    out = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    out.update(
        run=str(run),
        views=len(rows),
        resolution=[views[0].width, views[0].height],
        iteration=model.iteration,
        n_gaussians=model.gaussians.num,
        per_view=rows,
    )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--scene", type=Path, help="scene folder (default: the run's own)")
    ap.add_argument("--json", type=Path, help="write every figure, per view too, here")
    ap.add_argument("--figure", type=Path, help="PNG of the first held-out views")
    a = ap.parse_args()
    results = []
    print("| run | views | res | PSNR | SSIM | PSNR in mask | SSIM in mask | alpha IoU |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    for run in a.runs:
        r = score_run(run, a.scene)
        results.append(r)

        def f(k: str, d: int, r: dict = r) -> str:
            return f"{r[k]:.{d}f}" if k in r else "–"

        print(
            f"| {run} | {r['views']} | {r['resolution'][0]}×{r['resolution'][1]} | "
            f"{f('psnr', 2)} | {f('ssim', 4)} | {f('psnr_mask', 2)} | {f('ssim_mask', 4)} | "
            f"{f('alpha_iou', 4)} |",
            flush=True,
        )
    if a.json:
        a.json.write_text(json.dumps(results, indent=2))
    if a.figure:
        print(f"wrote {figure(a.runs[0], a.figure, a.scene)}")


if __name__ == "__main__":
    main()
