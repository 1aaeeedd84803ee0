"""The cube map's padded mip chain (``envmap_mips._packed_levels(cube_mip_chain(t))``, or
one padded level, ``envmap.pad_cube``) built in one compiled pass, with its adjoint.

Every training step rebuilds it from the learned map: box-average each face down the
chain, give every level its seamless one-texel border, pack them into one buffer. In
torch that is ~35 small ops (means, gathers, a corner ``index_copy``, a ``cat``) and as
many autograd nodes on a map of a few thousand texels: 2.7 ms forward and backward on
two cores at R = 32, all of it op overhead (the data is 70 kB). Here the forward builds
the coarser levels in one loop and gathers the packed rows through a table built once
per face size from ``cube_faces.pad_plan_cpu`` (each packed row one texel of one
level, or a corner's mean of three; large maps split over the kernel threads). The
backward scatters the packed gradient onto the levels, then pushes each level's
gradient a quarter to each of its four finer texels, coarsest first, down to level 0.
The torch ops stay the reference (``tests/test_envmap_pack_compiled.py``) and the GPU's
path.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.kernels.pool import run_ranges
from core.render.cube_faces import mip_sizes, pad_plan_cpu

__all__ = ["packed_cube_levels"]

PARALLEL_ROWS = 16_384  # packed rows from which the gather is split over kernel threads


@lru_cache(maxsize=16)
def _gather_table(resolution: int, mips: bool) -> tuple[np.ndarray, ...]:
    """(sources (N, 3), counts (N,), level face sizes, unpadded level offsets, packed
    offsets, padded sizes) of the packed buffer of a map of face size ``resolution``:
    sources index the concatenated unpadded levels (6·R_k² rows each)."""
    sizes = mip_sizes(resolution) if mips else [int(resolution)]
    srcs, counts, lvl_off, pack_off, padded = [], [], [], [], []
    n_lvl = n_pack = 0
    for r in sizes:
        p = r + 2
        src, corner_pos, corner_src = (t.numpy() for t in pad_plan_cpu(r))
        s = np.zeros((6 * p * p, 3), np.int64)
        s[:, 0] = src
        c = np.ones(6 * p * p, np.int64)
        s[corner_pos] = corner_src
        c[corner_pos] = 3
        srcs.append(s + n_lvl)
        counts.append(c)
        lvl_off.append(n_lvl)
        pack_off.append(n_pack)
        padded.append(p)
        n_lvl += 6 * r * r
        n_pack += 6 * p * p
    return (
        np.concatenate(srcs), np.concatenate(counts), np.asarray(sizes, np.int64),
        np.asarray(lvl_off, np.int64), np.asarray(pack_off, np.int64),
        np.asarray(padded, np.int64),
    )  # fmt: skip


@njit(nogil=True, cache=True, inline="always")
def _texel_and_first_child(src, dst, r, rp, f, y, x):  # pragma: no cover - numba
    """Row of texel (f, y, x) of a level of face size r starting at ``dst``, and of the
    first of its four finer texels (+1, +rp, +rp+1 the others) in the level at ``src``."""
    return dst + f * r * r + y * r + x, src + f * rp * rp + 2 * y * rp + 2 * x


@njit(nogil=True, cache=True)
def _coarser_levels(texels, sizes, lvl_off, levels):  # pragma: no cover - numba
    """levels: every level but the first (rows ``lvl_off[k] - lvl_off[1]``), each the
    2×2 mean of the one before (level 0 is ``texels``)."""
    ch = texels.shape[1]
    base = lvl_off[1] if sizes.shape[0] > 1 else 0
    for k in range(1, sizes.shape[0]):
        r, rp = sizes[k], sizes[k - 1]
        dst = lvl_off[k] - base
        prev = texels if k == 1 else levels
        src = 0 if k == 1 else lvl_off[k - 1] - base
        for f in range(6):
            for y in range(r):
                for x in range(r):
                    o, a = _texel_and_first_child(src, dst, r, rp, f, y, x)
                    for c in range(ch):
                        levels[o, c] = (
                            prev[a, c] + prev[a + 1, c] + prev[a + rp, c] + prev[a + rp + 1, c]
                        ) * 0.25


@njit(nogil=True, cache=True)
def _gather_rows(lo, hi, texels, levels, sources, counts, out):  # pragma: no cover - numba
    """Packed rows [lo, hi): a texel of a level (level 0 read from ``texels``), or the
    mean of a corner's three."""
    ch = texels.shape[1]
    n0 = texels.shape[0]
    for n in range(lo, hi):
        m = counts[n]
        if m == 1:
            s = sources[n, 0]
            if s < n0:
                for c in range(ch):
                    out[n, c] = texels[s, c]
            else:
                for c in range(ch):
                    out[n, c] = levels[s - n0, c]
            continue
        for c in range(ch):
            acc = 0.0
            for t in range(m):
                s = sources[n, t]
                acc += texels[s, c] if s < n0 else levels[s - n0, c]
            out[n, c] = acc / m


