"""Roughness-aware cube lookup (``envmap_mips.sample_cube_lod``) as one compiled pass
per pixel, forward and backward, for training on the CPU.

The torch path is about thirty image-sized ops (face selection, two levels' tap
coordinates, two gathers, the lerps, the masks) and their autograd: 7.6 ms forward
and backward of a 60 ms multi-view step at 128² (docs/bench/step_breakdown.md), the
largest stage outside the rasteriser. Here a numba loop reads both levels per pixel
and a second one writes the gradients by hand: into the packed padded levels (each
worker into its own buffer, summed after), the reflected directions (through the face
projection u = sc/ma, v = tc/ma) and the LOD. The mip chain and its padding are built
(and their gradient taken back to the texels) by ``envmap_pack_compiled``.

Same formulas and guards as the torch path: an invalid direction (non-finite, or its
largest component below ``min_major``) returns 0 and passes no gradient; the LOD is
clamped to [0, levels − 1] (no gradient outside, a NaN LOD gives NaN); ties between
axes go to the lower one. Float64 inside (``tests/test_envmap_lookup_compiled.py``
holds it to the torch path, values and gradients).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.kernels.pool import kernel_threads, run_ranges, run_workers
from core.render.cube_faces import FACE_TABLE

__all__ = ["sample_packed_lod"]

# per face: major axis, major sign, sc axis, sc sign, tc axis, tc sign
_FACES = np.array(FACE_TABLE, np.int64)


@njit(nogil=True, cache=True, inline="always")
def _face_uv(dx, dy, dz):  # pragma: no cover - numba
    """(face, u, v, ma) of a finite, non-zero direction: the largest |component| picks
    the face (ties to the lower axis), u = sc/ma, v = tc/ma as in ``_FACES``.
    (``shading_compiled._face_st`` is the same selection: numba helpers are not shared
    across files, whose cache would not notice an edit in the other.)"""
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    if ax >= ay and ax >= az:
        if not dx < 0:
            return 0, -dz / ax, -dy / ax, ax
        return 1, dz / ax, -dy / ax, ax
    if ay >= az:
        if not dy < 0:
            return 2, dx / ay, dz / ay, ay
        return 3, dx / ay, -dz / ay, ay
    if not dz < 0:
        return 4, dx / az, -dy / az, az
    return 5, -dx / az, -dy / az, az


@njit(nogil=True, cache=True, inline="always")
def _pixel_setup(dx, dy, dz, lod, n_levels, min_major):  # pragma: no cover - numba
    """(valid, face, u, v, ma, lo, frac, lod_passes_grad) of one pixel (float64 inputs)."""
    valid = (
        math.isfinite(dx) and math.isfinite(dy) and math.isfinite(dz)
        and max(abs(dx), abs(dy), abs(dz)) > min_major
    )  # fmt: skip
    if not valid:
        dx, dy, dz = 0.0, 0.0, 1.0
    f, u, v, ma = _face_uv(dx, dy, dz)
    top = float(n_levels - 1)
    passes = lod >= 0.0 and lod <= top  # torch.clamp's gradient mask (False for NaN)
    lod_c = min(max(lod, 0.0), top) if lod == lod else lod
    lo = 0
    if lod_c == lod_c:
        lo = min(max(math.floor(lod_c), 0), max(n_levels - 2, 0))
    frac = lod_c - lo
    return valid, f, u, v, ma, lo, frac, passes


@njit(nogil=True, cache=True, inline="always")
def _level_tap(u, v, f, lev, offsets, sizes):  # pragma: no cover - numba
    """First flat index, bilinear weights (fx, fy), padded size and half the face size
    of the 2×2 taps at level ``lev`` (``envmap._PaddedBilinear``'s coordinates)."""
    p = sizes[lev]
    half_r = 0.5 * (p - 2.0)
    x = (u + 1.0) * half_r + 0.5
    y = (v + 1.0) * half_r + 0.5
    x0 = min(max(math.floor(x), 0.0), p - 2.0)
    y0 = min(max(math.floor(y), 0.0), p - 2.0)
    return offsets[lev] + f * p * p + int(y0) * p + int(x0), x - x0, y - y0, p, half_r


@njit(nogil=True, cache=True, inline="always")
def _bilinear(flat, i00, p, fx, fy, c):  # pragma: no cover - numba
    t0, t1 = np.float64(flat[i00, c]), np.float64(flat[i00 + 1, c])
    t2, t3 = np.float64(flat[i00 + p, c]), np.float64(flat[i00 + p + 1, c])
    top = t0 + fx * (t1 - t0)
    return top + fy * ((t2 + fx * (t3 - t2)) - top)


@njit(nogil=True, cache=True)
def _forward_rows(
    lo_px, hi_px, flat, dirs, lod, offsets, sizes, min_major, out
):  # pragma: no cover - numba
    """Values of pixels [lo_px, hi_px) into ``out`` (P, C)."""
    n_levels = offsets.shape[0]
    ch = flat.shape[1]
    for i in range(lo_px, hi_px):
        valid, f, u, v, _, lo, frac, _ = _pixel_setup(
            np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2]),
            np.float64(lod[i]), n_levels, min_major,
        )  # fmt: skip
        if not valid:
            for c in range(ch):
                out[i, c] = 0.0
            continue
        a00, afx, afy, ap, _ = _level_tap(u, v, f, lo, offsets, sizes)
        if n_levels == 1:
            for c in range(ch):
                out[i, c] = _bilinear(flat, a00, ap, afx, afy, c)
            continue
        b00, bfx, bfy, bp, _ = _level_tap(u, v, f, lo + 1, offsets, sizes)
        for c in range(ch):
            va = _bilinear(flat, a00, ap, afx, afy, c)
            vb = _bilinear(flat, b00, bp, bfx, bfy, c)
            out[i, c] = va + frac * (vb - va)


