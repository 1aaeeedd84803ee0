"""L_single (Eq. 10–11) as compiled passes with a hand-written backward (CPU).

The torch path back-projects the depth, takes the central (or same-surface one-sided)
differences, their cross product, normalises both normals and averages 1 − n·N: about
forty image-sized ops and their autograd, 4.2 ms of a 55 ms multi-view step at 128²
(docs/bench/step_breakdown.md). Here one pass per pixel computes the loss and each
pixel's gradient with respect to its two difference vectors; a second pass gathers
those into each pixel's back-projected point (every pixel only reads its four
neighbours, so rows run in parallel without shared writes) and on into its depth.

Same definition as ``core.training.losses.single_view_loss`` (interior pixels whose
stencil is valid and whose cross product is above 1e-12, normals facing the camera,
the rendered normal normalised with a 1e-12 floor, the one-sided choice made on
detached lengths); float64 inside (``tests/test_depth_normal_compiled.py`` holds it to
the torch path, value and gradients).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.kernels.pool import run_ranges

__all__ = ["single_view_loss_compiled"]

_CENTRAL, _FWD, _BWD = 0, 1, 2


@njit(nogil=True, cache=True, inline="always")
def _point(depth, rays, j, i):  # pragma: no cover - numba
    d = np.float64(depth[j, i])
    return d * rays[j, i, 0], d * rays[j, i, 1], d * rays[j, i, 2]


@njit(nogil=True, cache=True, inline="always")
def _step(ax, ay, az, mx, my, mz, bx, by, bz, ratio):  # pragma: no cover - numba
    """Difference across the pixel (a: the +1 neighbour, m: the pixel, b: the −1 one):
    central, or twice the shorter side where one side is ``ratio``× longer (ratio ≤ 0:
    always central). Returns (dx, dy, dz, which)."""
    if ratio > 0.0:
        fx, fy, fz = ax - mx, ay - my, az - mz
        gx, gy, gz = mx - bx, my - by, mz - bz
        lf = math.sqrt(fx * fx + fy * fy + fz * fz)
        lb = math.sqrt(gx * gx + gy * gy + gz * gz)
        if max(lf, lb) > ratio * min(lf, lb):
            if lf <= lb:
                return 2.0 * fx, 2.0 * fy, 2.0 * fz, _FWD
            return 2.0 * gx, 2.0 * gy, 2.0 * gz, _BWD
    return ax - bx, ay - by, az - bz, _CENTRAL


@njit(nogil=True, cache=True)
def _pixel_rows(
    lo, hi, depth, valid, normal, rays, weight, ratio, sums, g_du, g_dv, which, g_normal,
):  # fmt: skip  # pragma: no cover - numba
    """Rows [lo, hi) (interior only): per-pixel loss into ``sums[row]`` (value, count)
    and, as if the loss were the plain weighted sum, the gradients of each pixel's
    differences (``g_du``, ``g_dv``), its one-sided choices (``which``) and the
    rendered normal's gradient (``g_normal``). The caller scales by 1 / count."""
    h, w = depth.shape
    has_w = weight.shape[0] > 0
    for j in range(lo, hi):
        total = 0.0
        count = 0.0
        for i in range(w):
            g_du[j, i, 0] = g_du[j, i, 1] = g_du[j, i, 2] = 0.0
            g_dv[j, i, 0] = g_dv[j, i, 1] = g_dv[j, i, 2] = 0.0
            g_normal[j, i, 0] = g_normal[j, i, 1] = g_normal[j, i, 2] = 0.0
            which[j, i, 0] = which[j, i, 1] = _CENTRAL
            if j == 0 or i == 0 or j == h - 1 or i == w - 1:
                continue
            if not (valid[j, i] and valid[j, i + 1] and valid[j, i - 1]
                    and valid[j + 1, i] and valid[j - 1, i]):  # fmt: skip
                continue
            mx, my, mz = _point(depth, rays, j, i)
            rx, ry, rz = _point(depth, rays, j, i + 1)
            lx, ly, lz = _point(depth, rays, j, i - 1)
            dx, dy, dz = _point(depth, rays, j + 1, i)
            ux, uy, uz = _point(depth, rays, j - 1, i)
            aux, auy, auz, wu = _step(rx, ry, rz, mx, my, mz, lx, ly, lz, ratio)
            avx, avy, avz, wv = _step(dx, dy, dz, mx, my, mz, ux, uy, uz, ratio)
            # cross = dv × du
            cx = avy * auz - avz * auy
            cy = avz * aux - avx * auz
            cz = avx * auy - avy * aux
            norm = math.sqrt(cx * cx + cy * cy + cz * cz)
            if not norm > 1e-12:
                continue
            nx, ny, nz = cx / norm, cy / norm, cz / norm
            s = 1.0 if nx * mx + ny * my + nz * mz <= 0.0 else -1.0  # face the camera
            px, py, pz = (np.float64(normal[j, i, 0]), np.float64(normal[j, i, 1]),
                          np.float64(normal[j, i, 2]))  # fmt: skip
            plen = math.sqrt(px * px + py * py + pz * pz)
            big = plen > 1e-12
            pl = plen if big else 1e-12
            ex, ey, ez = px / pl, py / pl, pz / pl
            wt = np.float64(weight[j, i]) if has_w else 1.0
            dot = s * (ex * nx + ey * ny + ez * nz)
            total += wt * (1.0 - dot)
            count += 1.0
            # d(wt (1 − e·N)) : g_e = −wt N, g_N = −wt e, N = s c/|c|
            gex, gey, gez = -wt * s * nx, -wt * s * ny, -wt * s * nz
            if big:
                k = ex * gex + ey * gey + ez * gez
                gex, gey, gez = (gex - ex * k) / pl, (gey - ey * k) / pl, (gez - ez * k) / pl
            else:
                gex, gey, gez = gex / pl, gey / pl, gez / pl
            g_normal[j, i, 0], g_normal[j, i, 1], g_normal[j, i, 2] = gex, gey, gez
            gnx, gny, gnz = -wt * s * ex, -wt * s * ey, -wt * s * ez
            k = nx * gnx + ny * gny + nz * gnz
            gcx, gcy, gcz = (gnx - nx * k) / norm, (gny - ny * k) / norm, (gnz - nz * k) / norm
            # c = a × b with a = dv, b = du: g_a = b × g_c, g_b = g_c × a
            g_dv[j, i, 0] = auy * gcz - auz * gcy
            g_dv[j, i, 1] = auz * gcx - aux * gcz
            g_dv[j, i, 2] = aux * gcy - auy * gcx
            g_du[j, i, 0] = gcy * avz - gcz * avy
            g_du[j, i, 1] = gcz * avx - gcx * avz
            g_du[j, i, 2] = gcx * avy - gcy * avx
            which[j, i, 0] = wu
            which[j, i, 1] = wv
        sums[j, 0] = total
        sums[j, 1] = count


