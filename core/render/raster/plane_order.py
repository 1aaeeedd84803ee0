"""Per-pixel plane order (``TrainConfig.splat_order = 'plane'``): each pixel composites
its splats in the order in which their planes meet its ray.

Why. Tile lists are sorted by centre depth, one order for every pixel of a tile. Along
a tilted surface the splats of one stretch of surface overlap at a pixel with centres
at different depths, so the one whose centre lies toward the camera comes first and
weighs most wherever it reaches, even where its own plane lies behind its neighbours'.
Colours and normals then lean toward the splats displaced toward the camera (measured:
the slab order, which removes the centre order inside a surface, made images and
normals better on most dev scenes; docs/benchmarks.md, issue 36). A planar splat's
place along a pixel's ray is where its plane meets the ray, so this order sorts each
pixel's contributors by that depth (StopThePop sorts 3D Gaussians per pixel by their
density maximum along the ray, which is the same point for a flat one).

What. Per splat: its plane in camera space (unit normal ``n``, the axis of its smallest
scale; ``d = n·μ``), its centre depth ``z`` and a reach ``h`` (three times its largest
scale). On the ray through pixel centre (u, v), ``r = ((u - cx)/fx, (v - cy)/fy, 1)``,
the plane lies at camera depth ``d / (n·r)``, clamped to ``[z - h, z + h]`` (an
edge-on splat's plane meets the ray arbitrarily far away; where the splat has any
alpha its plane is within its reach). Ties (equal keys) keep the tile's centre order.
The order is piecewise constant, so it carries no gradient: the weights are the usual
``alpha_i Π_{j before i} (1 - alpha_j)`` in that order, early termination included.

The torch reference (:func:`rasterize_reference_plane`) sorts per pixel with a stable
argsort; the numba kernels (pixel-major: each pixel gathers its contributors from the
tile list, insertion-sorts them, stops gathering what lies behind the point where its
compositing saturates, and composites; the forward keeps the composited runs with
their transmittances for the backward within ``RUN_STORE_BYTES``; the backward sums a
tile's gradients per entry before adding them to the Gaussians') are tested against it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from core.kernels.pool import (
    BufferPool,
    kernel_threads,
    run_ranges,
    run_workers,
    scratch_zeros,
    store_dtype,
    zeros_touched,
)
from core.render.raster.binning import TileBins
from core.render.raster.cpu import (
    _G_A,
    _G_F,
    _G_MX,
    _G_O,
    _GEO_HX,
    _GEO_HY,
    _compute_dtype,
    _np,
    _reduce_split_range,
    _row_span,
    _Setup,
    _span,
)
from core.render.raster.projection import ALPHA_MAX, ALPHA_MIN, T_MIN, Projected
from core.render.raster.reference import tile_pixels
from core.render.rotations import normalize_quats, quat_to_rotmat
from core.scene.cameras import Camera

try:
    from numba import njit
except ImportError:  # pragma: no cover - numba is a declared dependency

    def njit(*_args, **_kwargs):  # type: ignore[no-redef]
        return lambda fn: fn


__all__ = [
    "PlaneKeys", "plane_keys", "plane_reach", "rasterize_cpu_plane", "rasterize_reference_plane",
]  # fmt: skip

# A splat's plane is searched for within this many of its largest standard deviations
# of its centre along the ray (its alpha is below 1/255 beyond about 3.3 σ).
REACH_SIGMAS = 3.0
# Early termination (:func:`_fill_sorted`): a saturated pixel's run is walked again after
# this many insertions, and the tile's stop is looked for every this many list entries.
_WALK_EVERY = 4
_TILE_CHECK_EVERY = 32
# A tile's runs first get 64 entries a pixel; a tile that needs more grows the arrays to
# twice its largest run a pixel, up to this many entries (16 bytes each), or to its count.
_MAX_GROWN_ROOM = 1 << 22


@dataclass
class PlaneKeys:
    """What the per-pixel order needs: ``planes`` (N, 6) float64 rows
    (n_x, n_y, n_z, d, z, h) in camera space, and the pinhole intrinsics."""

    planes: Tensor
    fx: float
    fy: float
    cx: float
    cy: float

    def rays(self, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """Camera-ray x and y slopes of pixel-centre coordinates (float64)."""
        return (u.to(torch.float64) - self.cx) / self.fx, (v.to(torch.float64) - self.cy) / self.fy

    def keys(self, ids: Tensor, rx: Tensor, ry: Tensor) -> Tensor:
        """(P, K) depth along each pixel's ray (rx, ry: (P,)) of the planes ``ids`` (K,)."""
        p = self.planes[ids]
        nx, ny, nz, d, z, h = (p[:, k][None, :] for k in range(6))
        ndot = nx * rx[:, None] + ny * ry[:, None] + nz
        t = d / ndot
        t = torch.where(torch.isfinite(t), t, z.expand_as(t))
        return torch.minimum(torch.maximum(t, z - h), z + h)


