"""Structural similarity (SSIM) of two images: the D-SSIM term of the training loss
(Eq. 15) and the SSIM figure of evaluations are the same function."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from core.kernels.dispatch import cpu_float

_SSIM_C1 = 0.01**2
_SSIM_C2 = 0.03**2


def _gaussian_taps(size: int, sigma: float, like: Tensor) -> Tensor:
    """The normalised 1D Gaussian whose outer product is 3DGS's SSIM window."""
    x = torch.arange(size, dtype=like.dtype, device=like.device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _gaussian_blur(maps: Tensor, taps: Tensor) -> Tensor:
    """Blur every channel of (1, K, H, W) with the separable window, zero padding.

    Two 1D passes instead of one 11×11: 22 multiply-adds per pixel instead of 121,
    the same result up to rounding.
    """
    k, n = maps.shape[1], taps.numel()
    pad = n // 2
    rows = F.conv2d(maps, taps.view(1, 1, 1, n).expand(k, 1, 1, n), padding=(0, pad), groups=k)
    return F.conv2d(rows, taps.view(1, 1, n, 1).expand(k, 1, n, 1), padding=(pad, 0), groups=k)


def _mean_ssim(mu_x: Tensor, mu_y: Tensor, exx: Tensor, eyy: Tensor, exy: Tensor) -> Tensor:
    """Mean SSIM from the blurred moments (means, E[x²], E[y²], E[xy])."""
    sxx = exx - mu_x**2
    syy = eyy - mu_y**2
    sxy = exy - mu_x * mu_y
    num = (2 * mu_x * mu_y + _SSIM_C1) * (2 * sxy + _SSIM_C2)
    den = (mu_x**2 + mu_y**2 + _SSIM_C1) * (sxx + syy + _SSIM_C2)
    return (num / den).mean()


def ssim(
    img: Tensor,
    ref: Tensor,
    window: int = 11,
    sigma: float = 1.5,
    *,
    compiled: bool | None = None,
) -> Tensor:
    """Mean SSIM of two (H, W, C) images, 3DGS's variant: 11×11 Gaussian, zero padding.

    The local moments are blurred separably, the rendered image's three in one call and
    the reference's two in another. ``compiled`` (None: on CPU float tensors): the
    compiled passes of core.evaluation.ssim_compiled (the whole term when only ``img``
    takes a gradient, else its blur), otherwise grouped convolutions (the torch path,
    the GPU's); all give the 2D window's value up to rounding (``python -m
    bench.ssim_loss`` times them).
    """
    x = img.permute(2, 0, 1)
    y = ref.permute(2, 0, 1)
    c = x.shape[0]
    taps = _gaussian_taps(window, sigma, x)
    if compiled is None:
        compiled = cpu_float(img, ref)
    if compiled and not ref.requires_grad and img.dtype == ref.dtype:
        from core.evaluation.ssim_compiled import ssim_compiled

        return ssim_compiled(img, ref, taps, _SSIM_C1, _SSIM_C2)
    if compiled:
        from core.evaluation.ssim_compiled import blur_compiled

        def blur(maps: Tensor) -> Tensor:
            return blur_compiled(maps, taps)
    else:

        def blur(maps: Tensor) -> Tensor:
            return _gaussian_blur(maps[None], taps)[0]

    mu_x, exx, exy = blur(torch.cat([x, x * x, x * y])).split(c)
    mu_y, eyy = blur(torch.cat([y, y * y])).split(c)
    return _mean_ssim(mu_x, mu_y, exx, eyy, exy)


def ssim_reference(img: Tensor, ref: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """SSIM by its plain definition, one 2D window per moment: what :func:`ssim` is
    tested and benchmarked against."""
    x, y = img.permute(2, 0, 1)[None], ref.permute(2, 0, 1)[None]
    c = x.shape[1]
    g = _gaussian_taps(window, sigma, x)
    w = torch.outer(g, g).expand(c, 1, window, window).contiguous()

    def blur(m: Tensor) -> Tensor:
        return F.conv2d(m, w, padding=window // 2, groups=c)

    return _mean_ssim(blur(x), blur(y), blur(x * x), blur(y * y), blur(x * y))
