"""Compiled CPU compositing backend ("cpu"): numba kernels, forward and backward.

float32 composites on 16-px tiles go to the SIMD C kernels of ``core.render.raster.cpu_simd``
where they are built (same decisions, vector arithmetic); these numba kernels are
the rest (float64, other tile sizes, machines without a compiler or prebuilt
kernel) and the exact kernels the SIMD ones are tested against.

Same semantics as ``core.render.raster.reference`` (the oracle), tile by tile:
front-to-back over each tile's depth-sorted Gaussians, alpha = min(0.99, o·exp(power))
skipped below 1/255 or when power > 0, stopping before T would fall below 1e-4.

Why it is fast:

* Gaussian-major loops inside a tile. Each tile keeps its pixels' running state (T,
  done flags, and in the backward T and a scalar suffix sum), and each of the tile's
  Gaussians, in depth order, updates only the pixels it can reach. Per-pixel order is
  still front to back, so the result is the one a pixel-major loop gives.
* Exact culling. The 3σ box used for binning is far larger than where alpha can reach
  1/255. Per Gaussian we solve o·exp(power) ≥ 1/255 for the ellipse (with a safety
  margin), skip tiles it misses and, per pixel row, visit only the columns inside it.
  Every visited pixel is evaluated with the reference formula, so skipping never
  changes a result; it only avoids exp() where alpha is certainly below 1/255.
* No Python loop over tiles: one compiled call per worker thread (``nogil``; as
  many workers as ``set_kernel_threads`` says, else ``torch.get_num_threads()``)
  composites tiles w, w + n_workers, ...
  Striping balances the centre-heavy load statically and deterministically.

Backward is 3DGS-style: the forward stores each pixel's final T and the count of
tile-list entries up to the last contributing Gaussian; the backward walks the list
back to front, recovering T_before = T_after / (1 - alpha) and a scalar suffix sum
R = Σ_{later k} alpha_k T_k (g · f_k) (g = dL/dfeatures of the pixel), so that

    dL/dalpha_i = T_i (g · f_i) - R / (1 - alpha_i) + g_alpha T_final / (1 - alpha_i).

A clamped alpha (o·G > 0.99) passes no gradient to o or the footprint. Gradients are
race-free: a worker sums a Gaussian's gradient over the pixels of one tile in local
variables and adds it to its own slot of a (n_workers, N, 6 + C) buffer; the slots
are summed afterwards. Tiles are assigned to workers statically, so results are
deterministic for a given thread count.

Compute is in float32, or float64 when an input is float64; the backward keeps its
running T, suffix sums and gradient sums in float64. Numba compiles the kernels on
first use (about 4-8 s for forward + backward of one dtype on a 2-core machine) and
caches the machine code (``cache=True``, in ``__pycache__`` or numba's user cache),
so later processes only load it (about 0.5 s).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from core.kernels.pool import (
    kernel_threads,
    run_ranges,
    run_workers,
    scratch_zeros,
    store_dtype,
    zeros_touched,
)
from core.render.raster import cpu_simd
from core.render.raster.binning import TileBins
from core.render.raster.projection import ALPHA_MAX, ALPHA_MIN, T_MIN, Projected

try:
    from numba import njit

    _NUMBA_ERROR: str | None = None
except ImportError as exc:  # pragma: no cover - numba is a declared dependency
    _NUMBA_ERROR = f"numba is not importable ({exc})"

    def njit(*_args, **_kwargs):  # type: ignore[no-redef]
        return lambda fn: fn


__all__ = ["CpuComposite", "available", "rasterize_cpu"]

# Culling margin: a pixel is skipped only when power < log(ALPHA_MIN / o) - _MARGIN / 2,
# i.e. alpha is below 1/255 by ≥ 5 %, far beyond float32 rounding of the power.
_MARGIN = 0.1
# Relative float32 rounding allowance on the quadratic form's terms (long thin ellipses).
_REL_MARGIN = 1e-5
# Pixel-coordinate slack when rounding a culling interval to pixel indices.
_PIX_EPS = 1e-3

# Columns of the per-Gaussian gradient rows: mean (2), conic (3), opacity, features.
_G_MX, _G_MY, _G_A, _G_B, _G_C, _G_O, _G_F = range(7)


def available(device: torch.device) -> str | None:
    """None where the backend can run, otherwise why not."""
    device = torch.device(device)
    if _NUMBA_ERROR is not None:
        return _NUMBA_ERROR
    if device.type != "cpu":
        return f"the 'cpu' backend runs on CPU tensors only; device is {device}"
    return None


# ---------------------------------------------------------------------------------------
# Per-Gaussian culling data (numpy, float64)
# ---------------------------------------------------------------------------------------

# Columns of ``geo``: half-extents of the culling ellipse in x and y, the slope of its
# row centres (x_centre(dy) = mx - slope·dy) and (u, v) with row half-width
# sqrt(u - v·dy²).
_GEO_HX, _GEO_HY, _GEO_SLOPE, _GEO_U, _GEO_V = range(5)


@njit(nogil=True, fastmath=False, cache=True)
def _prepare_range(
    lo, hi, means2d, conics, opac, alpha_min, margin, rel_margin, mode, geo
):  # pragma: no cover - numba
    """Fill ``mode`` and ``geo`` for Gaussians [lo, hi) (see :func:`_prepare`)."""
    for g in range(lo, hi):
        o = np.float64(opac[g])
        mx, my = np.float64(means2d[g, 0]), np.float64(means2d[g, 1])
        a, b, c = np.float64(conics[g, 0]), np.float64(conics[g, 1]), np.float64(conics[g, 2])
        det = a * c - b * b
        finite_c = math.isfinite(a) and math.isfinite(b) and math.isfinite(c)
        pd = finite_c and a > 0 and c > 0 and det > 0
        # NaN opacity or a non-finite centre never passes the reference's tests; an
        # infinite opacity does (alpha clamps to 0.99), so it is evaluated without culling.
        live = o >= alpha_min and math.isfinite(mx) and math.isfinite(my)
        if not live:
            mode[g] = 0
        elif pd and math.isfinite(o):
            mode[g] = 1
        else:
            mode[g] = 2
        if mode[g] != 1:
            a, b, c, det, o = 1.0, 0.0, 1.0, 1.0, 1.0
        k0 = -2.0 * math.log(alpha_min / o)
        hx0 = math.sqrt(k0 * c / det)
        hy0 = math.sqrt(k0 * a / det)
        mag = a * hx0 * hx0 + c * hy0 * hy0 + 2.0 * abs(b) * hx0 * hy0
        k = k0 + margin + rel_margin * mag
        geo[g, 0] = math.sqrt(k * c / det)
        geo[g, 1] = math.sqrt(k * a / det)
        geo[g, 2] = b / a
        geo[g, 3] = k / a
        geo[g, 4] = det / (a * a)


def _prepare(
    means2d: np.ndarray, conics: np.ndarray, opac: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per Gaussian: how to cull it (mode) and its alpha ≥ 1/255 ellipse (geo).

    mode 0: never contributes (o < 1/255 or NaN, or a non-finite centre);
    mode 1: positive-definite conic, culled with the ellipse
            a dx² + 2b dx dy + c dy² ≤ K, K = -2 log(ALPHA_MIN / o) + margins;
    mode 2: anything else: every pixel of its tiles is evaluated (exact, no culling).
    ``geo`` holds the mode-1 ellipse (float64); other modes get a unit placeholder.
    """
    n = opac.shape[0]
    mode = np.empty(n, np.int8)
    geo = np.empty((n, 5), np.float64)
    args = (means2d, conics, opac, ALPHA_MIN, _MARGIN, _REL_MARGIN, mode, geo)
    run_ranges(_prepare_range, n, args)
    return mode, geo


