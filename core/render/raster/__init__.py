"""One rasteriser interface, several backends.

``rasterize`` splats N Gaussians with arbitrary per-Gaussian feature channels for
one camera and returns blended features (H, W, C) and alpha (H, W), plus the
screen-space means whose gradient drives densification. Backends differ only in
how they composite; projection (EWA, low-pass) and tile binning are shared.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Literal

import torch
from torch import Tensor

from core.errors import BackendUnavailableError
from core.render.raster.binning import TileBins, bin_gaussians
from core.render.raster.projection import (
    ALPHA_MIN,
    Projected,
    covariances_from,
    project_gaussians,
)
from core.render.raster.reference import rasterize_reference
from core.scene.cameras import Camera
from core.stages import stage

__all__ = [
    "BACKENDS",
    "PIPELINES",
    "PROJECTORS",
    "Projected",
    "RasterResult",
    "TileBins",
    "available_backends",
    "bin_gaussians",
    "covariances_from",
    "fallback_backend",
    "project_gaussians",
    "rasterize",
    "register_backend",
    "resolve_backend",
]


@dataclass
class RasterResult:
    """Output of one splatting pass.

    ``features`` (H, W, C) are blended without background (premultiplied by
    coverage); ``alpha`` (H, W) is the accumulated opacity. ``means2d`` (N, 2) are the
    projected centres: call ``retain_grad()`` before backward to read the view-space
    positional gradient (densification). ``radii`` (N,) is 0 for culled Gaussians.
    Packed backends (gsplat) return ``means2d`` with one row per *visible* Gaussian
    and ``gaussian_ids`` naming them; :meth:`screen_grad` gives (N, 2) either way.
    """

    features: Tensor
    alpha: Tensor
    means2d: Tensor
    radii: Tensor
    depths: Tensor
    backend: str
    gaussian_ids: Tensor | None = None

    def screen_grad(self, n: int, *, absolute: bool = False) -> Tensor | None:
        """(n, 2) gradient of the loss w.r.t. the screen-space means after backward.

        ``absolute``: the per-pixel absolute gradient sum (AbsGS), which only the
        CUDA backend computes (rasterize with ``absgrad=True``). None when backward
        has not filled it (``retain_grad()`` not called, or no absgrad computed).
        """
        g = getattr(self.means2d, "absgrad", None) if absolute else self.means2d.grad
        if g is None:
            return None
        g = g.detach()
        if self.gaussian_ids is None:
            return g.reshape(n, 2)
        out = torch.zeros(n, 2, dtype=g.dtype, device=g.device)
        return out.index_add(0, self.gaussian_ids.long(), g.reshape(-1, 2))


# name -> (is_available(device) -> str | None (reason when unavailable), composite fn)
_Composite = Callable[..., tuple[Tensor, Tensor]]
BACKENDS: dict[str, tuple[Callable[[torch.device], str | None], _Composite]] = {}


def register_backend(
    name: str, available: Callable[[torch.device], str | None], fn: _Composite
) -> None:
    """Add a compositing backend; ``available`` returns None or why it cannot run."""
    BACKENDS[name] = (available, fn)


register_backend("reference", lambda device: None, rasterize_reference)


def available_backends(device: torch.device | str = "cpu") -> list[str]:
    device = torch.device(device)
    return [n for n, (ok, _) in BACKENDS.items() if ok(device) is None]


def resolve_backend(backend: str, device: torch.device | str) -> str:
    """Turn 'auto' into a concrete backend; raise if a named one cannot run here."""
    device = torch.device(device)
    if backend == "auto":
        preferred = ["cuda", "reference"] if device.type == "cuda" else ["cpu", "reference"]
        for name in preferred:
            if name in BACKENDS and BACKENDS[name][0](device) is None:
                return name
        return "reference"
    if backend not in BACKENDS:
        known = ", ".join(["auto", *BACKENDS])
        raise BackendUnavailableError(f"unknown rasteriser backend '{backend}' (known: {known})")
    reason = BACKENDS[backend][0](device)
    if reason is not None:
        raise BackendUnavailableError(f"rasteriser backend '{backend}' is unavailable: {reason}")
    return backend


def fallback_backend(preferred: str, device: torch.device | str) -> tuple[str, str | None]:
    """``preferred`` resolved on ``device``, or 'auto''s choice and why it was replaced.

    For rendering a finished run on another machine: the backend it trained with may
    not exist here (a GPU worker's 'cuda' on a CPU-only server), but any backend
    renders the same model.
    """
    try:
        return resolve_backend(preferred, device), None
    except BackendUnavailableError as exc:
        return resolve_backend("auto", device), str(exc)


# Backends that run the whole pipeline (projection, binning, compositing) themselves.
_Pipeline = Callable[..., RasterResult]
PIPELINES: dict[str, _Pipeline] = {}


# Compiled projections (quats/scales → Projected) a compositing backend brings along;
# the others use the PyTorch ``project_gaussians``. Same signature as project_compiled.
_Projector = Callable[..., Projected]
PROJECTORS: dict[str, _Projector] = {}


def _composite_unused(*_: object, **__: object) -> tuple[Tensor, Tensor]:
    raise RuntimeError("this backend runs the whole pipeline: call rasterize(), not its composite")


def rasterize(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    opacities: Tensor,
    features: Tensor,
    camera: Camera,
    *,
    covariances: Tensor | None = None,
    backend: str = "auto",
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    tile_size: int = 16,
    absgrad: bool = False,
    antialiased: bool = False,
    order_slab: float | None = None,
    plane_order: bool | Literal["auto"] = False,
    plane_normals: Tensor | None = None,
    plane_reach: Tensor | None = None,
    pixels: Tensor | None = None,
) -> RasterResult:
    """Splat Gaussians for one camera.

    Shapes: means (N, 3) world; quats (N, 4) wxyz; scales (N, 3) positive (not log);
    opacities (N,) in [0, 1]; features (N, C). ``covariances`` (N, 3, 3), when given,
    replaces quats/scales (full-covariance ablation and tests). ``absgrad`` (CUDA
    backend only) also accumulates AbsGS's absolute screen gradient. ``antialiased``
    scales each opacity by the low-pass compensation (``Projected.compensation``).
    ``order_slab`` (world units): composite in slabs of centre depth, index order
    within one (``TrainConfig.splat_order``; not on gsplat, which sorts by itself).
    ``plane_order``: each pixel composites its splats in the order their planes meet
    its ray (``core.render.raster.plane_order``; cpu and reference backends only);
    ``"auto"``: where the backend can, else centre order (gsplat). ``plane_normals``
    (N, 3, world): the planes' normals where the caller has them (the G-buffer's);
    ``plane_reach`` (N,): their ``plane_reach`` where the caller kept it (a frozen model).
    ``pixels`` (H, W) bool: the pixels the caller will read; the others come back empty
    (zero features and alpha). Plane order's kernels skip them (a training step reads a
    few thousand of its neighbour view's pixels); elsewhere they are composited and
    zeroed.
    """
    if pixels is not None and tuple(pixels.shape) != (camera.height, camera.width):
        raise ValueError(
            f"pixels must be (H, W) = ({camera.height}, {camera.width}), got {tuple(pixels.shape)}"
        )
    if pixels is not None and pixels.dtype != torch.bool:
        raise ValueError(f"pixels must be a bool mask, got dtype {pixels.dtype}")
    if covariances is None and (quats is None or scales is None):
        raise ValueError("rasterize needs quats and scales, or covariances")
    if features.ndim != 2 or features.shape[0] != means.shape[0]:
        raise ValueError(
            f"features must be (N, C) with N={means.shape[0]}, got {tuple(features.shape)}"
        )
    name = resolve_backend(backend, means.device)
    if plane_order == "auto":
        plane_order = name not in PIPELINES
    if (order_slab is not None or plane_order) and name in PIPELINES:
        which = "plane" if plane_order else "slab"
        raise BackendUnavailableError(
            f"splat_order '{which}' needs the cpu or reference backend; '{name}' composites "
            "in its own centre-depth order (set splat_order: centre)"
        )
    if name in PIPELINES:
        res = PIPELINES[name](
            means, quats, scales, opacities, features, camera, covariances=covariances,
            near=near, far=far, eps2d=eps2d, tile_size=tile_size, absgrad=absgrad,
            antialiased=antialiased,
        )  # fmt: skip
        return _only(res, pixels)
    if absgrad:
        raise BackendUnavailableError(
            f"absgrad (AbsGS densification) needs the cuda backend; '{name}' does not compute it"
        )
    W, H = camera.width, camera.height
    projector = PROJECTORS.get(name)
    with stage("project"):
        if projector is not None and (covariances is None or not covariances.requires_grad):
            proj = projector(
                means, quats, scales, camera, covariances=covariances, near=near, far=far,
                eps2d=eps2d,
            )  # fmt: skip
        else:
            if covariances is None:
                covariances = covariances_from(quats, scales)
            proj = project_gaussians(means, covariances, camera, near=near, far=far, eps2d=eps2d)
    with stage("bin"):
        bins = bin_gaussians(
            proj.means2d, proj.depths, _bin_radii(proj.radii, opacities), W, H, tile_size,
            slab=order_slab,
        )  # fmt: skip
    fn = BACKENDS[name][1]
    native_pixels = False
    if plane_order:
        keys = plane_keys(means, quats, scales, camera, covariances, plane_normals, plane_reach)
        if name == "cpu":
            fn, native_pixels = partial(rasterize_cpu_plane, order=keys, pixels=pixels), True
        else:
            fn = partial(rasterize_reference_plane, order=keys)
    if antialiased and proj.compensation is not None:
        opacities = opacities * proj.compensation
    with stage("composite"):
        feats, alpha = fn(proj, opacities, features, bins, W, H)
    res = RasterResult(feats, alpha, proj.means2d, proj.radii, proj.depths, name)
    return res if native_pixels else _only(res, pixels)


def _only(res: RasterResult, pixels: Tensor | None) -> RasterResult:
    """``res`` with the pixels outside ``pixels`` emptied (a backend that composited
    them all)."""
    if pixels is None:
        return res
    keep = pixels.to(res.alpha.device)  # bool: rasterize refuses any other dtype
    return replace(
        res,
        features=torch.where(keep[..., None], res.features, res.features.new_zeros(())),
        alpha=torch.where(keep, res.alpha, res.alpha.new_zeros(())),
    )


def _bin_radii(radii: Tensor, opacities: Tensor) -> Tensor:
    """The radii to bin by: 0 for the Gaussians whose opacity is below ALPHA_MIN, which
    no compositing kernel evaluates (a splat's alpha is at most its opacity; NaN
    included). One-sided culling zeroes 40-50% of a trained closed object's opacities
    in every view: left in the tile lists they were sorted, placed and walked past
    for nothing. The radii the result reports (densification's visibility) stay the
    projection's."""
    live = opacities.detach().reshape(-1) >= ALPHA_MIN
    if bool(live.all()):
        return radii
    return torch.where(live.to(radii.device), radii, radii.new_zeros(()))


from core.render.raster import cpu as _cpu_backend  # noqa: E402,F401  registers "cpu"
from core.render.raster.plane_order import (  # noqa: E402  (needs the cpu backend's kernels)
    plane_keys,
    rasterize_cpu_plane,
    rasterize_reference_plane,
)
from core.render.raster.projection_compiled import project_compiled  # noqa: E402

PROJECTORS["cpu"] = project_compiled
from core.render.raster import cuda as _cuda_backend  # noqa: E402

register_backend("cuda", _cuda_backend.available, _composite_unused)
PIPELINES["cuda"] = _cuda_backend.rasterize_gsplat
