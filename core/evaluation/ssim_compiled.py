"""SSIM on the CPU in compiled passes: the separable blur, and the whole D-SSIM term.

The D-SSIM term blurs 15 maps a step (the rendered image's three moments, the
reference's two) and its backward 9 more. torch's grouped ``conv2d`` does this at
about 1 GFLOP/s on one CPU thread: 4.5 ms of a 128² step's 6.7 ms RGB loss, 240 ms
at 800² (``python -m bench.ssim_loss``). Here each map is blurred by rows then by
columns, each pass a sum of shifted rows (loops numba vectorises), maps split over
the kernel threads. With zero padding and symmetric taps the blur is its own
adjoint, so its backward is the same blur (``blur_compiled``).

``ssim_compiled`` goes further for the training loss, where only the rendered image
takes a gradient: one pass over the blurred moments gives each pixel's SSIM and its
three partial derivatives (in mu_x, E[x²], E[xy]), and the backward is one blur of
those and one combine, instead of some twenty torch ops and their autograd.
``tests/test_ssim_compiled.py`` holds values and gradients to the ``conv2d`` path
and to the 2D-window reference.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.kernels.pool import run_ranges

__all__ = ["blur_compiled", "ssim_compiled"]


@njit(nogil=True, cache=True)
def _blur_range(lo, hi, src, taps, tmp, dst):  # pragma: no cover - numba
    """Maps lo..hi of src (K, H, W) blurred into dst; tmp (K, H, W) holds the row pass.

    Both passes add shifted, contiguous slices (``out[a:b] += t * in[a+o:b+o]``), which
    LLVM vectorises; indexing ``in[j + o]`` inside the loop instead was 6–8× slower."""
    _, H, W = src.shape
    r = taps.shape[0] // 2
    for k in range(lo, hi):
        for i in range(H):
            row = tmp[k, i]
            s = src[k, i]
            row[:] = 0.0
            for o in range(-r, r + 1):
                a, b = max(0, -o), min(W, W - o)
                if a >= b:
                    continue
                t = taps[o + r]
                out = row[a:b]
                shifted = s[a + o : b + o]
                for j in range(b - a):
                    out[j] += t * shifted[j]
        for i in range(H):
            out = dst[k, i]
            out[:] = 0.0
            for o in range(-r, r + 1):
                ii = i + o
                if ii < 0 or ii >= H:
                    continue
                t = taps[o + r]
                above = tmp[k, ii]
                for j in range(W):
                    out[j] += t * above[j]


def _blur(maps: np.ndarray, taps: np.ndarray) -> np.ndarray:
    tmp = np.empty_like(maps)
    out = np.empty_like(maps)
    run_ranges(_blur_range, maps.shape[0], (maps, taps, tmp, out))
    return out


class _Blur(torch.autograd.Function):
    @staticmethod
    def forward(ctx, maps, taps):  # type: ignore[override]
        t = taps.detach().to(maps.dtype).contiguous().numpy()
        ctx.taps = t
        return torch.from_numpy(_blur(maps.detach().contiguous().numpy(), t))

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        return torch.from_numpy(_blur(grad.contiguous().numpy(), ctx.taps)), None


def blur_compiled(maps: Tensor, taps: Tensor) -> Tensor:
    """Every map of ``maps`` (K, H, W), CPU float32/float64, blurred with the separable
    window of the odd-length, symmetric 1D ``taps``, zero padding (same size out);
    differentiable in ``maps``."""
    if maps.ndim != 3:
        raise ValueError(f"maps must be (K, H, W), got {tuple(maps.shape)}")
    n = taps.numel()
    if n % 2 == 0 or not torch.equal(taps, taps.flip(0)):
        raise ValueError("taps must be odd in length and symmetric (the backward reuses them)")
    return _Blur.apply(maps, taps)


@njit(nogil=True, cache=True)
def _ssim_map_range(lo, hi, mx, my, exx, eyy, exy, c1, c2, want, partial, sums):  # pragma: no cover
    """Maps lo..hi: each pixel's SSIM summed into sums[k] (float64), and, if ``want``,
    its partial derivatives in the image's blurred moments into partial (3, K, H, W):
    by mu_x, by E[x^2], by E[xy]. S = N / D, N = (2 mx my + C1)(2 sxy + C2), D = (mx^2 + my^2 + C1)
    (sxx + syy + C2); written as (dN - S dD) / D, no division by a term that may be 0."""
    _, H, W = mx.shape
    for k in range(lo, hi):
        acc = 0.0
        for i in range(H):
            for j in range(W):
                ux, uy = mx[k, i, j], my[k, i, j]
                sxx = exx[k, i, j] - ux * ux
                syy = eyy[k, i, j] - uy * uy
                sxy = exy[k, i, j] - ux * uy
                a1 = 2 * ux * uy + c1
                a2 = 2 * sxy + c2
                b1 = ux * ux + uy * uy + c1
                b2 = sxx + syy + c2
                d = b1 * b2
                s = a1 * a2 / d
                acc += s
                if not want:
                    continue
                partial[0, k, i, j] = (2 * uy * (a2 - a1) - s * 2 * ux * (b2 - b1)) / d
                partial[1, k, i, j] = -s * b1 / d
                partial[2, k, i, j] = 2 * a1 / d
        sums[k] = acc


@njit(nogil=True, cache=True)
def _ssim_grad_range(lo, hi, blurred, x, y, scale, out):  # pragma: no cover - numba
    """Maps lo..hi of the image gradient: scale (blur(dS/dmu_x) + 2x blur(dS/dE[x^2])
    + y blur(dS/dE[xy]))."""
    _, H, W = x.shape
    for k in range(lo, hi):
        for i in range(H):
            for j in range(W):
                out[k, i, j] = scale * (blurred[0, k, i, j] + 2 * x[k, i, j] * blurred[1, k, i, j]
                                        + y[k, i, j] * blurred[2, k, i, j])  # fmt: skip


class _SSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, img, ref, taps, c1, c2):  # type: ignore[override]
        x = img.detach().permute(2, 0, 1).contiguous().numpy()
        y = ref.detach().permute(2, 0, 1).contiguous().numpy()
        t = taps.detach().to(img.dtype).contiguous().numpy()
        k = x.shape[0]
        mu_x, exx, exy = np.split(_blur(np.concatenate([x, x * x, x * y]), t), 3)
        mu_y, eyy = np.split(_blur(np.concatenate([y, y * y]), t), 2)
        want = bool(ctx.needs_input_grad[0])  # evaluations skip the partials
        partial = np.empty((3, *x.shape) if want else (3, 0, 0, 0), x.dtype)
        sums = np.zeros(k, np.float64)
        run_ranges(_ssim_map_range, k, (mu_x, mu_y, exx, eyy, exy, x.dtype.type(c1),
                                        x.dtype.type(c2), want, partial, sums))  # fmt: skip
        ctx.saved = (x, y, t, partial)
        return torch.tensor(float(sums.sum()) / x.size, dtype=img.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        x, y, t, partial = ctx.saved
        k = x.shape[0]
        blurred = _blur(partial.reshape(3 * k, *x.shape[1:]), t).reshape(partial.shape)
        out = np.empty_like(x)
        scale = x.dtype.type(float(grad) / x.size)
        run_ranges(_ssim_grad_range, k, (blurred, x, y, scale, out))
        return torch.from_numpy(out).permute(1, 2, 0), None, None, None, None


def ssim_compiled(img: Tensor, ref: Tensor, taps: Tensor, c1: float, c2: float) -> Tensor:
    """Mean SSIM of (H, W, C) CPU float images in one compiled pass (the moments'
    blurs, then each pixel's SSIM and its partials), with a backward of one blur and
    one combine; differentiable in ``img`` only (``ref`` is the fixed target)."""
    if img.shape != ref.shape or img.ndim != 3:
        raise ValueError(f"img and ref must be the same (H, W, C), got {tuple(img.shape)} "
                         f"and {tuple(ref.shape)}")  # fmt: skip
    if ref.requires_grad:
        raise ValueError("ssim_compiled differentiates in img only; ref requires grad")
    if img.dtype != ref.dtype:
        raise ValueError(f"img is {img.dtype}, ref is {ref.dtype}")
    return _SSIM.apply(img, ref, taps, c1, c2)
