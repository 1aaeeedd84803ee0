"""Silhouette points: surface points and normals the masks pin down, as depth targets.

Why. A photo's alpha at the silhouette is the pixel's coverage, and splats blur their
own silhouette outwards (their footprints have tails, and near the rim many of them
pile up). Fitting the photos' alpha then leaves two ways to put the silhouette right:
make the rim splats smaller, or move the whole surface inwards by the blur. Training
takes the second: on the dev scenes every surface ended ~0.9 px (0.02 in scene
units at 128 px) inside the truth, for mirror, gold and textured plastic alike,
whatever the losses of the paper did, because nothing in them sees that shift (a
shrunk surface is just as consistent across views). The masks do see it.

What. A silhouette pixel of view A looks along a ray that grazes the object: the
surface touches the ray where it passes through the visual hull of the other views.
That point, with its normal (perpendicular to the ray, along the silhouette's
outward normal in A's image), is a surface point known from the masks alone. Seen
from a view B that faces it, the rendered depth at its pixel must be its depth.
Where along the chord the ray touches, the masks do not say; the surface does: it
lies behind the ray everywhere but there. So each step takes, of the chord's
samples, the one the rendered surface comes nearest to (on a smooth object that is
about the chord's middle; over a sharp edge or a concavity the middle hangs in the
air). Points something else hides in B (rendered nearer than the point) are skipped.

Measured on sphere_mirror at 1500 iterations (2026-11-25): rendered depth error
+0.019 → +0.003 (median), probe CD×10² 1.40 → 0.55, normal error 5.9° → 3.7°.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from core.kernels.dispatch import cpu_float
from core.render.depth_geometry import DEPTH_FACING_DEG, BilinearTaps, bilinear_taps
from core.scene.cameras import Camera
from core.scene.views import Scene
from core.training.init_points import bisect_hull_boundary, inside_hull

MAX_POINTS = 40_000
MARCH_SAMPLES = 64
BISECTIONS = 8
# A view uses the points whose normal is within this angle of the direction to it: the
# planar depth of a surface seen at a grazing angle is ill-conditioned (1/cos).
FACING_DEG = DEPTH_FACING_DEG
# A point rendered this many pixel footprints behind the surface in front of it is
# hidden there (another part of the object is in the way), not a depth error.
OCCLUDED_PX = 3.0
# A point this many footprints in front of the rendered surface is in the air: the
# middle of a hull chord that bridges a concavity (the term corrects sub-pixel shrinking,
# ~1 px; 19% of fandisk_copper's points lie > 0.02 off the truth, most over concavities,
# bench.silhouette_error). It lets go of such a surface instead of holding it on the hull;
# measured on six rendered scenes, CD −0.4% to −3% on each (docs/benchmarks.md).
FLOATING_PX = 3.0
# Points along each silhouette ray's hull chord that the term looks at for where the ray
# touches the surface (the one the rendered surface comes closest to): about one per
# pixel footprint along 90% of the chords, at least CHORD_SAMPLES and at most
# CHORD_SAMPLES_MAX (memory: every view caches the taps of all its rays' samples).
CHORD_SAMPLES = 9
CHORD_SAMPLES_MAX = 33


# The chord's middle stands for its ray unless the rendered surface comes this many
# footprints nearer the ray at another sample: the depth's own noise along a smooth
# surface (sphere_mirror: the middle's 3×3-mean gap exceeds the chord's smallest by
# 0.07 px at the 90th percentile). Below it, the smallest gap is the noise's pick and
# the surface settled that far behind its rays (sphere_mirror CD×10² 0.457 → 0.508 at
# 0, 0.457 at 0.25; teapot_gold and spot_plastic gain most at 0; docs/benchmarks.md).
TOUCH_MARGIN_PX = 0.25


def chord_samples(length_px: Tensor) -> int:
    """Samples per chord: about one per pixel footprint along 90% of the chords (their
    lengths ``length_px`` in footprints of the view they come from), odd so that one is
    the middle, from CHORD_SAMPLES to CHORD_SAMPLES_MAX."""
    if length_px.numel() == 0:
        return CHORD_SAMPLES
    n = math.ceil(float(torch.quantile(length_px.float(), 0.9))) + 1
    return min(max(n, CHORD_SAMPLES), CHORD_SAMPLES_MAX) | 1


def _local_mean(depth: Tensor, valid: Tensor) -> Tensor:
    """(H, W) mean of the valid depth over each pixel's 3×3 neighbourhood (0 where none
    is valid)."""
    v = valid.to(depth)[None, None]
    num = torch.nn.functional.avg_pool2d(depth[None, None] * v, 3, 1, 1)
    den = torch.nn.functional.avg_pool2d(v, 3, 1, 1)
    return (num / den.clamp_min(1e-6))[0, 0]


@dataclass
class SilhouettePoints:
    """Surface points from the masks: ``points`` (M, 3) and unit outward ``normals``
    (M, 3), float64 world; ``source`` (M,) the training view whose silhouette gave each;
    ``chords`` (M, K, 3) evenly spaced points along each ray's chord through the hull
    (ends included; None: the middle point alone stands for its ray)."""

    points: Tensor
    normals: Tensor
    source: Tensor
    chords: Tensor | None = None

    def __len__(self) -> int:
        return int(self.points.shape[0])


def boundary_pixels(mask: Tensor) -> Tensor:
    """Flat indices of the silhouette pixels: inside (≥ 0.5) with a 4-neighbour outside."""
    m = mask >= 0.5
    pad = torch.nn.functional.pad(m[None, None].float(), (1, 1, 1, 1))[0, 0] > 0.5
    outside_nb = ~pad[:-2, 1:-1] | ~pad[2:, 1:-1] | ~pad[1:-1, :-2] | ~pad[1:-1, 2:]
    return (m & outside_nb).reshape(-1).nonzero()[:, 0]


def pixel_centres(idx: Tensor, width: int) -> Tensor:
    """(N, 2) float64 continuous positions of the centres of flat pixel indices ``idx``."""
    return torch.stack([(idx % width).double() + 0.5, (idx // width).double() + 0.5], -1)


def pixel_rays(camera: Camera, uv: Tensor) -> tuple[Tensor, Tensor]:
    """The camera's centre (3,) and unit directions (N, 3), float64, through the
    continuous pixel positions ``uv`` (N, 2)."""
    o = camera.center
    d = camera.backproject(uv, torch.ones(len(uv), dtype=torch.float64)) - o
    return o, d / d.norm(dim=-1, keepdim=True)


def sphere_march(
    o: Tensor, d: Tensor, center: Tensor, radius: float, samples: int
) -> tuple[Tensor, Tensor]:
    """(N, samples) evenly spaced distances along each ray from ``o`` over its chord
    through the sphere (from the origin when it lies inside), and (N,) whether the ray
    meets the sphere at all."""
    oc = o - center
    b = (d * oc).sum(-1)
    disc = b * b - (oc * oc).sum() + radius * radius
    root = disc.clamp_min(0).sqrt()
    t0, t1 = (-b - root).clamp_min(1e-6), -b + root
    t = t0[:, None] + (t1 - t0)[:, None] * torch.linspace(0, 1, samples, dtype=torch.float64)
    return t, disc > 0


def edge_offsets(mask: Tensor, idx: Tensor) -> tuple[Tensor, Tensor]:
    """(M, 2) pixel offsets from boundary pixel centres to the silhouette itself, and
    (M, 2) the silhouette's unit outward normals in the image.

    The coverage of a pixel whose centre lies s pixels inside a straight edge is 0.5 + s
    (box filter, |s| ≤ 0.5), so the edge is (coverage − 0.5) pixels out along the
    outward normal, the negated mask gradient. A binary mask (coverage 1 at the edge)
    gives half a pixel.
    """
    m = mask.double()
    pad = torch.nn.functional.pad(m[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    gx = 0.5 * (pad[1:-1, 2:] - pad[1:-1, :-2]).reshape(-1)[idx]
    gy = 0.5 * (pad[2:, 1:-1] - pad[:-2, 1:-1]).reshape(-1)[idx]
    outward = -torch.stack([gx, gy], -1)
    outward = outward / outward.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    coverage = m.reshape(-1)[idx].clamp(0.5, 1.0)
    return outward * (coverage - 0.5)[:, None], outward


@torch.no_grad()
def silhouette_points(
    scene: Scene,
    *,
    max_points: int = MAX_POINTS,
    samples: int = MARCH_SAMPLES,
    bisections: int = BISECTIONS,
    min_fraction: float = 0.9,
    seed: int = 0,
) -> SilhouettePoints | None:
    """The surface points the masked training views' silhouettes give (see the module
    docstring), at most ``max_points``; None with fewer than two masked views.

    Each silhouette ray is marched through the scene's bounding sphere and the ends of
    its chord through the visual hull are bisected; rays whose chord is broken (they
    pass two parts of the hull) touch no single point and are dropped.
    """
    masked = [i for i, v in enumerate(scene.train) if v.mask is not None]
    if len(masked) < 2:
        return None
    gen = torch.Generator().manual_seed(seed)
    c, r = scene.center.to(torch.float64), float(scene.radius)
    per_view = max(1, max_points // len(masked))
    origins, dirs, lo_out, lo_in, hi_in, hi_out, normals, source = ([] for _ in range(8))
    for vi in masked:
        v = scene.train[vi]
        assert v.mask is not None
        idx = boundary_pixels(v.mask)
        if idx.numel() > per_view:
            idx = idx[torch.randperm(idx.numel(), generator=gen)[:per_view]]
        if idx.numel() == 0:
            continue
        off, outward = edge_offsets(v.mask, idx)
        o, d = pixel_rays(v.camera, pixel_centres(idx, v.width) + off)
        t, meets = sphere_march(o, d, c, r, samples)
        inside = inside_hull((o + d[:, None, :] * t[..., None]).reshape(-1, 3), scene, min_fraction)
        inside = inside.reshape(len(idx), samples) & meets[:, None]
        first = inside.float().argmax(1)
        last = samples - 1 - inside.flip(1).float().argmax(1)
        span = torch.arange(samples)[None, :]
        between = (span >= first[:, None]) & (span <= last[:, None])
        keep = (inside.any(1) & (inside | ~between).all(1)).nonzero()[:, 0]
        if keep.numel() == 0:
            continue
        rows, f, la = keep, first[keep], last[keep]
        origins.append(o.expand(len(keep), 3))
        dirs.append(d[keep])
        lo_in.append(t[rows, f])
        lo_out.append(torch.where(f > 0, t[rows, (f - 1).clamp_min(0)], t[rows, f]))
        hi_in.append(t[rows, la])
        hi_out.append(
            torch.where(la < samples - 1, t[rows, (la + 1).clamp_max(samples - 1)], t[rows, la])
        )
        normals.append(_rim_normals(v.camera, d[keep], outward[keep]))
        source.append(torch.full((len(keep),), vi, dtype=torch.long))
    if not dirs:
        return None
    O, D = torch.cat(origins), torch.cat(dirs)
    t_in = bisect_hull_boundary(
        O, D, torch.cat(lo_out), torch.cat(lo_in), scene, min_fraction, bisections
    )
    t_out = bisect_hull_boundary(
        O, D, torch.cat(hi_out), torch.cat(hi_in), scene, min_fraction, bisections
    )
    points = O + D * (0.5 * (t_in + t_out))[:, None]
    src = torch.cat(source)
    views = src.unique()  # sorted
    focal = torch.tensor(
        [float(scene.train[int(i)].camera.intrinsics.fx) for i in views], dtype=torch.float64
    )[torch.searchsorted(views, src)]
    length_px = (t_out - t_in) / (0.5 * (t_in + t_out) / focal)  # in its view's footprints
    s = torch.linspace(0, 1, chord_samples(length_px), dtype=torch.float64)
    along = t_in[:, None] + (t_out - t_in)[:, None] * s[None, :]
    chords = O[:, None, :] + D[:, None, :] * along[..., None]
    return SilhouettePoints(points, torch.cat(normals), src, chords)


def _rim_normals(camera: Camera, dirs: Tensor, outward: Tensor) -> Tensor:
    """World normals at the touching points: the image's outward silhouette normal,
    lifted to camera space and made perpendicular to the ray."""
    n = torch.cat([outward, torch.zeros(len(outward), 1, dtype=outward.dtype)], -1)
    ray = dirs @ camera.R.T
    n = n - (n * ray).sum(-1, keepdim=True) * ray
    n = n @ camera.R  # camera → world (row form of Rᵀ n)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


class SilhouetteDepth:
    """The depth loss of the silhouette points, per training view.

    ``__call__(view_index, camera, depth, valid)`` is the mean |rendered − point depth|
    in pixel footprints over the points that view faces (normal within FACING_DEG of
    the direction to the camera, inside its frame, from another view's silhouette),
    skipping points hidden behind nearer surface (OCCLUDED_PX) and points floating
    in front of a surface that lies well behind them (FLOATING_PX).
    """

    def __init__(
        self, pts: SilhouettePoints, cameras: Sequence[Camera], *, touching: bool = True
    ) -> None:
        # touching: each ray's chord samples, of which every step keeps the one the
        # rendered surface comes closest to (the ray touches the surface there); off,
        # or without chords, the chord's middle stands for its ray.
        self.points = pts.points
        self._along = pts.chords if touching else None
        self.samples = 1 if self._along is None else int(self._along.shape[1])
        self._cache: dict[tuple[Any, ...], tuple[Camera, BilinearTaps, Tensor]] = {}
        cos_min = math.cos(math.radians(FACING_DEG))
        self.per_view: list[Tensor] = []
        for b, cam in enumerate(cameras):
            to_cam = cam.center[None, :] - pts.points
            to_cam = to_cam / to_cam.norm(dim=-1, keepdim=True)
            facing = (to_cam * pts.normals).sum(-1) > cos_min
            uv, z = cam.project(pts.points)
            framed = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0)
            framed &= (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height)
            self.per_view.append((facing & framed & (pts.source != b)).nonzero()[:, 0])

    def counts(self) -> list[int]:
        return [int(i.numel()) for i in self.per_view]

    def _taps(self, view_index: int, camera: Camera, depth: Tensor) -> tuple[BilinearTaps, Tensor]:
        """The points' taps in this view's depth image and their depth: fixed points
        and a fixed camera, so computed at a view's first step and kept (the same
        values the step computed each time)."""
        key = (view_index, depth.dtype, depth.device, depth.shape)
        hit = self._cache.get(key)
        if hit is not None and hit[0] is camera:
            return hit[1], hit[2]
        rays = self.per_view[view_index]
        pts = self.points[rays] if self._along is None else self._along[rays].reshape(-1, 3)
        uv, z = camera.project(pts)
        uv, z = uv.to(depth), z.to(depth)
        taps = bilinear_taps(depth.shape[0], depth.shape[1], uv)
        self._cache[key] = (camera, taps, z)
        return taps, z

    def _touching(
        self, taps: BilinearTaps, z: Tensor, depth: Tensor, valid: Tensor, focal: float,
        compiled: bool,
    ) -> tuple[BilinearTaps, Tensor]:  # fmt: skip
        """Each ray's chord sample nearest the rendered surface (smallest gap among the
        samples the term would count or that lie behind it; the middle one unless the
        nearest is TOUCH_MARGIN_PX nearer than it), as the taps and depth of one point
        per ray.

        Why the nearest: a silhouette ray grazes the object, so the surface touches it
        once and lies behind it everywhere else. Over a sharp edge or a concavity the
        hull chord is long and its middle hangs in the air: holding the surface there
        pulled fandisk_copper's faces out (depth bias −0.018 with the term, −0.002
        without it); the nearest sample asks only that the surface reach the ray.
        Chosen on the depth averaged over 3×3 pixels: along a smooth surface several
        samples lie within a fraction of a pixel of the ray, and the smallest raw gap
        among them is the one pixel noise brought nearest, which let teapot_gold and
        spot_plastic settle 0.1 px behind their rays (docs/benchmarks.md).
        """
        if compiled:
            from core.training.silhouette_compiled import nearest_samples_compiled

            pick = nearest_samples_compiled(
                depth, valid, taps, z, focal, self.samples, OCCLUDED_PX, TOUCH_MARGIN_PX
            )
        else:
            pick = self._nearest_samples(taps, z, depth, valid, focal)
        sub = BilinearTaps(
            taps.width, taps.i00[pick], taps.fx[pick], taps.fy[pick], taps.inside[pick]
        )
        return sub, z[pick]

    def _nearest_samples(
        self, taps: BilinearTaps, z: Tensor, depth: Tensor, valid: Tensor, focal: float
    ) -> Tensor:
        """The torch reference of ``nearest_samples_compiled``: indices into the taps."""
        with torch.no_grad():
            covered = taps.sample(valid.to(depth))
            d = taps.sample(_local_mean(depth.detach(), valid))
            gap = (d - z) / (z / focal)
            ok = taps.inside & (covered > 0.999) & (gap > -OCCLUDED_PX)
            gap = torch.where(ok, gap, torch.full_like(gap, math.inf)).reshape(-1, self.samples)
            best = gap.min(dim=1)
            middle = self.samples // 2
            keep = gap[:, middle] <= best.values + TOUCH_MARGIN_PX
            index = torch.where(keep, torch.full_like(best.indices, middle), best.indices)
            rays = torch.isfinite(best.values).nonzero()[:, 0]
            return rays * self.samples + index[rays]

    def __call__(
        self, view_index: int, camera: Camera, depth: Tensor, valid: Tensor,
        *, compiled: bool | None = None,
    ) -> Tensor:  # fmt: skip
        """``compiled``: one numba pass and its backward
        (``core.training.silhouette_compiled``; None: for CPU float depth), False: the
        torch ops below, the reference."""
        if self.per_view[view_index].numel() == 0:
            return depth.sum() * 0.0
        taps, z = self._taps(view_index, camera, depth)
        if compiled is None:
            compiled = cpu_float(depth)
        if self.samples > 1:
            taps, z = self._touching(taps, z, depth, valid, float(camera.intrinsics.fx), compiled)
        if compiled:
            from core.training.silhouette_compiled import silhouette_gap_compiled

            focal = float(camera.intrinsics.fx)
            return silhouette_gap_compiled(depth, valid, taps, z, focal, OCCLUDED_PX, FLOATING_PX)
        d, inside = taps.sample(depth), taps.inside
        covered = taps.sample(valid.to(depth))
        gap = (d - z) / (z / camera.intrinsics.fx)  # in pixel footprints, + = behind
        ok = inside & (covered > 0.999) & (gap > -OCCLUDED_PX) & (gap < FLOATING_PX)
        if not bool(ok.any()):
            return depth.sum() * 0.0
        return gap.abs()[ok].mean()