# ---------------------------------------------------------------------------------------
# numba kernels
# ---------------------------------------------------------------------------------------


@njit(fastmath=False, cache=True, inline="always")
def _ceil_clamped(v, lo, hi):  # pragma: no cover
    """ceil(v) clamped to [lo, hi] (clamping first keeps huge or inf v safe)."""
    v = min(max(v, lo - 1.0), hi + 1.0)
    return min(max(math.ceil(v), lo), hi)


@njit(fastmath=False, cache=True, inline="always")
def _floor_clamped(v, lo, hi):  # pragma: no cover
    """floor(v) clamped to [lo, hi]."""
    v = min(max(v, lo - 1.0), hi + 1.0)
    return min(max(math.floor(v), lo), hi)


@njit(fastmath=False, cache=True, inline="always")
def _span(mode, centre, half, lo, hi):  # pragma: no cover
    """Pixels [i0, i1) of [lo, hi) whose centres (i + 0.5) lie within centre ± half."""
    if mode == 2:
        return lo, hi
    i0 = _ceil_clamped(centre - half - 0.5 - _PIX_EPS, lo, hi)
    i1 = _floor_clamped(centre + half - 0.5 + _PIX_EPS, lo - 1, hi - 1) + 1
    return i0, i1


@njit(fastmath=False, cache=True, inline="always")
def _row_span(mode, geo_g, mx, dy, lo, hi):  # pragma: no cover
    """Columns [c0, c1) of [lo, hi) inside the culling ellipse on the row at offset dy."""
    if mode == 2:
        return lo, hi
    disc = geo_g[_GEO_U] - geo_g[_GEO_V] * dy * dy
    if disc < 0.0:
        return lo, lo
    return _span(1, mx - geo_g[_GEO_SLOPE] * dy, math.sqrt(disc), lo, hi)


