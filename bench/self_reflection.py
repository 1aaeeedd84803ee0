"""Where a shiny object reflects itself, and how much of a run's error lies there.

The deferred shading reflects a distant environment map: a reflected ray never meets
the object. Inside a concavity it does (the renderer traced 12 bounces), so there the
images show the object's own other wall, which no env-map lookup can give. This marks,
on each test view, the object pixels whose mirror reflection (true depth, true normal)
hits the true mesh again (embree, ``trimesh.ray``), reports their share of the object,
and with ``--run`` splits that run's rendered depth error and colour error between
those pixels and the rest.

    python -m bench.self_reflection ../shared/data/rocker_gold_256 [--run RUN [--plot PNG]]

``--plot`` draws the first test views: truth, render, the rendered depth's error and the
self-reflecting pixels, side by side.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh

from core.evaluation.geometry import SURFACE_ALPHA
from core.evaluation.metrics import to_display
from core.model.trained import TrainedModel
from core.render.shading import reflect
from core.scene.formats import load_scene
from core.scene.groundtruth import GroundTruth, load_ground_truth
from core.scene.views import View

# the reflected ray starts this far off the surface (scene units; the objects have radius 1),
# so it does not hit the triangle it leaves
RAY_OFFSET = 1e-3


def true_mesh(root: Path) -> trimesh.Trimesh:
    """The rendered scene's ``gt_mesh.ply``, or an exit naming the file it needs."""
    path = root / "gt_mesh.ply"
    if not path.is_file():
        raise SystemExit(f"{path}: missing (a rendered scene with its true mesh is needed)")
    return trimesh.load(path, process=False)


def self_reflecting(view: View, gt: GroundTruth, mesh: trimesh.Trimesh) -> np.ndarray:
    """(H, W) bool: object pixels whose mirror reflection meets the mesh again."""
    cam = view.camera
    points = cam.backproject(cam.pixel_centers(torch.float64), gt.depth.double())
    _, rays = cam.world_rays(torch.float64)
    n = F.normalize(gt.normal_world.double(), dim=-1)
    refl = reflect(rays, n)
    on = gt.mask.numpy()
    out = np.zeros(on.shape, bool)
    out[on] = mesh.ray.intersects_any((points + RAY_OFFSET * n).numpy()[on], refl.numpy()[on])
    return out


@torch.no_grad()
def split(root: Path, run: Path | None) -> dict:
    """The self-reflecting share of the test views' object pixels and, with a run, its
    mean |depth error|, signed median depth error (+ = behind the truth) and colour
    error (display values, as the run record's PSNR) on those pixels and on the rest."""
    mesh = true_mesh(root)
    model = TrainedModel.open(run) if run is not None else None
    pixels = {True: 0, False: 0}
    dz: dict[bool, list[np.ndarray]] = {True: [], False: []}
    sq: dict[bool, list[np.ndarray]] = {True: [], False: []}
    for v in load_scene(root).test:
        gt = load_ground_truth(root, v)
        if gt is None:
            continue
        mine = self_reflecting(v, gt, mesh)
        on = gt.mask.numpy()
        for k in (True, False):
            pixels[k] += int((on & (mine == k)).sum())
        if model is None:
            continue
        frame = model.render(v.camera, ("final", "depth"))
        depth, valid = frame.depth()
        both = on & (valid & (frame.gbuffer.alpha > SURFACE_ALPHA)).numpy()
        err = (depth.double() - gt.depth.double()).numpy()
        # display values, as the run record's PSNR
        img = to_display(frame.image("final")).double().numpy()
        truth = to_display(v.composited(model.background.cpu())).double().numpy()
        colour = ((img - truth) ** 2).mean(-1)
        for k in (True, False):
            dz[k].append(err[both & (mine == k)])
            sq[k].append(colour[on & (mine == k)])
    total = pixels[True] + pixels[False]
    out: dict = {"self_share": pixels[True] / max(total, 1)}
    if model is not None:
        errs = {k: np.concatenate(dz[k]) for k in (True, False)}
        sqs = {k: np.concatenate(sq[k]) for k in (True, False)}
        abs_total = sum(float(np.abs(e).sum()) for e in errs.values())
        sq_total = sum(float(c.sum()) for c in sqs.values())
        for k, name in ((True, "self"), (False, "other")):
            e, c = errs[k], sqs[k]
            out[name] = {
                "mean_abs_dz": float(np.abs(e).mean()),
                "signed_median_dz": float(np.median(e)),
                "share_of_abs_dz": float(np.abs(e).sum()) / abs_total,
                "psnr": float(10 * np.log10(1.0 / c.mean())),
                "share_of_sq_error": float(c.sum()) / sq_total,
            }
    return out


@torch.no_grad()
def plot(root: Path, run: Path, out: Path, views: int = 4) -> None:
    """Truth, render, signed depth error (+ = behind the truth) and the self-reflecting
    pixels of the first ``views`` test views, one row each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mesh = true_mesh(root)
    model = TrainedModel.open(run)
    picked = []
    for v in load_scene(root).test:
        gt = load_ground_truth(root, v)
        if gt is not None:
            picked.append((v, gt))
        if len(picked) == views:
            break
    if not picked:
        raise SystemExit(f"{root}: no test view with true depth and normals")
    fig, axes = plt.subplots(len(picked), 4, figsize=(13, 3.3 * len(picked)), squeeze=False)
    for row, (v, gt) in zip(axes, picked, strict=True):
        frame = model.render(v.camera, ("final", "depth"))
        depth, valid = frame.depth()
        err = (depth.double() - gt.depth.double()).numpy()
        err[~(gt.mask & valid).numpy()] = np.nan
        row[0].imshow(v.composited(model.background.cpu()).clamp(0, 1).numpy())
        row[1].imshow(frame.image("final").clamp(0, 1).numpy())
        im = row[2].imshow(err, cmap="coolwarm", vmin=-0.05, vmax=0.05)
        fig.colorbar(im, ax=row[2], fraction=0.046)
        row[3].imshow(self_reflecting(v, gt, mesh), cmap="gray")
        titles = ("truth", "render", "depth error (+ behind the truth)", "reflects itself")
        for ax, title in zip(row, titles, strict=True):
            ax.set_title(f"{v.name or ''} {title}".strip(), fontsize=9)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(out, dpi=70)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--run", type=Path, help="a run of the (single) scene to split the error of")
    ap.add_argument("--plot", type=Path, help="with --run: a PNG of the first test views")
    args = ap.parse_args()
    if args.run is not None and len(args.scenes) != 1:
        ap.error("--run takes one scene")
    if args.plot is not None and args.run is None:
        ap.error("--plot needs --run")
    for root in args.scenes:
        r = split(root, args.run)
        print(f"{root.name}: {r['self_share']:.1%} of the object pixels reflect the object")
        for name in ("self", "other"):
            if name in r:
                s = r[name]
                print(
                    f"  {name:5s} mean |dz| {s['mean_abs_dz']:.4f}  signed median "
                    f"{s['signed_median_dz']:+.4f}  share of |dz| {s['share_of_abs_dz']:.2f}  "
                    f"PSNR {s['psnr']:.2f}  share of squared colour error "
                    f"{s['share_of_sq_error']:.2f}"
                )
    if args.plot is not None:
        plot(args.scenes[0], args.run, args.plot)
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
