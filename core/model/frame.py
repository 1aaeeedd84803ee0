"""One rendered view of a trained model, and its channels as images.

The same mapping from G-buffer and shading to the user-facing channels (``final``,
``base``, ``specular``, ``normal``, ``depth``, ``w_r``, ``roughness``, ``alpha``) serves the
renders an export writes and the frames the viewer streams.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from core.model.channels import CHANNELS
from core.model.display8 import encode_srgb8
from core.render.gbuffer import GBuffer, geometry_depth
from core.render.shading import ShadeResult
from core.scene.cameras import Camera
from core.scene.imageio import srgb_to_linear

# channels that need deferred shading (env map lookups); the others read the G-buffer
SHADED = frozenset({"final", "specular"})
# channels that read the splats' roughness (when the model has one)
ROUGH = frozenset({"final", "specular", "roughness"})
# channels that need per-Gaussian colours (SH toward the camera)
COLOURED = frozenset({"final", "specular", "base"})
# channels that read the depth (D and centre z: two composited channels a frame of
# colour, normal, w_r, roughness or alpha leaves out)
DEPTH = frozenset({"depth"})


def colormap(x: Tensor, valid: Tensor, name: str = "turbo") -> Tensor:
    """Map a scalar image to RGB (linear) with a matplotlib colormap; invalid → black."""
    import matplotlib

    v = x[valid]
    lo, hi = (float(v.min()), float(v.max())) if v.numel() else (0.0, 1.0)
    t = ((x - lo) / max(hi - lo, 1e-12)).clamp(0, 1).cpu().numpy()
    rgb = matplotlib.colormaps[name](t)[..., :3].astype(np.float32)
    out = torch.from_numpy(rgb)
    out[~valid.cpu()] = 0.0
    # Colormaps are defined in display space; store linear so an sRGB encode round-trips.
    return srgb_to_linear(out)


def to_display(linear: Tensor) -> np.ndarray:
    """Linear RGB (H, W, 3) as display-ready 8-bit sRGB on the CPU (by table,
    ``core.model.display8``: exactly the formula, 8× faster)."""
    return encode_srgb8(linear)


@dataclass
class Frame:
    """A G-buffer (and its deferred shading, when a shaded channel was asked for)."""

    camera: Camera
    gbuffer: GBuffer
    shade: ShadeResult | None
    background: Tensor
    planar_depth: bool

    def depth(self) -> tuple[Tensor, Tensor]:
        """The depth the model's geometry uses (Eq. 8 planar, or Eq. 5) and where valid
        (a frame rendered without the ``depth`` channel has none: ValueError)."""
        return geometry_depth(self.gbuffer, self.planar_depth)

    def world_normals(self) -> Tensor:
        """Rendered normals in world space (not renormalised)."""
        gb = self.gbuffer
        return gb.normal @ self.camera.R.to(gb.normal)

    def image(self, channel: str) -> Tensor:
        """One channel as linear RGB (H, W, 3) on the render's device (depth: CPU)."""
        gb = self.gbuffer
        if channel in SHADED:
            if self.shade is None:
                raise ValueError(f"channel {channel!r} needs shading; render it with the frame")
            return self.shade.final if channel == "final" else self.shade.specular
        if channel == "base":
            return gb.base + (1 - gb.alpha[..., None]) * self.background
        if channel == "normal":
            n = self.world_normals()
            n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            # (n+1)/2 is a display encoding: store it linear so sRGB output gives it back
            return srgb_to_linear((n * 0.5 + 0.5) * gb.alpha[..., None])
        if channel == "depth":
            depth, valid = self.depth()
            return colormap(depth.cpu(), valid.cpu())
        if channel == "w_r":
            return gb.w_r[..., None].expand(-1, -1, 3)
        if channel == "roughness":  # like w_r: blended, i.e. ρ × coverage; 0 = mirror
            rough = gb.alpha.new_zeros(gb.alpha.shape) if gb.roughness is None else gb.roughness
            return rough[..., None].expand(-1, -1, 3)
        if channel == "alpha":
            return gb.alpha[..., None].expand(-1, -1, 3)
        raise ValueError(f"unknown channel {channel!r}; expected one of {', '.join(CHANNELS)}")

    def images(self, channels: tuple[str, ...] = CHANNELS) -> dict[str, Tensor]:
        """Several channels as linear RGB (H, W, 3) on the CPU."""
        return {ch: self.image(ch).cpu() for ch in channels}
