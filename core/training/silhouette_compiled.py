"""The silhouette points' depth term (``silhouette.SilhouetteDepth``) as one compiled pass,
with its backward, for training on the CPU.

Per step and view the torch path reads the rendered depth and coverage at each point's
four bilinear taps (eight gathers), forms the gap in pixel footprints, masks the points
that are hidden, floating or uncovered, and averages |gap|: some thirty small ops and,
backward, four index scatters into zeroed depth-sized buffers. Here one loop gives the
mean and keeps each counted point's sign; the backward scatters sign / (count ·
footprint) through the four taps' weights into one depth gradient. Same formulas and
masks as the torch path, float64 inside (``tests/test_silhouette.py``,
``test_the_compiled_term_matches_the_torch_path``, holds the value and gradient to it).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.render.depth_geometry import BilinearTaps

__all__ = ["nearest_samples_compiled", "silhouette_gap_compiled"]


@njit(nogil=True, cache=True, inline="always")
def _tap(flat, i00, w, fx, fy):  # pragma: no cover - numba
    v00, v01 = np.float64(flat[i00]), np.float64(flat[i00 + 1])
    v10, v11 = np.float64(flat[i00 + w]), np.float64(flat[i00 + w + 1])
    return (v00 * (1.0 - fx) + v01 * fx) * (1.0 - fy) + (v10 * (1.0 - fx) + v11 * fx) * fy


@njit(nogil=True, cache=True)
def _forward(
    depth, valid, width, i00, fxs, fys, inside, z, focal, occluded, floating, sign
):  # pragma: no cover - numba
    """Mean |gap| over the counted points and how many; ``sign[k]`` the counted point's
    sign of gap (0 where not counted, and where the gap is exactly 0, as torch's abs)."""
    total = 0.0
    count = 0
    for k in range(i00.shape[0]):
        sign[k] = 0.0
        if not inside[k]:
            continue
        fx, fy, i = np.float64(fxs[k]), np.float64(fys[k]), i00[k]
        if not _tap(valid, i, width, fx, fy) > 0.999:
            continue
        zk = np.float64(z[k])
        gap = (_tap(depth, i, width, fx, fy) - zk) / (zk / focal)
        if not (gap > -occluded and gap < floating):
            continue
        total += abs(gap)
        count += 1
        sign[k] = 1.0 if gap > 0 else (-1.0 if gap < 0 else 0.0)
    return total / max(count, 1), count


@njit(nogil=True, cache=True)
def _backward(g_depth, width, i00, fxs, fys, z, focal, sign, scale):  # pragma: no cover
    for k in range(i00.shape[0]):
        s = sign[k]
        if s == 0.0:
            continue
        fx, fy, i = np.float64(fxs[k]), np.float64(fys[k]), i00[k]
        g = scale * s / (np.float64(z[k]) / focal)
        g_depth[i] += g * (1.0 - fx) * (1.0 - fy)
        g_depth[i + 1] += g * fx * (1.0 - fy)
        g_depth[i + width] += g * (1.0 - fx) * fy
        g_depth[i + width + 1] += g * fx * fy


class _SilhouetteGap(torch.autograd.Function):
    @staticmethod
    def forward(ctx, depth, valid, taps, z, focal, occluded, floating):  # type: ignore[override]
        flat = depth.detach().contiguous().reshape(-1).numpy()
        cover = valid.detach().to(depth.dtype).contiguous().reshape(-1).numpy()
        arrays = (
            taps.i00.contiguous().numpy(), taps.fx.contiguous().numpy(),
            taps.fy.contiguous().numpy(), taps.inside.contiguous().numpy(),
        )  # fmt: skip
        z_np = z.detach().contiguous().numpy()
        sign = np.empty(z_np.shape[0], np.float64)
        mean, count = _forward(
            flat, cover, taps.width, *arrays, z_np, focal, occluded, floating, sign
        )
        ctx.meta = (taps.width, arrays[:3], z_np, focal, sign, count, depth.shape)
        return torch.tensor(mean, dtype=depth.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        width, (i00, fxs, fys), z_np, focal, sign, count, shape = ctx.meta
        g_depth = np.zeros(int(np.prod(shape)), np.float64)
        if count > 0:
            scale = float(grad) / count
            _backward(g_depth, width, i00, fxs, fys, z_np, focal, sign, scale)
        g = torch.from_numpy(g_depth).to(grad.dtype).reshape(shape)
        return g, None, None, None, None, None, None


def silhouette_gap_compiled(
    depth: Tensor, valid: Tensor, taps: BilinearTaps, z: Tensor, focal: float,
    occluded: float, floating: float,
) -> Tensor:  # fmt: skip
    """Mean |rendered − point depth| in pixel footprints (``z / focal``) over the points
    whose taps are inside the image, fully covered (> 0.999), and whose gap lies in
    (−``occluded``, ``floating``); 0 (with zero gradient) when none is. Differentiable
    in ``depth`` (H, W), a CPU float tensor."""
    return _SilhouetteGap.apply(depth, valid, taps, z, focal, occluded, floating)


@njit(nogil=True, cache=True)
def _local_mean(flat, cover, height, width, out):  # pragma: no cover - numba
    """out: the mean of the covered depth over each pixel's 3×3 neighbourhood (0 where
    none is covered), as ``silhouette._local_mean``; box sums by rows, then columns."""
    num_r = np.empty(height * width, np.float64)
    den_r = np.empty(height * width, np.float64)
    for y in range(height):
        row = y * width
        for x in range(width):
            n, d = 0.0, 0.0
            for xx in range(max(x - 1, 0), min(x + 2, width)):
                c = np.float64(cover[row + xx])
                n += np.float64(flat[row + xx]) * c
                d += c
            num_r[row + x], den_r[row + x] = n, d
    for y in range(height):
        for x in range(width):
            n, d = 0.0, 0.0
            for yy in range(max(y - 1, 0), min(y + 2, height)):
                n += num_r[yy * width + x]
                d += den_r[yy * width + x]
            out[y * width + x] = n / d if d > 0.0 else 0.0


@njit(nogil=True, cache=True)
def _nearest(
    flat,
    cover,
    height,
    width,
    i00,
    fxs,
    fys,
    inside,
    z,
    focal,
    samples,
    occluded,
    margin,
    pick,
):  # pragma: no cover - numba
    """pick[r]: the flat index of ray r's sample with the smallest gap on the 3×3 means
    among those inside, covered and not hidden, unless the middle sample is one of them
    and no more than ``margin`` footprints farther; −1 where none is."""
    mean = np.empty(height * width, np.float64)
    _local_mean(flat, cover, height, width, mean)
    middle = samples // 2
    for r in range(pick.shape[0]):
        best, arg, at_middle = np.inf, -1, np.inf
        for k in range(r * samples, (r + 1) * samples):
            if not inside[k]:
                continue
            fx, fy, i = np.float64(fxs[k]), np.float64(fys[k]), i00[k]
            if not _tap(cover, i, width, fx, fy) > 0.999:
                continue
            zk = np.float64(z[k])
            gap = (_tap(mean, i, width, fx, fy) - zk) / (zk / focal)
            if not gap > -occluded:
                continue
            if k - r * samples == middle:
                at_middle = gap
            if gap < best:
                best, arg = gap, k
        if arg >= 0 and at_middle <= best + margin:
            arg = r * samples + middle
        pick[r] = arg


def nearest_samples_compiled(
    depth: Tensor, valid: Tensor, taps: BilinearTaps, z: Tensor, focal: float,
    samples: int, occluded: float, margin: float,
) -> Tensor:  # fmt: skip
    """Indices (into the taps) of each ray's chord sample nearest the rendered surface,
    for the rays that have one: ``SilhouetteDepth._touching``'s choice in one pass
    (torch's ``avg_pool2d`` for the 3×3 means took 0.5 ms at 128² and 22 ms at 800² on
    one thread)."""
    flat = depth.detach().contiguous().reshape(-1).numpy()
    cover = valid.detach().to(depth.dtype).contiguous().reshape(-1).numpy()
    pick = np.empty(z.shape[0] // samples, np.int64)
    _nearest(
        flat, cover, depth.shape[0], depth.shape[1], taps.i00.contiguous().numpy(),
        taps.fx.contiguous().numpy(), taps.fy.contiguous().numpy(),
        taps.inside.contiguous().numpy(), z.detach().contiguous().numpy(), focal, samples,
        occluded, margin, pick,
    )  # fmt: skip
    out = torch.from_numpy(pick)
    return out[out >= 0]
