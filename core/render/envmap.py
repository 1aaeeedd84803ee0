"""The learnable environment map E of Eq. 9: a cube map with seamless bilinear lookup.

Faces, in storage order, follow the OpenGL / DirectX cube-map convention::

    index  face  major axis   sc     tc
      0     +X      +x        -z     -y
      1     -X      -x        +z     -y
      2     +Y      +y        +x     +z
      3     -Y      -y        +x     -z
      4     +Z      +z        +x     -y
      5     -Z      -z        -x     -y

For a direction d the face is that of its largest |component| (ties go to the lower
axis: x before y before z; the lookup is continuous there, so the choice does not
change the value). With ma = |d_major|: s = (sc / ma + 1) / 2 is the column coordinate
and t = (tc / ma + 1) / 2 the row coordinate, both in [0, 1]; texel (row j, column i)
of an R×R face has its centre at s = (i + 0.5) / R, t = (j + 0.5) / R. Texels are stored
channel-last, (6, R, R, C). The cube lives in whatever world frame the cameras use
(the dev scenes are +Z up; nothing here assumes an up axis).

Seams: each face is padded with a one-texel border copied from the neighbouring faces
(the neighbour's edge texel at the same position along the shared edge), and each
padded corner is the mean of the three texels that meet at that cube corner. Bilinear
filtering inside the padded face is then continuous across every edge and corner: on
an edge both faces blend the same two texel rows with the same weights, and at a cube
corner all three faces return the mean of the three corner texels. The padding is a
gather from the parameters, rebuilt each call (6·(R+2)² texels), so gradients reach
the texels that the border copies.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from core.kernels.dispatch import cpu_float
from core.render.cube_faces import (
    direction_to_face_uv,
    face_uv_to_direction,
    pad_plan_cpu,
)

FACE_NAMES: tuple[str, ...] = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


def texel_directions(
    resolution: int,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    normalize: bool = True,
) -> Tensor:
    """(6, R, R, 3) world directions through the texel centres, in storage order."""
    r = resolution
    c = (torch.arange(r, dtype=torch.float64) + 0.5) * (2.0 / r) - 1.0
    vv, uu = torch.meshgrid(c, c, indexing="ij")
    face = torch.arange(6).view(6, 1, 1).expand(6, r, r)
    d = face_uv_to_direction(face, uu.expand(6, r, r), vv.expand(6, r, r))
    if normalize:
        d = d / d.norm(dim=-1, keepdim=True)
    return d.to(dtype=dtype, device=device)


@lru_cache(maxsize=16)
def _pad_plan(resolution: int, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    return tuple(t.to(device) for t in pad_plan_cpu(resolution))  # type: ignore[return-value]


def pad_cube(texels: Tensor) -> Tensor:
    """(6, R, R, C) -> (6, R+2, R+2, C) with a seamless one-texel border (differentiable)."""
    six, r, r2, ch = texels.shape
    if six != 6 or r != r2:
        raise ValueError(f"cube texels must be (6, R, R, C), got {tuple(texels.shape)}")
    src, corner_pos, corner_src = _pad_plan(r, texels.device)
    flat = texels.reshape(6 * r * r, ch)
    padded = flat[src]
    corners = flat[corner_src].mean(dim=1)
    padded = padded.index_copy(0, corner_pos, corners)
    return padded.view(6, r + 2, r + 2, ch)


def _min_major(dtype: torch.dtype) -> float:
    # Below this the 1/ma factors of the projection and its gradient could overflow.
    return math.sqrt(torch.finfo(dtype).tiny)


def guarded_face_uv(dirs: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Flattened (valid, face, u, v) of directions (..., 3): a non-finite or zero-length
    direction is marked invalid and projected as +Z, so nothing downstream sees NaN."""
    d = dirs.reshape(-1, 3).to(dtype)
    valid = torch.isfinite(d).all(dim=-1) & (d.abs().amax(dim=-1) > _min_major(d.dtype))
    plus_z = torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype, device=d.device)
    d = torch.where(valid.unsqueeze(-1), d, plus_z)
    return (valid, *direction_to_face_uv(d))