def plane_reach(scales: Tensor) -> Tensor:
    """(N,) how far along the ray from its centre a splat's plane is searched for:
    REACH_SIGMAS of its largest scale (no gradient)."""
    return REACH_SIGMAS * scales.detach().to(torch.float64).amax(-1)


def plane_keys(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    camera: Camera,
    covariances: Tensor | None = None,
    normals: Tensor | None = None,
    reach: Tensor | None = None,
) -> PlaneKeys:
    """Each splat's camera-space plane, centre depth and reach (no gradient).

    ``normals`` (N, 3, world, any sign): the planes' normals where the caller has them
    (the G-buffer's Eq. 6 normals), so that a model rendered from its rotations and the
    same model rendered from frozen covariances sort their splats alike; otherwise the
    axis of the smallest scale, or of the covariance's smallest eigenvalue. ``reach``
    (N,): :func:`plane_reach` where the caller kept it (a frozen model: otherwise every
    frame would take the eigenvalues of every covariance, ~0.1 s at 134k splats)."""
    with torch.no_grad():
        if reach is not None and normals is not None:
            reach = reach.detach().to(torch.float64)
        elif quats is not None and scales is not None:
            s = scales.detach().to(torch.float64)
            reach = plane_reach(scales)
            if normals is None:
                R = quat_to_rotmat(normalize_quats(quats.detach().to(torch.float64)))
                k = s.argmin(-1)[:, None, None].expand(-1, 3, 1)
                normals = torch.gather(R, 2, k)[..., 0]
        elif covariances is not None:
            covs = covariances.detach().to(torch.float64)
            if normals is None:
                evals, evecs = torch.linalg.eigh(covs)
                normals = evecs[..., 0]
            else:
                evals = torch.linalg.eigvalsh(covs)
            reach = REACH_SIGMAS * evals[..., -1].clamp_min(0.0).sqrt()
        else:
            raise ValueError("plane order needs quats and scales, or covariances")
        n_world = normals.detach().to(torch.float64)
        Rc = camera.R.to(torch.float64)
        tc = camera.t.to(torch.float64)
        mu = means.detach().to(torch.float64) @ Rc.T + tc
        n = n_world @ Rc.T
        d = (n * mu).sum(-1)
        planes = torch.cat([n, d[:, None], mu[:, 2:3], reach[:, None]], dim=1).contiguous()
    i = camera.intrinsics
    return PlaneKeys(planes, float(i.fx), float(i.fy), float(i.cx), float(i.cy))


# ---------------------------------------------------------------------------------------
# torch reference
# ---------------------------------------------------------------------------------------


def rasterize_reference_plane(
    proj: Projected,
    opacities: Tensor,
    features: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    order: PlaneKeys,
) -> tuple[Tensor, Tensor]:
    """(H, W, C) features and (H, W) alpha, each pixel composited in plane order.

    Plain autograd over dense (pixels × tile list) tensors: the oracle for small
    scenes, not for training."""
    dtype, device = features.dtype, features.device
    C = features.shape[1]
    ts = bins.tile_size
    img = torch.zeros(height * width, C, dtype=dtype, device=device)
    alpha_img = torch.zeros(height * width, dtype=dtype, device=device)
    offsets = bins.offsets.tolist()
    opac = opacities.reshape(-1)
    for ty in range(bins.tiles_y):
        for tx in range(bins.tiles_x):
            t = ty * bins.tiles_x + tx
            lo, hi = offsets[t], offsets[t + 1]
            if hi == lo:
                continue
            pix, uu, vv = tile_pixels(tx, ty, ts, width, height, dtype, device)
            ids = bins.gauss_ids[lo:hi].long()
            d = pix[:, None, :] - proj.means2d[ids][None, :, :]
            dx, dy = d[..., 0], d[..., 1]
            a, b, c = (proj.conics[ids, k] for k in range(3))
            power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
            alpha = torch.clamp(opac[ids] * torch.exp(power.clamp_max(0.0)), max=ALPHA_MAX)
            keep = (power <= 0) & (alpha >= ALPHA_MIN)
            alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
            rx, ry = order.rays(pix[:, 0], pix[:, 1])
            perm = torch.sort(order.keys(ids, rx, ry), dim=1, stable=True).indices
            alpha = alpha.gather(1, perm)
            one_minus = 1.0 - alpha
            T_after = torch.cumprod(one_minus, dim=1)
            T_before = T_after / one_minus
            included = T_after >= T_MIN
            w = torch.where(included, alpha * T_before, torch.zeros_like(alpha))
            f = features[ids][perm]  # (P, K, C)
            out = (w[..., None] * f).sum(1)
            T = torch.where(included, one_minus, torch.ones_like(one_minus)).prod(dim=1)
            idx = vv * width + uu
            img = img.index_copy(0, idx, out)
            alpha_img = alpha_img.index_copy(0, idx, 1.0 - T)
    return img.reshape(height, width, C), alpha_img.reshape(height, width)


