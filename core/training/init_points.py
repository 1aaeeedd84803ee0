"""Initial points for scenes that come without a sparse cloud.

Object captures with masks (alpha or mask files) get points on the surface of the
visual hull: rays through masked pixels are marched from the camera and the first
sample that falls inside the masks of (almost) every other view that sees it is
kept, coloured by its pixel. This puts Gaussians where the object is from the
first iteration; a random ball needs thousands of iterations to get there.
"""

from __future__ import annotations

import torch
from torch import Tensor

from core.render.depth_geometry import bilinear_lookup
from core.scene.views import Scene


def inside_hull(
    points: Tensor, scene: Scene, min_fraction: float, *, compiled: bool | None = None
) -> Tensor:
    """(M,) bool: inside the mask in ≥ ``min_fraction`` of the views that see the point.

    ``compiled``: one numba pass over the points (core.training.init_points_compiled;
    None: wherever it applies), False: the torch loop below, the reference."""
    views = [v for v in scene.train if v.mask is not None]
    if compiled is not False:
        from core.training.init_points_compiled import compilable, inside_hull_compiled

        if views and compilable(points, views):
            return inside_hull_compiled(points, views, min_fraction)
        if compiled:
            raise ValueError(
                "inside_hull: the compiled pass needs float64 CPU points and float32 masks"
            )
    inside = torch.zeros(points.shape[0])
    seen = torch.zeros(points.shape[0])
    for v in views:
        uv, z = v.camera.project(points)
        m, ok = bilinear_lookup(v.mask, uv.to(v.mask.dtype))
        ok = ok & (z > 0)
        seen += ok.float()
        inside += (ok & (m > 0.5)).float()
    return (seen > 0) & (inside >= min_fraction * seen)


def bisect_hull_boundary(
    origins: Tensor,
    dirs: Tensor,
    outside: Tensor,
    inside: Tensor,
    scene: Scene,
    min_fraction: float,
    bisections: int,
) -> Tensor:
    """Ray parameters (M,) of the hull boundary, by bisection between ``outside`` (a
    parameter outside the hull, or equal to ``inside`` for a ray that starts inside) and
    ``inside``; the inside end of the last bracket."""
    for _ in range(bisections):
        mid = 0.5 * (outside + inside)
        hit = inside_hull(origins + dirs * mid[:, None], scene, min_fraction)
        inside = torch.where(hit, mid, inside)
        outside = torch.where(hit, outside, mid)
    return inside


def inside_sample(inside: Tensor, t: Tensor, fraction: float, gen: torch.Generator) -> Tensor:
    """(M,) a ray parameter drawn among each ray's inside samples for a ``fraction`` of
    the rays (uniform over them, jittered by up to half a step either way), NaN for the
    rest. ``inside``, ``t``: (M, S) the march's inside flags and parameters."""
    m = inside.shape[0]
    out = torch.full((m,), float("nan"), dtype=torch.float64)
    if fraction <= 0.0 or m == 0:
        return out
    chosen = torch.rand(m, generator=gen, dtype=torch.float64) < fraction
    score = torch.rand(inside.shape, generator=gen, dtype=torch.float64) * inside
    k = score.argmax(1)
    step = (t[:, -1] - t[:, 0]) / max(1, t.shape[1] - 1)
    jitter = (torch.rand(m, generator=gen, dtype=torch.float64) - 0.5) * step
    tk = t.gather(1, k[:, None])[:, 0] + jitter
    return torch.where(chosen & inside.any(1), tk, out)


