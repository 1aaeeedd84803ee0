"""Do a capture's masks agree with each other? A probe for when the mask hull is safe.

The mesh's mask hull (``glint mesh --hull``, ``core.meshing.tsdf`` ``hull_dist``) lifts
every voxel some view's mask puts outside the object. It is only right when every mask
holds the whole object: a real capture's masks (segmentation slips, pose error) each
miss a little, and their intersection erodes the object (goldcape_llff,
docs/benchmarks.md). A pixel one pixel inside a view's silhouette looks at the object, so
its ray must cross the intersection of every view's mask somewhere; rays are marched
through the scene's sphere and each sample tested against all masks
(:func:`core.training.init_points.inside_hull` with every view required). The share of
rays that never enter the intersection is how much the masks disagree: 0–0.16% on the
ten rendered dev captures, 37% on goldcape's photo masks.

Agreement is necessary, not sufficient: on lego_real (0.16%) the hull still cut holes
where the model's surface lies more than a truncation outside the masks (docs/benchmarks.md).

    python -m bench.mask_agreement ../shared/data/teapot_gold ../shared/data/goldcape_llff:2
"""

from __future__ import annotations

import argparse
from typing import Any

import torch
import torch.nn.functional as F

from core.scene.formats import load_scene
from core.scene.views import Scene
from core.training.init_points import inside_hull
from core.training.silhouette import boundary_pixels

RAYS_PER_VIEW = 100
MARCH_SAMPLES = 192


def unsupported_rim_share(
    scene: Scene,
    *,
    rays_per_view: int = RAYS_PER_VIEW,
    samples: int = MARCH_SAMPLES,
    seed: int = 0,
) -> dict[str, Any]:
    """Share of rays through pixels one pixel inside the masked training views'
    silhouettes that cross no point inside every mask (mean over views; see the module
    docstring), with the number of views and rays it comes from. ``share`` is None with
    fewer than two masked views (nothing to compare)."""
    masked = [v for v in scene.train if v.mask is not None]
    if len(masked) < 2:
        return {"share": None, "views": len(masked), "rays": 0}
    gen = torch.Generator().manual_seed(seed)
    c, r = scene.center.to(torch.float64), float(scene.radius)
    shares: list[float] = []
    rays = 0
    for v in masked:
        assert v.mask is not None
        inside = (v.mask >= 0.5).float()[None, None]
        eroded = -F.max_pool2d(-inside, 3, 1, 1)[0, 0]  # one pixel in from the edge
        idx = boundary_pixels(eroded)
        if idx.numel() == 0:
            continue
        idx = idx[torch.randperm(idx.numel(), generator=gen)[:rays_per_view]]
        W = v.width
        uv = torch.stack([(idx % W).double() + 0.5, (idx // W).double() + 0.5], -1)
        o = v.camera.center.to(torch.float64)
        d = v.camera.backproject(uv, torch.ones(len(idx), dtype=torch.float64)) - o
        d = d / d.norm(dim=-1, keepdim=True)
        oc = o - c
        b = (d * oc).sum(-1)
        disc = (b * b - (oc * oc).sum() + r * r).clamp_min(0).sqrt()
        t0, t1 = (-b - disc).clamp_min(1e-6), -b + disc
        t = t0[:, None] + (t1 - t0)[:, None] * torch.linspace(0, 1, samples, dtype=torch.float64)
        pts = (o + d[:, None, :] * t[..., None]).reshape(-1, 3)
        hit = inside_hull(pts, scene, 1.0).reshape(len(idx), samples).any(1)
        shares.append(float((~hit).float().mean()))
        rays += len(idx)
    if not shares:
        return {"share": None, "views": len(masked), "rays": 0}
    return {
        "share": sum(shares) / len(shares),
        "worst_view": max(shares),
        "views": len(shares),
        "rays": rays,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", help="scene folders, each optionally :DOWNSCALE (>= 1)")
    ap.add_argument("--rays", type=int, default=RAYS_PER_VIEW, help="rays per masked view")
    args = ap.parse_args(argv)
    print(f"{'scene':<40} {'views':>5} {'rays':>6} {'unsupported':>11} {'worst view':>10}")
    for spec in args.scenes:
        path, _, ds = spec.partition(":")
        m = unsupported_rim_share(
            load_scene(path, downscale=float(ds or 1)), rays_per_view=args.rays
        )
        if m["share"] is None:
            print(f"{path:<40} {m['views']:>5} fewer than two masked views")
            continue
        share, worst = m["share"], m["worst_view"]
        print(f"{path:<40} {m['views']:>5} {m['rays']:>6} {share:>11.4f} {worst:>10.4f}")


if __name__ == "__main__":
    main()
