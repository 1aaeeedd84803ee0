"""Meshes from depth maps: TSDF fusion of the planar depths, marching cubes, clean-up.

The paper scores geometry on meshes (Table 1, 3: Chamfer distance), extracted like
PGSR's: render the planar depth (Eq. 8) of every training view, fuse the depth maps
into a truncated signed distance field, and take its zero level set.

- **Fusion** is vectorised torch over the voxels of a narrow band: the voxels within
  the truncation distance of some back-projected surface pixel (for the dev teapot
  1.4M of the 8.0M voxels of its 257×189×165 grid; 64 views fuse in about 13 s on
  one CPU thread). Each view updates the voxels in front of (and up to one
  truncation behind) its surface with the projective distance ``d(pixel) − z``,
  weighted by the cosine between the pixel's ray and its surface normal (a depth seen
  at a grazing angle is the least certain) and by 0.05 at occlusion edges (a blend of
  two surfaces' depths), the depth read bilinearly between pixel centres: CD and normal
  consistency better on all seven rendered dev scenes (docs/benchmarks.md, "Meshing");
  pixels the view knows to be empty (outside its mask, or with no rendered
  coverage when there is no mask) *carve*: the voxels they see get "empty", which
  removes floaters outside the object's silhouettes.
- **The masks' hull bounds the distance** (``hull_dist``): a voxel whose projection lies
  d pixels from anything a view's mask may hold is at least about d·z/f from the object,
  whatever the other views' depths say, so its value is raised to that bound. Carving
  alone is one vote among many: a membrane the model spans across a through hole, or a
  slab thicker than a thin part, is seen as surface by every view that does not look
  through it, and outvotes the few that do (rocker_gold_256's bore; docs/benchmarks.md).
  The hull is the intersection of every view's mask, so masks that disagree by more than
  half a pixel (a real capture's) cut the object: the run's plan turns it on only where
  the masks agree (``core.training.mask_agreement``; ``hull=True/False`` overrides). Where
  the model's surface lies more than a truncation outside the masks the bound lifts the
  whole band there, and nothing inside it holds the true surface: the *closure*
  (``TSDFVolume._closure``) gives the unobserved voxels within four truncations of a lifted
  voxel the depths put inside an inside (−1) where every mask may hold them, so the
  surface closes on the masks' hull instead of leaving a hole (lego_real's thin base plate:
  held-out mask IoU 0.932 without it, 0.983 with it, 0.980 without the hull).
- **Bounds** tighten the scene's sphere (which loaders derive conservatively from the
  cameras) to robust percentiles of the back-projected surface pixels; voxel size
  and truncation default to 2·radius/256 and 4 voxels of the tightened box.
- **Marching cubes** is scikit-image's Lewiner implementation (compiled, with the
  topologically consistent tables; a torch port would be ~300 lines of tables and
  tests for no gain at these sizes), restricted to edges between observed voxels so
  that unobserved space never produces a surface. Cost: the dependency, and the TSDF
  is copied to the CPU (32 MB per 256³ grid); extraction with colours and component
  labelling takes about 1.6 s for the teapot grid above.
- **Clean-up** keeps the largest connected component and any other at least
  ``keep_fraction`` of its size (floaters inside the silhouettes become small islands).
- **Colour**: each view's rendered colour is fused alongside the distance (only near
  the surface) and interpolated trilinearly at the vertices.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from core.scene.cameras import Camera
from core.scene.imageio import linear_to_srgb

if TYPE_CHECKING:
    import trimesh

DEFAULT_RESOLUTION = 256
DEFAULT_TRUNC_VOXELS = 4.0
# Rendered coverage a pixel needs before its depth counts as a surface observation,
# and below which (without a mask) the pixel counts as empty space.
SURFACE_ALPHA = 0.5
EMPTY_ALPHA = 0.05
# A view's mask value below which its pixel is background (carved), above which object.
MASK_EMPTY, MASK_OBJECT = 0.05, 0.5
# A voxel's projection this many pixels from the nearest pixel a mask may hold can still
# touch the object: that pixel's far corner (half its diagonal), so a correct mask never
# lifts a voxel of the object.
HULL_MARGIN_PX = math.sqrt(0.5)
# Fusion weights: a surface seen edge-on (> 87 degrees), or a pixel on an occlusion edge,
# still counts this much; a pixel whose 3×3 neighbourhood spans a depth jump above
# EDGE_JUMP_PX pixel footprints (depth / focal length) lies on such an edge.
MIN_INCIDENCE_WEIGHT = 0.05
EDGE_JUMP_PX = 2.5
# The closure behind a lifted surface reaches this many truncations into the unobserved
# space: 2 left part of lego_real's plate open (held-out IoU 0.9765), 4 and 8 closed it
# alike (0.9830; rocker CD×10² 1.3745 / 1.3725), docs/benchmarks.md.
CLOSURE_REACH = 4.0


@dataclass
class DepthFrame:
    """One view's input to fusion.

    ``depth`` (H, W) z-depth; ``valid`` (H, W) bool: a surface was observed at that
    depth; ``empty`` (H, W) bool or None: the whole ray is known to be free space;
    ``color`` (H, W, 3) linear RGB of the surface, or None; ``weight`` (H, W) in (0, 1]
    or None (all 1): how much each surface observation counts, e.g. the cosine between
    the ray and the surface normal (:func:`incidence_weight`), since a depth seen at a
    grazing angle is off by far more along the ray than one seen head-on. Carving
    (``empty``) always counts 1. ``hull_dist`` (H, W) or None: each pixel's distance in
    pixels to the nearest pixel the view's *mask* does not call empty
    (:func:`mask_hull_distance`); only a mask gives one, never the model's own coverage.
    """

    camera: Camera
    depth: Tensor
    valid: Tensor
    empty: Tensor | None = None
    color: Tensor | None = None
    weight: Tensor | None = None
    hull_dist: Tensor | None = None


def mask_hull_distance(empty: Tensor) -> Tensor:
    """(H, W) float32: distance in pixels from each pixel's centre to the nearest pixel
    centre that is not ``empty`` (0 on those; every pixel's distance is 0 when none is:
    a mask with no object bounds nothing)."""
    from scipy.ndimage import distance_transform_edt

    e = empty.detach().cpu().numpy().astype(bool)
    if e.all():
        return torch.zeros(e.shape, dtype=torch.float32, device=empty.device)
    d = distance_transform_edt(e).astype(np.float32)
    return torch.from_numpy(d).to(empty.device)


def _bilinear_cell(u: Tensor, v: Tensor, W: int, H: int) -> tuple[Tensor, Tensor, Tensor]:
    """For continuous pixel positions (u, v) (pixel i spans [i, i + 1)), W, H ≥ 2: the
    flat index of the top-left of the four pixel centres around each, and the
    fractions (fu, fv) toward the right and lower ones, clamped at the border."""
    uc, vc = u - 0.5, v - 0.5
    i0 = torch.floor(uc).clamp(0, W - 2)
    j0 = torch.floor(vc).clamp(0, H - 2)
    return (j0 * W + i0).long(), (uc - i0).clamp(0, 1), (vc - j0).clamp(0, 1)


def _blend(d00: Tensor, d01: Tensor, d10: Tensor, d11: Tensor, fu: Tensor, fv: Tensor) -> Tensor:
    """Bilinear blend of the four corner values (top-left, top-right, bottom-left, …)."""
    return (d00 * (1 - fu) + d01 * fu) * (1 - fv) + (d10 * (1 - fu) + d11 * fu) * fv


def bilinear_at(values: Tensor, u: Tensor, v: Tensor, W: int, H: int) -> Tensor:
    """A flat (H·W,) map read at continuous pixel positions (u, v) (pixel i spans
    [i, i + 1)), bilinear between pixel centres, clamped at the border."""
    if W < 2 or H < 2:
        i = u.floor().clamp(0, W - 1)
        j = v.floor().clamp(0, H - 1)
        return values[(j * W + i).long()]
    b, fu, fv = _bilinear_cell(u, v, W, H)
    return _blend(values[b], values[b + 1], values[b + W], values[b + W + 1], fu, fv)


def hull_bound(dist_px: Tensor, z: Tensor, focal: float, trunc: float) -> Tensor:
    """Lower bound on a voxel's TSDF value (distance / ``trunc``, at most 1) from its
    projection's distance ``dist_px`` to a mask's object pixels at depth ``z``: a
    point off the voxel's ray by that angle is at least z·tan of it away."""
    return ((dist_px - HULL_MARGIN_PX).clamp_min(0) * z / (float(focal) * trunc)).clamp(max=1.0)