def sample_cube(texels: Tensor, dirs: Tensor, *, compiled: bool | None = None) -> Tensor:
    """Seamless bilinear lookup of cube texels (6, R, R, C) at directions (..., 3) -> (..., C).

    Directions need not be unit length. A direction that is not finite, or whose largest
    |component| is below sqrt(smallest normal of the dtype) (≈1e-19 in float32, i.e.
    zero length), returns 0 with zero gradient, so a bad pixel can neither produce nor
    propagate NaN into the texel gradients. Differentiable in texels and directions
    (the direction gradient runs through the face projection sc/ma, tc/ma).
    ``compiled``: the padding and the per-pixel lookup, each with its backward, as the
    numba loops of ``core.render.envmap_pack_compiled`` and
    ``core.render.envmap_lookup_compiled`` with one level (None: for CPU tensors), False:
    the torch ops below, the reference.
    """
    if dirs.shape[-1] != 3:
        raise ValueError(f"directions must be (..., 3), got {tuple(dirs.shape)}")
    r, ch = texels.shape[1], texels.shape[-1]
    p = r + 2
    lead = dirs.shape[:-1]
    if compiled is None:
        compiled = cpu_float(texels, dirs)
    if compiled:
        from core.render.envmap_lookup_compiled import sample_packed_lod
        from core.render.envmap_pack_compiled import packed_cube_levels

        d = dirs.reshape(-1, 3).to(texels.dtype)
        level0 = torch.zeros(d.shape[0], dtype=texels.dtype)
        padded, offsets, sizes = packed_cube_levels(texels, mips=False)
        out = sample_packed_lod(padded, offsets, sizes, d, level0, _min_major(texels.dtype))
        return out.reshape(*lead, ch)
    valid, face, u, v = guarded_face_uv(dirs, texels.dtype)

    # Continuous coordinates in the padded face, texel centres at integers:
    # u = -1 -> 0.5 (edge between border and first texel), u = +1 -> R + 0.5.
    x = (u + 1.0) * (0.5 * r) + 0.5
    y = (v + 1.0) * (0.5 * r) + 0.5
    padded = pad_cube(texels).reshape(-1, ch)
    out = _PaddedBilinear.apply(padded, x, y, face * (p * p), p)
    out = torch.where(valid.unsqueeze(-1), out, torch.zeros((), dtype=out.dtype, device=out.device))
    return out.reshape(*lead, ch)


class _PaddedBilinear(torch.autograd.Function):
    """Bilinear taps inside padded faces, with a hand-written backward.

    Autograd through the gather and the lerps allocates and zero-fills several
    (N, 4, C) buffers; this keeps the backward to one index_add into the texels and two
    dot products for the coordinates (a quarter less time for forward + backward on
    CPU). ``x``, ``y`` are padded texel coordinates in [0.5, R + 0.5]; ``base`` is the
    first flat index of each face; ``p`` the padded face size R + 2, one for all or
    one per lookup (``core.render.envmap_mips`` packs every mip level in one buffer).
    First derivatives only (nothing here needs more).
    """

    @staticmethod
    def forward(ctx, padded: Tensor, x: Tensor, y: Tensor, base: Tensor, p: int | Tensor) -> Tensor:
        if isinstance(p, Tensor):  # a padded size per lookup (mip levels of one chain)
            top = (p - 2).to(x.dtype)
            x0 = torch.minimum(x.floor().clamp_min(0), top)
            y0 = torch.minimum(y.floor().clamp_min(0), top)
        else:
            x0 = x.floor().clamp(0, p - 2)
            y0 = y.floor().clamp(0, p - 2)
        fx = (x - x0).unsqueeze(-1)
        fy = (y - y0).unsqueeze(-1)
        i00 = base + y0.long() * p + x0.long()
        idx = torch.stack([i00, i00 + 1, i00 + p, i00 + p + 1], dim=-1).view(-1)
        # index_select (backward: index_add) is much faster on CPU than advanced indexing.
        taps = padded.index_select(0, idx).view(-1, 4, padded.shape[-1])
        t0, t1, t2, t3 = taps.unbind(1)
        top = t0 + fx * (t1 - t0)
        bottom = t2 + fx * (t3 - t2)
        ctx.save_for_backward(idx, taps, fx, fy)
        ctx.num_texels = padded.shape[0]
        return top + fy * (bottom - top)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        idx, taps, fx, fy = ctx.saved_tensors
        grad_padded = grad_x = grad_y = None
        if ctx.needs_input_grad[0]:
            gx, gy = 1.0 - fx, 1.0 - fy
            w = torch.stack([gx * gy, fx * gy, gx * fy, fx * fy], dim=1)  # (N, 4, 1)
            contrib = (w * grad.unsqueeze(1)).view(-1, grad.shape[-1])
            grad_padded = grad.new_zeros(ctx.num_texels, grad.shape[-1])
            grad_padded.index_add_(0, idx, contrib)
        if ctx.needs_input_grad[1] or ctx.needs_input_grad[2]:
            t0, t1, t2, t3 = taps.unbind(1)
            d_top, d_bottom = t1 - t0, t3 - t2
            grad_x = (grad * (d_top + fy * (d_bottom - d_top))).sum(-1)
            d_y = (t2 - t0) + fx * (d_bottom - d_top)  # bottom - top
            grad_y = (grad * d_y).sum(-1)
        return grad_padded, grad_x, grad_y, None, None


