"""A PyTorch twin of ``gsplat.rasterization`` so the "cuda" code paths run on CPU.

No GPU has been lent to this project's development sessions, so everything Glint
does *around* gsplat (argument layout, packed outputs, densification statistics, the
GPU benchmark's plain 3DGS render) is checked here instead: projection is gsplat's
own PyTorch reference (``gsplat.cuda._torch_impl``), SH colours are its
``_spherical_harmonics`` (+0.5, clamped at 0, as gsplat does), and binning and
compositing are this project's reference rasteriser (the CUDA kernels' semantics,
to be checked against the real kernels on a GPU by ``tests/test_raster_cuda.py``).

``twin_as_cuda`` makes ``backend="cuda"`` resolve on CPU and run the twin.
"""

from __future__ import annotations

from typing import Any

import pytest
import torch
from torch import Tensor

from core.render.raster import Projected, bin_gaussians
from core.render.raster.reference import rasterize_reference


def _sh_colors(
    impl: Any, sh_degree: int, means: Tensor, coeffs: Tensor, viewmats: Tensor
) -> Tensor:
    """gsplat's SH evaluation for one camera: (N, K, 3) coefficients → (N, 3) colours."""
    campos = torch.linalg.inv(viewmats[0])[:3, 3]
    rgb = impl._spherical_harmonics(sh_degree, means - campos, coeffs)
    return torch.clamp_min(rgb + 0.5, 0.0)


def gsplat_twin(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    packed: bool = True,
    tile_size: int = 16,
    render_mode: str = "RGB",
    rasterize_mode: str = "classic",
    absgrad: bool = False,
    covars: Tensor | None = None,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """``gsplat.rasterization`` for one camera, same defaults and outputs, any device.

    ``absgrad`` is accepted but not computed (``means2d.absgrad`` stays unset), so
    code that needs it fails loudly here rather than reading a made-up value.
    """
    impl = pytest.importorskip("gsplat.cuda._torch_impl")
    if viewmats.shape[0] != 1 or render_mode != "RGB":
        raise NotImplementedError("the twin renders one camera in RGB mode")
    if covars is None:
        covars, _ = impl._quat_scale_to_covar_preci(quats, scales, True, False, triu=False)
    radii, means2d, depths, conics, comp = impl._fully_fused_projection(
        means, covars, viewmats, Ks, width, height,
        eps2d=eps2d, near_plane=near_plane, far_plane=far_plane,
        calc_compensations=rasterize_mode == "antialiased",
    )  # fmt: skip
    if comp is not None:
        opacities = opacities * comp[0]
    if sh_degree is not None:
        colors = _sh_colors(impl, sh_degree, means, colors, viewmats)
    radii, means2d, depths, conics = radii[0], means2d[0], depths[0], conics[0]
    visible = (radii > 0).all(dim=-1)
    if packed:
        ids = torch.nonzero(visible).squeeze(1)
        m2d_out = means2d[ids]  # gsplat's packed rows; compositing reads them back
        full = means2d.index_put((ids,), m2d_out)
        meta: dict[str, Any] = {"gaussian_ids": ids, "radii": radii[ids], "depths": depths[ids]}
    else:
        m2d_out = means2d[None]
        full = m2d_out[0]
        meta = {"gaussian_ids": None, "radii": radii[None], "depths": depths[None]}
    meta["means2d"] = m2d_out
    r = torch.where(visible, radii.amax(dim=-1), 0).to(torch.int64)
    proj = Projected(means2d=full, conics=conics, depths=depths, radii=r, cov2d=None)  # type: ignore[arg-type]
    bins = bin_gaussians(full, depths, r, width, height, tile_size)
    feats, alpha = rasterize_reference(proj, opacities, colors, bins, width, height)
    return feats[None], alpha[None, ..., None], meta


@pytest.fixture
def twin_as_cuda(monkeypatch: pytest.MonkeyPatch) -> None:
    """``backend="cuda"`` resolves on this machine and runs :func:`gsplat_twin`."""
    pytest.importorskip("gsplat.cuda._torch_impl")
    import core.render.raster as raster
    from core.render.raster import cuda as cuda_backend

    _, composite = raster.BACKENDS["cuda"]
    monkeypatch.setitem(raster.BACKENDS, "cuda", (lambda device: None, composite))
    monkeypatch.setattr(cuda_backend, "gsplat_rasterization", lambda: gsplat_twin)