def incidence_weight(normal: Tensor, rays: Tensor) -> Tensor:
    """|cos| of the angle between each pixel's ray and its surface normal (H, W), at
    least :data:`MIN_INCIDENCE_WEIGHT`: the usual TSDF confidence, since depth error
    along the ray grows as 1/cos at grazing angles. ``normal`` (H, W, 3) need not be
    unit (a blended G-buffer normal); pixels without one get the minimum."""
    norm = normal.norm(dim=-1) * rays.norm(dim=-1)
    cos = (normal * rays).sum(-1).abs() / norm.clamp_min(1e-12)
    return torch.where(norm > 0, cos, 0.0).clamp(MIN_INCIDENCE_WEIGHT, 1.0)


def depth_edges(
    depth: Tensor, valid: Tensor, focal: float, jump_px: float = EDGE_JUMP_PX
) -> Tensor:
    """(H, W) bool: valid pixels next to a depth jump of more than ``jump_px`` footprints
    among their valid 3×3 neighbours. A blended depth there lies between the two
    surfaces (fused as is it builds skirts across the edge); the silhouette, where the
    neighbours are invalid, is no edge."""
    d = depth.to(torch.float32)
    none = torch.full_like(d, -torch.inf)
    hi = F.max_pool2d(torch.where(valid, d, none)[None, None], 3, 1, 1)[0, 0]
    lo = -F.max_pool2d(torch.where(valid, -d, none)[None, None], 3, 1, 1)[0, 0]
    return valid & ((hi - lo) > jump_px * d / float(focal))