# Largest log radiance a texel can reach (e^16 ≈ 9e6: beyond any captured HDR sun).
MAX_LOG_RADIANCE = 16.0


FRESNEL_MIN_F0 = 0.02


class EnvMap(nn.Module):
    """Learnable cube map E (Eq. 9): ``log_radiance`` (6, R, R, C), radiance = exp of it.

    Why log radiance: an environment spans orders of magnitude (a studio's curtains at
    0.01, its lamps at 1000), and the map must reach whatever brightness w_r leaves it
    (w_r · E is what the photos fix; a mirror learned with w_r = 0.05 needs E twenty
    times the photo's radiance). Adam moves a parameter by about its learning rate per
    step, so in log space every texel changes by about the same *fraction* per step
    whatever the scene's exposure; with the earlier softplus (linear above ~1) the step
    was absolute, and a bright or dim capture needed more steps to get there. Measured
    on sphere_mirror at 1500 iterations (2026-11-25): env-map PSNR after exposure 20.6 dB
    with softplus, 25.9 dB in log space at the same learning rate. The default init is a
    constant grey of 0.5. Checkpoints from before (a ``raw`` softplus parameter) load
    converted.
    """

    def __init__(
        self,
        resolution: int = 128,
        channels: int = 3,
        init_value: float = 0.5,
        min_value: float = 1e-6,
    ) -> None:
        super().__init__()
        if resolution < 1 or channels < 1:
            raise ValueError("resolution and channels must be positive")
        if not (init_value > 0 and math.isfinite(init_value)):
            raise ValueError("init_value must be positive and finite (radiance is exp(log))")
        self.min_value = float(min_value)
        self.log_radiance = nn.Parameter(
            torch.full((6, resolution, resolution, channels), math.log(init_value))
        )
        # The scene's head-on reflectance for the Fresnel rise (core.render.fresnel): a
        # property of the material, kept with the light because Eq. 9 fixes only w_r · E,
        # so how far a reflection rises toward grazing angles is relative to this map's
        # scale. Learned with the map; starts at F0 = 0.51 (logit 0).
        self.fresnel_logit = nn.Parameter(torch.zeros(()))

    @property
    def resolution(self) -> int:
        return self.log_radiance.shape[1]

    @property
    def channels(self) -> int:
        return self.log_radiance.shape[-1]

    @property
    def fresnel_f0(self) -> Tensor:
        """F0 in [FRESNEL_MIN_F0, 1] (0-dim): the floor, water's 0.02, is the least any
        real surface reflects head-on and bounds the rise (1 − F0) / F0 at 49×."""
        return FRESNEL_MIN_F0 + (1.0 - FRESNEL_MIN_F0) * torch.sigmoid(self.fresnel_logit)

    def texels(self) -> Tensor:
        """Radiance per texel, (6, R, R, C), differentiable in ``log_radiance``."""
        return torch.exp(self.log_radiance.clamp(max=MAX_LOG_RADIANCE))

    def sample(self, dirs: Tensor) -> Tensor:
        """Radiance toward world directions (..., 3) -> (..., C); see :func:`sample_cube`."""
        return sample_cube(self.texels(), dirs)

    def forward(self, dirs: Tensor) -> Tensor:
        return self.sample(dirs)

    @torch.no_grad()
    def set_texels(self, values: Tensor) -> None:
        """Set the radiance to ``values`` (6, R, R, C); values below ``min_value`` are raised
        to it (a log has no zero)."""
        p = self.log_radiance
        if tuple(values.shape) != tuple(p.shape):
            raise ValueError(f"texels must be {tuple(p.shape)}, got {tuple(values.shape)}")
        v = values.detach().to(device=p.device, dtype=torch.float64)
        if not torch.isfinite(v).all():
            raise ValueError("environment map values must be finite")
        p.copy_(torch.log(v.clamp_min(self.min_value)).clamp(max=MAX_LOG_RADIANCE).to(p.dtype))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[override]
        legacy = prefix + "raw"
        if legacy in state_dict and prefix + "log_radiance" not in state_dict:
            # a checkpoint from before: radiance was softplus(raw)
            raw = state_dict.pop(legacy)
            radiance = nn.functional.softplus(raw.double()).clamp_min(self.min_value)
            state_dict[prefix + "log_radiance"] = torch.log(radiance).to(raw.dtype)
        if prefix + "fresnel_logit" not in state_dict:  # saved before Fresnel: unused there
            state_dict[prefix + "fresnel_logit"] = torch.zeros(())
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        return f"resolution={self.resolution}, channels={self.channels}, activation=exp"
