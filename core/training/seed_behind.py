"""Splats proposed behind the rendered surface where the images are worst explained.

Why: the masks cannot see into a concavity, so the visual hull bridges it, and the
splats that start on the bridge stay there: once opaque, a splat hardly moves along the
rays that see it, and densification only adds splats next to existing ones. Where such
a bridge stands, the training views disagree with it (they see the concavity's walls
at different places), so its pixels keep a large error. At an opacity reset every
splat is transparent again; splats proposed there along those pixels' rays, at random
depths inside the hull behind the current surface, compete with the bridge on equal
terms, and the colour loss over the many views that see them keeps the ones on the
true surface (the plan drops L_multi on the masked captures these proposals need). Pixels
the model explains well (a flat, dark, textureless face) get none, so a surface that
nothing in the images contradicts stays where it is.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from core.model.trained import TrainedModel
from core.scene.views import Scene, View
from core.training.init_points import inside_hull, inside_sample

# A proposal lies at least this many pixel footprints behind the rendered surface, so
# that it is not the surface splat's own neighbourhood.
MARGIN_PX = 2.0
# Samples of the march from the surface to the far side of the bounding sphere.
SAMPLES_PER_RAY = 48


@torch.no_grad()
def view_errors(model: TrainedModel, views: Sequence[View]) -> list[tuple[Tensor, Tensor]]:
    """Per view: (H·W,) mean absolute error of the render over the mask (NaN outside
    it and where no surface was rendered), and (H·W,) the rendered depth (+inf where
    none was)."""
    out = []
    for v in views:
        frame = model.render(v.camera, ("final", "depth"))
        rgb = frame.image("final").detach().cpu().to(torch.float32)
        depth, valid = frame.depth()
        err = (rgb - v.image.cpu().to(torch.float32)).abs().mean(-1)
        ok = valid.cpu() & (v.mask.cpu() > 0.5) if v.mask is not None else valid.cpu()
        err = torch.where(ok, err, torch.full_like(err, float("nan")))
        depth = torch.where(valid, depth, torch.full_like(depth, float("inf")))
        out.append((err.reshape(-1), depth.detach().cpu().to(torch.float64).reshape(-1)))
    return out


@torch.no_grad()
def hidden_everywhere(
    means: Tensor, views: Sequence[View], depths: Sequence[Tensor], margin_px: float = MARGIN_PX
) -> Tensor:
    """(N,) bool: the centre lies more than ``margin_px`` footprints behind the rendered
    surface in every view whose frame holds it (and in at least one). Such a splat draws
    nothing now, but after an opacity reset it competes with the surface in front of it
    on equal terms, and where nothing in the images pins the depth (a flat, dark face)
    it can win."""
    pts = means.detach().cpu().to(torch.float64)
    seen = torch.zeros(pts.shape[0], dtype=torch.bool)
    framed = torch.zeros(pts.shape[0], dtype=torch.bool)
    for v, depth in zip(views, depths, strict=True):
        uv, z = v.camera.project(pts)
        px = uv.floor().long()
        W, H = v.width, v.height
        inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
        idx = px[:, 1].clamp(0, H - 1) * W + px[:, 0].clamp(0, W - 1)
        d = depth[idx]
        front = ~torch.isfinite(d) | (z <= d * (1.0 + margin_px / v.camera.intrinsics.fx))
        seen |= inside & front
        framed |= inside
    return framed & ~seen


@torch.no_grad()
def propose_behind(
    model: TrainedModel,
    scene: Scene,
    n: int,
    gen: torch.Generator,
    *,
    errors: list[tuple[Tensor, Tensor]] | None = None,
    quantile: float = 0.9,
    min_fraction: float = 0.9,
) -> tuple[Tensor, Tensor] | None:
    """Up to ``n`` points (float64) and their pixels' linear colours: rays through the
    masked pixels whose error is in the top ``1 − quantile`` of every train view's
    masked pixels, each at a random depth inside the visual hull at least
    ``MARGIN_PX`` footprints behind the rendered surface. None when there is nothing to
    propose (no masks, no error, no hull behind any surface). ``errors``: the train
    views' :func:`view_errors`, when already rendered."""
    views = list(scene.train)
    if n <= 0 or not any(v.mask is not None for v in views):
        return None
    if errors is None:
        errors = view_errors(model, views)
    errors = [(e if v.mask is not None else torch.full_like(e, float("nan")), d)
              for v, (e, d) in zip(views, errors, strict=True)]  # fmt: skip
    pooled = torch.cat([e for e, _ in errors])
    pooled = pooled[~torch.isnan(pooled)]
    if pooled.numel() == 0:
        return None
    cut = float(torch.quantile(pooled, quantile))
    picks = []  # (view index, pixel index)
    for i, (e, _) in enumerate(errors):
        idx = (e > cut).nonzero()[:, 0]  # NaN compares False
        picks.append(torch.stack([torch.full_like(idx, i), idx], -1))
    cand = torch.cat(picks)
    if cand.shape[0] == 0:
        return None
    cand = cand[torch.randperm(cand.shape[0], generator=gen)[:n]]
    c, r = scene.center.to(torch.float64), float(scene.radius)
    points, colours = [], []
    for i in cand[:, 0].unique().tolist():
        v = views[i]
        pix = cand[cand[:, 0] == i, 1]
        W = v.width
        uv = torch.stack([(pix % W).double() + 0.5, (pix // W).double() + 0.5], -1)
        z0 = errors[i][1][pix]
        cam = v.camera
        z0 = z0 * (1.0 + MARGIN_PX / cam.intrinsics.fx)
        # march in z-depth from just behind the surface to the bounding sphere's far side
        far = float((cam.center - c).norm()) + r
        s = torch.linspace(0, 1, SAMPLES_PER_RAY, dtype=torch.float64)
        z = z0[:, None] + (far - z0).clamp_min(0)[:, None] * s[None]
        P = cam.backproject(uv[:, None, :].expand(-1, SAMPLES_PER_RAY, 2), z)
        inside = inside_hull(P.reshape(-1, 3), scene, min_fraction).reshape(z.shape)
        zs = inside_sample(inside, z, 1.0, gen)
        ok = ~torch.isnan(zs)
        if not bool(ok.any()):
            continue
        points.append(cam.backproject(uv[ok], zs[ok]))
        colours.append(v.image.reshape(-1, 3)[pix[ok]].double().cpu())
    if not points:
        return None
    return torch.cat(points), torch.cat(colours)
