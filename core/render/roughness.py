"""Per-Gaussian roughness: how blurred the environment each splat reflects is.

Eq. 9 reflects a single direction per pixel, which is right for a mirror and wrong
for everything else: brushed, rough or coated surfaces reflect a cone. Without a
roughness the only way to fit a blurred reflection is to blur the learned env map
itself (one map for the whole object, so a rough handle blurs the reflection in a
mirror-like body) or to lower w_r. With it, each splat carries ρ ∈ (0, 1) (glTF's
perceptual roughness, GGX α = ρ²), blended into the G-buffer like w_r, and the
deferred pass reads the env map's mip chain at the level ρ gives
(``core.render.envmap_mips``): the learned map can stay sharp.

The parameter is optional, like the grazing state: a model has it when its plan uses
roughness (``plan.roughness``: on with the env map unless switched off by
``ablation.roughness`` or ``plan_overrides``), and a model without it renders exactly
as before (ρ = 0, a mirror lookup), with no extra channel splatted.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

if TYPE_CHECKING:
    from core.render.gaussians import Gaussians

ROUGH_KEY = "rough_logits"
# Initial ρ: a lobe of about a texel of a 32² map (the auto resolution of 128-px
# captures), so the LOD has a gradient toward both sharper and blurrier from the start
# (at ρ → 0 the smooth LOD is flat and a splat could not learn to be rough).
DEFAULT_INIT_ROUGHNESS = 0.15


def has_roughness(gaussians: Gaussians) -> bool:
    return ROUGH_KEY in gaussians.params


def add_roughness_state(gaussians: Gaussians, init: float = DEFAULT_INIT_ROUGHNESS) -> None:
    """Give a model its learnable per-splat roughness (ρ = ``init``) if it has none."""
    if has_roughness(gaussians):
        return
    if not 0.0 < init < 1.0:
        raise ValueError(f"initial roughness must be in (0, 1), got {init}")
    p = gaussians.params["means"]
    logit = math.log(init / (1.0 - init))
    gaussians.params[ROUGH_KEY] = torch.nn.Parameter(
        torch.full((p.shape[0],), logit, dtype=p.dtype, device=p.device)
    )


def drop_roughness_state(gaussians: Gaussians) -> None:
    """Remove the roughness (the plan decided against an env map: it would cost for nothing)."""
    if has_roughness(gaussians):
        del gaussians.params[ROUGH_KEY]


def roughness(gaussians: Gaussians) -> Tensor | None:
    """ρ per splat (N,) in (0, 1), differentiable; None when the model has none."""
    if not has_roughness(gaussians):
        return None
    return torch.sigmoid(gaussians.params[ROUGH_KEY])