@njit(fastmath=False, cache=True, inline="always")
def _entry_rows(g, mode, geo, means2d, x0, x1, y0, y1):  # pragma: no cover
    """A tile entry's culling: Gaussian g's mode, its culling geometry, its centre in
    float64 and the rows [r0, r1) of the tile box [x0, x1) × [y0, y1) its culling box
    covers, empty (r0 == r1) where it is culled or covers none of the box's columns."""
    m = mode[g]
    geo_g = geo[g]
    mxd = np.float64(means2d[g, 0])
    myd = np.float64(means2d[g, 1])
    if m == 0:
        return m, geo_g, mxd, myd, y0, y0
    c0, c1 = _span(m, mxd, geo_g[_GEO_HX], x0, x1)
    if c0 >= c1:
        return m, geo_g, mxd, myd, y0, y0
    r0, r1 = _span(m, myd, geo_g[_GEO_HY], y0, y1)
    return m, geo_g, mxd, myd, r0, r1


@njit(nogil=True, fastmath=False, cache=True)
def _forward_worker(
    w, n_workers, means2d, conics, opac, feats, gauss_ids, offsets, tiles_x, tile_size,
    xs, ys, consts, mode, geo, out_feat, out_T, out_last,
):  # fmt: skip  # pragma: no cover
    """Composite tiles w, w + n_workers, ... (out_T starts at 1, the others at 0).

    ``consts`` = (0.5, 1, ALPHA_MIN, ALPHA_MAX, T_MIN) in the compute dtype, so the
    per-pixel arithmetic stays in that dtype, as in the reference.
    """
    height, width, n_ch = out_feat.shape
    n_tiles = offsets.shape[0] - 1
    half, one, a_min, a_max, t_min = consts[0], consts[1], consts[2], consts[3], consts[4]
    npix = tile_size * tile_size
    done = np.zeros(npix, np.uint8)
    row_left = np.zeros(tile_size, np.int64)
    # The tile's running state lives in small local buffers (L1-sized) and is written
    # back once per tile: the image rows a tile spans are far apart in memory.
    T_loc = np.empty(npix, out_T.dtype)
    F_loc = np.empty((npix, n_ch), out_feat.dtype)
    last_loc = np.empty(npix, out_last.dtype)
    f_g = np.empty(n_ch, feats.dtype)
    for t in range(w, n_tiles, n_workers):
        lo, hi = offsets[t], offsets[t + 1]
        if hi == lo:
            continue
        x0 = (t % tiles_x) * tile_size
        y0 = (t // tiles_x) * tile_size
        x1 = min(x0 + tile_size, width)
        y1 = min(y0 + tile_size, height)
        n_left = (x1 - x0) * (y1 - y0)
        for r in range(y1 - y0):
            row_left[r] = x1 - x0
            done[r * tile_size : r * tile_size + x1 - x0] = 0
        T_loc[:] = one
        F_loc[:, :] = 0
        last_loc[:] = 0
        for i in range(lo, hi):
            g = gauss_ids[i]
            m, geo_g, mxd, myd, r0, r1 = _entry_rows(g, mode, geo, means2d, x0, x1, y0, y1)
            if r0 >= r1:
                continue
            mx, my = means2d[g, 0], means2d[g, 1]
            a, b, c, o = conics[g, 0], conics[g, 1], conics[g, 2], opac[g]
            for ch in range(n_ch):
                f_g[ch] = feats[g, ch]
            for py in range(r0, r1):
                r = py - y0
                if row_left[r] == 0:
                    continue
                q0, q1 = _row_span(m, geo_g, mxd, py + 0.5 - myd, x0, x1)
                dy = ys[py] - my
                for px in range(q0, q1):
                    p = r * tile_size + (px - x0)
                    if done[p]:
                        continue
                    dx = xs[px] - mx
                    power = -half * (a * dx * dx + c * dy * dy) - b * dx * dy
                    if not (power <= 0):
                        continue
                    alpha = o * math.exp(power)
                    if alpha > a_max:  # written out so that a NaN stays NaN (and is skipped)
                        alpha = a_max
                    if not (alpha >= a_min):
                        continue
                    T = T_loc[p]
                    test_T = T * (one - alpha)
                    if test_T < t_min:
                        done[p] = 1
                        row_left[r] -= 1
                        n_left -= 1
                        continue
                    wgt = alpha * T
                    for ch in range(n_ch):
                        F_loc[p, ch] += f_g[ch] * wgt
                    T_loc[p] = test_T
                    last_loc[p] = i - lo + 1
            if n_left == 0:
                break
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * tile_size + (px - x0)
                out_T[py, px] = T_loc[p]
                out_last[py, px] = last_loc[p]
                for ch in range(n_ch):
                    out_feat[py, px, ch] = F_loc[p, ch]


@njit(nogil=True, fastmath=False, cache=True)
def _backward_worker(
    w, n_workers, means2d, conics, opac, feats, gauss_ids, offsets, tiles_x, tile_size,
    xs, ys, consts, mode, geo, final_T, last, grad_feat, grad_alpha, gbuf,
):  # fmt: skip  # pragma: no cover
    """Back to front over tiles w, w + n_workers, ...; adds into gbuf[w, gaussian]."""
    height, width, n_ch = grad_feat.shape
    n_tiles = offsets.shape[0] - 1
    half, a_min, a_max = consts[0], consts[2], consts[3]
    npix = tile_size * tile_size
    T_cur = np.zeros(npix, np.float64)
    R = np.zeros(npix, np.float64)
    ga_T = np.zeros(npix, np.float64)  # dL/dalpha_out · T_final: the alpha output's share
    row_last = np.zeros(tile_size, np.int64)
    acc_f = np.zeros(n_ch, np.float64)
    f_g = np.zeros(n_ch, np.float64)  # this Gaussian's features in float64
    g_tile = np.zeros((npix, n_ch), np.float64)  # dL/dfeatures of the tile, float64
    last_t = np.zeros(npix, np.int64)  # the tile's slice of ``last``
    for t in range(w, n_tiles, n_workers):
        lo, hi = offsets[t], offsets[t + 1]
        if hi == lo:
            continue
        x0 = (t % tiles_x) * tile_size
        y0 = (t // tiles_x) * tile_size
        x1 = min(x0 + tile_size, width)
        y1 = min(y0 + tile_size, height)
        n_last = 0
        for py in range(y0, y1):
            row_last[py - y0] = 0
            for px in range(x0, x1):
                p = (py - y0) * tile_size + (px - x0)
                T_cur[p] = final_T[py, px]
                ga_T[p] = np.float64(grad_alpha[py, px]) * np.float64(final_T[py, px])
                R[p] = 0.0
                last_t[p] = last[py, px]
                for ch in range(n_ch):
                    g_tile[p, ch] = np.float64(grad_feat[py, px, ch])
                row_last[py - y0] = max(row_last[py - y0], last[py, px])
            n_last = max(n_last, row_last[py - y0])
        for i in range(lo + n_last - 1, lo - 1, -1):
            g = gauss_ids[i]
            m, geo_g, mxd, myd, r0, r1 = _entry_rows(g, mode, geo, means2d, x0, x1, y0, y1)
            if r0 >= r1:
                continue
            mx, my = means2d[g, 0], means2d[g, 1]
            a, b, c, o = conics[g, 0], conics[g, 1], conics[g, 2], opac[g]
            ad, bd, cd = np.float64(a), np.float64(b), np.float64(c)
            k = i - lo
            touched = False
            acc_f[:] = 0.0
            for ch in range(n_ch):
                f_g[ch] = np.float64(feats[g, ch])
            a_mx = 0.0
            a_my = 0.0
            a_a = 0.0
            a_b = 0.0
            a_c = 0.0
            a_o = 0.0
            for py in range(r0, r1):
                r = py - y0
                if k >= row_last[r]:
                    continue
                q0, q1 = _row_span(m, geo_g, mxd, py + 0.5 - myd, x0, x1)
                dy = ys[py] - my
                for px in range(q0, q1):
                    p = r * tile_size + (px - x0)
                    if k >= last_t[p]:
                        continue
                    dx = xs[px] - mx
                    power = -half * (a * dx * dx + c * dy * dy) - b * dx * dy
                    if not (power <= 0):
                        continue
                    G = math.exp(power)
                    raw = o * G
                    alpha = a_max if raw > a_max else raw
                    if not (alpha >= a_min):
                        continue
                    touched = True
                    al = np.float64(alpha)
                    one_m = 1.0 - al
                    T_before = T_cur[p] / one_m
                    wgt = al * T_before
                    gf = 0.0
                    for ch in range(n_ch):
                        gc = g_tile[p, ch]
                        gf += gc * f_g[ch]
                        acc_f[ch] += wgt * gc
                    d_alpha = T_before * gf + (ga_T[p] - R[p]) / one_m
                    R[p] += wgt * gf
                    T_cur[p] = T_before
                    if raw > a_max:
                        continue  # clamped: alpha depends on neither o nor the footprint
                    d_pow = al * d_alpha
                    dxd, dyd = np.float64(dx), np.float64(dy)
                    a_mx += (ad * dxd + bd * dyd) * d_pow
                    a_my += (cd * dyd + bd * dxd) * d_pow
                    a_a -= 0.5 * dxd * dxd * d_pow
                    a_b -= dxd * dyd * d_pow
                    a_c -= 0.5 * dyd * dyd * d_pow
                    a_o += np.float64(G) * d_alpha
            if touched:
                gbuf[w, g, 0] += a_mx
                gbuf[w, g, 1] += a_my
                gbuf[w, g, 2] += a_a
                gbuf[w, g, 3] += a_b
                gbuf[w, g, 4] += a_c
                gbuf[w, g, 5] += a_o
                for ch in range(n_ch):
                    gbuf[w, g, 6 + ch] += acc_f[ch]


# ---------------------------------------------------------------------------------------
# torch glue
# ---------------------------------------------------------------------------------------


def _np(t: Tensor, dtype: torch.dtype) -> np.ndarray:
    return t.detach().to(dtype).contiguous().numpy()


def has_gradient(grad_feat: np.ndarray, grad_alpha: np.ndarray, last: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels a compositing backward walks, those with contributors and
    a non-zero upstream gradient. A loss that reads a few pixels (L_multi reads about a
    quarter of its neighbour view at 128²) leaves the others at zero, and their
    contributions' gradients are zero too. One compiled pass that stops at a pixel's
    first non-zero channel: numpy's ``!=``/``any`` over every channel took 16 ms a
    backward at 800² where every pixel is read."""
    out = np.empty(last.shape, np.bool_)
    _has_gradient(grad_feat, grad_alpha, last, out)
    return out


@njit(nogil=True, cache=True)
def _has_gradient(grad_feat, grad_alpha, last, out):  # pragma: no cover - numba
    height, width, n_ch = grad_feat.shape
    for py in range(height):
        for px in range(width):
            live = last[py, px] > 0 and grad_alpha[py, px] != 0
            ch = 0
            while last[py, px] > 0 and not live and ch < n_ch:
                live = grad_feat[py, px, ch] != 0
                ch += 1
            out[py, px] = live


class _Setup:
    """Numpy views and per-Gaussian culling data shared by forward and backward."""

    def __init__(
        self,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        features: Tensor,
        bins: TileBins,
        width: int,
        height: int,
        dtype: torch.dtype,
    ) -> None:
        npdt = np.float32 if dtype == torch.float32 else np.float64
        self.means2d = _np(means2d, dtype)
        self.conics = _np(conics, dtype)
        self.opac = _np(opacities.reshape(-1), dtype)
        self.feats = _np(features, dtype)
        self.gauss_ids = bins.gauss_ids.detach().to(torch.int64).contiguous().numpy()
        self.offsets = bins.offsets.detach().to(torch.int64).contiguous().numpy()
        self.tiles_x = int(bins.tiles_x)
        self.tile_size = int(bins.tile_size)
        self.xs = (np.arange(width, dtype=npdt) + npdt(0.5)).astype(npdt)
        self.ys = (np.arange(height, dtype=npdt) + npdt(0.5)).astype(npdt)
        self.consts = np.array([0.5, 1.0, ALPHA_MIN, ALPHA_MAX, T_MIN], dtype=npdt)
        self.mode, self.geo = _prepare(self.means2d, self.conics, self.opac)

    def args(self) -> tuple:
        return (
            self.means2d, self.conics, self.opac, self.feats, self.gauss_ids, self.offsets,
            self.tiles_x, self.tile_size, self.xs, self.ys, self.consts, self.mode, self.geo,
        )  # fmt: skip


def _compute_dtype(*tensors: Tensor) -> torch.dtype:
    dtype = torch.float32
    for t in tensors:
        if t.dtype == torch.float64:
            dtype = torch.float64
    return dtype


class CpuComposite(torch.autograd.Function):
    """Differentiable tile compositing on the CPU: numba or, with ``simd``, the C kernels
    (``backward=False``: a frame, which needs none of the backward's state)."""

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
        simd: bool = False,
        backward: bool = True,
    ) -> tuple[Tensor, Tensor]:
        dtype = _compute_dtype(means2d, conics, opacities, features)
        n_ch = features.shape[1]
        npdt = np.float32 if dtype == torch.float32 else np.float64
        out_feat = zeros_touched((height, width, n_ch), npdt)
        out_T = np.ones((height, width), npdt)
        # a SIMD frame needs no last-contributor counts (the numba kernel writes them anyway)
        out_last = zeros_touched((height, width), np.int32) if backward or not simd else None
        setup = None
        kernel = None  # the SIMD kernel's state, which its backward reuses
        if bins.gauss_ids.numel() > 0 and n_ch > 0:
            setup = _Setup(means2d, conics, opacities, features, bins, width, height, dtype)
            if simd and not backward:  # a frame: no last-contributor counts, no state
                cpu_simd.composite(setup.args(), kernel_threads(), out_feat, out_T)
            elif simd:
                kernel = cpu_simd.SimdComposite(setup.args(), width, height)
                kernel.forward(kernel_threads(), out_feat, out_T, out_last)
            else:
                args = (*setup.args(), out_feat, out_T, out_last)
                run_workers(_forward_worker, kernel_threads(), args)
        # The numpy arrays in ``setup`` may alias the inputs: saving the inputs makes
        # autograd refuse a backward after they were modified in place.
        ctx.save_for_backward(means2d, conics, opacities, features)
        ctx.setup = setup
        ctx.kernel = kernel
        ctx.meta = (dtype, width, height, n_ch)
        ctx.in_dtypes = (means2d.dtype, conics.dtype, opacities.dtype, features.dtype)
        ctx.shapes = (means2d.shape, conics.shape, opacities.shape, features.shape)
        ctx.state = (out_T, out_last)
        feats_t = torch.from_numpy(out_feat)
        alpha_t = 1.0 - torch.from_numpy(out_T)
        return feats_t, alpha_t

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
                out_T, out_last = ctx.state
                if grad_feat is None:
                    gf = np.zeros((height, width, n_ch), out_T.dtype)
                else:
                    gf = _np(grad_feat, dtype)
                if grad_alpha is None:
                    ga = np.zeros((height, width), out_T.dtype)
                else:
                    ga = _np(grad_alpha, dtype)
                # a pixel no loss reads walks nothing (its contributions' gradients are 0)
                last = np.where(has_gradient(gf, ga, out_last), out_last, 0)
                if ctx.kernel is not None:  # the SIMD forward's decisions, replayed
                    ctx.kernel.backward(n_workers, out_T, last, gf, ga, gbuf)
                else:
                    args = (*setup.args(), out_T, last, gf, ga, gbuf)
                    run_workers(_backward_worker, n_workers, args)
            # the workers' sums added and split into the four inputs' gradients, in their
            # dtypes, in one pass (nothing may keep a view of the pooled buffer)
            widths = (_G_A - _G_MX, _G_O - _G_A, _G_F - _G_O, n_ch)  # gbuf's column groups
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


@njit(nogil=True, cache=True)
def _reduce_split_range(lo, hi, gbuf, g_m2d, g_con, g_op, g_feat):  # pragma: no cover - numba
    """Rows [lo, hi) of the per-worker gradient sums (W, N, 6 + C), added worker by worker
    (the order ``np.add`` took) and stored, rounded once, into (N, 2) screen means, (N, 3)
    conics, (N, 1) opacities and (N, C) features."""
    n_workers, n_ch = gbuf.shape[0], g_feat.shape[1]
    for g in range(lo, hi):
        for k in range(6 + n_ch):
            acc = gbuf[0, g, k]
            for w in range(1, n_workers):
                acc += gbuf[w, g, k]
            if k < _G_A:
                g_m2d[g, k] = acc
            elif k < _G_O:
                g_con[g, k - _G_A] = acc
            elif k == _G_O:
                g_op[g, 0] = acc
            else:
                g_feat[g, k - _G_F] = acc


def rasterize_cpu(
    proj: Projected,
    opacities: Tensor,
    features: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    simd: bool | None = None,
) -> tuple[Tensor, Tensor]:
    """Composite projected Gaussians into (H, W, C) features and (H, W) alpha.

    float32 composites on 16-px tiles take the SIMD kernel of ``core.render.raster.cpu_simd``
    where it is built (``simd=None``), forward and backward; ``simd=False`` keeps the
    numba kernels, ``simd=True`` insists on the SIMD one (tests, benchmarks).
    """
    tensors = (proj.means2d, proj.conics, opacities, features)
    use_simd = simd is not False and cpu_simd.supports(tensors, bins.tile_size)
    if simd and not use_simd:
        why = cpu_simd.why_unavailable() or "it needs float32 inputs and 16-px tiles"
        raise RuntimeError(f"the SIMD compositing kernel does not apply here: {why}")
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    feats, alpha = CpuComposite.apply(*tensors, bins, width, height, use_simd, needs_grad)
    return feats.to(features.dtype), alpha.to(features.dtype)


# Registered even without numba, so that asking for "cpu" says why it cannot run.
from core.render.raster import register_backend  # noqa: E402  (core.render.raster imports this module last)

register_backend("cpu", available, rasterize_cpu)
