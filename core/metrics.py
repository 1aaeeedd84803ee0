"""Image and geometry metrics, computed the way papers report them.

Images live in linear light inside Glint; PSNR and SSIM are computed on the
sRGB-encoded, [0, 1]-clipped values that a viewer displays (the convention of
NeRF/3DGS benchmarks, whose ground truth is sRGB PNG).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from core.imageio import linear_to_srgb
from core.losses import ssim


def to_display(img: Tensor) -> Tensor:
    return linear_to_srgb(img.clamp(0.0, 1.0)).clamp(0.0, 1.0)


def psnr(img: Tensor, ref: Tensor, *, display: bool = True) -> float:
    """Peak signal-to-noise ratio in dB (peak 1); inf for identical images."""
    a, b = (to_display(img), to_display(ref)) if display else (img, ref)
    mse = float(((a - b) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def ssim_srgb(img: Tensor, ref: Tensor) -> float:
    """SSIM with 3DGS's 11×11 Gaussian window on display values."""
    return float(ssim(to_display(img), to_display(ref)))


def normal_angle_error_deg(pred: Tensor, gt: Tensor, mask: Tensor) -> float:
    """Mean angle in degrees between unit-normalised normal maps over ``mask``."""
    if not bool(mask.any()):
        return math.nan
    p = pred[mask]
    g = gt[mask]
    p = p / p.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    g = g / g.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos = (p * g).sum(-1).clamp(-1.0, 1.0)
    return float(torch.rad2deg(torch.acos(cos)).mean())


def depth_error(pred: Tensor, gt: Tensor, mask: Tensor) -> dict[str, float]:
    """Mean absolute and mean relative z-depth error over ``mask``."""
    if not bool(mask.any()):
        return {"abs": math.nan, "rel": math.nan}
    d = (pred[mask] - gt[mask]).abs()
    return {"abs": float(d.mean()), "rel": float((d / gt[mask].abs().clamp_min(1e-12)).mean())}
