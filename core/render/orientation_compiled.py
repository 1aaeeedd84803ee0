"""The one-sided splats' per-step visibility record in one compiled pass (CPU models).

``core.render.orientation.record_visibility`` projects every centre, reads the view's
depth and valid mask bilinearly and adds the direction to the camera to the splats on
the rendered surface: about twenty torch ops over the model plus two gathers, 2.2 ms of
a 60 ms multi-view step at 20k Gaussians (docs/bench/step_breakdown.md), all forward.
Here one loop per Gaussian does it and adds to the sums in place (each row is its own,
so the threads never share one). Same formulas, in float64
(``tests/test_orientation_compiled.py`` checks it against the torch function).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor

from core.kernels.pool import run_ranges
from core.scene.cameras import Camera

__all__ = ["record_compiled"]


@njit(nogil=True, cache=True, inline="always")
def _bilinear(img, x, y):  # pragma: no cover - numba
    """``depth_geometry.bilinear_lookup`` of one point (x, y already minus 0.5, finite)."""
    h, w = img.shape
    x0 = min(max(math.floor(x), 0.0), max(w - 2, 0))
    y0 = min(max(math.floor(y), 0.0), max(h - 2, 0))
    fx = min(max(x - x0, 0.0), 1.0)
    fy = min(max(y - y0, 0.0), 1.0)
    i, j = int(x0), int(y0)
    i1, j1 = min(i + 1, w - 1), min(j + 1, h - 1)  # a 1-px image: bilinear_lookup's flat[i+1]
    v00, v01 = np.float64(img[j, i]), np.float64(img[j, i1])
    v10, v11 = np.float64(img[j1, i]), np.float64(img[j1, i1])
    return (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy


@njit(nogil=True, cache=True)
def _record_range(
    lo, hi, means, depth, valid, rot, trans, intr, centre, tol_px, seen, count, hits,
):  # fmt: skip  # pragma: no cover - numba
    """Rows [lo, hi): add the unit direction to the camera where the centre is on the
    rendered surface; ``hits[lo]`` gets how many (one slot per range)."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    h, w = depth.shape
    n_hit = 0
    for g in range(lo, hi):
        mx, my, mz = np.float64(means[g, 0]), np.float64(means[g, 1]), np.float64(means[g, 2])
        px = rot[0, 0] * mx + rot[0, 1] * my + rot[0, 2] * mz + trans[0]
        py = rot[1, 0] * mx + rot[1, 1] * my + rot[1, 2] * mz + trans[1]
        z = rot[2, 0] * mx + rot[2, 1] * my + rot[2, 2] * mz + trans[2]
        if not z > 0.0:
            continue
        x = fx * px / z + cx - 0.5
        y = fy * py / z + cy - 0.5
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        if x < 0.0 or y < 0.0 or x > w - 1 or y > h - 1:
            continue
        if not _bilinear(valid, x, y) > 0.999:
            continue
        if not z <= _bilinear(depth, x, y) + tol_px * (z / fx):
            continue
        tx, ty, tz = centre[0] - mx, centre[1] - my, centre[2] - mz
        inv = 1.0 / math.sqrt(tx * tx + ty * ty + tz * tz)
        seen[g, 0] += tx * inv
        seen[g, 1] += ty * inv
        seen[g, 2] += tz * inv
        count[g] += 1.0
        n_hit += 1
    hits[lo] = n_hit


def record_compiled(
    means: Tensor, seen: Tensor, count: Tensor, camera: Camera, depth: Tensor, valid: Tensor,
    tol_px: float,
) -> int:  # fmt: skip
    """Add this view's directions into ``seen`` (N, 3) and ``count`` (N,) in place
    (contiguous CPU tensors); returns how many Gaussians were on its surface."""
    if not (seen.is_contiguous() and count.is_contiguous()):
        raise ValueError("the visibility sums must be contiguous to be updated in place")
    n = means.shape[0]
    hits = np.zeros(max(n, 1), np.int64)
    intr = camera.intrinsics
    args = (
        means.detach().contiguous().numpy(),
        depth.detach().contiguous().numpy(),
        valid.detach().to(depth.dtype).contiguous().numpy(),
        camera.R.detach().to(torch.float64).contiguous().numpy(),
        camera.t.detach().to(torch.float64).reshape(3).contiguous().numpy(),
        np.array([intr.fx, intr.fy, intr.cx, intr.cy], np.float64),
        camera.center.detach().to(torch.float64).reshape(3).numpy(),
        float(tol_px),
        seen.detach().numpy(),
        count.detach().numpy(),
        hits,
    )
    run_ranges(_record_range, n, args)
    return int(hits.sum())
