"""The visual-hull test of :func:`core.training.init_points.inside_hull` in one compiled
pass (CPU).

Finding the initial points and the silhouette points asks "inside the masks of the
views that see it?" of every ray-march sample and bisection point: in torch that is a
projection and a bilinear mask lookup per view over all the points, 150 rounds of 64
views for a 128² object, 9 of the 10 s a run spends before its first step
(docs/benchmarks.md). Here each point walks the views in one loop on the kernel
threads, and stops at the view after which it can no longer pass (most ray-march
samples lie outside the hull, and a 0.9 fraction rules them out after a few views:
the same answer, exactly). The same arithmetic as the torch code, which stays the reference
(``inside_hull(..., compiled=False)``): the projection in float64, the lookup in the
masks' float32 (``tests/test_init_points_compiled.py``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor

from core.kernels.pool import run_ranges
from core.scene.views import View

__all__ = ["inside_hull_compiled"]

_F0, _F1, _HALF = np.float32(0.0), np.float32(1.0), np.float32(0.5)


@njit(nogil=True, cache=True, inline="always")
def _can_pass(seen, inside, remaining, frac):  # pragma: no cover - numba
    """Whether the final test ``seen > 0 and inside >= frac·seen`` can still hold after
    ``remaining`` more views. Each further view adds 1 to both counts (seen inside) or
    nothing (not seen); inside − frac·seen moves one way with that count, so the best
    case is one of the two ends: all remaining views inside, or none seen."""
    if seen + remaining > 0 and inside + remaining >= frac * (seen + remaining):
        return True
    return seen > 0 and inside >= frac * seen


@njit(nogil=True, cache=True)
def _inside_range(  # pragma: no cover - numba
    lo, hi, pts, R, t, intr, sizes, offsets, masks, min_fraction, out
):  # fmt: skip
    n_views = R.shape[0]
    frac = np.float32(min_fraction)
    for m in range(lo, hi):
        x, y, z = pts[m, 0], pts[m, 1], pts[m, 2]
        seen = np.float32(0.0)
        inside = np.float32(0.0)
        for vi in range(n_views):
            pz = x * R[vi, 2, 0] + y * R[vi, 2, 1] + z * R[vi, 2, 2] + t[vi, 2]
            if not pz > 0:  # behind the camera (or NaN): not seen, and no division by 0
                continue
            px = x * R[vi, 0, 0] + y * R[vi, 0, 1] + z * R[vi, 0, 2] + t[vi, 0]
            py = x * R[vi, 1, 0] + y * R[vi, 1, 1] + z * R[vi, 1, 2] + t[vi, 1]
            u = np.float32(intr[vi, 0] * px / pz + intr[vi, 2]) - _HALF
            v = np.float32(intr[vi, 1] * py / pz + intr[vi, 3]) - _HALF
            W, H = sizes[vi, 0], sizes[vi, 1]
            if not (math.isfinite(u) and math.isfinite(v)):
                continue
            if not (u >= 0 and v >= 0 and u <= W - 1 and v <= H - 1):
                continue
            seen += _F1
            x0 = min(max(math.floor(u), 0), max(W - 2, 0))
            y0 = min(max(math.floor(v), 0), max(H - 2, 0))
            fx = min(max(u - np.float32(x0), _F0), _F1)
            fy = min(max(v - np.float32(y0), _F0), _F1)
            b = offsets[vi] + int(y0) * W + int(x0)
            val = (masks[b] * (_F1 - fx) + masks[b + 1] * fx) * (_F1 - fy) + (
                masks[b + W] * (_F1 - fx) + masks[b + W + 1] * fx
            ) * fy
            if val > _HALF:
                inside += _F1
            elif not _can_pass(seen, inside, np.float32(n_views - vi - 1), frac):
                break  # outside too many views already: no remaining views can save it
        out[m] = seen > 0 and inside >= frac * seen


def compilable(points: Tensor, views: list[View]) -> bool:
    """The compiled pass covers float64 CPU points and float32 masks of at least 2×2
    pixels (the reference's bilinear lookup needs two pixel centres each way)."""
    return (
        points.device.type == "cpu"
        and points.dtype == torch.float64
        and all(
            v.mask is not None
            and v.mask.dtype == torch.float32
            and v.mask.device.type == "cpu"
            and min(v.mask.shape) >= 2
            for v in views
        )
    )


def inside_hull_compiled(points: Tensor, views: list[View], min_fraction: float) -> Tensor:
    """(M,) bool as :func:`core.training.init_points.inside_hull` for ``views`` (all
    masked; see :func:`compilable`)."""
    n = points.shape[0]
    R = np.stack([v.camera.R.to(torch.float64).numpy() for v in views])
    t = np.stack([v.camera.t.to(torch.float64).numpy() for v in views])
    intr = np.array(
        [[c.intrinsics.fx, c.intrinsics.fy, c.intrinsics.cx, c.intrinsics.cy]
         for c in (v.camera for v in views)], np.float64,
    )  # fmt: skip
    sizes = np.array([[v.mask.shape[1], v.mask.shape[0]] for v in views], np.int64)
    counts = sizes[:, 0] * sizes[:, 1]
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    masks = np.concatenate([v.mask.contiguous().reshape(-1).numpy() for v in views])
    out = np.zeros(n, np.bool_)
    pts = points.contiguous().numpy()
    args = (pts, R, t, intr, sizes, offsets, masks, float(min_fraction), out)
    run_ranges(_inside_range, n, args)
    return torch.from_numpy(out)