# ---------------------------------------------------------------------------------------
# numba kernels (pixel-major)
# ---------------------------------------------------------------------------------------


@njit(nogil=True, fastmath=False, cache=True)
def _count_candidates(
    lo, hi, x0, x1, y0, y1, tile_size, means2d, gauss_ids, mode, geo, begin
):  # fmt: skip  # pragma: no cover - numba
    """``begin[p]``: where pixel p's run starts, room for every entry whose culling
    ellipse covers the pixel (a superset of its contributors: no exp() here); returns
    the room needed in all."""
    npix = tile_size * tile_size
    begin[:] = 0
    for i in range(lo, hi):
        g = gauss_ids[i]
        m = mode[g]
        if m == 0:
            continue
        geo_g = geo[g]
        mxd = np.float64(means2d[g, 0])
        myd = np.float64(means2d[g, 1])
        c0, c1 = _span(m, mxd, geo_g[_GEO_HX], x0, x1)
        if c0 >= c1:
            continue
        r0, r1 = _span(m, myd, geo_g[_GEO_HY], y0, y1)
        for py in range(r0, r1):
            q0, q1 = _row_span(m, geo_g, mxd, py + 0.5 - myd, x0, x1)
            for px in range(q0, q1):
                begin[(py - y0) * tile_size + (px - x0) + 1] += 1
    for p in range(npix):
        begin[p + 1] += begin[p]
    return begin[npix]


