"""Image and geometry metrics, computed the way papers report them.

Images live in linear light inside Glint; PSNR and SSIM are computed on the
sRGB-encoded, [0, 1]-clipped values that a viewer displays (the convention of
NeRF/3DGS benchmarks, whose ground truth is sRGB PNG).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from core.evaluation.ssim import ssim
from core.scene.imageio import linear_to_srgb


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
    """Mean absolute and mean relative z-depth error over ``mask``, and the median
    signed error (rendered − true: positive = behind the true surface), which tells a
    shifted surface from a noisy one."""
    if not bool(mask.any()):
        return {"abs": math.nan, "rel": math.nan, "signed_median": math.nan}
    e = pred[mask] - gt[mask]
    d = e.abs()
    return {
        "abs": float(d.mean()),
        "rel": float((d / gt[mask].abs().clamp_min(1e-12)).mean()),
        "signed_median": float(e.median()),
    }


# -- LPIPS (only with local weights) --------------------------------------------

# torchvision's AlexNet checkpoint, which the ``lpips`` package loads as its backbone.
_LPIPS_BACKBONE = "alexnet-owt-7be5be79.pth"


def lpips_unavailable_reason() -> str | None:
    """Why LPIPS cannot be computed here, or None when it can.

    LPIPS needs the ``lpips`` package *and* its pretrained AlexNet backbone in the
    local torch hub cache; nothing is ever downloaded, so a missing piece means the
    metric is reported as unavailable rather than approximated.
    """
    import importlib.util
    from pathlib import Path

    if importlib.util.find_spec("lpips") is None:
        return "the lpips package is not installed"
    ckpt = Path(torch.hub.get_dir()) / "checkpoints" / _LPIPS_BACKBONE
    if not ckpt.is_file():
        return f"LPIPS backbone weights not found locally ({ckpt})"
    return None


_lpips_model: torch.nn.Module | None = None


def lpips_distance(img: Tensor, ref: Tensor) -> float:
    """LPIPS (AlexNet) between two linear (H, W, 3) images, on display values.

    Raises RuntimeError when :func:`lpips_unavailable_reason` says it cannot run.
    """
    global _lpips_model
    reason = lpips_unavailable_reason()
    if reason is not None:
        raise RuntimeError(f"LPIPS unavailable: {reason}")
    if _lpips_model is None:
        import lpips  # type: ignore[import-not-found]

        _lpips_model = lpips.LPIPS(net="alex", verbose=False).eval()
    model = _lpips_model.to(img.device)

    def prep(x: Tensor) -> Tensor:
        return to_display(x).permute(2, 0, 1)[None] * 2.0 - 1.0

    with torch.no_grad():
        return float(model(prep(img), prep(ref)).mean())


# -- Chamfer distance and F-score (../shared/data/README.md, "Chamfer distance") --


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform by area on a triangle mesh: (points (n, 3), face index (n,))."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if not area.sum() > 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(f), size=n, p=area / area.sum())
    r1 = np.sqrt(rng.random((n, 1)))
    r2 = rng.random((n, 1))
    pts = (1 - r1) * a[idx] + r1 * (1 - r2) * b[idx] + r1 * r2 * c[idx]
    return pts, idx


def _fscore(precision: float, recall: float) -> float:
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)


def chamfer_distance(
    pred: np.ndarray,
    gt: np.ndarray,
    *,
    max_radius: float | None = 1.1,
    threshold: float = 0.01,
    gt_seen: np.ndarray | None = None,
    pred_normals: np.ndarray | None = None,
    gt_normals: np.ndarray | None = None,
    gt_tree: Any = None,
    cap: float | None = None,
) -> dict[str, float | int]:
    """Point-to-point Chamfer distance, both directions, the data README's recipe.

    Predicted points farther than ``max_radius`` from the origin are dropped first
    (background floaters; the objects lie inside the unit sphere) and counted in
    ``dropped``. ``cd = (d(P→G) + d(G→P)) / 2`` with Euclidean nearest-neighbour
    distances (cKDTree), reported also ×100. F-score at ``threshold``: harmonic
    mean of the fraction of P within it of G (precision) and of G within it of P
    (recall). ``gt_seen`` (bool per GT point) adds the same numbers against the
    GT points seen in some training view (``*_seen``); with both normal sets,
    ``normal_consistency`` is the mean |n_p · n_g| over P→G nearest pairs. ``gt_tree``:
    a ``cKDTree`` of ``gt`` already built (a caller scoring many point sets). ``cap``:
    nearest-neighbour distances above it count as ``cap`` (bounded searches: a cloud far
    from the surface otherwise costs seconds to score; off by default).
    """
    from scipy.spatial import cKDTree

    P = np.asarray(pred, dtype=np.float64).reshape(-1, 3)
    G = np.asarray(gt, dtype=np.float64).reshape(-1, 3)
    if len(G) == 0:
        raise ValueError("chamfer_distance: no ground-truth points")
    keep = np.isfinite(P).all(axis=1)
    if max_radius is not None:
        keep &= np.linalg.norm(P, axis=1) <= max_radius
    dropped = int(len(P) - keep.sum())
    P = P[keep]
    out: dict[str, float | int] = {
        "n_pred": len(P),
        "n_gt": len(G),
        "dropped": dropped,
        "max_radius": math.inf if max_radius is None else float(max_radius),
        "threshold": float(threshold),
    }
    if len(P) == 0:
        nan = math.nan
        out.update(cd=nan, cd_x100=nan, p2g=nan, g2p=nan, precision=0.0, recall=0.0, fscore=0.0)
        return out
    bound = {} if cap is None else {"distance_upper_bound": float(cap)}
    tree = gt_tree if gt_tree is not None else cKDTree(G)
    d_pg, i_pg = tree.query(P, workers=-1, **bound)
    d_gp, _ = cKDTree(P).query(G, workers=-1, **bound)
    if cap is not None:  # misses come back as inf (and index len(G))
        i_pg = np.minimum(i_pg, len(G) - 1)
        d_pg, d_gp = np.minimum(d_pg, cap), np.minimum(d_gp, cap)

    def summary(d_pg: np.ndarray, d_gp: np.ndarray, suffix: str) -> None:
        p2g, g2p = float(d_pg.mean()), float(d_gp.mean())
        prec, rec = float((d_pg < threshold).mean()), float((d_gp < threshold).mean())
        out.update(
            {
                f"p2g{suffix}": p2g,
                f"g2p{suffix}": g2p,
                f"cd{suffix}": (p2g + g2p) / 2,
                f"cd_x100{suffix}": 100 * (p2g + g2p) / 2,
                f"precision{suffix}": prec,
                f"recall{suffix}": rec,
                f"fscore{suffix}": _fscore(prec, rec),
            }
        )

    summary(d_pg, d_gp, "")
    if gt_seen is not None:
        seen = np.asarray(gt_seen, dtype=bool).reshape(-1)
        if seen.shape[0] != len(G):
            raise ValueError(f"gt_seen has {seen.shape[0]} entries for {len(G)} GT points")
        if seen.any():
            d_ps, _ = cKDTree(G[seen]).query(P, workers=-1)
            summary(d_ps, d_gp[seen], "_seen")
        out["n_gt_seen"] = int(seen.sum())
    if pred_normals is not None and gt_normals is not None:
        pn = np.asarray(pred_normals, dtype=np.float64).reshape(-1, 3)[keep]
        gn = np.asarray(gt_normals, dtype=np.float64).reshape(-1, 3)[i_pg]
        pn = pn / np.maximum(np.linalg.norm(pn, axis=1, keepdims=True), 1e-12)
        gn = gn / np.maximum(np.linalg.norm(gn, axis=1, keepdims=True), 1e-12)
        out["normal_consistency"] = float(np.abs((pn * gn).sum(axis=1)).mean())
    return out


# -- rendering speed ---------------------------------------------------------------


def time_renders(
    render: Callable[[int], object],
    n_frames: int,
    *,
    warmup: int = 3,
    device: torch.device | str = "cpu",
) -> dict[str, float | int]:
    """Frames per second of ``render(i)``: warm-up, synchronised timing, median.

    Each frame is timed on its own (CUDA synchronised before and after, so queued
    kernels are counted); the median frame time is robust to the hiccups of a
    shared machine. FPS = 1 / median.
    """
    dev = torch.device(device)

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    for i in range(warmup):
        render(i)
    sync()
    times = []
    for i in range(n_frames):
        t0 = time.perf_counter()
        render(i)
        sync()
        times.append(time.perf_counter() - t0)
    med = float(np.median(times))
    return {
        "fps": 1.0 / med if med > 0 else math.inf,
        "median_ms": 1000.0 * med,
        "frames": n_frames,
        "warmup": warmup,
    }