@njit(nogil=True, cache=True)
def _backward(grad, sources, counts, sizes, lvl_off, g_levels):  # pragma: no cover
    """g_levels (zeroed, float64): the packed gradient onto the unpadded levels, then
    each level's a quarter onto each of its four finer texels, coarsest first."""
    ch = grad.shape[1]
    for n in range(grad.shape[0]):
        m = counts[n]
        for t in range(m):
            s = sources[n, t]
            for c in range(ch):
                g_levels[s, c] += grad[n, c] / m
    for k in range(sizes.shape[0] - 1, 0, -1):
        r, rp = sizes[k], sizes[k - 1]
        src, dst = lvl_off[k - 1], lvl_off[k]
        for f in range(6):
            for y in range(r):
                for x in range(r):
                    o, a = _texel_and_first_child(src, dst, r, rp, f, y, x)
                    for c in range(ch):
                        q = g_levels[o, c] * 0.25
                        g_levels[a, c] += q
                        g_levels[a + 1, c] += q
                        g_levels[a + rp, c] += q
                        g_levels[a + rp + 1, c] += q


class _PackLevels(torch.autograd.Function):
    @staticmethod
    def forward(ctx, texels, mips):  # type: ignore[override]
        r, ch = texels.shape[1], texels.shape[-1]
        sources, counts, sizes, lvl_off, _, _ = _gather_table(r, mips)
        flat = texels.detach().contiguous().reshape(-1, ch).numpy()
        n_coarse = int(lvl_off[-1] + 6 * sizes[-1] ** 2) - flat.shape[0]
        levels = np.empty((max(n_coarse, 1), ch), flat.dtype)
        if n_coarse > 0:
            _coarser_levels(flat, sizes, lvl_off, levels)
        out = np.empty((sources.shape[0], ch), flat.dtype)
        args = (flat, levels, sources, counts, out)
        if sources.shape[0] < PARALLEL_ROWS:  # a thread hand-off costs more than the rows
            _gather_rows(0, sources.shape[0], *args)
        else:
            run_ranges(_gather_rows, sources.shape[0], args)
        ctx.meta = (r, mips, texels.shape)
        return torch.from_numpy(out)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        r, mips, shape = ctx.meta
        sources, counts, sizes, lvl_off, _, _ = _gather_table(r, mips)
        g_levels = np.zeros((int(lvl_off[-1] + 6 * sizes[-1] ** 2), shape[-1]), np.float64)
        _backward(grad.detach().contiguous().numpy(), sources, counts, sizes, lvl_off, g_levels)
        g = torch.from_numpy(g_levels[: 6 * r * r]).to(grad.dtype).reshape(shape)
        return g, None


def packed_cube_levels(texels: Tensor, mips: bool) -> tuple[Tensor, list[int], list[int]]:
    """(packed padded rows (N, C), first row of each level, padded face size of each
    level) of CPU float cube texels (6, R, R, C): its mip chain when ``mips``, else level
    0 alone. Differentiable in the texels."""
    six, r, r2, _ = texels.shape
    if six != 6 or r != r2:
        raise ValueError(f"cube texels must be (6, R, R, C), got {tuple(texels.shape)}")
    _, _, _, _, pack_off, padded = _gather_table(r, mips)
    return _PackLevels.apply(texels, mips), pack_off.tolist(), padded.tolist()
