"""3DGS adaptive density control as a small strategy object (gsplat's ``DefaultStrategy`` shape).

The trainer calls :meth:`DensifyStrategy.step_pre_backward` on each render (so the
screen-space means keep their gradient) and :meth:`DensifyStrategy.step_post_backward`
after ``backward``. The strategy accumulates the mean view-space positional gradient
per Gaussian and, on schedule,

* **grows**: clones small Gaussians with a large gradient (under-reconstruction) and
  splits large ones (over-reconstruction) into two samples of N(μ, Σ) with scales
  divided by 1.6, the parent removed;
* **prunes** near-transparent Gaussians and, after the first opacity reset, those too
  large on screen or in the world;
* **resets opacity** to at most 0.01 so floaters must earn their opacity back.

Every topology change rewrites ``gaussians.params`` *in place* (new leaf Parameters in
the same ParameterDict) and remaps each optimizer's parameter and Adam moments with
the same row map (kept rows keep their moments, new rows start at zero, ``step`` is
kept), so the trainer's ``gaussians`` and ``optimizers`` objects stay valid. All keys
are carried, including ``refl_logits`` and any extra per-Gaussian parameter.

The schedule marks (start, stop, opacity reset interval) are on the 30k
schedule and scaled with :meth:`TrainConfig.scaled`, so a short run keeps the full
run's shape.

Differences from the references, on purpose: size pruning uses the *tracked* maximum
screen radius (3DGS zeroes ``max_radii2D`` in ``densification_postfix`` before its
prune test, so its screen-size criterion never fires); the opacity reset uses a plain
``and`` (gsplat 1.5.3 writes ``step % reset_every == 0 & step > 0``, which Python
chains as ``… == (0 & step) > 0`` and is always False, so its reset never fires).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn

from core.config import TrainConfig
from core.model.schedule import opacity_reset_every
from core.render.gaussians import Gaussians, scalar_logit
from core.render.rotations import normalize_quats, quat_to_rotmat
from core.training.adam import Adam
from core.training.optim import gather_rows, replace_param

if TYPE_CHECKING:
    from core.render.raster import RasterResult

# 3DGS constants.
RESET_OPACITY = 0.01
MIN_INTERVAL = 10
SPLIT_SAMPLES = 2
SPLIT_SCALE_DIVISOR = 0.8 * SPLIT_SAMPLES  # 1.6
WORLD_SIZE_FRACTION = 0.1  # prune when max scale > this × scene radius

STATE_VERSION = 1


def _no_stats(n: int) -> dict[str, int]:
    return {"cloned": 0, "split": 0, "pruned": 0, "reset": 0, "n": n}


class DensifyStrategy:
    """Clone / split / prune / opacity reset on the 3DGS schedule (see module docstring).

    ``scene_radius`` sets the clone/split boundary (``percent_dense`` × radius) and the
    world-space size limit (0.1 × radius), as 3DGS's ``cameras_extent``.
    """

    def __init__(self, cfg: TrainConfig, scene_radius: float) -> None:
        if not (math.isfinite(scene_radius) and scene_radius > 0):
            raise ValueError(f"scene_radius must be finite and > 0, got {scene_radius}")
        d = cfg.densify
        self.enabled = bool(d.enabled)
        self.reschedule(cfg)
        self.grad_threshold = float(d.grad_threshold)
        self.absgrad = bool(d.absgrad)
        self.split_scale = float(d.percent_dense) * scene_radius
        self.world_max_scale = WORLD_SIZE_FRACTION * scene_radius
        self.prune_opacity = float(d.prune_opacity)
        self.max_screen_size = float(d.max_screen_size)
        self.max_gaussians = int(d.max_gaussians)
        # Own CPU generator: split samples are reproducible and resume exactly.
        self._gen = torch.Generator().manual_seed(int(cfg.seed) + 0x5EED)
        # Per-Gaussian accumulators (lazily sized on the first call).
        self.grad2d: Tensor | None = None  # Σ |∂L/∂μ₂ᴰ| in NDC units
        self.count: Tensor | None = None  # views in which the Gaussian was visible
        self.max_radii: Tensor | None = None  # max screen radius / max(W, H)

    # -- schedule -----------------------------------------------------------
    def reschedule(self, cfg: TrainConfig, iteration: int = 0) -> None:
        """Place start, stop, interval and opacity resets on ``cfg``'s length (again,
        when a time-budgeted run re-plans). The reset interval stays as it was once a
        reset has passed, so two resets never fall closer than it."""
        d = cfg.densify
        self.start = cfg.scaled(d.start)
        self.stop = cfg.scaled(d.stop)
        # The interval is a number of views to average gradients over, not a point on
        # the schedule: it stays as configured, shortened so that a short run still
        # gets about ten densification steps, but never below MIN_INTERVAL views (a
        # gradient averaged over one or two views selects almost everything).
        self.interval = max(
            min(MIN_INTERVAL, d.interval), min(d.interval, (self.stop - self.start) // 10)
        )
        every = opacity_reset_every(cfg)
        old = getattr(self, "reset_every", None)
        if old is None or not (0 < old <= iteration):
            self.reset_every = every

    def is_refine_step(self, iteration: int) -> bool:
        """Grow + prune at this iteration: every ``interval`` in [start, stop), never at 0."""
        return (
            self.enabled
            and iteration > 0
            and self.start <= iteration < self.stop
            and iteration % self.interval == 0
        )

    def is_reset_step(self, iteration: int) -> bool:
        """Opacity reset at this iteration: every ``reset_every`` (0 disables) until stop."""
        return (
            self.enabled
            and self.reset_every > 0
            and 0 < iteration < self.stop
            and iteration % self.reset_every == 0
        )

    def size_pruning(self, iteration: int) -> bool:
        """Screen/world size pruning only after the first opacity reset (as 3DGS)."""
        return self.reset_every > 0 and iteration > self.reset_every

    # -- hooks ----------------------------------------------------------------
    def step_pre_backward(self, result: RasterResult) -> None:
        """Keep ``result.means2d.grad`` after backward: it is a non-leaf tensor."""
        if not result.means2d.requires_grad:
            raise ValueError("means2d does not require grad: render with autograd enabled")
        result.means2d.retain_grad()

    def step_post_backward(
        self,
        gaussians: Gaussians,
        optimizers: dict[str, Adam],
        result: RasterResult,
        iteration: int,
        width: int,
        height: int,
    ) -> dict[str, int]:
        """Accumulate this view's statistics, then grow/prune and reset opacity on schedule.

        Returns ``{"cloned", "split", "pruned", "reset", "n"}`` (``n``: the new count).
        """
        if not self.enabled or iteration >= self.stop:
            return _no_stats(gaussians.num)
        with torch.no_grad():
            self._accumulate(gaussians, result, width, height)
            stats = _no_stats(gaussians.num)
            if self.is_refine_step(iteration):
                stats.update(self._refine(gaussians, optimizers, iteration))
            if self.is_reset_step(iteration):
                self._reset_opacity(gaussians, optimizers)
                stats["reset"] = 1
        stats["n"] = gaussians.num
        return stats

    # -- accumulators -------------------------------------------------------
    def _ensure(self, n: int, device: torch.device) -> None:
        if self.grad2d is None or self.count is None or self.max_radii is None:
            self._zero(n, device)
            return
        if self.grad2d.shape[0] != n:
            raise ValueError(
                f"densify accumulators have {self.grad2d.shape[0]} rows but there are {n} "
                "Gaussians: the set was changed outside the strategy or the wrong state was loaded"
            )
        if self.grad2d.device != device:
            self.grad2d = self.grad2d.to(device)
            self.count = self.count.to(device)
            self.max_radii = self.max_radii.to(device)

    def _zero(self, n: int, device: torch.device) -> None:
        self.grad2d = torch.zeros(n, dtype=torch.float32, device=device)
        self.count = torch.zeros(n, dtype=torch.int32, device=device)
        self.max_radii = torch.zeros(n, dtype=torch.float32, device=device)

    def _accumulate(
        self, gaussians: Gaussians, result: RasterResult, width: int, height: int
    ) -> None:
        n, device = gaussians.num, gaussians.device
        self._ensure(n, device)
        assert self.grad2d is not None and self.count is not None and self.max_radii is not None
        radii = result.radii.detach().reshape(-1).to(device)
        if radii.shape[0] != n:
            raise ValueError(f"result has {radii.shape[0]} Gaussians, the set has {n}")
        visible = radii > 0
        if not bool(visible.any()):
            return
        grad = result.screen_grad(n, absolute=self.absgrad)
        if grad is None:
            raise RuntimeError(
                "means2d has no gradient: call step_pre_backward(result) before backward"
                + (" and render with absgrad=True" if self.absgrad else "")
            )
        # Pixel-space gradient → NDC units (x_ndc = 2 x_pix / W − 1), as 3DGS/gsplat.
        g = grad.to(device=device, dtype=torch.float32)
        g = g * torch.tensor([width / 2.0, height / 2.0], device=device)
        norms = torch.nan_to_num(g.norm(dim=-1), nan=0.0, posinf=0.0, neginf=0.0)
        self.grad2d[visible] += norms[visible]
        self.count[visible] += 1
        frac = radii.to(torch.float32) / float(max(width, height))
        self.max_radii = torch.where(visible, torch.maximum(self.max_radii, frac), self.max_radii)

    # -- grow + prune -----------------------------------------------------------
    def _refine(
        self, gaussians: Gaussians, optimizers: dict[str, Adam], iteration: int
    ) -> dict[str, int]:
        assert self.grad2d is not None and self.count is not None and self.max_radii is not None
        p = gaussians.params
        n, device = gaussians.num, gaussians.device
        grads = self.grad2d / self.count.clamp_min(1).to(torch.float32)
        log_scales = p["log_scales"].detach()
        max_scale = log_scales.exp().amax(dim=1)
        high = grads >= self.grad_threshold
        clone = high & (max_scale <= self.split_scale)
        split = high & (max_scale > self.split_scale)

        # Each clone or split adds one Gaussian net; keep the strongest within the cap.
        budget = max(0, self.max_gaussians - n)
        cand = (clone | split).nonzero(as_tuple=True)[0]
        if cand.numel() > budget:
            order = torch.argsort(grads[cand], descending=True, stable=True)
            chosen = torch.zeros(n, dtype=torch.bool, device=device)
            chosen[cand[order[:budget]]] = True
            clone &= chosen
            split &= chosen
        clone_idx = clone.nonzero(as_tuple=True)[0]
        split_idx = split.nonzero(as_tuple=True)[0]
        k_c, k_s = clone_idx.numel(), split_idx.numel()

        # Grown set = [originals, clones, split children (sample 0 of all, then 1)].
        parent = torch.cat(
            [torch.arange(n, device=device), clone_idx, split_idx.repeat(SPLIT_SAMPLES)]
        )
        children: dict[str, Tensor] = {}
        if k_s:
            means, ls = p["means"].detach(), log_scales[split_idx]
            R = quat_to_rotmat(normalize_quats(p["quats"].detach()[split_idx]))
            z = torch.randn(SPLIT_SAMPLES, k_s, 3, generator=self._gen)
            z = z.to(device=device, dtype=means.dtype)
            offsets = torch.einsum("nij,bnj->bni", R, ls.exp()[None] * z)  # ~ N(0, Σ)
            children["means"] = (means[split_idx][None] + offsets).reshape(-1, 3)
            children["log_scales"] = (ls - math.log(SPLIT_SCALE_DIVISOR)).repeat(SPLIT_SAMPLES, 1)
        grown: dict[str, Tensor] = {}
        for key, param in p.items():
            t = param.detach()
            child = children.get(key)
            if child is None:  # every other key (colour, opacity, w_r, ...) is inherited
                child = t[split_idx].repeat(SPLIT_SAMPLES, *([1] * (t.ndim - 1)))
            grown[key] = torch.cat([t, t[clone_idx], child.to(t.dtype)])

        # Prune on the grown set; new rows inherit their parent's screen radius.
        opacity = torch.sigmoid(grown["opacity_logits"])
        prune = opacity < self.prune_opacity
        if self.size_pruning(iteration):
            too_big_screen = self.max_radii[parent] > self.max_screen_size
            too_big_world = grown["log_scales"].exp().amax(dim=1) > self.world_max_scale
            prune |= too_big_screen | too_big_world
        is_split_parent = torch.zeros_like(prune)
        is_split_parent[split_idx] = True
        keep = ~(prune | is_split_parent)
        n_pruned = int((prune & ~is_split_parent).sum())

        # Guarantee the cap even if the set started above it: drop the least opaque.
        excess = int(keep.sum()) - self.max_gaussians
        if excess > 0:
            kept = keep.nonzero(as_tuple=True)[0]
            drop = kept[torch.argsort(opacity[kept], stable=True)[:excess]]
            keep[drop] = False
            n_pruned += excess

        if k_c == 0 and k_s == 0 and bool(keep.all()):
            self._zero(n, device)
            return {"cloned": 0, "split": 0, "pruned": 0}

        keep_idx = keep.nonzero(as_tuple=True)[0]
        src = torch.cat([torch.arange(n, device=device), torch.full_like(parent[n:], -1)])
        src = src[keep_idx]
        self._apply(gaussians, optimizers, {k: v[keep_idx] for k, v in grown.items()}, src)
        self._zero(gaussians.num, device)
        return {"cloned": k_c, "split": k_s, "pruned": n_pruned}

    def append(
        self, gaussians: Gaussians, optimizers: dict[str, Adam], values: dict[str, Tensor]
    ) -> int:
        """Add the rows ``values`` (every key of ``gaussians.params``) after the existing
        ones; their Adam moments start at zero. Returns how many were added."""
        if set(values) != set(gaussians.params):
            raise ValueError(
                f"new rows have keys {sorted(values)}, the set has {sorted(gaussians.params)}"
            )
        n, k = gaussians.num, int(values["means"].shape[0])
        if k == 0:
            return 0
        grown = {
            key: torch.cat([p.detach(), values[key].to(p)]) for key, p in gaussians.params.items()
        }
        device = gaussians.device
        src = torch.cat(
            [torch.arange(n, device=device), torch.full((k,), -1, device=device, dtype=torch.long)]
        )
        self._apply(gaussians, optimizers, grown, src)
        self._zero(gaussians.num, device)
        return k

    def remove(self, gaussians: Gaussians, optimizers: dict[str, Adam], drop: Tensor) -> int:
        """Remove the rows where ``drop`` (N,) is True, keeping the others' Adam moments;
        returns how many went (never all: a set with none left cannot train)."""
        n = gaussians.num
        if drop.shape != (n,):
            raise ValueError(f"drop mask has shape {tuple(drop.shape)}, the set has {n} rows")
        drop = drop.to(gaussians.device, torch.bool)
        k = int(drop.sum())
        if k == 0 or k == n:
            return 0
        keep_idx = (~drop).nonzero(as_tuple=True)[0]
        p = gaussians.params
        self._apply(
            gaussians, optimizers, {key: t.detach()[keep_idx] for key, t in p.items()}, keep_idx
        )
        self._zero(gaussians.num, gaussians.device)
        return k

    @staticmethod
    def _apply(
        gaussians: Gaussians,
        optimizers: dict[str, Adam],
        values: dict[str, Tensor],
        src: Tensor,
    ) -> None:
        """Install new rows in place; row i of everything came from old row src[i] (or is new)."""
        for key, opt in optimizers.items():  # check all first: never leave a half-updated set
            if key in values and opt.param_groups[0]["params"][0] is not gaussians.params[key]:
                raise ValueError(f"optimizer '{key}' does not hold gaussians.params['{key}']")
        fn = gather_rows(src)
        for key, value in values.items():
            old = gaussians.params[key]
            new = nn.Parameter(value.contiguous(), requires_grad=old.requires_grad)
            if old.grad is not None:  # a step right after densifying still sees this view
                new.grad = fn(old.grad)
            if key in optimizers:
                replace_param(optimizers[key], new, fn)
            gaussians.params[key] = new

    # -- opacity reset -------------------------------------------------------
    @staticmethod
    def _reset_opacity(gaussians: Gaussians, optimizers: dict[str, Adam]) -> None:
        """opacity ← min(opacity, 0.01) in logit space; its Adam moments restart from zero."""
        logits = gaussians.params["opacity_logits"]
        logits.data.clamp_(max=scalar_logit(RESET_OPACITY))
        opt = optimizers.get("opacity_logits")
        if opt is not None:
            replace_param(opt, logits, torch.zeros_like)

    # -- checkpointing -------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Accumulators and split RNG (weights_only-loadable): a resumed run continues exactly."""

        def cpu(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.detach().cpu().clone()

        return {
            "version": STATE_VERSION,
            "grad2d": cpu(self.grad2d),
            "count": cpu(self.count),
            "max_radii": cpu(self.max_radii),
            "rng": self._gen.get_state(),
            "reset_every": self.reset_every,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if int(state.get("version", -1)) != STATE_VERSION:
            raise ValueError(f"unsupported densify state version {state.get('version')!r}")
        tensors = [state.get(k) for k in ("grad2d", "count", "max_radii")]
        if any(t is None for t in tensors) and not all(t is None for t in tensors):
            raise ValueError("densify state: accumulators must be all present or all None")
        if tensors[0] is not None and len({int(t.shape[0]) for t in tensors}) != 1:
            raise ValueError("densify state: accumulators have different lengths")
        device = self.grad2d.device if self.grad2d is not None else torch.device("cpu")

        def load(t: Tensor | None, dtype: torch.dtype) -> Tensor | None:
            return None if t is None else torch.as_tensor(t).to(device=device, dtype=dtype).clone()

        self.grad2d = load(tensors[0], torch.float32)
        self.count = load(tensors[1], torch.int32)
        self.max_radii = load(tensors[2], torch.float32)
        self._gen.set_state(torch.as_tensor(state["rng"], dtype=torch.uint8).cpu())
        if state.get("reset_every") is not None:  # older states: the config's, as built
            self.reset_every = int(state["reset_every"])