@njit(nogil=True, cache=True, inline="always")
def _take(g, which, j, i, role, scale, acc):  # pragma: no cover - numba
    """Add pixel (j, i)'s difference gradient ``g`` as seen by one of its stencil
    points: role +1 (the +1 neighbour), −1 (the −1 neighbour), 0 (the pixel)."""
    c = 0.0
    if which == _CENTRAL:
        c = 1.0 if role == 1 else (-1.0 if role == -1 else 0.0)
    elif which == _FWD:
        c = 2.0 if role == 1 else (-2.0 if role == 0 else 0.0)
    else:
        c = 2.0 if role == 0 else (-2.0 if role == -1 else 0.0)
    if c != 0.0:
        acc[0] += c * scale * g[j, i, 0]
        acc[1] += c * scale * g[j, i, 1]
        acc[2] += c * scale * g[j, i, 2]


@njit(nogil=True, cache=True)
def _gather_rows(lo, hi, rays, g_du, g_dv, which, scale, g_depth):  # pragma: no cover - numba
    """Rows [lo, hi): each pixel's point gradient from the stencils that read it, then
    its depth gradient (P = d · ray)."""
    h, w = g_depth.shape
    acc = np.zeros(3)
    for j in range(lo, hi):
        for i in range(w):
            acc[0] = acc[1] = acc[2] = 0.0
            _take(g_du, which[j, i, 0], j, i, 0, scale, acc)
            _take(g_dv, which[j, i, 1], j, i, 0, scale, acc)
            if i > 0:
                _take(g_du, which[j, i - 1, 0], j, i - 1, 1, scale, acc)
            if i < w - 1:
                _take(g_du, which[j, i + 1, 0], j, i + 1, -1, scale, acc)
            if j > 0:
                _take(g_dv, which[j - 1, i, 1], j - 1, i, 1, scale, acc)
            if j < h - 1:
                _take(g_dv, which[j + 1, i, 1], j + 1, i, -1, scale, acc)
            g_depth[j, i] = acc[0] * rays[j, i, 0] + acc[1] * rays[j, i, 1] + acc[2] * rays[j, i, 2]


class _SingleView(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal, depth, valid, rays, weight, ratio):  # type: ignore[override]
        h, w = depth.shape
        d = depth.detach().contiguous().numpy()
        r = rays.detach().to(torch.float64).contiguous().numpy()
        wt = (np.empty((0, 0)) if weight is None
              else weight.detach().to(torch.float64).contiguous().numpy())  # fmt: skip
        sums = np.zeros((h, 2))
        g_du = np.empty((h, w, 3))
        g_dv = np.empty((h, w, 3))
        which = np.empty((h, w, 2), np.int8)
        g_normal = np.empty((h, w, 3))
        args = (
            d, valid.contiguous().numpy(), normal.detach().contiguous().numpy(), r, wt,
            float(ratio), sums, g_du, g_dv, which, g_normal,
        )  # fmt: skip
        run_ranges(_pixel_rows, h, args)
        total, count = float(sums[:, 0].sum()), float(sums[:, 1].sum())
        ctx.meta = (r, g_du, g_dv, which, g_normal, count, normal.dtype, depth.dtype)
        return normal.new_tensor(total / count if count > 0 else 0.0)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        r, g_du, g_dv, which, g_normal, count, n_dtype, d_dtype = ctx.meta
        scale = float(grad) / count if count > 0 else 0.0
        g_depth = np.empty(r.shape[:2])
        run_ranges(_gather_rows, r.shape[0], (r, g_du, g_dv, which, scale, g_depth))
        g_n = torch.from_numpy(g_normal * scale).to(n_dtype)
        return g_n, torch.from_numpy(g_depth).to(d_dtype), None, None, None, None


def single_view_loss_compiled(
    rendered_normal: Tensor,
    depth: Tensor,
    valid: Tensor,
    rays: Tensor,
    weight: Tensor | None = None,
    jump_ratio: float | None = None,
) -> Tensor:
    """Eq. 11 on CPU tensors: ``rendered_normal`` (H, W, 3), ``depth`` (H, W), ``valid``
    (H, W) bool, ``rays`` (H, W, 3) the camera rays K⁻¹(u, v, 1) of ``depth``'s view,
    ``weight`` (H, W) or None, ``jump_ratio`` as ``normals_from_depth``'s. 0 (with zero
    gradients) when no pixel qualifies."""
    return _SingleView.apply(
        rendered_normal, depth, valid, rays, weight, -1.0 if jump_ratio is None else jump_ratio
    )