def observation_weight(depth: Tensor, valid: Tensor, normal: Tensor, camera: Camera) -> Tensor:
    """How much each pixel's depth counts in fusion (H, W): its :func:`incidence_weight`,
    times :data:`MIN_INCIDENCE_WEIGHT` on :func:`depth_edges` (a blend of two surfaces
    still counts a little, so that a part only a pixel or two wide is not lost)."""
    rays = camera.camera_rays(normal.dtype, normal.device)
    weight = incidence_weight(normal, rays)
    edges = depth_edges(depth, valid, camera.intrinsics.fx)
    return torch.where(edges, weight * MIN_INCIDENCE_WEIGHT, weight)


def interpolated_depth(
    depth: Tensor,
    valid: Tensor,
    nearest: Tensor,
    u: Tensor,
    v: Tensor,
    W: int,
    H: int,
    focal: float,
) -> Tensor:
    """Depth at continuous pixel positions (u, v) (pixel i spans [i, i + 1)) from a
    flat (H·W,) map: bilinear between the four nearest pixel centres where all four
    hold a surface within :data:`EDGE_JUMP_PX` footprints of each other, else the
    pixel ``nearest`` (flat indices) itself. A voxel rarely projects onto a pixel
    centre, and on a slanted surface the nearest pixel's depth is off by up to half a
    footprint times the slope: fused as is, meshes come out stepped."""
    d_near = depth[nearest]
    if W < 2 or H < 2:
        return d_near
    base, fu, fv = _bilinear_cell(u, v, W, H)
    corners = (base, base + 1, base + W, base + W + 1)
    d = torch.stack([depth[c] for c in corners], -1)
    ok = torch.stack([valid[c] for c in corners], -1).all(-1)
    ok &= (d.max(-1).values - d.min(-1).values) <= EDGE_JUMP_PX * d_near / float(focal)
    return torch.where(ok, _blend(*d.unbind(-1), fu, fv), d_near)