@njit(nogil=True, fastmath=False, cache=True)
def _fill_sorted(
    lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys, consts,
    mode, geo, planes, rx, ry, begin, end, cand_i, cand_key, cand_g, stop_key, t_all,
    since, reach_min,
):  # fmt: skip  # pragma: no cover - numba
    """Each pixel p's contributors (alpha ≥ 1/255) as places in the tile list (entry
    ``lo + k`` holds Gaussian ``gauss_ids[lo + k]``) ``cand_i[begin[p]:end[p]]``, sorted
    by plane depth (stable: entries arrive in tile
    order and ties keep it), with their Gaussian factor exp(power) in ``cand_g``.
    Gaussian-major over the entries with the compiled backend's culling ellipses (a
    culling only: every visited pixel is tested with the reference formula). Insertion
    sort: the centre order is close to the plane order, so a heap (tried) was 2.6×
    slower on the bench scene.

    Early termination, exact: once a pixel's sorted run saturates (the compositing
    would stop at an entry with key ``stop_key[p]``), an entry whose key is not below
    that lands behind it and is never composited, so it is not inserted (nor its
    exp() taken where even its nearest possible key, z - h, is not below); the entries
    behind the stop are dropped. The run is walked again (:func:`_saturate`) after
    every ``_WALK_EVERY`` insertions, and first once the product of all its (1 - alpha),
    which does not depend on the order, falls below T_MIN. The tile stops early where
    every pixel has saturated in front of the nearest plane any later entry can
    have (``reach_min``: suffix minima of z - h).

    Returns False, leaving the runs unfinished, where a pixel's run outgrows its room
    (``begin[p + 1] - begin[p]``): with rooms from :func:`_count_candidates` it cannot."""
    half, one, a_min, a_max, t_min = consts[0], consts[1], consts[2], consts[3], consts[4]
    npix = tile_size * tile_size
    inf = np.inf
    for p in range(npix):
        end[p] = begin[p]
        stop_key[p] = inf
        t_all[p] = 1.0
        since[p] = 0
    n = hi - lo
    lowest = inf
    for k in range(n - 1, -1, -1):
        g = gauss_ids[lo + k]
        zlo = planes[g, 4] - planes[g, 5]
        if zlo < lowest:
            lowest = zlo
        reach_min[k] = lowest
    tile_stop = inf
    for i in range(lo, hi):
        if (i - lo) % _TILE_CHECK_EVERY == 0 and i > lo:
            tile_stop = -inf
            for py in range(y0, y1):
                for px in range(x0, x1):
                    k_p = stop_key[(py - y0) * tile_size + (px - x0)]
                    if k_p > tile_stop:
                        tile_stop = k_p
        if reach_min[i - lo] >= tile_stop:
            break
        g = gauss_ids[i]
        m = mode[g]
        if m == 0:
            continue
        geo_g = geo[g]
        mxd = np.float64(means2d[g, 0])
        myd = np.float64(means2d[g, 1])
        c0, c1 = _span(m, mxd, geo_g[_GEO_HX], x0, x1)
        if c0 >= c1:
            continue
        r0, r1 = _span(m, myd, geo_g[_GEO_HY], y0, y1)
        mx, my = means2d[g, 0], means2d[g, 1]
        a, b, c, o = conics[g, 0], conics[g, 1], conics[g, 2], opac[g]
        nx, ny, nz, d = planes[g, 0], planes[g, 1], planes[g, 2], planes[g, 3]
        z, h = planes[g, 4], planes[g, 5]
        zlo = z - h
        for py in range(r0, r1):
            q0, q1 = _row_span(m, geo_g, mxd, py + 0.5 - myd, x0, x1)
            dy = ys[py] - my
            ny_ry = ny * ry[py - y0] + nz
            for px in range(q0, q1):
                p = (py - y0) * tile_size + (px - x0)
                if zlo >= stop_key[p]:
                    continue
                dx = xs[px] - mx
                power = -half * (a * dx * dx + c * dy * dy) - b * dx * dy
                if not (power <= 0):
                    continue
                G = math.exp(power)
                alpha = o * G
                if alpha > a_max:
                    alpha = a_max
                if not (alpha >= a_min):
                    continue
                key = d / (nx * rx[px - x0] + ny_ry)
                if not math.isfinite(key):
                    key = z
                key = min(max(key, zlo), z + h)
                if key >= stop_key[p]:
                    continue
                j = end[p]
                if j >= begin[p + 1]:
                    return False
                s0 = begin[p]
                while j > s0 and cand_key[j - 1] > key:  # entries arrive in tile order,
                    cand_key[j] = cand_key[j - 1]  # nearly sorted: a few shifts
                    cand_i[j] = cand_i[j - 1]
                    cand_g[j] = cand_g[j - 1]
                    j -= 1
                cand_key[j] = key
                cand_i[j] = i - lo
                cand_g[j] = G
                end[p] += 1
                since[p] += 1
                t_all[p] *= 1.0 - np.float64(alpha)
                if since[p] >= _WALK_EVERY or (t_all[p] < t_min and stop_key[p] == inf):
                    since[p] = 0
                    if t_all[p] < t_min:
                        stop_key[p] = _saturate(
                            begin[p], end, p, cand_i, cand_key, cand_g, opac, gauss_ids, lo, one,
                            a_max, t_min,
                        )  # fmt: skip
    return True


@njit(nogil=True, fastmath=False, cache=True)
def _saturate(
    s0, end, p, cand_i, cand_key, cand_g, opac, gauss_ids, lo, one, a_max, t_min
):  # fmt: skip  # pragma: no cover - numba
    """Walk pixel p's sorted run front to back as the compositing does; where it stops
    (the entry that takes the transmittance below T_MIN) drop what lies behind and
    return that entry's key, else +inf."""
    T = one
    for j in range(s0, end[p]):
        alpha = opac[gauss_ids[lo + cand_i[j]]] * cand_g[j]
        if alpha > a_max:
            alpha = a_max
        test_T = T * (one - alpha)
        if test_T < t_min:
            end[p] = j + 1
            return cand_key[j]
        T = test_T
    return np.inf