@njit(nogil=True, cache=True)
def _backward_part(
    w_id, n_workers, flat, dirs, lod, offsets, sizes, faces, min_major, grad, g_flat,
    g_dirs, g_lod,
):  # fmt: skip  # pragma: no cover - numba
    """Pixels of worker ``w_id``: gradients into ``g_flat[w_id]``, ``g_dirs``, ``g_lod``."""
    n_px = dirs.shape[0]
    step = (n_px + n_workers - 1) // n_workers
    lo_px, hi_px = w_id * step, min((w_id + 1) * step, n_px)
    n_levels = offsets.shape[0]
    ch = flat.shape[1]
    gf = g_flat[w_id]
    for i in range(lo_px, hi_px):
        valid, f, u, v, ma, lo, frac, passes = _pixel_setup(
            np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2]),
            np.float64(lod[i]), n_levels, min_major,
        )  # fmt: skip
        g_dirs[i, 0] = 0.0
        g_dirs[i, 1] = 0.0
        g_dirs[i, 2] = 0.0
        g_lod[i] = 0.0
        if not valid:
            continue
        # a pixel no gradient reaches adds exact zeros everywhere (over a finite map):
        # skipped, as are the uncovered pixels of a training view (specular = w_r ·
        # radiance with w_r = 0 there); a NaN gradient is not zero and goes through
        reached = False
        for c in range(ch):
            if grad[i, c] != 0.0:
                reached = True
                break
        if not reached:
            continue
        n_read = 2 if n_levels > 1 else 1
        du = 0.0
        dv = 0.0
        level_val0 = 0.0
        level_val1 = 0.0
        for k in range(n_read):
            i00, fx, fy, p, half_r = _level_tap(u, v, f, lo + k, offsets, sizes)
            w = (1.0 - frac) if (k == 0 and n_read == 2) else (frac if k == 1 else 1.0)
            gx = 0.0
            gy = 0.0
            val = 0.0
            for c in range(ch):
                g = np.float64(grad[i, c])
                t0, t1 = np.float64(flat[i00, c]), np.float64(flat[i00 + 1, c])
                t2, t3 = np.float64(flat[i00 + p, c]), np.float64(flat[i00 + p + 1, c])
                top = t0 + fx * (t1 - t0)
                bottom = t2 + fx * (t3 - t2)
                val += g * (top + fy * (bottom - top))
                gw = g * w
                gf[i00, c] += gw * (1.0 - fx) * (1.0 - fy)
                gf[i00 + 1, c] += gw * fx * (1.0 - fy)
                gf[i00 + p, c] += gw * (1.0 - fx) * fy
                gf[i00 + p + 1, c] += gw * fx * fy
                d_top, d_bottom = t1 - t0, t3 - t2
                gx += gw * (d_top + fy * (d_bottom - d_top))
                gy += gw * ((t2 - t0) + fx * (d_bottom - d_top))
            if k == 0:
                level_val0 = val
            else:
                level_val1 = val
            du += gx * half_r
            dv += gy * half_r
        if n_read == 2 and passes:
            g_lod[i] = level_val1 - level_val0
        # u = s1 d_a1 / ma, v = s2 d_a2 / ma, ma = sm d_m
        g_dirs[i, faces[f, 2]] += du * faces[f, 3] / ma
        g_dirs[i, faces[f, 4]] += dv * faces[f, 5] / ma
        g_dirs[i, faces[f, 0]] += -(du * u + dv * v) * faces[f, 1] / ma


