"""The per-view opacity factors in one compiled pass, for CPU models.

``core.render.orientation.facing`` and ``core.render.grazing.grazing_factor`` are about
thirty small torch ops over (N, 3) tensors (norms, a sort of the log-scales, masks),
run for both views of every training step and for every frame: 5.6 ms of a 60 ms
multi-view step at 20k Gaussians (docs/bench/step_breakdown.md), nearly all of it
forward, for factors no gradient reaches except the fade's through its logits. Here
one loop per Gaussian gives the cull (0/1) and the fade's angle term
``(1 − |cos θ|)^p``; the caller applies ``1 − sigmoid(logits) · term`` in torch, so the
logits keep their gradient. Same formulas as those functions, in float64
(``tests/test_view_opacity_compiled.py`` checks both against them).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor

from core.kernels.pool import run_ranges
from core.render import orientation as ori

__all__ = ["view_factors"]

_LOG_FLAT = math.log(ori.MAX_FLATNESS)


@njit(nogil=True, cache=True)
def _factors_range(
    lo, hi, normals, means, seen, count, log_scales, centre, consts, cull, angle,
):  # fmt: skip  # pragma: no cover - numba
    """Rows [lo, hi): ``cull`` (1 kept, 0 culled) when it has rows, ``angle`` likewise.

    consts: log(MAX_FLATNESS), MIN_VIEWS, MIN_AGREEMENT, MIN_SIDE_COS, exponent."""
    do_cull = cull.shape[0] > 0
    do_angle = angle.shape[0] > 0
    log_flat, min_views, min_agree, min_side, expo = (
        consts[0], consts[1], consts[2], consts[3], consts[4],
    )  # fmt: skip
    for i in range(lo, hi):
        nx, ny, nz = np.float64(normals[i, 0]), np.float64(normals[i, 1]), np.float64(normals[i, 2])
        tx = centre[0] - np.float64(means[i, 0])
        ty = centre[1] - np.float64(means[i, 1])
        tz = centre[2] - np.float64(means[i, 2])
        if do_cull:
            sx, sy, sz = np.float64(seen[i, 0]), np.float64(seen[i, 1]), np.float64(seen[i, 2])
            seen_len = math.sqrt(sx * sx + sy * sy + sz * sz)
            side = nx * sx + ny * sy + nz * sz
            a, b, c = (
                np.float64(log_scales[i, 0]), np.float64(log_scales[i, 1]),
                np.float64(log_scales[i, 2]),
            )  # fmt: skip
            # smallest and middle of three
            if a > b:
                a, b = b, a
            if b > c:
                b = c
            if a > b:
                a, b = b, a
            n_seen = np.float64(count[i])
            known = (
                a - b <= log_flat
                and n_seen >= min_views
                and seen_len >= min_agree * n_seen
                and abs(side) >= min_side * seen_len
            )
            sgn = 1.0 if side > 0 else (-1.0 if side < 0 else 0.0)
            back = known and sgn * (nx * tx + ny * ty + nz * tz) < 0.0
            cull[i] = 0.0 if back else 1.0
        if do_angle:
            denom = max(
                math.sqrt(nx * nx + ny * ny + nz * nz) * math.sqrt(tx * tx + ty * ty + tz * tz),
                1e-12,
            )
            cos = abs(nx * tx + ny * ty + nz * tz) / denom
            if cos > 1.0:
                cos = 1.0
            angle[i] = (1.0 - cos) ** expo


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def view_factors(
    normals: Tensor,
    means: Tensor,
    camera_centre: Tensor,
    *,
    seen: Tensor | None,
    count: Tensor | None,
    log_scales: Tensor | None,
    exponent: float | None,
) -> tuple[Tensor | None, Tensor | None]:
    """(cull, angle term), each (N,) in the inputs' dtype or None when not asked for.

    ``seen``/``count``/``log_scales``: the orientation state (None: no culling);
    ``exponent``: the fade's (None: no angle term). CPU tensors only."""
    n = means.shape[0]
    dtype = np.float32 if means.dtype == torch.float32 else np.float64
    do_cull = seen is not None and count is not None and log_scales is not None
    cull = np.empty(n if do_cull else 0, dtype)
    angle = np.empty(n if exponent is not None else 0, dtype)
    empty3 = np.empty((0, 3), dtype)
    consts = np.array(
        [_LOG_FLAT, ori.MIN_VIEWS, ori.MIN_AGREEMENT, ori.MIN_SIDE_COS, exponent or 1.0]
    )
    centre = camera_centre.detach().to(torch.float64).reshape(3).numpy()
    args = (
        _np(normals), _np(means),
        _np(seen) if do_cull else empty3,
        _np(count) if do_cull else np.empty(0, dtype),
        _np(log_scales) if do_cull else empty3,
        centre, consts, cull, angle,
    )  # fmt: skip
    run_ranges(_factors_range, n, args)
    return (
        torch.from_numpy(cull) if do_cull else None,
        torch.from_numpy(angle) if exponent is not None else None,
    )