@njit(nogil=True, fastmath=False, cache=True)
def _tile_runs(
    lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys, consts,
    mode, geo, planes, intr, begin, end, cand_i, cand_key, cand_g, rx, ry, stop_key, t_all,
    since, reach_min,
):  # fmt: skip  # pragma: no cover - numba
    """The tile's per-pixel contributor runs in plane order (:func:`_fill_sorted`);
    returns the candidate arrays and the suffix-minimum buffer (grown where needed).

    Each pixel first gets an equal share of the candidate arrays; only a tile where a
    run outgrows its share pays for the counting pass (exact rooms from the culling
    ellipses) and a second fill, and the arrays grow to twice what it needed, so the
    next tiles' shares fit (most tiles of a trained model: no counting pass at all)."""
    for px in range(x0, x1):
        rx[px - x0] = (np.float64(xs[px]) - intr[2]) / intr[0]
    for py in range(y0, y1):
        ry[py - y0] = (np.float64(ys[py]) - intr[3]) / intr[1]
    if hi - lo > reach_min.shape[0]:
        reach_min = np.empty(2 * (hi - lo), np.float64)
    npix = tile_size * tile_size
    share = cand_i.shape[0] // npix
    for p in range(npix + 1):
        begin[p] = p * share
    if _fill_sorted(
        lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys, consts,
        mode, geo, planes, rx, ry, begin, end, cand_i, cand_key, cand_g, stop_key, t_all,
        since, reach_min,
    ):  # fmt: skip
        return cand_i, cand_key, cand_g, reach_min
    total = _count_candidates(
        lo, hi, x0, x1, y0, y1, tile_size, means2d, gauss_ids, mode, geo, begin
    )
    most = 0
    for p in range(npix):
        most = max(most, begin[p + 1] - begin[p])
    want = max(total, min(2 * most * npix, _MAX_GROWN_ROOM))
    if want > cand_i.shape[0]:
        cand_i = np.empty(want, np.int32)
        cand_key = np.empty(want, np.float64)
        cand_g = np.empty(want, cand_g.dtype)
    _fill_sorted(
        lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys, consts,
        mode, geo, planes, rx, ry, begin, end, cand_i, cand_key, cand_g, stop_key, t_all,
        since, reach_min,
    )  # fmt: skip
    return cand_i, cand_key, cand_g, reach_min


@njit(nogil=True, fastmath=False, cache=True)
def _scratch(tile_size, opac):  # pragma: no cover - numba
    """A worker's buffers: run bounds, room for 64 contributors a pixel (grown per tile
    where needed), the tile's ray slopes, the early termination's per-pixel state and
    the tile list's suffix minima (grown where needed)."""
    npix = tile_size * tile_size
    return (
        np.zeros(npix + 1, np.int64),
        np.zeros(npix, np.int64),
        np.empty(64 * npix, np.int32),
        np.empty(64 * npix, np.float64),
        np.empty(64 * npix, opac.dtype),
        np.empty(tile_size, np.float64),
        np.empty(tile_size, np.float64),
        np.empty(npix, np.float64),
        np.empty(npix, np.float64),
        np.empty(npix, np.int32),
        np.empty(1024, np.float64),
    )


