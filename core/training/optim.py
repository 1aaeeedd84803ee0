"""One Adam per parameter (as gsplat does), learning-rate schedules, state surgery.

Keeping one optimizer per tensor makes densification simple: pruning or adding
Gaussians edits each optimizer's moment buffers alongside its parameter.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from core.config import TrainConfig
from core.render.gaussians import UNTRAINED_KEYS, Gaussians
from core.render.grazing import GRAZE_KEY
from core.render.roughness import ROUGH_KEY
from core.training.adam import Adam


def make_optimizers(g: Gaussians, cfg: TrainConfig, scene_radius: float) -> dict[str, Adam]:
    lr = cfg.lr
    rates = {
        "means": lr.means_init * scene_radius,
        "log_scales": lr.scales,
        "quats": lr.quats,
        "opacity_logits": lr.opacity,
        "sh_dc": lr.sh_dc,
        "sh_rest": lr.sh_rest,
        "refl_logits": lr.refl,
        GRAZE_KEY: lr.opacity,
        ROUGH_KEY: lr.roughness,
    }
    return {
        k: Adam([g.params[k]], lr=rates[k], eps=1e-15) for k in g.params if k not in UNTRAINED_KEYS
    }


def means_lr(cfg: TrainConfig, iteration: int, scene_radius: float) -> float:
    """3DGS's exponential decay of the position learning rate, scaled by the scene radius."""
    t = min(max(iteration / max(cfg.iterations, 1), 0.0), 1.0)
    lo, hi = math.log(cfg.lr.means_final), math.log(cfg.lr.means_init)
    return math.exp(hi * (1 - t) + lo * t) * scene_radius


def set_lr(opt: Adam, value: float) -> None:
    for group in opt.param_groups:
        group["lr"] = value


def replace_param(opt: Adam, new: torch.nn.Parameter, state_fn: Callable[[Tensor], Tensor]) -> None:
    """Swap the optimizer's single parameter for ``new``, mapping per-row state with ``state_fn``.

    Every state tensor shaped like the old parameter (Adam's ``exp_avg``, ``exp_avg_sq``,
    AMSGrad's ``max_exp_avg_sq``) is mapped; scalars such as ``step`` are kept, so the
    bias correction of surviving rows continues unchanged. ``new`` may be the old
    parameter itself (e.g. to zero its moments after an in-place edit).
    """
    group = opt.param_groups[0]
    old = group["params"][0]
    state = opt.state.pop(old, None)
    group["params"][0] = new
    if state:
        for key, value in list(state.items()):
            if torch.is_tensor(value) and value.ndim > 0 and value.shape == old.shape:
                state[key] = state_fn(value)
        opt.state[new] = state


def select_rows(idx: Tensor) -> Callable[[Tensor], Tensor]:
    return lambda buf: buf[idx]


def append_zero_rows(n: int) -> Callable[[Tensor], Tensor]:
    def fn(buf: Tensor) -> Tensor:
        return torch.cat([buf, buf.new_zeros((n, *buf.shape[1:]))])

    return fn


def gather_rows(src: Tensor) -> Callable[[Tensor], Tensor]:
    """Row ``i`` of the result is row ``src[i]`` of the buffer, or zeros where ``src[i] < 0``.

    One map expresses any densification step (kept rows, pruned rows dropped, new rows
    with fresh zero moments), so parameters and moments cannot drift apart.
    """

    def fn(buf: Tensor) -> Tensor:
        idx = src.to(buf.device)
        out = buf.new_zeros((idx.numel(), *buf.shape[1:]))
        old = idx >= 0
        out[old] = buf[idx[old]]
        return out

    return fn
