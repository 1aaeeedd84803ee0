"""CUDA backend ("cuda"): gsplat's fused projection, tile intersection and compositing.

Unlike the CPU backends, which only composite after the shared torch projection,
gsplat fuses projection, binning and rasterisation in CUDA kernels, so this backend
takes the whole pipeline: ``rasterize`` hands it quats/scales (or covariances) and it
returns a :class:`~core.render.raster.RasterResult` in this project's layout.

Conventions that make it a drop-in for the reference (checked on CPU against gsplat's
own PyTorch twin of the projection, ``tests/test_raster_cuda.py``): cameras are
OpenCV world-to-camera 4×4 (gsplat's ``viewmats``) with a general K; pixel centres at
+0.5; features are N-D colours blended without background; alpha is skipped below
1/255 and compositing stops before T falls below 1e-4. Known differences, within the
tested tolerances: gsplat clamps a Gaussian's alpha at 0.999 (3DGS and the reference:
0.99), bins with a per-axis, opacity-aware radius, and adds the 2D low-pass without
our PSD clamp for rank-1 footprints.

``packed=True`` (the default) keeps only visible (Gaussian, camera) pairs, which saves
memory at 300k+ Gaussians; ``RasterResult.gaussian_ids`` then maps rows of
``means2d`` back to Gaussians and :meth:`RasterResult.screen_grad` scatters the
gradient for densification. ``absgrad=True`` makes gsplat also accumulate the
per-pixel absolute gradient (AbsGS), read by ``screen_grad(absolute=True)``.

gsplat is an optional dependency (``pip install 'glint[cuda]'``); its CUDA extension
is compiled at image build time in ``docker/worker.Dockerfile`` or JIT on first use
(docs/deploy.md lists what the JIT build needs). CPU machines never import it.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from core.scene.cameras import Camera

INSTALL_HINT = "pip install 'glint[cuda]' (gsplat; see docs/deploy.md for its CUDA build)"

Rasterization = Callable[..., tuple[Tensor, Tensor, dict[str, Any]]]


def available(device: torch.device) -> str | None:
    """None when gsplat can run on ``device``, else why not (for the error message)."""
    if device.type != "cuda":
        return f"it needs a CUDA device, got '{device.type}'"
    if not torch.cuda.is_available():
        return "this torch build has no usable CUDA (CPU-only build or no driver)"
    if importlib.util.find_spec("gsplat") is None:
        return f"gsplat is not installed: {INSTALL_HINT}"
    return None


def gsplat_rasterization() -> Rasterization:
    """gsplat's ``rasterization`` (imported lazily: importing it on CPU costs time)."""
    from gsplat import rasterization

    return rasterization


def camera_matrices(
    camera: Camera, dtype: torch.dtype, device: torch.device
) -> tuple[Tensor, Tensor]:
    """(viewmats (1, 4, 4), Ks (1, 3, 3)) in gsplat's layout for one camera."""
    viewmat = camera.world_to_cam.to(device=device, dtype=dtype)[None]
    K = camera.intrinsics.K(dtype=dtype, device=device)[None]
    return viewmat, K


def _unbatch(t: Tensor, n: int, ids: Tensor | None, fill: float = 0.0) -> Tensor:
    """gsplat's (1, N, …) or packed (nnz, …) per-Gaussian output → (N, …)."""
    if ids is None:
        return t.reshape(n, *t.shape[2:])
    out = torch.full((n, *t.shape[1:]), fill, dtype=t.dtype, device=t.device)
    return out.index_copy(0, ids.long(), t)


def rasterize_gsplat(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    opacities: Tensor,
    features: Tensor,
    camera: Camera,
    *,
    covariances: Tensor | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    tile_size: int = 16,
    packed: bool = True,
    absgrad: bool = False,
    antialiased: bool = False,
    impl: Rasterization | None = None,
) -> Any:
    """One view through gsplat; returns a RasterResult (features (H, W, C), alpha (H, W)).

    gsplat's kernels are float32: other dtypes are cast on the way in and the outputs
    cast back, so autograd still reaches the caller's tensors. ``impl`` replaces
    gsplat's ``rasterization`` (tests run a PyTorch twin of it on CPU).
    """
    from core.render.raster import RasterResult

    fn = impl or gsplat_rasterization()
    dtype, device = means.dtype, means.device
    f32 = torch.float32
    n = means.shape[0]
    viewmats, Ks = camera_matrices(camera, f32, device)
    if covariances is not None:
        quats_in, scales_in, covars = None, None, covariances.to(f32)
    else:
        if quats is None or scales is None:
            raise ValueError("rasterize_gsplat needs quats and scales, or covariances")
        quats_in, scales_in, covars = quats.to(f32), scales.to(f32), None
    colors, alphas, meta = fn(
        means.to(f32),
        quats_in,
        scales_in,
        opacities.to(f32),
        features.to(f32),
        viewmats,
        Ks,
        camera.width,
        camera.height,
        near_plane=float(near),
        far_plane=float(far),
        eps2d=float(eps2d),
        sh_degree=None,
        packed=packed,
        tile_size=int(tile_size),
        render_mode="RGB",
        rasterize_mode="antialiased" if antialiased else "classic",
        absgrad=absgrad,
        covars=covars,
    )
    ids = meta.get("gaussian_ids") if packed else None
    radii = meta["radii"]
    if radii.ndim >= 2 and radii.shape[-1] == 2:  # gsplat ≥ 1.5: per-axis radii
        radii = radii.amax(dim=-1)
    radii = _unbatch(radii.to(torch.int64), n, ids)
    depths = _unbatch(meta["depths"].detach().to(dtype), n, ids)
    return RasterResult(
        features=colors[0].to(dtype),
        alpha=alphas[0, ..., 0].to(dtype),
        means2d=meta["means2d"],
        radii=radii,
        depths=depths,
        backend="cuda",
        gaussian_ids=ids,
    )