@torch.no_grad()
def visual_hull_points(
    scene: Scene,
    n: int,
    *,
    samples_per_ray: int = 64,
    min_fraction: float = 0.9,
    bisections: int = 8,
    seed: int = 0,
    volume_fraction: float = 0.0,
) -> tuple[Tensor, Tensor] | None:
    """Up to ``n`` points (float64) with linear colours on the visual-hull surface, and a
    ``volume_fraction`` of them inside it.

    Each ray is marched in ``samples_per_ray`` steps through the bounding sphere, and
    its entry into the hull is then located by ``bisections`` halvings of the step it
    fell in. Why: the first inside sample lies up to a step (radius/32) past the entry,
    half a step on average; on the dev scenes that started every point ~0.03 (1.3 px)
    inside the object, and training never moved the surface back out.

    ``volume_fraction`` of the rays instead keep a random sample among their samples inside
    the hull (jittered within its step, not bisected). Why: the masks cannot see into a
    concavity, so the hull bridges it, and splats started on the bridge stay there (a
    splat hardly moves along the rays that see it once it is opaque); started inside, some
    lie on the concave surface. On rocker_gold_256 0.3 took the Chamfer distance from
    1.05 to 0.76 ×10², but splats started inside also surface where nothing in the images
    pins the depth (teapot_gold's flat dark bottom: 0.42 → 0.84; the mirror sphere 0.44 →
    1.43), so it is off by default (docs/benchmarks.md, 2026-11-29).

    Returns None when the scene has no masks or no ray finds the hull.
    """
    if not 0.0 <= volume_fraction <= 1.0:
        raise ValueError(f"volume_fraction must be in [0, 1], got {volume_fraction}")
    views = [v for v in scene.train if v.mask is not None]
    if not views:
        return None
    gen = torch.Generator().manual_seed(seed)
    per_view = max(1, (2 * n) // len(views))
    origins, dirs, t_out, t_in, cols, deep = [], [], [], [], [], []
    c, r = scene.center.to(torch.float64), float(scene.radius)
    for v in views:
        idx = (v.mask.reshape(-1) > 0.5).nonzero()[:, 0]
        if idx.numel() == 0:
            continue
        pick = idx[torch.randint(idx.numel(), (per_view,), generator=gen)]
        W = v.width
        uv = torch.stack([(pick % W).double() + 0.5, (pick // W).double() + 0.5], -1)
        uv = uv + torch.rand(uv.shape, generator=gen, dtype=torch.float64) - 0.5
        o = v.camera.center
        d = v.camera.backproject(uv, torch.ones(per_view, dtype=torch.float64)) - o
        d = d / d.norm(dim=-1, keepdim=True)
        # March through the bounding sphere along each ray.
        oc = o - c
        b = (d * oc).sum(-1)
        disc = b * b - (oc * oc).sum() + r * r
        hit = disc > 0
        t0 = (-b - disc.clamp_min(0).sqrt()).clamp_min(1e-6)
        t1 = -b + disc.clamp_min(0).sqrt()
        s = torch.linspace(0, 1, samples_per_ray, dtype=torch.float64)
        t = t0[:, None] + (t1 - t0)[:, None] * s[None]
        P = o + d[:, None, :] * t[..., None]
        inside = inside_hull(P.reshape(-1, 3), scene, min_fraction).reshape(per_view, -1)
        inside &= hit[:, None]
        found = inside.any(1)
        first = inside.float().argmax(1)
        sel = found.nonzero()[:, 0]
        if sel.numel() == 0:
            continue
        rows, k = sel, first[sel]
        origins.append(o.expand(sel.numel(), 3))
        dirs.append(d[sel])
        t_in.append(t[rows, k])
        t_out.append(torch.where(k > 0, t[rows, (k - 1).clamp_min(0)], t[rows, k]))
        cols.append(v.image.reshape(-1, 3)[pick[sel]].double())
        deep.append(inside_sample(inside[sel], t[sel], volume_fraction, gen))
    if not dirs:
        return None
    O, D = torch.cat(origins), torch.cat(dirs)
    t_hit = bisect_hull_boundary(
        O, D, torch.cat(t_out), torch.cat(t_in), scene, min_fraction, bisections
    )
    t_deep = torch.cat(deep)
    t_hit = torch.where(torch.isnan(t_deep), t_hit, t_deep)
    P = O + D * t_hit[:, None]
    C = torch.cat(cols)
    if P.shape[0] > n:
        keep = torch.randperm(P.shape[0], generator=gen)[:n]
        P, C = P[keep], C[keep]
    return P, C