@dataclass
class VoxelGrid:
    """A regular grid: voxel (i, j, k) has its centre at ``origin + voxel · (i, j, k)``."""

    origin: tuple[float, float, float]
    voxel: float
    shape: tuple[int, int, int]

    @property
    def count(self) -> int:
        return self.shape[0] * self.shape[1] * self.shape[2]

    def centers(self, flat_index: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
        """World positions (M, 3) of voxels given by flat (C-order) indices."""
        _, ny, nz = self.shape
        i = flat_index // (ny * nz)
        j = (flat_index // nz) % ny
        k = flat_index % nz
        ijk = torch.stack([i, j, k], dim=-1).to(dtype)
        return torch.tensor(self.origin, dtype=dtype, device=flat_index.device) + ijk * self.voxel

    def index_of(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Nearest voxel (M, 3) int64 of world points and whether it lies in the grid."""
        o = torch.tensor(self.origin, dtype=points.dtype, device=points.device)
        ijk = torch.round((points - o) / self.voxel).long()
        hi = torch.tensor(self.shape, device=points.device)
        inside = ((ijk >= 0) & (ijk < hi)).all(dim=-1)
        return ijk, inside


@dataclass
class FusionParams:
    """Grid and truncation actually used (recorded next to the mesh)."""

    lo: list[float]
    hi: list[float]
    voxel: float
    trunc: float
    shape: list[int]
    band_voxels: int = 0
    frames: int = 0
    carve: bool = True
    hull: bool = False
    extra: dict[str, Any] = field(default_factory=dict)


def frame_points(f: DepthFrame) -> Tensor:
    """World points (M, 3) float64 of every valid pixel of one frame."""
    if not bool(f.valid.any()):
        return torch.zeros(0, 3, dtype=torch.float64)
    uv = f.camera.pixel_centers(torch.float64, f.depth.device)[f.valid]
    return f.camera.backproject(uv, f.depth[f.valid].to(torch.float64))


def backproject_frames(frames: Sequence[DepthFrame]) -> Tensor:
    """World points (M, 3) float64 of every valid pixel of every frame."""
    pts = [frame_points(f) for f in frames]
    return torch.cat(pts) if pts else torch.zeros(0, 3, dtype=torch.float64)


def sample_points(frames: Iterable[DepthFrame], budget: int, seed: int = 0) -> Tensor:
    """At most about ``budget`` surface points (float64, CPU) drawn evenly from the frames,
    one frame at a time: what the bounds need, without holding the frames."""
    gen = torch.Generator().manual_seed(seed)
    kept: list[Tensor] = []
    seen = 0
    for f in frames:
        pts = frame_points(f).cpu()
        seen += len(pts)
        kept.append(pts)
        total = sum(len(k) for k in kept)
        if total > budget:  # thin what is kept to the budget, in proportion
            keep = budget / total
            kept = [k[torch.rand(len(k), generator=gen) < keep] for k in kept]
    return torch.cat(kept) if kept else torch.zeros(0, 3, dtype=torch.float64)


def fusion_bounds(
    frames: Sequence[DepthFrame] | Tensor,
    center: Tensor | Sequence[float] | None = None,
    radius: float | None = None,
    *,
    percentile: float = 0.5,
    margin: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box (lo, hi) of the surface seen in the frames.

    Robust per-axis percentiles of the back-projected surface pixels (floaters far off
    do not stretch the box), grown by ``margin`` × the box's largest side on every side
    (percentiles clip the extreme tips), and clipped to the scene's bounding sphere
    (``center``, ``radius``) when given. ``frames`` may also be the surface points.
    """
    pts = frames if isinstance(frames, Tensor) else backproject_frames(frames)
    pts = pts.cpu().numpy()
    if len(pts) == 0:
        if center is None or radius is None:
            raise ValueError("no valid depth in any frame and no scene bounds to fall back on")
        c = np.asarray(center, dtype=np.float64)
        return c - radius, c + radius
    lo = np.percentile(pts, percentile, axis=0)
    hi = np.percentile(pts, 100.0 - percentile, axis=0)
    pad = margin * float(np.max(hi - lo)) + 1e-6
    lo, hi = lo - pad, hi + pad
    if center is not None and radius is not None:
        c = np.asarray(torch.as_tensor(center, dtype=torch.float64).cpu(), dtype=np.float64)
        lo, hi = np.maximum(lo, c - radius), np.minimum(hi, c + radius)
        if np.any(hi <= lo):  # the surface lies outside the scene sphere: trust the surface
            lo = np.percentile(pts, percentile, axis=0) - pad
            hi = np.percentile(pts, 100.0 - percentile, axis=0) + pad
    return lo, hi


def make_grid(
    lo: np.ndarray, hi: np.ndarray, voxel: float | None = None, resolution: int = DEFAULT_RESOLUTION
) -> VoxelGrid:
    """Grid covering [lo, hi]; voxel = 2·radius/resolution by default, radius = half
    the box's largest side (the scene radius once the box is tightened)."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    if voxel is None:
        voxel = float(np.max(hi - lo)) / resolution
    if not voxel > 0:
        raise ValueError(f"voxel size must be positive, got {voxel}")
    nx, ny, nz = (math.ceil(s / voxel) + 1 for s in (hi - lo))
    shape = (nx, ny, nz)
    if shape[0] * shape[1] * shape[2] > 1024**3:
        raise ValueError(f"voxel {voxel:g} gives a {shape} grid: too many voxels")
    return VoxelGrid((float(lo[0]), float(lo[1]), float(lo[2])), float(voxel), shape)


def narrow_band(frames: Iterable[DepthFrame], grid: VoxelGrid, trunc: float) -> Tensor:
    """Flat indices (M,) of the voxels within ``trunc`` of a back-projected surface pixel
    (frames are read one at a time)."""
    occ = np.zeros(grid.shape, dtype=bool)  # one byte a voxel: 58 MB for a 512³ box
    for f in frames:
        pts = frame_points(f)
        if not len(pts):
            continue
        ijk, inside = grid.index_of(pts.cpu())
        ijk = ijk[inside].numpy()
        occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    r = math.ceil(trunc / grid.voxel)
    for axis in range(3):  # separable dilation by a (2r+1)³ cube, one axis at a time
        occ = _dilate_axis(occ, r, axis)
    return torch.from_numpy(np.flatnonzero(occ))


def _dilate_axis(occ: np.ndarray, r: int, axis: int) -> np.ndarray:
    """Boolean dilation by ±``r`` voxels along one axis (in place of a float max-pool:
    an eighth of the memory)."""
    out = occ.copy()
    n = occ.shape[axis]
    for d in range(1, min(r, n - 1) + 1):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, n - d), slice(d, n)
        out[tuple(lo)] |= occ[tuple(hi)]
        out[tuple(hi)] |= occ[tuple(lo)]
    return out


class TSDFVolume:
    """A truncated signed distance field over the narrow band of a voxel grid.

    Values are the distance to the surface divided by ``trunc``, clipped to [−1, 1],
    positive in front of the surface (free space), weighted running averages over
    views. Voxels no view has observed keep weight 0 and never produce a surface.
    """

    def __init__(
        self, grid: VoxelGrid, trunc: float, band: Tensor, *, device: torch.device | str = "cpu"
    ) -> None:
        if not trunc > 0:
            raise ValueError(f"truncation must be positive, got {trunc}")
        self.grid = grid
        self.trunc = float(trunc)
        self.device = torch.device(device)
        self.index = band.to(self.device)
        self.points = grid.centers(self.index)  # voxel centres (M, 3), float32
        m = self.index.numel()
        self.tsdf = torch.ones(m, device=self.device)
        self.weight = torch.zeros(m, device=self.device)
        self.color = torch.zeros(m, 3, device=self.device)
        self.color_weight = torch.zeros(m, device=self.device)
        # the masks' lower bound on each voxel's value (0: none), applied by dense();
        # allocated by the first view that brings hull distances
        self.hull: Tensor | None = None
        # each such view's camera and hull distances (float16), to bound the voxels the
        # closure adds behind a lifted surface (dense())
        self.hull_views: list[tuple[Camera, Tensor]] = []

    @torch.no_grad()
    def integrate(
        self,
        frame: DepthFrame,
        *,
        carve: bool = True,
        hull: bool = False,
        chunk: int = 1 << 22,
        compiled: bool | None = None,
    ) -> None:
        """Fuse one view (depth between pixel centres, projective distance along z);
        with ``hull``, also raise each voxel's lower bound from the view's
        ``hull_dist`` (when it has one).

        Only the voxels the view updates are touched (index ops), so a view costs
        one projection of the band plus work proportional to what it sees.
        ``compiled``: one numba pass over the band (core.meshing.tsdf_compiled; None:
        on the CPU), False: the torch ops below, the reference.
        """
        cam = frame.camera
        H, W = cam.height, cam.width
        depth = frame.depth.to(self.device, torch.float32).reshape(-1)
        valid = frame.valid.to(self.device).reshape(-1)
        empty = None
        if carve and frame.empty is not None:
            empty = frame.empty.to(self.device).reshape(-1)
        view_w = None
        if frame.weight is not None:
            view_w = frame.weight.to(self.device, torch.float32).reshape(-1)
        color = None
        if frame.color is not None:
            color = frame.color.to(self.device, torch.float32).reshape(-1, 3)
        hull_dist = None
        if hull and frame.hull_dist is not None:
            hull_dist = frame.hull_dist.to(self.device, torch.float32).reshape(-1)
            if self.hull is None:
                self.hull = torch.zeros_like(self.tsdf)
            self.hull_views.append((cam, frame.hull_dist.detach().to("cpu", torch.float16)))
        # P = K [R | t]: (u·z, v·z, z) = P (x, 1)
        P = cam.K(torch.float64) @ torch.cat([cam.R, cam.t[:, None]], 1)
        P = P.to(self.device, torch.float32)
        if compiled is None:
            compiled = self.device.type == "cpu"
        if compiled:
            from core.meshing.tsdf_compiled import integrate_compiled

            def arr(t: Tensor | None) -> np.ndarray | None:
                return None if t is None else t.contiguous().numpy()

            integrate_compiled(
                self.points.numpy(), P.numpy(), arr(depth), arr(valid), arr(empty),
                arr(view_w), arr(color), arr(hull_dist), W, H, cam.intrinsics.fx, EDGE_JUMP_PX,
                HULL_MARGIN_PX, self.trunc, self.tsdf.numpy(), self.weight.numpy(),
                self.color.numpy(), self.color_weight.numpy(), arr(self.hull),
            )  # fmt: skip
            return
        for s in range(0, self.points.shape[0], chunk):
            uvz = self.points[s : s + chunk] @ P[:, :3].T + P[:, 3]
            z = uvz[:, 2]
            zs = z.clamp_min(1e-6)
            u = torch.floor(uvz[:, 0] / zs)
            v = torch.floor(uvz[:, 1] / zs)
            inimg = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
            sel = inimg.nonzero()[:, 0]
            pix = (v[sel] * W + u[sel]).long()
            u_sel, v_sel = uvz[sel, 0] / zs[sel], uvz[sel, 1] / zs[sel]
            if hull_dist is not None and self.hull is not None:
                at = bilinear_at(hull_dist, u_sel, v_sel, W, H)
                bound = hull_bound(at, z[sel], cam.intrinsics.fx, self.trunc)
                hidx = sel + s
                self.hull[hidx] = torch.maximum(self.hull[hidx], bound)
            d_at = interpolated_depth(depth, valid, pix, u_sel, v_sel, W, H, cam.intrinsics.fx)
            sdf = d_at - z[sel]
            upd = valid[pix] & (sdf > -self.trunc)
            obs = (sdf / self.trunc).clamp(max=1.0)
            if empty is not None:
                free = empty[pix] & ~upd
                obs = torch.where(free, torch.ones_like(obs), obs)
                upd = upd | free
            idx = sel[upd] + s
            w = self.weight[idx]
            if view_w is None:
                wo = torch.ones_like(w)
            else:  # surface observations by their weight, carving by 1
                wo = view_w[pix[upd]]
                if empty is not None:
                    wo = torch.where(free[upd], 1.0, wo)
            self.tsdf[idx] = (self.tsdf[idx] * w + obs[upd] * wo) / (w + wo)
            self.weight[idx] = w + wo
            if color is not None:
                # colour only from surface observations near the surface, never carving
                near = upd & (sdf.abs() < self.trunc) & valid[pix]
                cidx = sel[near] + s
                cw = self.color_weight[cidx]
                c = color[pix[near]]
                self.color[cidx] = (self.color[cidx] * cw[:, None] + c) / (cw + 1.0)[:, None]
                self.color_weight[cidx] = cw + 1.0

    def dense(self) -> tuple[np.ndarray, np.ndarray]:
        """Dense TSDF (unobserved = +1) and observed mask, as numpy grids; each observed
        voxel's value at least its hull bound."""
        n = self.grid.count
        vol = torch.ones(n)
        obs = torch.zeros(n, dtype=torch.bool)
        seen = self.weight.cpu() > 0
        idx = self.index.cpu()
        tsdf = self.tsdf.cpu()
        inside = None
        if self.hull is not None:  # a bound of 0 says nothing (on or in the object)
            hull = self.hull.cpu()
            inside = self._closure(idx[seen], (hull[seen] > 0) & (tsdf[seen] < 0))
            tsdf = torch.where(hull > 0, torch.maximum(tsdf, hull), tsdf)
        vol[idx[seen]] = tsdf[seen]
        obs[idx[seen]] = True
        if inside is not None:
            cidx, cval = inside
            vol[cidx] = cval
            obs[cidx] = True
        return vol.reshape(self.grid.shape).numpy(), obs.reshape(self.grid.shape).numpy()

    def _closure(self, band_idx: Tensor, lifted_solid: Tensor) -> tuple[Tensor, Tensor] | None:
        """Voxels behind a surface the hull lifts: the unobserved voxels within
        :data:`CLOSURE_REACH` truncations of a band voxel the depths put inside (tsdf < 0)
        and the hull outside, each given −1 where every mask may hold it (bound 0), else
        its bound, so a slab thicker than the band closes at the hull's boundary instead
        of leaving a hole (flat indices, values)."""
        from scipy.ndimage import binary_dilation

        if not bool(lifted_solid.any()):
            return None
        shape = self.grid.shape
        reach = max(1, math.ceil(CLOSURE_REACH * self.trunc / self.grid.voxel))
        band = np.stack(np.unravel_index(band_idx.numpy(), shape), 1)
        seeds = band[lifted_solid.numpy()]
        # everything happens in the seeds' box grown by the reach (the dilation cannot
        # leave it): a few % of the grid where the hull lifts little
        lo = np.maximum(seeds.min(0) - reach, 0)
        hi = np.minimum(seeds.max(0) + reach + 1, shape)
        grown = np.zeros(tuple(hi - lo), dtype=bool)
        grown[tuple((seeds - lo).T)] = True
        grown = binary_dilation(grown, iterations=reach)
        in_box = ((band >= lo) & (band < hi)).all(1)
        grown[tuple((band[in_box] - lo).T)] = False  # observed voxels keep their values
        cand = torch.from_numpy(np.ravel_multi_index((np.argwhere(grown) + lo).T, shape))
        if cand.numel() == 0:
            return None
        pts = self.grid.centers(cand).to(torch.float64)
        bound = torch.zeros(cand.numel())
        for cam, dist in self.hull_views:
            H, W = cam.height, cam.width
            uv, z = cam.project(pts)
            u, v = uv[:, 0].float(), uv[:, 1].float()
            ok = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
            if not bool(ok.any()):
                continue
            at = bilinear_at(dist.reshape(-1).float(), u[ok], v[ok], W, H)
            b = hull_bound(at, z[ok].float(), cam.intrinsics.fx, self.trunc)
            bound[ok] = torch.maximum(bound[ok], b)
        return cand, torch.where(bound > 0, bound, torch.full_like(bound, -1.0))

    def vertex_colors(self, verts_ijk: np.ndarray) -> np.ndarray | None:
        """Linear RGB (V, 3) at continuous voxel coordinates; None when nothing was fused.

        Trilinear over the 8 surrounding voxels that hold a colour, looked up in the
        sorted band (no dense colour grid: 4 floats a voxel would be 0.9 GB at 512³).
        """
        if not bool((self.color_weight > 0).any()):
            return None
        X, Y, Z = self.grid.shape
        band, order = self.index.cpu().sort()
        has = (self.color_weight.cpu() > 0)[order]
        col = self.color.cpu()[order]
        p = torch.as_tensor(np.ascontiguousarray(verts_ijk), dtype=torch.float64)
        base = p.floor().long()
        frac = (p - base).float()
        acc = torch.zeros(len(p), 3)
        wsum = torch.zeros(len(p))
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    i, j, k = base[:, 0] + dx, base[:, 1] + dy, base[:, 2] + dz
                    ok = (i >= 0) & (i < X) & (j >= 0) & (j < Y) & (k >= 0) & (k < Z)
                    flat = (i.clamp(0, X - 1) * Y + j.clamp(0, Y - 1)) * Z + k.clamp(0, Z - 1)
                    pos = torch.searchsorted(band, flat).clamp(max=len(band) - 1)
                    ok = ok & (band[pos] == flat) & has[pos]
                    w = (
                        (frac[:, 0] if dx else 1 - frac[:, 0])
                        * (frac[:, 1] if dy else 1 - frac[:, 1])
                        * (frac[:, 2] if dz else 1 - frac[:, 2])
                    ) * ok
                    acc += col[pos] * w[:, None]
                    wsum += w
        return (acc / wsum.clamp_min(1e-6)[:, None]).clamp(0, 1).numpy()


FrameSource = Callable[[int], DepthFrame]
ProgressFn = Callable[[str, int, int], None]
POINT_BUDGET = 4_000_000  # surface points kept for the bounds (≈ 100 MB)


def fuse_frames(
    n_frames: int,
    frame_at: FrameSource,
    *,
    bounds_frame_at: FrameSource | None = None,
    band_frame_at: FrameSource | None = None,
    center: Tensor | Sequence[float] | None = None,
    radius: float | None = None,
    voxel: float | None = None,
    trunc: float | None = None,
    resolution: int = DEFAULT_RESOLUTION,
    carve: bool = True,
    hull: bool = False,
    device: torch.device | str = "cpu",
    progress: ProgressFn | None = None,
    max_resolution: int | None = None,
) -> tuple[TSDFVolume, FusionParams]:
    """Fuse ``n_frames`` views into a TSDF, holding one view's frame at a time.

    ``frame_at(i)`` makes frame i (a render, typically) to integrate;
    ``band_frame_at`` (default ``frame_at``; colour is not needed) marks the narrow band
    and ``bounds_frame_at`` (e.g. a quarter-resolution render; default ``frame_at``)
    gives the points the grid is fitted to. Memory: the band's voxels, one frame, and at most
    :data:`POINT_BUDGET` points. ``progress(stage, done, total)`` is called after
    each view of each pass; ``max_resolution`` refuses a grid with a longer side.
    """
    if n_frames <= 0:
        raise ValueError("no frames to fuse")
    report = progress or (lambda stage, done, total: None)
    bounds_at = bounds_frame_at or frame_at
    band_at = band_frame_at or frame_at

    def bounds_frames() -> Iterator[DepthFrame]:
        for i in range(n_frames):
            yield bounds_at(i)
            report("bounds", i + 1, n_frames)

    pts = sample_points(bounds_frames(), POINT_BUDGET)
    lo, hi = fusion_bounds(pts, center, radius)
    grid = make_grid(lo, hi, voxel, resolution)
    if max_resolution is not None and max(grid.shape) > max_resolution + 1:
        raise ValueError(
            f"the grid would be {grid.shape[0]}×{grid.shape[1]}×{grid.shape[2]} voxels, "
            f"beyond the limit of {max_resolution} per side: use a larger voxel"
        )
    trunc = float(trunc) if trunc is not None else DEFAULT_TRUNC_VOXELS * grid.voxel

    def band_frames() -> Iterator[DepthFrame]:
        for i in range(n_frames):
            yield band_at(i)
            report("band", i + 1, n_frames)

    band = narrow_band(band_frames(), grid, trunc)
    vol = TSDFVolume(grid, trunc, band, device=device)
    for i in range(n_frames):
        vol.integrate(frame_at(i), carve=carve, hull=hull)
        report("integrate", i + 1, n_frames)
    params = FusionParams(
        lo=[float(x) for x in lo],
        hi=[float(x) for x in hi],
        voxel=grid.voxel,
        trunc=trunc,
        shape=list(grid.shape),
        band_voxels=int(band.numel()),
        frames=n_frames,
        carve=carve,
        hull=hull,
    )
    return vol, params


def fuse_depth_frames(
    frames: Sequence[DepthFrame],
    *,
    center: Tensor | Sequence[float] | None = None,
    radius: float | None = None,
    voxel: float | None = None,
    trunc: float | None = None,
    resolution: int = DEFAULT_RESOLUTION,
    carve: bool = True,
    hull: bool = False,
    device: torch.device | str = "cpu",
) -> tuple[TSDFVolume, FusionParams]:
    """Fuse depth frames already in memory (see :func:`fuse_frames`)."""
    return fuse_frames(
        len(frames), frames.__getitem__, center=center, radius=radius, voxel=voxel,
        trunc=trunc, resolution=resolution, carve=carve, hull=hull, device=device,
    )  # fmt: skip


def _real_crossings(verts: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """(V,) bool: the vertex lies on a grid edge whose two end voxels were both observed.

    Marching cubes puts each vertex on the edge between two voxels; if one of them
    was never observed (value +1 by convention), the crossing is an artefact (e.g. a
    false shell at the inner edge of the band). scikit-image's ``mask`` does not rule
    these out on its own, so they are filtered here.
    """
    r = np.round(verts)
    near = np.abs(verts - r) < 1e-6
    lo = np.where(near, r, np.floor(verts)).astype(np.int64)
    hi = np.where(near, r, np.ceil(verts)).astype(np.int64)
    hi = np.minimum(hi, np.asarray(observed.shape) - 1)
    return observed[lo[:, 0], lo[:, 1], lo[:, 2]] & observed[hi[:, 0], hi[:, 1], hi[:, 2]]


def extract_mesh(vol: TSDFVolume) -> trimesh.Trimesh:
    """Zero level set by marching cubes over observed voxels, outward-facing, coloured."""
    import trimesh
    from skimage.measure import marching_cubes

    tsdf, observed = vol.dense()
    if not (observed.any() and (tsdf[observed] < 0).any() and (tsdf[observed] > 0).any()):
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    verts, faces, _, _ = marching_cubes(tsdf, level=0.0, mask=observed)
    faces = faces[_real_crossings(verts, observed)[faces].all(axis=1)]
    g = vol.grid
    world = np.asarray(g.origin) + verts.astype(np.float64) * g.voxel
    colors = vol.vertex_colors(verts)
    vc = None
    if colors is not None:
        srgb = np.asarray(linear_to_srgb(np.clip(colors, 0.0, 1.0)))
        vc = np.concatenate([np.round(srgb * 255), np.full((len(srgb), 1), 255)], 1).astype(
            np.uint8
        )
    return trimesh.Trimesh(world, faces.astype(np.int64), vertex_colors=vc, process=True)


def keep_largest_components(
    mesh: trimesh.Trimesh, keep_fraction: float = 0.1
) -> tuple[trimesh.Trimesh, dict[str, int]]:
    """Keep the largest connected component (by faces) and any with ≥ ``keep_fraction``
    of its faces; returns the mesh and how many components/faces were dropped."""
    import trimesh

    nf = len(mesh.faces)
    if nf == 0:
        return mesh, {"components": 0, "kept": 0, "faces_dropped": 0}
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=nf)
    sizes = np.bincount(labels)
    keep_labels = np.nonzero(sizes >= keep_fraction * sizes.max())[0]
    keep = np.isin(labels, keep_labels)
    out = mesh.submesh([np.nonzero(keep)[0]], append=True, repair=False)
    stats = {
        "components": len(sizes),
        "kept": len(keep_labels),
        "faces_dropped": int(nf - keep.sum()),
    }
    return out, stats
