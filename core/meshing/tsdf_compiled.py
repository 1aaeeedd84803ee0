"""One view's TSDF update as one compiled pass over the band's voxels (CPU).

``TSDFVolume.integrate`` in torch projects every voxel of the narrow band, looks its
depth up between pixel centres (:func:`core.meshing.tsdf.interpolated_depth`) and
updates the voxels the view sees: some thirty band-sized temporaries per view, about
0.2 s a view for a 128² teapot's band, 13 s of the 40 s a `glint train` spends after
its last step (docs/benchmarks.md). Here each voxel is projected, looked up and
updated in one loop iteration, on the kernel threads (a voxel is written by its own
iteration only, so the threads never meet). Same definition as the torch code, which
stays the reference (``integrate(..., compiled=False)``); float32 like it, so the two
agree to rounding (``tests/test_tsdf_compiled.py``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from core.kernels.pool import run_ranges

__all__ = ["integrate_compiled"]

_F0, _F1, _HALF = np.float32(0.0), np.float32(1.0), np.float32(0.5)
_TINY = np.float32(1e-6)


@njit(nogil=True, cache=True, inline="always")
def _raise_hull(hull, m, dist_px, margin, scale):  # pragma: no cover - numba
    """tsdf.hull_bound: hull[m] = max(hull[m], min((dist_px − margin)⁺ · scale, 1))."""
    bound = min(max(dist_px - margin, _F0) * scale, _F1)
    if bound > hull[m]:
        hull[m] = bound


@njit(nogil=True, cache=True)
def _integrate_range(  # pragma: no cover - numba
    lo, hi, points, P, depth, valid, empty, view_w, color, hull_dist, flags, W, H, jump,
    margin, hull_scale, trunc, tsdf, weight, col, col_w, hull,
):  # fmt: skip
    has_empty, has_w, has_color, has_hull = flags[0], flags[1], flags[2], flags[3]
    for m in range(lo, hi):
        x, y, z = points[m, 0], points[m, 1], points[m, 2]
        uz = x * P[0, 0] + y * P[0, 1] + z * P[0, 2] + P[0, 3]
        vz = x * P[1, 0] + y * P[1, 1] + z * P[1, 2] + P[1, 3]
        zz = x * P[2, 0] + y * P[2, 1] + z * P[2, 2] + P[2, 3]
        if not zz > _TINY:
            continue
        uf, vf = uz / zz, vz / zz
        u, v = math.floor(uf), math.floor(vf)
        if not (u >= 0 and u < W and v >= 0 and v < H):
            continue
        pix = int(v) * W + int(u)
        d = depth[pix]
        if W >= 2 and H >= 2:  # interpolated_depth (and bilinear_at for the hull)
            uc, vc = uf - _HALF, vf - _HALF
            i0 = min(max(math.floor(uc), 0), W - 2)
            j0 = min(max(math.floor(vc), 0), H - 2)
            fu = min(max(uc - np.float32(i0), _F0), _F1)
            fv = min(max(vc - np.float32(j0), _F0), _F1)
            b = int(j0) * W + int(i0)
            if has_hull:
                top = hull_dist[b] * (_F1 - fu) + hull_dist[b + 1] * fu
                bottom = hull_dist[b + W] * (_F1 - fu) + hull_dist[b + W + 1] * fu
                _raise_hull(hull, m, top * (_F1 - fv) + bottom * fv, margin, zz * hull_scale)
            d0, d1, d2, d3 = depth[b], depth[b + 1], depth[b + W], depth[b + W + 1]
            hi_d = max(max(d0, d1), max(d2, d3))
            lo_d = min(min(d0, d1), min(d2, d3))
            ok = valid[b] and valid[b + 1] and valid[b + W] and valid[b + W + 1]
            if ok and hi_d - lo_d <= jump * d:
                top = d0 * (_F1 - fu) + d1 * fu
                bottom = d2 * (_F1 - fu) + d3 * fu
                d = top * (_F1 - fv) + bottom * fv
        elif has_hull:
            _raise_hull(hull, m, hull_dist[pix], margin, zz * hull_scale)
        sdf = d - zz
        upd = valid[pix] and sdf > -trunc
        obs = min(sdf / trunc, _F1)
        free = False
        if has_empty and empty[pix] and not upd:
            free, upd, obs = True, True, _F1
        if not upd:
            continue
        wo = view_w[pix] if has_w and not free else _F1
        w = weight[m]
        tsdf[m] = (tsdf[m] * w + obs * wo) / (w + wo)
        weight[m] = w + wo
        if has_color and valid[pix] and abs(sdf) < trunc:
            cw = col_w[m]
            for c in range(3):
                col[m, c] = (col[m, c] * cw + color[pix, c]) / (cw + _F1)
            col_w[m] = cw + _F1


def integrate_compiled(
    points: np.ndarray,
    P: np.ndarray,
    depth: np.ndarray,
    valid: np.ndarray,
    empty: np.ndarray | None,
    view_w: np.ndarray | None,
    color: np.ndarray | None,
    hull_dist: np.ndarray | None,
    W: int,
    H: int,
    focal: float,
    jump_px: float,
    margin_px: float,
    trunc: float,
    tsdf: np.ndarray,
    weight: np.ndarray,
    col: np.ndarray,
    col_w: np.ndarray,
    hull: np.ndarray | None,
) -> None:
    """Update ``tsdf``, ``weight``, ``col``, ``col_w`` and the lower bounds ``hull``
    (the band's, float32) in place with one view: ``points`` (M, 3) voxel centres,
    ``P`` (3, 4) = K [R | t], flat (H·W,) ``depth``/``valid`` and the optional carving
    mask, pixel weights, colours (H·W, 3) and mask-hull distances. ``jump_px``: the
    corners' depth spread, in footprints, above which the nearest pixel's depth is
    used instead of the bilinear one; ``margin_px``: tsdf.HULL_MARGIN_PX."""
    f32 = np.float32
    none_b, none_f = np.zeros(1, np.bool_), np.zeros(1, f32)
    flags = np.array(
        [empty is not None, view_w is not None, color is not None, hull_dist is not None],
        np.bool_,
    )
    args = (
        points, P.astype(f32), depth, valid,
        none_b if empty is None else empty,
        none_f if view_w is None else view_w,
        np.zeros((1, 3), f32) if color is None else color,
        none_f if hull_dist is None else hull_dist,
        flags, int(W), int(H), f32(f32(jump_px) / f32(focal)), f32(margin_px),
        f32(f32(1.0) / (f32(focal) * f32(trunc))), f32(trunc),
        tsdf, weight, col, col_w, none_f if hull is None else hull,
    )  # fmt: skip
    run_ranges(_integrate_range, points.shape[0], args)