class _CubeLod(torch.autograd.Function):
    @staticmethod
    def forward(ctx, flat, dirs, lod, offsets, sizes, min_major):  # type: ignore[override]
        n_px = dirs.shape[0]
        f_np = flat.detach().contiguous().numpy()
        out = np.empty((n_px, flat.shape[1]), f_np.dtype)
        d_np = dirs.detach().contiguous().numpy()
        l_np = lod.detach().contiguous().numpy()
        run_ranges(_forward_rows, n_px, (f_np, d_np, l_np, offsets, sizes, min_major, out))
        ctx.save_for_backward(flat, dirs, lod)
        ctx.meta = (offsets, sizes, min_major)
        return torch.from_numpy(out)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        flat, dirs, lod = ctx.saved_tensors
        offsets, sizes, min_major = ctx.meta
        n_px = dirs.shape[0]
        nw = max(1, min(kernel_threads(), n_px))
        g_flat = np.zeros((nw, *flat.shape), np.float64)
        np_dtype = np.float32 if flat.dtype == torch.float32 else np.float64
        g_dirs = np.empty((n_px, 3), np_dtype)
        g_lod = np.empty(n_px, np_dtype)
        args = (
            flat.detach().contiguous().numpy(), dirs.detach().contiguous().numpy(),
            lod.detach().contiguous().numpy(), offsets, sizes, _FACES, min_major,
            grad.detach().contiguous().numpy(), g_flat, g_dirs, g_lod,
        )  # fmt: skip
        run_workers(_backward_part, nw, args)
        return (
            torch.from_numpy(g_flat.sum(0)).to(flat.dtype),
            torch.from_numpy(g_dirs),
            torch.from_numpy(g_lod),
            None,
            None,
            None,
        )


def sample_packed_lod(
    flat: Tensor, offsets: list[int], sizes: list[int], dirs: Tensor, lod: Tensor,
    min_major: float,
) -> Tensor:  # fmt: skip
    """(P, C) radiance of packed padded levels ``flat`` (``envmap_mips._packed_levels``)
    toward ``dirs`` (P, 3) at ``lod`` (P,); differentiable in all three. CPU tensors
    of one float dtype."""
    return _CubeLod.apply(
        flat, dirs, lod, np.asarray(offsets, np.int64), np.asarray(sizes, np.int64), min_major
    )