@njit(nogil=True, fastmath=False, cache=True, inline="always")
def _tile_box(t, tiles_x, tile_size, width, height):  # pragma: no cover - numba
    """Pixel bounds x0, y0, x1, y1 (exclusive) of tile t."""
    x0 = (t % tiles_x) * tile_size
    y0 = (t // tiles_x) * tile_size
    return x0, y0, min(x0 + tile_size, width), min(y0 + tile_size, height)


@njit(nogil=True, fastmath=False, cache=True)
def _forward_worker(
    w, n_workers, means2d, conics, opac, feats, gauss_ids, offsets, tiles_x, tile_size,
    xs, ys, consts, mode, geo, planes, intr, out_feat, out_T, out_last,
    run_g, run_G, run_T, run_at, tile_kept,
):  # fmt: skip  # pragma: no cover - numba
    """Tiles w, w + n_workers, ...: each pixel's contributors in plane order, composited
    front to back (out_T starts at 1, the others at 0); ``out_last`` counts the
    contributors composited. Where ``run_g`` has room (``run_g.shape[0] // n_tiles``
    entries a tile) the composited runs are kept for the backward: pixel (y, x)'s
    places in the tile list, exp(power) and transmittance in front of each at
    ``run_at[y, x]`` on, and ``tile_kept[t] = 1``."""
    height, width, n_ch = out_feat.shape
    n_tiles = offsets.shape[0] - 1
    one, a_max, t_min = consts[1], consts[3], consts[4]
    room = run_g.shape[0] // max(n_tiles, 1)
    begin, end, cand_i, cand_key, cand_g, rx, ry, stop_key, t_all, since, reach_min = _scratch(
        tile_size, opac
    )
    for t in range(w, n_tiles, n_workers):
        lo, hi = offsets[t], offsets[t + 1]
        if hi == lo:
            continue
        x0, y0, x1, y1 = _tile_box(t, tiles_x, tile_size, width, height)
        cand_i, cand_key, cand_g, reach_min = _tile_runs(
            lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys,
            consts, mode, geo, planes, intr, begin, end, cand_i, cand_key, cand_g, rx, ry,
            stop_key, t_all, since, reach_min,
        )  # fmt: skip
        kept = room > 0
        at = t * room
        stop = at + room
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * tile_size + (px - x0)
                if room > 0:
                    run_at[py, px] = at
                T = one
                m_used = 0
                for j in range(begin[p], end[p]):
                    k = cand_i[j]
                    g = gauss_ids[lo + k]
                    G = cand_g[j]
                    alpha = opac[g] * G
                    if alpha > a_max:
                        alpha = a_max
                    test_T = T * (one - alpha)
                    if test_T < t_min:
                        break
                    wgt = alpha * T
                    for ch in range(n_ch):
                        out_feat[py, px, ch] += feats[g, ch] * wgt
                    if kept:
                        if at < stop:
                            run_g[at] = k
                            run_G[at] = G
                            run_T[at] = T
                            at += 1
                        else:
                            kept = False
                    T = test_T
                    m_used += 1
                out_T[py, px] = T
                out_last[py, px] = m_used
        tile_kept[t] = 1 if kept else 0


@njit(nogil=True, fastmath=False, cache=True, inline="always")
def _contribution_backward(
    k, g, G, T_before, R, ga_T, px, py, means2d, conics, opac, feats, xs, ys, a_max,
    grad_feat, acc,
):  # fmt: skip  # pragma: no cover - numba
    """One contributor's gradients (Gaussian g, place k in the tile list), back to front
    (the compiled backend's formulas), added into ``acc[k]``, given the transmittance in
    front of it; returns the colour behind it. The
    transmittance comes from the forward rather than from dividing back from the
    final one: that division chained each contributor to the next (a pixel-major
    walk has nothing else to overlap it with) and was most of the backward's time."""
    n_ch = feats.shape[1]
    raw = opac[g] * G
    alpha = a_max if raw > a_max else raw
    al = np.float64(alpha)
    one_m = 1.0 - al
    wgt = al * T_before
    gf = 0.0
    for ch in range(n_ch):
        gc = np.float64(grad_feat[py, px, ch])
        gf += gc * np.float64(feats[g, ch])
        acc[k, 6 + ch] += wgt * gc
    d_alpha = T_before * gf + (ga_T - R) / one_m
    R += wgt * gf
    if raw > a_max:
        return R  # clamped: alpha depends on neither o nor the footprint
    d_pow = al * d_alpha
    dxd = np.float64(xs[px] - means2d[g, 0])
    dyd = np.float64(ys[py] - means2d[g, 1])
    ad, bd, cd = np.float64(conics[g, 0]), np.float64(conics[g, 1]), np.float64(conics[g, 2])
    acc[k, 0] += (ad * dxd + bd * dyd) * d_pow
    acc[k, 1] += (cd * dyd + bd * dxd) * d_pow
    acc[k, 2] -= 0.5 * dxd * dxd * d_pow
    acc[k, 3] -= dxd * dyd * d_pow
    acc[k, 4] -= 0.5 * dyd * dyd * d_pow
    acc[k, 5] += np.float64(G) * d_alpha
    return R


@njit(nogil=True, fastmath=False, cache=True)
def _backward_worker(
    w, n_workers, means2d, conics, opac, feats, gauss_ids, offsets, tiles_x, tile_size,
    xs, ys, consts, mode, geo, planes, intr, final_T, last, run_g, run_G, run_T, run_at,
    tile_kept, grad_feat, grad_alpha, gbuf,
):  # fmt: skip  # pragma: no cover - numba
    """Each pixel's contributors in the forward's order, back to front: the forward's
    kept runs, or (a tile it had no room for) the runs rebuilt, their transmittances
    recomputed front to back as the forward did. A tile's gradients are summed per
    entry of its list first (``acc``: a few thousand rows, in cache, where scattering
    each contribution into gbuf[w, gaussian] missed it half the backward's time), then
    added into gbuf once an entry."""
    height, width, _ = grad_feat.shape
    n_tiles = offsets.shape[0] - 1
    one, a_max = consts[1], consts[3]
    begin, end, cand_i, cand_key, cand_g, rx, ry, stop_key, t_all, since, reach_min = _scratch(
        tile_size, opac
    )
    n_q = 6 + feats.shape[1]
    acc = np.empty((1024, n_q), np.float64)
    for t in range(w, n_tiles, n_workers):
        lo, hi = offsets[t], offsets[t + 1]
        if hi == lo:
            continue
        x0, y0, x1, y1 = _tile_box(t, tiles_x, tile_size, width, height)
        if hi - lo > acc.shape[0]:
            acc = np.empty((2 * (hi - lo), n_q), np.float64)
        acc[: hi - lo] = 0.0
        kept = tile_kept[t] == 1
        if not kept:
            cand_i, cand_key, cand_g, reach_min = _tile_runs(
                lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys,
                consts, mode, geo, planes, intr, begin, end, cand_i, cand_key, cand_g, rx, ry,
                stop_key, t_all, since, reach_min,
            )  # fmt: skip
        for py in range(y0, y1):
            for px in range(x0, x1):
                m_used = last[py, px]
                if m_used == 0:
                    continue
                ga_T = np.float64(grad_alpha[py, px]) * np.float64(final_T[py, px])
                R = 0.0
                if kept:
                    at = run_at[py, px]
                    for j in range(at + m_used - 1, at - 1, -1):
                        k = run_g[j]
                        R = _contribution_backward(
                            k, gauss_ids[lo + k], run_G[j], np.float64(run_T[j]), R, ga_T, px,
                            py, means2d, conics, opac, feats, xs, ys, a_max, grad_feat, acc,
                        )  # fmt: skip
                    continue
                p = (py - y0) * tile_size + (px - x0)
                s0 = begin[p]
                T = one  # the sort keys are spent: their slots take the transmittances
                for j in range(s0, s0 + m_used):
                    cand_key[j] = T
                    alpha = opac[gauss_ids[lo + cand_i[j]]] * cand_g[j]
                    if alpha > a_max:
                        alpha = a_max
                    T = T * (one - alpha)
                for j in range(s0 + m_used - 1, s0 - 1, -1):
                    k = cand_i[j]
                    R = _contribution_backward(
                        k, gauss_ids[lo + k], cand_g[j], cand_key[j], R, ga_T, px, py, means2d,
                        conics, opac, feats, xs, ys, a_max, grad_feat, acc,
                    )  # fmt: skip
        for k in range(hi - lo):
            g = gauss_ids[lo + k]
            for q in range(n_q):
                gbuf[w, g, q] += acc[k, q]


# Memory the forward may keep its composited runs in for the backward (which otherwise
# rebuilds them: about half its time); a tile whose runs do not fit is rebuilt. 12 bytes
# an entry in float32: 8M entries, 32 a pixel at 512².
RUN_STORE_BYTES = 96 * 2**20


def _run_room(n_tiles: int, npdt: type) -> int:
    """Entries a tile may keep: an equal share of the budget (the buffers are allocated
    untouched, so only what the runs fill costs memory)."""
    per_entry = 4 + 2 * np.dtype(npdt).itemsize
    return int(RUN_STORE_BYTES // max(1, n_tiles * per_entry))


# The kept runs' buffers, reused from step to step so their pages stay mapped (a fresh
# store paid about 2 ms of page faults per MiB it filled): a training step has two
# forwards (the view and its neighbour) waiting for their backwards, four arrays each.
_RUNS = BufferPool(keep=8)


def _take_runs(entries: int, pixels: int, npdt: type) -> tuple[np.ndarray, ...]:
    """Pooled flat buffers for a forward's kept runs: places, exp(power), transmittances
    and each pixel's start."""
    return (
        _RUNS.take(entries, np.int32),
        _RUNS.take(entries, npdt),
        _RUNS.take(entries, npdt),
        _RUNS.take(pixels, np.int64),
    )


def _kept_views(pooled: tuple[np.ndarray, ...], entries: int, height: int, width: int):
    """The kernels' views of the pooled buffers."""
    k, G, T, at = pooled
    return k[:entries], G[:entries], T[:entries], at[: height * width].reshape(height, width)


def _no_runs(npdt: type) -> tuple[np.ndarray, ...]:
    """Nothing kept (no gradient wanted): empty arrays of the kernels' types."""
    return (
        np.empty(0, np.int32),
        np.empty(0, npdt),
        np.empty(0, npdt),
        np.empty((0, 0), np.int64),
    )


def _give_runs(ctx) -> None:
    """Return a forward's run buffers to the pool once its backward has read them; a
    second backward (retain_graph) then rebuilds every tile instead of reading them."""
    if ctx.pooled:
        ctx.state[-1][:] = 0  # tile_kept: nothing kept any more
        for buf in ctx.pooled:
            _RUNS.give(buf)
        ctx.pooled = ()


class PlaneOrderComposite(torch.autograd.Function):
    """Differentiable plane-order compositing on the CPU (numba, pixel-major)."""

    @staticmethod
    def forward(
        ctx,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        features: Tensor,
        bins: TileBins,
        width: int,
        height: int,
        order: PlaneKeys,
        keep_runs: bool = True,
    ) -> tuple[Tensor, Tensor]:
        dtype = _compute_dtype(means2d, conics, opacities, features)
        n_ch = features.shape[1]
        npdt = np.float32 if dtype == torch.float32 else np.float64
        out_feat = zeros_touched((height, width, n_ch), npdt)
        out_T = np.ones((height, width), npdt)
        out_last = zeros_touched((height, width), np.int32)
        setup = None
        extra: tuple = ()
        ctx.pooled = ()
        if bins.gauss_ids.numel() > 0 and n_ch > 0:
            setup = _Setup(means2d, conics, opacities, features, bins, width, height, dtype)
            intr = np.array([order.fx, order.fy, order.cx, order.cy], np.float64)
            planes = order.planes.detach().to(torch.float64).contiguous().numpy()
            extra = (planes, intr)
            n_tiles = int(bins.offsets.numel()) - 1
            room = _run_room(n_tiles, npdt) if keep_runs else 0
            pooled = _take_runs(n_tiles * room, height * width, npdt) if room > 0 else ()
            runs = (
                *(_kept_views(pooled, n_tiles * room, height, width) if pooled else _no_runs(npdt)),
                np.zeros(n_tiles, np.int8),
            )
            args = (*setup.args(), *extra, out_feat, out_T, out_last, *runs)
            run_workers(_forward_worker, kernel_threads(), args)
            ctx.pooled = pooled
        ctx.save_for_backward(means2d, conics, opacities, features)
        ctx.setup, ctx.extra = setup, extra
        ctx.meta = (dtype, width, height, n_ch)
        ctx.in_dtypes = (means2d.dtype, conics.dtype, opacities.dtype, features.dtype)
        ctx.shapes = (means2d.shape, conics.shape, opacities.shape, features.shape)
        ctx.state = (out_T, out_last, *runs) if setup is not None else None
        return torch.from_numpy(out_feat), 1.0 - torch.from_numpy(out_T)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_feat: Tensor | None, grad_alpha: Tensor | None):
        ctx.saved_tensors  # noqa: B018  (raises if an input was modified in place)
        dtype, width, height, n_ch = ctx.meta
        setup: _Setup | None = ctx.setup
        shapes, in_dtypes = ctx.shapes, ctx.in_dtypes
        n = shapes[0][0]
        n_workers = kernel_threads() if setup is not None and n > 0 else 1
        with scratch_zeros((n_workers, n, 6 + n_ch)) as gbuf:
            if setup is not None and n > 0:
                out_T, out_last, *runs = ctx.state
                gf = (
                    np.zeros((height, width, n_ch), out_T.dtype)
                    if grad_feat is None
                    else _np(grad_feat, dtype)
                )
                ga = (
                    np.zeros((height, width), out_T.dtype)
                    if grad_alpha is None
                    else _np(grad_alpha, dtype)
                )
                args = (*setup.args(), *ctx.extra, out_T, out_last, *runs, gf, ga, gbuf)
                run_workers(_backward_worker, n_workers, args)
                _give_runs(ctx)
            widths = (_G_A - _G_MX, _G_O - _G_A, _G_F - _G_O, n_ch)
            parts = [
                np.empty((n, w), store_dtype(d)) for w, d in zip(widths, in_dtypes, strict=True)
            ]
            run_ranges(_reduce_split_range, n, (gbuf, *parts))
            out = [
                torch.from_numpy(g).to(d).reshape(s) if need else None
                for g, s, d, need in zip(
                    parts, shapes, in_dtypes, ctx.needs_input_grad[:4], strict=True
                )
            ]
        return (*out, None, None, None, None, None)


def rasterize_cpu_plane(
    proj: Projected,
    opacities: Tensor,
    features: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    order: PlaneKeys,
) -> tuple[Tensor, Tensor]:
    """The compiled backend's compositing in per-pixel plane order (float32 or float64)."""
    tensors = (proj.means2d, proj.conics, opacities.reshape(-1), features)
    keep = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    feats, alpha = PlaneOrderComposite.apply(*tensors, bins, width, height, order, keep)
    return feats.to(features.dtype), alpha.to(features.dtype)
