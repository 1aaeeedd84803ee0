"""The G-buffer: one splatting pass gives everything deferred shading and the
geometric losses need (paper Sect. 4.1, Eq. 5, 6, 8)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.kernels.dispatch import cpu_float
from core.render.gbuffer_compiled import (
    FeatureLayout,
    can_build_compiled,
    features_compiled,
    lower_median_positive,
)
from core.render.raster import RasterResult, rasterize
from core.render.roughness import roughness as splat_roughness
from core.scene.cameras import Camera
from core.stages import stage

if TYPE_CHECKING:
    from core.render.gaussians import Gaussians


# Pixels whose accumulated opacity is below this have no depth (Eq. 5 and Eq. 8).
MIN_ALPHA = 0.05
# Pixels whose blended normal is this close to perpendicular to the ray (|cos| below,
# about 87.1°) have no planar depth: 1/cos amplifies any normal error beyond use.
MIN_COS = 0.05
# Near plane as a fraction of the median depth of the Gaussians in front of the
# camera. A fixed near plane in world units makes rendering depend on the scene's
# unit: at the rasteriser's 0.01 a scene in millimetres (object ~3e-3 away) was
# culled entirely. Relative to the view's own depth scale it is unit-free.
NEAR_FRACTION = 1e-3


@dataclass
class GBuffer:
    """Per-pixel buffers of one view; all (H, W[, C]) float tensors on one device.

    - ``base``: blended base colour (SH evaluated for this view), (H, W, 3).
    - ``normal``: blended camera-space normal (OpenCV axes, not normalised), (H, W, 3).
    - ``plane_dist``: blended plane distance D = n·μ in camera space, (H, W); None
      when the pass left the depth out (``render_gbuffer_tensors(depth=False)``).
    - ``w_r``: blended reflection strength in [0, 1], (H, W).
    - ``alpha``: accumulated opacity, (H, W).
    - ``camera``: the view these buffers belong to.
    - ``z_blend``: blended centre z Σ z_i α_i T_i (premultiplied), (H, W); None when
      the buffers were not splatted (then ``center_depth`` is unavailable).
    - ``roughness``: blended (premultiplied) roughness ρ, (H, W); None when the model
      has none (``core.render.roughness``): the env map is then read as a mirror.

    Derived on first use and then kept (a viewer frame of the final colour never pays
    for depth):

    - ``depth``: planar z-depth d = D / (N·r̃) (Eq. 8), 0 where invalid, (H, W).
    - ``depth_valid``: bool (H, W), False where alpha or |N·r̃| is too small.
    - ``center_depth``: conventional blended centre depth (Eq. 5) divided by alpha
      where alpha is large enough, 0 elsewhere, (H, W).
    """

    base: Tensor
    normal: Tensor
    plane_dist: Tensor | None
    w_r: Tensor
    alpha: Tensor
    camera: Camera
    z_blend: Tensor | None = None
    roughness: Tensor | None = None
    normal_held: Tensor | None = None
    plane_dist_held: Tensor | None = None
    min_alpha: float = MIN_ALPHA
    min_cos: float = MIN_COS

    def _eq8(self, normal: Tensor, plane_dist: Tensor) -> tuple[Tensor, Tensor]:
        return planar_depth(
            normal, plane_dist, self.alpha, self.camera, min_alpha=self.min_alpha,
            min_cos=self.min_cos,
        )  # fmt: skip

    @cached_property
    def _planar(self) -> tuple[Tensor, Tensor]:
        if self.plane_dist is None:
            raise ValueError(
                "this G-buffer has no depth: it was rendered without its depth channels "
                "(render it with the 'depth' channel)"
            )
        return self._eq8(self.normal, self.plane_dist)

    @property
    def depth(self) -> Tensor:
        return self._planar[0]

    @cached_property
    def depth_normals_held(self) -> Tensor:
        """Eq. 8's depth, same values as ``depth``, whose gradient moves the splats'
        planes along their normals and never turns them (see ``held_plane`` in
        :func:`render_gbuffer_tensors`)."""
        if self.normal_held is None or self.plane_dist_held is None:
            raise ValueError("this G-buffer has no held-normal plane distance (held_plane=False)")
        return self._eq8(self.normal_held, self.plane_dist_held)[0]

    @property
    def depth_valid(self) -> Tensor:
        return self._planar[1]

    @cached_property
    def center_depth(self) -> Tensor:
        if self.z_blend is None:
            raise ValueError("this G-buffer has no blended centre z (it was not splatted)")
        covered = self.alpha > self.min_alpha
        return torch.where(covered, self.z_blend / torch.where(covered, self.alpha, 1.0), 0.0)


def gbuffer_features(
    means: Tensor,
    colors: Tensor | None,
    normals_world: Tensor,
    w_r: Tensor | None,
    camera: Camera,
    *,
    roughness: Tensor | None = None,
    held: bool = False,
    compiled: bool = True,
) -> Tensor:
    """(N, C) channels each Gaussian splats, in :class:`FeatureLayout` order: base (3),
    facing camera normal (3), D, w_r, z; roughness (N,) as a tenth when given; the held
    normal (3) and held D (normals detached) last when ``held``. ``colors`` None: a
    geometry-only pass, normal (3), D and z (``w_r`` and ``roughness`` unused).

    CPU float tensors take the compiled kernel and its hand-written backward
    (``core.render.gbuffer_compiled``); ``compiled=False`` keeps this PyTorch path, the
    reference it is tested against (and the path on a GPU).
    """
    geometry_only = colors is None
    rough = None if geometry_only else roughness
    w_r = None if geometry_only else w_r
    layout = FeatureLayout(geometry_only, rough is not None, held and not geometry_only)
    if compiled and can_build_compiled(means, colors, normals_world, w_r, rough):
        return features_compiled(means, colors, normals_world, w_r, camera, layout, rough)
    n_cam, D, mu_cam = _facing_planes(means, normals_world, camera)
    if geometry_only:
        return torch.cat([n_cam, D, mu_cam[:, 2:3]], dim=-1)
    cols = [colors, n_cam, D, w_r[:, None], mu_cam[:, 2:3]]
    if rough is not None:
        cols.append(rough[:, None])
    if layout.held:
        n_held, _, _ = _facing_planes(means, normals_world.detach(), camera)
        cols += [n_held, (n_held * mu_cam).sum(-1, keepdim=True)]
    return torch.cat(cols, dim=-1)


def _facing_planes(means: Tensor, normals_world: Tensor, camera: Camera) -> tuple[Tensor, ...]:
    """Camera-space normal flipped to face the camera (n·μ_cam ≤ 0), plane distance
    D = n·μ_cam (N, 1) and camera-space centre (N, 3)."""
    R = camera.R.to(means)
    mu_cam = means @ R.T + camera.t.to(means)
    n_cam = normals_world @ R.T
    sign = torch.where((n_cam * mu_cam).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(means)
    n_cam = n_cam * sign
    return n_cam, (n_cam * mu_cam).sum(-1, keepdim=True), mu_cam


def near_plane(z_cam: Tensor, fraction: float = NEAR_FRACTION) -> float:
    """Scale-free near plane: ``fraction`` × the median of the positive camera depths.

    ``z_cam`` (N,) are the Gaussians' camera-space z. With none in front of the
    camera nothing is visible and any positive value will do (1.0 is returned).
    """
    z = z_cam.detach()
    if z.device.type == "cpu" and z.dtype == torch.float32:  # the median by radix select
        med = lower_median_positive(z)
        return 1.0 if med is None else fraction * med
    z = z[torch.isfinite(z) & (z > 0)]
    if z.numel() == 0:
        return 1.0
    return fraction * float(z.median())


def planar_depth(
    normal: Tensor,
    plane_dist: Tensor,
    alpha: Tensor,
    camera: Camera,
    *,
    min_alpha: float = MIN_ALPHA,
    min_cos: float = MIN_COS,
    compiled: bool | None = None,
) -> tuple[Tensor, Tensor]:
    """Eq. 8 per pixel: d = D / (N·r̃) with r̃ = K⁻¹(u, v, 1); (depth, valid).

    Invalid pixels (low alpha, grazing normal, non-positive or non-finite depth) get
    depth 0 and no gradient: the division is guarded, never Inf or NaN. ``compiled``:
    one numba pass and its backward (core.render.planar_depth_compiled; None: for CPU
    buffers), False: the torch ops below, the reference.
    """
    rays = camera.camera_rays(normal.dtype, normal.device)
    if compiled is None:
        compiled = cpu_float(normal)
    if compiled:
        from core.render.planar_depth_compiled import planar_depth_compiled

        return planar_depth_compiled(normal, plane_dist, alpha, rays, min_alpha, min_cos)
    ndotr = (normal * rays).sum(-1)
    norm = normal.norm(dim=-1) * rays.norm(dim=-1)
    cos = ndotr.abs() / norm.clamp_min(1e-30)
    valid = (alpha > min_alpha) & (cos > min_cos) & (norm > 0)
    safe_den = torch.where(valid, ndotr, torch.ones_like(ndotr))
    d = plane_dist / safe_den
    valid = valid & (d > 0) & torch.isfinite(d)
    depth = torch.where(valid, d, torch.zeros_like(d))
    return depth, valid


def geometry_depth(gb: GBuffer, planar: bool) -> tuple[Tensor, Tensor]:
    """(depth, valid) that losses, exports and meshes use: planar Eq. 8, or the Eq. 5
    blended centre depth of the ablation (valid wherever it was computed)."""
    if planar:
        return gb.depth, gb.depth_valid
    return gb.center_depth, gb.alpha > MIN_ALPHA


def order_slab(scales: Tensor | None, covariances: Tensor | None) -> float | None:
    """Depth slab of ``TrainConfig.splat_order = 'slab'``: twice the median of the splats'
    largest extents (σ, world units), so the splats of one stretch of surface share a
    slab and are composited in index order, whatever their centres' depth along a
    tilted surface (None: no splats). With centre order the splats displaced toward the
    camera come first and weigh most, and colours and normals lean toward them."""
    if scales is not None:
        extent = scales.detach().amax(-1)
    elif covariances is not None:
        extent = torch.diagonal(covariances.detach(), dim1=-2, dim2=-1).amax(-1).clamp_min(0).sqrt()
    else:
        return None
    if extent.numel() == 0:
        return None
    h = 2.0 * float(extent.median())
    return h if h > 0 and math.isfinite(h) else None


def render_gbuffer_tensors(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    opacities: Tensor,
    colors: Tensor | None,
    normals_world: Tensor,
    w_r: Tensor,
    camera: Camera,
    *,
    covariances: Tensor | None = None,
    backend: str = "auto",
    min_alpha: float = MIN_ALPHA,
    min_cos: float = MIN_COS,
    near: float | None = None,
    absgrad: bool = False,
    antialiased: bool = False,
    lowpass: float = 0.3,
    roughness: Tensor | None = None,
    held_plane: bool = False,
    depth: bool = True,
    splat_order: str = "centre",
    plane_reach: Tensor | None = None,
    pixels: Tensor | None = None,
) -> tuple[GBuffer, RasterResult]:
    """One splatting pass with 9 channels: base (3), normal (3), D, w_r, centre z, and
    roughness as a tenth when ``roughness`` (N,) is given.

    ``colors`` (N, 3) are already evaluated for this view; None splats the geometry
    only (normal, D, centre z: a pass read for depth, e.g. a training step's neighbour
    view): its ``base`` and ``w_r`` are zeros, and ``w_r``/``roughness`` are ignored.
    ``normals_world`` (N, 3)
    are Eq. 6 normals (any sign: they are flipped toward the camera here). ``near``
    (world units) defaults to :func:`near_plane` of this view, so the same scene in
    millimetres, metres or kilometres renders the same images. ``lowpass`` (px²) is the
    screen-space filter added to each splat (``TrainConfig.lowpass_2d``). ``splat_order``
    (``TrainConfig.splat_order``): 'slab' composites in depth slabs of
    :func:`order_slab`, 'plane' each pixel in the order its ray meets the splats' planes,
    'auto' plane order where the backend has it (not on gsplat: centre order).

    ``held_plane`` splats four more channels, last: the normal and D again, n̄ and n̄·μ
    with the splats' normals detached (``GBuffer.normal_held``, ``plane_dist_held``). A
    loss that should move the surface without turning it reads Eq. 8 through them: its
    gradient reaches each centre along its normal and the blending weights by how far
    each splat's plane is from the pixel's point. Detaching the blended N or D instead
    breaks that balance (D = n·μ alone varies by |μ| with a splat's orientation), and
    training collapsed each way it was tried (docs/benchmarks.md, issue 36).

    ``depth=False`` composites neither D nor centre z (``plane_dist`` and ``z_blend``
    are None): a frame read for its colour, normal, w_r or roughness only (the viewer's
    shaded frame) splats 7 channels instead of 9. ``plane_reach`` (N,): a frozen model's
    kept ``plane_reach`` of its scales, for plane order (else taken from ``covariances``).
    ``pixels`` (H, W) bool: the pixels the caller reads; the others come back empty
    (``rasterize``; plane order does not composite them).
    """
    geometry_only = colors is None
    held = held_plane and not geometry_only
    with stage("features"):
        feats = gbuffer_features(
            means, colors, normals_world, w_r, camera, roughness=roughness, held=held
        )
    # the columns as gbuffer_features laid them out
    lay = FeatureLayout(geometry_only, roughness is not None and not geometry_only, held)
    if near is None:
        near = near_plane(feats[:, lay.z])
    if not depth:
        feats = feats[:, lay.columns_without_depth()]
    res = rasterize(
        means,
        quats,
        scales,
        opacities,
        feats,
        camera,
        covariances=covariances,
        backend=backend,
        near=near,
        absgrad=absgrad,
        antialiased=antialiased,
        eps2d=lowpass,
        order_slab=order_slab(scales, covariances) if splat_order == "slab" else None,
        plane_order="auto" if splat_order == "auto" else splat_order == "plane",
        plane_normals=normals_world,
        plane_reach=plane_reach,
        pixels=pixels,
    )
    ch = split_channels(res.features, lay, depth=depth)
    if geometry_only:
        zero = res.features.new_zeros(res.features.shape[:-1])
        ch["base"], ch["w_r"] = zero[..., None].expand(*zero.shape, 3), zero
    gb = GBuffer(
        base=ch["base"],
        normal=ch["normal"],
        plane_dist=ch.get("plane_dist"),
        w_r=ch["w_r"],
        alpha=res.alpha,
        camera=camera,
        z_blend=ch.get("z_blend"),
        roughness=ch.get("roughness"),
        normal_held=ch.get("normal_held"),
        plane_dist_held=ch.get("plane_dist_held"),
        min_alpha=min_alpha,
        min_cos=min_cos,
    )
    return gb, res


def split_channels(features: Tensor, lay: FeatureLayout, depth: bool = True) -> dict[str, Tensor]:
    """The composited features (H, W, C) as their G-buffer fields (``depth=False``: a
    pass that left D and centre z out). Their gradients come back as one concatenation:
    slicing each field off the image instead made autograd zero a full-size gradient
    buffer per field and add them up (5 fills, 4 adds and their copies, ~1 ms of a CPU
    training step)."""
    groups = lay.groups(depth)
    parts = _SplitChannels.apply(features, tuple(w for _, w in groups))
    return {
        name: part if w > 1 else part.squeeze(-1)
        for (name, w), part in zip(groups, parts, strict=True)
    }


class _SplitChannels(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features, widths):  # type: ignore[override]
        ctx.set_materialize_grads(False)
        ctx.widths = widths
        ctx.lead = features.shape[:-1]
        return features.split(list(widths), dim=-1)

    @staticmethod
    @once_differentiable
    def backward(ctx, *grads):  # type: ignore[override]
        if all(g is None for g in grads):
            return None, None
        like = next(g for g in grads if g is not None)
        parts = [
            g if g is not None else like.new_zeros(*ctx.lead, w)
            for g, w in zip(grads, ctx.widths, strict=True)
        ]
        return torch.cat(parts, dim=-1), None


def render_gbuffer(
    gaussians: Gaussians,
    camera: Camera,
    *,
    sh_degree: int,
    backend: str = "auto",
    opacity_scale: Tensor | None = None,
    normals: Tensor | None = None,
    with_roughness: bool = True,
    geometry_only: bool = False,
    **kw,
) -> tuple[GBuffer, RasterResult]:
    """G-buffer of a Gaussian model for one view (SH evaluated toward this camera).

    ``normals``: the model's Eq. 6 normals when the caller already has them (a training
    step renders two views and the opacity factors read them too: computed once, their
    backward runs once). ``with_roughness=False`` leaves the model's roughness out (a
    frame or phase that does not read the env map splats no channel for it).
    ``geometry_only``: splat normal, D and centre z only, no colours (a view read for
    its depth; see :func:`render_gbuffer_tensors`)."""
    op = gaussians.opacities if opacity_scale is None else gaussians.opacities * opacity_scale
    colors = None
    if not geometry_only:
        with stage("sh_colors"):
            colors = gaussians.colors(camera, sh_degree)
    if normals is None:
        with stage("normals"):
            normals = gaussians.normals()
    return render_gbuffer_tensors(
        gaussians.params["means"],
        # raw: every projection normalises (and differentiates through) it itself
        gaussians.params["quats"],
        gaussians.scales,
        op,
        colors,
        normals,
        gaussians.w_r,
        camera,
        backend=backend,
        roughness=splat_roughness(gaussians) if with_roughness and not geometry_only else None,
        **kw,
    )
