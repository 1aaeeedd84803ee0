"""Do the capture's masks agree with each other? The test that lets the mask hull bound meshes.

Why. The mesh's mask hull (``core.meshing.tsdf``, ``hull_dist``) lifts every voxel that
some view's mask puts outside the object, which removes membranes across holes and slabs
over thin parts that the depths alone keep (rocker_gold_256 CD×10² 1.80 → 1.37). It is
only right when every mask holds the whole object: a real capture's masks (segmentation
slips, pose error) each miss a little, their intersection erodes the object, and the hull
then cuts it (goldcape_llff: 2.0% → 4.9% of the held-out masks left out;
docs/benchmarks.md). Fewer votes or a wider margin trade the two together, so the
decision has to come from the masks themselves.

What. A pixel just inside a view's silhouette (one pixel in from its edge) looks at the
object, so its ray must cross the intersection of every view's mask somewhere. Rays are
marched through the scene's sphere and each sample tested against all masks
(:func:`core.training.init_points.inside_hull` with every view required); the share of
rays that never enter the intersection is how much the masks disagree. Rendered masks
score 0–0.2% on the ten dev captures (rounding at thin parts), goldcape's photo masks 37%.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from core.scene.views import Scene
from core.training.init_points import inside_hull
from core.training.silhouette import boundary_pixels, pixel_centres, pixel_rays, sphere_march

RAYS_PER_VIEW = 100
MARCH_SAMPLES = 192
# The hull bounds meshes when at most this share of the rays finds no common inside: ten
# times the worst rendered capture's (lego_real 0.16%), a twentieth of goldcape's (37%).
MAX_UNSUPPORTED = 0.02


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
        o, d = pixel_rays(v.camera, pixel_centres(idx, v.width))
        t, _ = sphere_march(o, d, c, r, samples)
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
