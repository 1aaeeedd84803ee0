"""Adam with torch.optim.Adam's update and state_dict, without torch.optim.

Why not torch.optim: its ``Optimizer`` imports ``torch._dynamo`` on first use (the
``add_param_group`` and ``step`` wrappers), 1.6–2 s of every training process's start
on this CPU (each API job, CLI run and test), and each ``step`` of the nine per-tensor
optimizers goes through its hooks, profiler ranges and grad-mode switches. Here a step
is the fused kernel torch.optim itself calls (``torch._fused_adam_``), or, where that
kernel does not apply, the textbook update (the reference the tests hold both to, with
torch.optim.Adam beside them).

The object keeps the attributes the trainer and densification use (``param_groups``
with ``params``/``lr``, ``state`` keyed by parameter), and ``state_dict`` has
torch.optim.Adam's layout, so checkpoints written by either load in the other.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import torch
from torch import Tensor

# devices with a fused Adam kernel in torch (for floating-point tensors)
FUSED_DEVICES = ("cpu", "cuda")

# group entries torch.optim.Adam writes; kept so either class reads the other's state
_GROUP_DEFAULTS: dict[str, Any] = {
    "weight_decay": 0.0,
    "amsgrad": False,
    "maximize": False,
    "foreach": None,
    "capturable": False,
    "differentiable": False,
    "decoupled_weight_decay": False,
}
_MOMENTS = ("exp_avg", "exp_avg_sq")


def fused_kernel_applies(params: Iterable[Tensor]) -> bool:
    """torch has a fused Adam kernel for floating-point tensors on the CPU and CUDA."""
    return all(p.is_floating_point() and p.device.type in FUSED_DEVICES for p in params)


class Adam:
    """Adam (no weight decay, no AMSGrad) over a list of tensors that share one rate.

    ``fused=None`` takes torch's fused kernel where it has one for these tensors: one
    pass per tensor instead of a dozen elementwise ops (3.3 -> 0.7 ms for a 20k-Gaussian
    model's eight groups on one CPU core; equal to the plain update to float32 rounding,
    tested). ``load_state_dict`` keeps that choice: a checkpoint written before the fused
    kernel (``fused: None`` in its groups) does not switch it off."""

    def __init__(
        self,
        params: Iterable[Tensor],
        *,
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        fused: bool | None = None,
    ) -> None:
        params = list(params)
        if not params:
            raise ValueError("Adam needs at least one parameter")
        if not lr >= 0.0 or not eps >= 0.0 or not all(0.0 <= b < 1.0 for b in betas):
            raise ValueError(f"Adam: lr={lr}, eps={eps}, betas={betas} out of range")
        if fused is None:
            fused = fused_kernel_applies(params)
        elif fused and not fused_kernel_applies(params):
            raise ValueError("Adam: the fused kernel needs floating-point CPU or CUDA tensors")
        group = {"params": params, "lr": float(lr), "betas": tuple(betas), "eps": float(eps)}
        group.update(_GROUP_DEFAULTS, fused=True if fused else None)
        self.param_groups: list[dict[str, Any]] = [group]
        self.state: dict[Tensor, dict[str, Tensor]] = {}

    # --- the update ----------------------------------------------------------------

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.detach_().zero_()

    def _state_of(self, p: Tensor, fused: bool) -> dict[str, Tensor]:
        st = self.state.get(p)
        if st is None:
            # torch.optim.Adam's placement: the step count beside the parameter for the
            # fused kernel, else a CPU scalar
            step = (
                torch.zeros((), dtype=torch.float32, device=p.device)
                if fused
                else torch.tensor(0.0, dtype=_scalar_dtype())
            )
            st = {"step": step}
            for name in _MOMENTS:
                st[name] = torch.zeros_like(p, memory_format=torch.preserve_format)
            self.state[p] = st
        return st

    @torch.no_grad()
    def step(self) -> None:
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            fused = bool(group.get("fused"))
            states = [self._state_of(p, fused) for p in params]
            if fused:
                self._fused_step(group, params, states)
            else:
                for p, st in zip(params, states, strict=True):
                    adam_update(p, p.grad, st, group)

    @staticmethod
    def _fused_step(group: dict[str, Any], params: list[Tensor], states: list[dict]) -> None:
        beta1, beta2 = group["betas"]
        steps = [st["step"] for st in states]
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(
            params,
            [p.grad for p in params],
            [st["exp_avg"] for st in states],
            [st["exp_avg_sq"] for st in states],
            [],
            steps,
            amsgrad=False,
            lr=group["lr"],
            beta1=beta1,
            beta2=beta2,
            weight_decay=0.0,
            eps=group["eps"],
            maximize=False,
            grad_scale=None,
            found_inf=None,
        )

    # --- state ---------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """torch.optim.Adam's layout: parameters numbered in order across the groups."""
        index: dict[int, int] = {}
        groups = []
        for group in self.param_groups:
            ids = []
            for p in group["params"]:
                index.setdefault(id(p), len(index))
                ids.append(index[id(p)])
            groups.append({**{k: v for k, v in group.items() if k != "params"}, "params": ids})
        state = {index[id(p)]: dict(st) for p, st in self.state.items() if id(p) in index}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Load a state saved by this class or by torch.optim.Adam; this optimizer keeps
        its own kernel choice (a state saved without the fused kernel would switch it off),
        and the moments take each parameter's dtype and device."""
        saved = state_dict.get("param_groups")
        if not isinstance(saved, list) or len(saved) != len(self.param_groups):
            raise ValueError(
                f"optimizer state has {len(saved) if isinstance(saved, list) else 'no'} "
                f"parameter groups, expected {len(self.param_groups)}"
            )
        by_id: dict[Any, tuple[Tensor, bool]] = {}
        for mine, theirs in zip(self.param_groups, saved, strict=True):
            if len(mine["params"]) != len(theirs["params"]):
                raise ValueError(
                    f"optimizer state has a group of {len(theirs['params'])} parameters, "
                    f"expected {len(mine['params'])}"
                )
            fused = bool(mine.get("fused"))
            for key, p in zip(theirs["params"], mine["params"], strict=True):
                by_id[key] = (p, fused)
        new_state: dict[Tensor, dict[str, Tensor]] = {}
        for key, st in state_dict.get("state", {}).items():
            if key in by_id:
                p, fused = by_id[key]
                new_state[p] = self._placed(p, st, fused)
        for mine, theirs in zip(self.param_groups, saved, strict=True):
            keep = {"params": mine["params"], "fused": mine.get("fused"), "foreach": None}
            mine.update({k: v for k, v in theirs.items() if k not in keep}, **keep)
            mine["betas"] = tuple(mine["betas"])
        self.state = new_state

    @staticmethod
    def _placed(p: Tensor, st: dict[str, Any], fused: bool) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name, value in st.items():
            if not torch.is_tensor(value):
                out[name] = value
            elif name == "step":
                step = value.detach().clone()
                out[name] = (
                    step.to(device=p.device, dtype=torch.float32)
                    if fused
                    else step.to(device="cpu", dtype=_scalar_dtype())
                )
            else:
                out[name] = value.detach().to(device=p.device, dtype=p.dtype).clone()
        return out


def _scalar_dtype() -> torch.dtype:
    return torch.float64 if torch.get_default_dtype() == torch.float64 else torch.float32


def adam_update(p: Tensor, grad: Tensor, st: dict[str, Tensor], group: dict[str, Any]) -> None:
    """One Adam update of ``p`` in place (Kingma & Ba, with torch's epsilon placement):
    the reference the fused kernel is tested against."""
    beta1, beta2 = group["betas"]
    exp_avg, exp_avg_sq = st["exp_avg"], st["exp_avg_sq"]
    if torch.is_complex(p):  # as torch.optim does: the real and imaginary parts apart
        p, grad = torch.view_as_real(p), torch.view_as_real(grad)
        exp_avg, exp_avg_sq = torch.view_as_real(exp_avg), torch.view_as_real(exp_avg_sq)
    st["step"] += 1
    t = float(st["step"])
    exp_avg.lerp_(grad, 1.0 - beta1)
    exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1.0 - beta2)
    bias1 = 1.0 - beta1**t
    bias2 = 1.0 - beta2**t
    denom = (exp_avg_sq.sqrt() / math.sqrt(bias2)).add_(group["eps"])
    p.addcdiv_(exp_avg, denom, value=-group["lr"] / bias1)
