"""Phased PGSR-DR training: composes schedule, losses, densification, plan and reports.

The loop is deliberately thin: each concern lives in its own module and is tested
there. The trainer owns the state that must survive a restart (parameters,
optimizers, densification accumulators, RNG, clock) and writes it atomically.
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from core.config import ConfigError, TrainConfig
from core.devices import require_device
from core.errors import BackendUnavailableError
from core.evaluation.progress import CHAMFER_FRACTIONS, ProgressEvaluator
from core.model.checkpoint import load_checkpoint, save_checkpoint
from core.model.plan import Decision, ScenePlan
from core.model.schedule import Marks, Phase, phase_at
from core.model.trained import (
    CHECKPOINT_NAME,
    TrainedModel,
    envmap_from_state,
    scene_record,
)
from core.outputs.report import MetricsLog
from core.render.depth_geometry import facing_view, oblique_depth
from core.render.envmap import EnvMap
from core.render.gaussians import UNTRAINED_KEYS, Gaussians
from core.render.gbuffer import GBuffer, geometry_depth, render_gbuffer
from core.render.grazing import GRAZE_KEY, add_grazing_state
from core.render.orientation import SEEN_DIR, add_orientation_state, record_visibility
from core.render.raster import resolve_backend
from core.render.roughness import ROUGH_KEY, add_roughness_state, drop_roughness_state
from core.render.shading import ShadeResult, deferred_shade
from core.render.view_opacity import view_opacity_scale
from core.scene.views import Scene, View
from core.stages import stage
from core.training.adam import Adam
from core.training.budget import TimeBudget
from core.training.densify import RESET_OPACITY, DensifyStrategy
from core.training.init_points import visual_hull_points
from core.training.losses import (
    edge_weight,
    mask_loss,
    multi_view_footprint,
    multi_view_loss,
    multi_view_pixels,
    rgb_loss,
    scale_loss,
    single_view_loss,
)
from core.training.optim import make_optimizers, means_lr, set_lr
from core.training.planner import (
    check_overrides,
    decide_envmap,
    plan_scene,
    probe_view_dependence,
)
from core.training.seed_behind import hidden_everywhere, propose_behind, view_errors
from core.training.silhouette import SilhouetteDepth, silhouette_points

Event = dict[str, Any]
# Cadence evaluations while training may take at most this share of the training time:
# a cadence point is skipped when they have taken more (small images, slow renders).
# Phase ends, the run's end and the Chamfer probes are always evaluated.
EVAL_SHARE = 0.05


@dataclass
class TrainResult:
    status: str  # "succeeded" | "cancelled"
    iteration: int
    train_seconds: float
    last_metrics: dict[str, Any] = field(default_factory=dict)
    stopped_by: str = "iterations"  # "iterations" | "time" (the budget was spent)
    skipped_steps: int = 0


def background_color(cfg: TrainConfig, device: torch.device, gen: torch.Generator) -> Tensor:
    bg = cfg.background
    if bg == "white":
        return torch.ones(3, device=device)
    if bg == "black":
        return torch.zeros(3, device=device)
    if bg == "random":
        return torch.rand(3, generator=gen).to(device)
    return torch.tensor(bg, dtype=torch.float32, device=device)


def check_runnable(cfg: TrainConfig) -> torch.device:
    """The run's device, after refusing what this machine cannot train.

    Called before anything is written, so a wrong device or backend leaves no half-made
    run folder: the device must exist, the backend must run on it, and
    ``densify.absgrad`` needs the CUDA backend. Errors name the field.
    """
    device = require_device(cfg.device)
    try:
        backend = resolve_backend(cfg.backend, device)
    except BackendUnavailableError as exc:
        raise BackendUnavailableError(f"field 'backend': {exc}") from None
    if cfg.densify.absgrad and backend != "cuda":
        raise ConfigError(
            "field 'densify.absgrad': AbsGS gradients come from gsplat; it needs "
            f"backend cuda on a CUDA device (this run: backend '{cfg.backend}' on {device})"
        )
    return device


# the env map's optimisers (its texels, the scene's Fresnel F0): stepped only while the
# phase shades with the map, and dropped with it when the plan decides against one
ENVMAP_OPTIMIZERS = ("envmap", "fresnel")


def forward_view(
    gaussians: Gaussians,
    envmap: EnvMap | None,
    view_camera,
    phase: Phase,
    background: Tensor,
    backend: str,
    *,
    absgrad: bool = False,
    opacity_scale: Tensor | None = None,
    normals: Tensor | None = None,
    held_plane: bool = False,
) -> tuple[GBuffer, ShadeResult, Any]:
    """The training forward pass of one view: G-buffer + deferred shading for ``phase``
    (with gradients; readers of a trained model use ``TrainedModel.render``)."""
    with stage("gbuffer"):
        gb, res = render_gbuffer(
            gaussians, view_camera, sh_degree=phase.sh_degree, backend=backend, absgrad=absgrad,
            antialiased=phase.antialiased, lowpass=phase.lowpass, opacity_scale=opacity_scale,
            normals=normals, with_roughness=phase.envmap and envmap is not None,
            held_plane=held_plane, splat_order=phase.splat_order,
        )  # fmt: skip
    with stage("deferred_shading"):
        shade = deferred_shade(
            gb, envmap, background, enabled=phase.envmap and envmap is not None,
            fresnel=phase.fresnel,
        )  # fmt: skip
    return gb, shade, res


class Trainer:
    """Trains one scene into ``out_dir``; resumable; reports through ``on_event``."""

    def __init__(
        self,
        scene: Scene,
        cfg: TrainConfig,
        out_dir: str | Path,
        *,
        on_event: Callable[[Event], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        progress: bool = False,
    ) -> None:
        if not scene.train:
            raise ValueError("scene has no training views")
        self.device = check_runnable(cfg)  # before anything is written
        self.scene = scene
        self.cfg = cfg
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.on_event = on_event or (lambda e: None)
        self.should_stop = should_stop or (lambda: False)
        self.progress = progress
        self.radius = float(scene.radius)
        self.budget = TimeBudget.of(cfg)
        self.sched = cfg  # the config the schedule follows: cfg, resized to the time budget
        self.marks = Marks.of(cfg)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.iteration = 0
        self.train_seconds = 0.0  # training steps only
        self.eval_seconds = 0.0  # evaluation while training (metrics rows)
        self.cadence_seconds = 0.0  # of which image and per-pixel geometry evaluations
        self.io_seconds = 0.0  # checkpoints
        self.chamfer_probes = 0  # CHAMFER_FRACTIONS passed so far
        self.skipped_steps = 0
        self._step_phase: str | None = None  # the phase the last step ran in
        self._evaluator: ProgressEvaluator | None = None
        self._costs: dict[str, float] = {}  # mean seconds of one eval / chamfer / checkpoint
        self.metrics = MetricsLog(self.out / "metrics.jsonl")
        self._order: list[int] = []
        self._targets = [self._to_device(v) for v in scene.train]
        check_overrides(cfg)  # a bad override fails here, not after setup's work
        self._plan: ScenePlan | None = None  # planned on first use: a resume reads its own
        self.gaussians: Gaussians
        self.envmap: EnvMap | None = None
        self.optimizers: dict[str, Adam] = {}
        self.strategy = DensifyStrategy(cfg, self.radius)
        self.silhouette: SilhouetteDepth | None = None
        self.last_eval: dict[str, Any] = {}
        self.last_losses: dict[str, float] = {}

    @property
    def plan(self) -> ScenePlan:
        """The scene plan: the checkpoint's on resume, else planned from the capture on
        first use (planning measures the masks, 1–4 s, which a resume would throw away)."""
        if self._plan is None:
            self._plan = plan_scene(self.scene, self.cfg)
        return self._plan

    @plan.setter
    def plan(self, plan: ScenePlan) -> None:
        self._plan = plan

    # -- setup ------------------------------------------------------------
    def _to_device(self, v: View) -> View:
        mask = None if v.mask is None else v.mask.to(self.device)
        return View(v.camera, v.image.to(self.device), mask, v.name, v.path)

    def _init_fresh(self) -> None:
        random.seed(self.cfg.seed)
        np.random.seed(self.cfg.seed % (2**32))
        torch.manual_seed(self.cfg.seed)
        kw = {
            "sh_degree": self.cfg.sh_degree,
            "init_opacity": self.cfg.init_opacity,
            "init_refl": self.cfg.init_refl,
        }
        hull = None
        if self.scene.points is None and self.scene.has_masks:
            hull = visual_hull_points(
                self.scene,
                self.cfg.init_points,
                seed=self.cfg.seed,
                volume_fraction=self.cfg.init_volume_fraction,
            )
        if hull is not None:
            g = Gaussians.from_points(hull[0], hull[1], radius=self.radius, **kw)
            self.plan.init = {
                "method": "visual hull of the masks",
                "points": g.num,
                "inside_fraction": self.cfg.init_volume_fraction,
            }
        else:
            g = Gaussians.from_scene(
                self.scene, n_random=self.cfg.init_points, seed=self.cfg.seed, **kw
            )
            method = "sparse point cloud" if self.scene.points is not None else "random in bounds"
            self.plan.init = {"method": method, "points": g.num}
        self.gaussians = g.to(self.device)
        if self.cfg.ablation.one_sided:
            add_orientation_state(self.gaussians)
        if self.cfg.ablation.grazing_opacity:
            add_grazing_state(self.gaussians)
        if self.plan.envmap_possible(self.cfg):
            self.envmap = EnvMap(int(self.plan.envmap_resolution.value)).to(self.device)
        if self.plan.roughness_possible(self.cfg):
            add_roughness_state(self.gaussians, self.cfg.init_roughness)
        self.optimizers = self._make_optimizers()
        self._prepare_silhouette()
        self.plan.save(self.out / "plan.json")

    def _seeds_behind(self) -> bool:
        """Whether resets propose splats behind the surface (the proposals need the hull,
        so a scene without masks gets none)."""
        return self.cfg.densify.seed_behind > 0 and self.scene.has_masks

    def _after_reset(self, it: int, renders: list[tuple[Tensor, Tensor]]) -> dict[str, int]:
        """Prune the splats hidden in every view and propose splats behind the surface
        (``densify.prune_hidden``, ``densify.seed_behind``), from the train views
        ``renders`` (view_errors) taken just before the reset."""
        d, out = self.cfg.densify, {}
        if d.prune_hidden:
            depths = [depth for _, depth in renders]
            hidden = hidden_everywhere(self.gaussians.params["means"], self.scene.train, depths)
            out["hidden_pruned"] = self.strategy.remove(self.gaussians, self.optimizers, hidden)
        if self._seeds_behind():
            gen = torch.Generator().manual_seed(self.cfg.seed * 100_003 + it)
            n = round(d.seed_behind * self.gaussians.num)
            found = propose_behind(self.model, self.scene, n, gen, errors=renders)
            out["seeded"] = 0 if found is None else self._add_splats(*found)
        return out

    def _add_splats(self, points: Tensor, colours: Tensor) -> int:
        """Append Gaussians at ``points`` as the init makes them, at the opacity a reset
        leaves (so they compete with the rest on equal terms); returns how many."""
        g = Gaussians.from_points(
            points,
            colours,
            radius=self.radius,
            sh_degree=self.gaussians.sh_degree,
            init_opacity=RESET_OPACITY,
            init_refl=self.cfg.init_refl,
        )
        live = self.gaussians.params
        if SEEN_DIR in live:
            add_orientation_state(g)
        if GRAZE_KEY in live:
            add_grazing_state(g)
        if ROUGH_KEY in live:
            add_roughness_state(g, self.cfg.init_roughness)
        values = {k: g.params[k].detach().to(self.device) for k in live}
        return self.strategy.append(self.gaussians, self.optimizers, values)

    def _prepare_silhouette(self) -> None:
        """Find the silhouette points the plan asks for (again on resume: they are a
        deterministic function of the masks), and record how many there are."""
        self.silhouette = None
        dec = self.plan.silhouette
        if not dec.value:
            return
        pts = silhouette_points(self.scene, seed=self.cfg.seed)
        if pts is None or len(pts) == 0:
            self.plan.silhouette = Decision(
                False, "no silhouette ray touches the visual hull", dec.evidence, dec.overridden
            )
            return
        self.silhouette = SilhouetteDepth(
            pts, [v.camera for v in self.scene.train],
            touching=self.cfg.ablation.silhouette_touching,
        )  # fmt: skip
        counts = self.silhouette.counts()
        dec.evidence = {
            **dec.evidence,
            "points": len(pts),
            "median_points_per_view": int(np.median(counts)) if counts else 0,
        }

    def _resize_schedule(self, iterations: int) -> None:
        """Scale the schedule (phases, densification, learning rate) to ``iterations``."""
        if iterations == self.sched.iterations:
            return
        self.sched = self.cfg.model_copy(update={"iterations": int(iterations)})
        self.marks = Marks.of(self.sched)
        self.strategy.reschedule(self.sched, self.iteration)

    @property
    def used_seconds(self) -> float:
        """What the run has spent of its time budget: training, evaluation, checkpoints."""
        return self.train_seconds + self.eval_seconds + self.io_seconds

    def time_left(self) -> float | None:
        if self.budget is None:
            return None
        return max(0.0, self.budget.seconds - self.used_seconds)

    def _make_optimizers(self) -> dict[str, Adam]:
        opts: dict[str, Adam] = dict(make_optimizers(self.gaussians, self.cfg, self.radius))
        if self.envmap is not None:
            envmap_key, fresnel_key = ENVMAP_OPTIMIZERS
            opts[envmap_key] = Adam([self.envmap.log_radiance], lr=self.cfg.lr.envmap)
            # its own optimiser: checkpoints from before it (no such state) resume as is
            opts[fresnel_key] = Adam([self.envmap.fresnel_logit], lr=self.cfg.lr.envmap)
        return opts

    @property
    def checkpoint_path(self) -> Path:
        return self.out / CHECKPOINT_NAME

    def setup(self, resume: bool = True) -> None:
        """Start fresh, or continue from ``out_dir/checkpoint.pt`` when it exists."""
        if resume and self.checkpoint_path.is_file():
            self._load(self.checkpoint_path)
        else:
            self.metrics.truncate_after(-1)
            self._init_fresh()

    # -- checkpoints ------------------------------------------------------
    def save(self, path: Path | None = None) -> Path:
        t0 = time.perf_counter()
        path = path or self.checkpoint_path
        extra = {
            "iteration": self.iteration,
            "train_seconds": self.train_seconds,
            "eval_seconds": self.eval_seconds,
            "cadence_seconds": self.cadence_seconds,
            "io_seconds": self.io_seconds,
            "chamfer_probes": self.chamfer_probes,
            "schedule_iterations": self.sched.iterations,
            "budget": None if self.budget is None else self.budget.state_dict(),
            "skipped_steps": self.skipped_steps,
            "config": self.cfg.model_dump(mode="json"),
            "plan": self.plan.to_dict(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "densify": self.strategy.state_dict(),
            "envmap": None if self.envmap is None else self.envmap.state_dict(),
            "scene": scene_record(
                self.scene.center, self.radius, [v.camera for v in self.scene.train]
            ),
            "order": list(self._order),
            "rng_torch": torch.get_rng_state(),
            "rng_gen": self.gen.get_state(),
            "rng_python": list(random.getstate()[1]),
            "rng_python_pos": random.getstate()[2] if random.getstate()[2] is not None else -1,
        }
        save_checkpoint(path, self.gaussians, extra)
        dt = time.perf_counter() - t0
        self.io_seconds += dt
        self._note_cost("checkpoint", dt)
        self.on_event({"type": "checkpoint", "iteration": self.iteration, "path": str(path)})
        return path

    def _load(self, path: Path) -> None:
        ck = load_checkpoint(path, self.device)
        x = ck.extra
        self.gaussians = ck.gaussians
        for k, p in self.gaussians.params.items():
            p.requires_grad_(k not in UNTRAINED_KEYS)
        if self.cfg.ablation.one_sided:
            add_orientation_state(self.gaussians)  # a run from before one-sided splats
        if self.cfg.ablation.grazing_opacity:
            add_grazing_state(self.gaussians)  # a run from before grazing opacity
        self.plan = ScenePlan.from_dict(x["plan"])
        self.envmap = envmap_from_state(x.get("envmap"), self.device)
        self.optimizers = self._make_optimizers()
        self._prepare_silhouette()
        for k, o in self.optimizers.items():
            if k in x["optimizers"]:
                o.load_state_dict(x["optimizers"][k])
        self.strategy.load_state_dict(x["densify"])
        self.iteration = int(x["iteration"])
        self.train_seconds = float(x["train_seconds"])
        self.eval_seconds = float(x.get("eval_seconds", 0.0))
        self.cadence_seconds = float(x.get("cadence_seconds", self.eval_seconds))
        self.io_seconds = float(x.get("io_seconds", 0.0))
        self.chamfer_probes = int(x.get("chamfer_probes", 0))
        if self.budget is not None and isinstance(x.get("budget"), dict):
            # the time left is the checkpoint's: a crash does not refill the budget
            self.budget.load_state_dict(x["budget"])
        self._resize_schedule(int(x.get("schedule_iterations", self.cfg.iterations)))
        self.skipped_steps = int(x["skipped_steps"])
        self._order = [int(i) for i in x["order"]]
        torch.set_rng_state(x["rng_torch"].cpu())
        self.gen.set_state(x["rng_gen"].cpu())
        pos = int(x["rng_python_pos"])
        random.setstate((3, tuple(int(v) for v in x["rng_python"]), None if pos < 0 else pos))
        self.metrics.truncate_after(self.iteration)
        rows = self.metrics.rows()
        if rows and rows[-1].get("iteration") == self.iteration:
            # the row of this iteration is recorded already (a run stopped after its
            # last evaluation): the end of train() must not record it twice
            self.last_eval = rows[-1]
        self.on_event({"type": "resumed", "iteration": self.iteration})

    # -- one step ---------------------------------------------------------
    def _next_view(self) -> int:
        if not self._order:
            self._order = torch.randperm(len(self.scene.train), generator=self.gen).tolist()
        return self._order.pop()

    def current_phase(self, iteration: int | None = None) -> Phase:
        it = self.iteration if iteration is None else iteration
        return phase_at(
            self.sched,
            it,
            envmap_planned=bool(self.plan.envmap.value),
            multi_view_planned=bool(self.plan.multi_view.value),
            max_sh_degree=int(self.plan.sh_degree.value),
            reset_every=self.strategy.reset_every,
            silhouette_planned=bool(self.plan.silhouette.value),
        )

    def _gradient_ratios(self) -> list[Tensor]:
        """Each parameter's max |gradient| over √(dtype max), as 0-dim tensors.

        A gradient is usable when its ratio is < 1: finite *and* below √max, since a
        finite gradient whose square overflows would put Inf into Adam's second
        moment, freeze that parameter for good and make every later checkpoint refuse
        to save (NaN-free by contract). NaN compares False, so it fails too.
        """
        ratios = []
        for o in self.optimizers.values():
            for grp in o.param_groups:
                for p in grp["params"]:
                    if p.grad is None or p.grad.numel() == 0:
                        continue
                    limit = math.sqrt(torch.finfo(p.grad.dtype).max)
                    # max |g| from min and max: no |g| buffer the size of the gradient
                    lo, hi = torch.aminmax(p.grad.detach())
                    ratios.append(torch.maximum(-lo, hi).float() / limit)
        return ratios

    def step(self) -> dict[str, float]:
        # ``stage`` labels (torch profiler ranges, ~µs each) let bench/step_breakdown.py
        # say where a step's time goes, forward and backward.
        cfg, it = self.cfg, self.iteration
        phase = self.current_phase()
        set_lr(self.optimizers["means"], means_lr(self.sched, it, self.radius))
        vi = self._next_view()
        view = self._targets[vi]
        bg = background_color(cfg, self.device, self.gen)
        # the silhouette term reads Eq. 8 through the held-normal channels
        # (Ablation.silhouette_holds_normals; the Eq. 5 ablation has no planes)
        sil_on = phase.silhouette and self.silhouette is not None
        hold_normals = sil_on and phase.planar_depth and cfg.ablation.silhouette_holds_normals
        with stage("normals"):  # once per step: both views and their opacity factors
            normals = self.gaussians.normals()
        with stage("view_opacity"):
            cull = view_opacity_scale(
                self.gaussians, view.camera, one_sided=phase.one_sided, grazing=phase.grazing,
                normals=normals,
            )  # fmt: skip
        gb, shade, res = forward_view(
            self.gaussians, self.envmap, view.camera, phase, bg, cfg.backend,
            absgrad=cfg.densify.absgrad, opacity_scale=cull, normals=normals,
            held_plane=hold_normals,
        )  # fmt: skip
        self.strategy.step_pre_backward(res)
        with stage("rgb_loss"):
            target = view.composited(bg)
            terms: dict[str, Tensor] = {"rgb": rgb_loss(shade.final, target, cfg.loss.l1)}
            if cfg.halo_weight > 0 and view.mask is not None:
                terms["mask"] = cfg.halo_weight * mask_loss(gb.alpha, view.mask)
            if phase.scale_loss and cfg.loss.scale > 0:
                # Eq. 7 in units of the scene radius: in world units the same capture in
                # millimetres or kilometres would weigh flatness 1e6× differently.
                terms["scale"] = cfg.loss.scale * scale_loss(self.gaussians.scales / self.radius)
        with stage("depth"):
            depth, valid = geometry_depth(gb, phase.planar_depth)
            if view.mask is not None:
                valid = valid & (view.mask > 0.5)
        if phase.one_sided:
            with stage("one_sided"):
                record_visibility(self.gaussians, view.camera, depth.detach(), valid)
        # The silhouette term picks its own facing points; L_single and L_multi trust
        # the depth only where the surface faces the view (DEPTH_FACING_DEG).
        sil_valid = valid
        if cfg.ablation.facing_depth:
            valid = valid & facing_view(gb.normal, view.camera)
        if phase.single_view and cfg.loss.single_view > 0:
            with stage("single_view_loss"):
                weight = edge_weight(target) if cfg.loss.single_view_edge_aware else None
                sv_depth, sv_valid = depth, valid
                if (
                    self.plan.oblique_depth.value
                    and phase.planar_depth
                    and cfg.ablation.facing_depth
                ):
                    sv_depth, sv_valid = oblique_depth(gb, depth, sil_valid, view.camera)
                terms["single_view"] = cfg.loss.single_view * single_view_loss(
                    gb.normal, sv_depth, sv_valid, view.camera, weight,
                    same_surface=cfg.ablation.same_surface_normals,
                )  # fmt: skip
        if sil_on:
            with stage("silhouette_loss"):
                sil_depth = gb.depth_normals_held if hold_normals else depth  # same values
                terms["silhouette"] = cfg.loss.silhouette * self.silhouette(
                    vi, view.camera, sil_depth, sil_valid
                )
        nb = self.plan.neighbour_of(vi)
        if phase.multi_view and cfg.loss.multi_view > 0 and nb is not None:
            nview = self._targets[nb]
            with stage("multi_view_pixels"):
                # drawn before the neighbour is rendered, so it is rendered where the
                # loss reads it only (same loss and gradients as a whole view)
                mv_pixels = multi_view_pixels(valid, cfg.loss.multiview_pixels, self.gen)
                footprint = multi_view_footprint(
                    depth.detach(), mv_pixels, view.camera, nview.camera
                )
            with stage("neighbour"):
                with stage("view_opacity"):
                    cull_n = view_opacity_scale(
                        self.gaussians,
                        nview.camera,
                        one_sided=phase.one_sided,
                        grazing=phase.grazing,
                        normals=normals,
                    )
                with stage("gbuffer"):
                    gb_n, _ = render_gbuffer(
                        self.gaussians, nview.camera, sh_degree=0, backend=cfg.backend,
                        antialiased=phase.antialiased, lowpass=phase.lowpass,
                        opacity_scale=cull_n, normals=normals, with_roughness=False,
                        geometry_only=True,  # read for its depth and normals only
                        splat_order=phase.splat_order, pixels=footprint,
                    )  # fmt: skip
                with stage("depth"):
                    d_n, v_n = geometry_depth(gb_n, phase.planar_depth)
                    if cfg.ablation.facing_depth:
                        v_n = v_n & facing_view(gb_n.normal, nview.camera)
                    if nview.mask is not None:
                        v_n = v_n & (nview.mask > 0.5)
            with stage("multi_view_loss"):
                mv, _ = multi_view_loss(
                    depth, valid, view.camera, d_n, v_n, nview.camera,
                    max_error_px=cfg.loss.multiview_max_error_px, pixels=mv_pixels,
                    error_weighting=cfg.loss.multiview_error_weighting,
                )  # fmt: skip
            terms["multi_view"] = cfg.loss.multi_view * mv
        loss = sum(terms.values())
        for o in self.optimizers.values():
            o.zero_grad(set_to_none=True)
        values = [t.detach().float() for t in (*terms.values(), loss)]
        with stage("backward"):
            loss.backward()  # a non-finite loss gives non-finite gradients: caught below
        with stage("nan_guard"):
            # One host read-back per step for the loss values and the NaN guard together:
            # on a GPU each read is a sync, and one per parameter stalled the queue 8 times.
            host = torch.stack(values + self._gradient_ratios()).tolist()
        losses, ratios = host[: len(values)], host[len(values) :]
        ok = math.isfinite(losses[-1]) and all(r < 1.0 for r in ratios)
        if not ok:
            # The NaN guard: a non-finite loss or gradient never reaches the parameters.
            self.skipped_steps += 1
            for o in self.optimizers.values():
                o.zero_grad(set_to_none=True)
            self.iteration += 1
            return {"skipped": 1.0}
        if not phase.envmap:
            for k in ENVMAP_OPTIMIZERS:
                if k in self.optimizers:
                    self.optimizers[k].zero_grad(set_to_none=True)
        with stage("optimizer"):
            for k, o in self.optimizers.items():
                if k in ENVMAP_OPTIMIZERS and not phase.envmap:
                    continue
                o.step()
        with stage("densify"):
            renders = None
            if self.strategy.is_reset_step(it) and (
                self.cfg.densify.prune_hidden or self._seeds_behind()
            ):
                # rendered before the reset makes every splat transparent
                renders = view_errors(self.model, self.scene.train)
            stats = self.strategy.step_post_backward(
                self.gaussians, self.optimizers, res, it, view.camera.width, view.camera.height
            )
            if renders is not None and stats.get("reset"):
                stats.update(self._after_reset(it, renders))
        self.iteration += 1
        out = dict(zip(terms, losses[:-1], strict=True))
        out["total"] = losses[-1]
        out.update({f"densify_{k}": float(v) for k, v in stats.items() if v})
        return out

    # -- evaluation -------------------------------------------------------
    @property
    def model(self) -> TrainedModel:
        """The live state as a trained model (shares the tensors; nothing is copied)."""
        return TrainedModel(
            gaussians=self.gaussians,
            envmap=self.envmap,
            config=self.cfg,
            plan=self.plan,
            iteration=self.iteration,
            schedule_iterations=self.sched.iterations,
            device=self.device,
            backend=self.cfg.backend,
            cameras=[v.camera for v in self.scene.train],
            center=self.scene.center,
            radius=self.radius,
            train_seconds=self.train_seconds,
            skipped_steps=self.skipped_steps,
            path=self.checkpoint_path,
        )

    def progress_views(self) -> list[View]:
        """The few held-out views scored while training (``eval.views`` of them)."""
        pool = self.scene.test if self.scene.test else self.scene.train
        n = min(self.cfg.eval.views, len(pool))
        idx = np.linspace(0, len(pool) - 1, n).round().astype(int)
        return [pool[i] for i in idx]

    @property
    def evaluator(self) -> ProgressEvaluator:
        if self._evaluator is None:
            self._evaluator = ProgressEvaluator(
                self.progress_views(), self.scene.train, self.scene.root, self.device
            )
        return self._evaluator

    def progress_fraction(self) -> float:
        """How far the run is: of its time budget, or of its iterations, whichever is
        further (the one that ends it)."""
        frac = self.iteration / max(self.sched.iterations, 1)
        if self.budget is not None:
            frac = max(frac, self.used_seconds / self.budget.seconds)
        return min(frac, 1.0)

    def _chamfer_due(self, final: bool) -> bool:
        if self.evaluator.gt_points is None:
            return False
        if final:
            return True
        due = sum(f <= self.progress_fraction() for f in CHAMFER_FRACTIONS)
        return due > self.chamfer_probes

    @torch.no_grad()
    def evaluate(self, final: bool = False, cadence: bool = False) -> dict[str, Any]:
        """Held-out error (and geometry error or consistency) of the live model; the
        Chamfer distance of its surface points at the probe points. Timed as evaluation
        (``cadence``: a cadence point, which EVAL_SHARE limits)."""
        t0 = time.perf_counter()
        # nothing changes while evaluating: rotations and normals once, not per render
        model = self.model.freeze()
        out: dict[str, Any] = self.evaluator.images_and_geometry(model)
        out["geometry"] = self.evaluator.kind
        dt = time.perf_counter() - t0
        self._note_cost("eval", dt)
        if cadence:
            self.cadence_seconds += dt
        if self._chamfer_due(final):
            ch = self.evaluator.chamfer(model)
            if ch is not None:
                out.update(
                    cd_x100=ch["cd_x100"], fscore=ch["fscore"], chamfer_seconds=ch["seconds"]
                )
                self._note_cost("chamfer", float(ch["seconds"]))
            self.chamfer_probes = sum(f <= self.progress_fraction() for f in CHAMFER_FRACTIONS)
        self.eval_seconds += time.perf_counter() - t0
        return out

    # -- the loop ---------------------------------------------------------
    def _eval_affordable(self) -> bool:
        """A cadence evaluation runs while evaluating has cost at most EVAL_SHARE of the
        training time (phase ends and the run's end are always evaluated)."""
        return self.cadence_seconds <= EVAL_SHARE * self.train_seconds

    def _eval_every(self) -> int:
        return self.cfg.eval.every or max(1, self.sched.iterations // 20)

    def _ckpt_every(self) -> int:
        return self.cfg.checkpoint_every or max(1, self.sched.iterations // 5)

    def _record(
        self, losses: dict[str, float], final: bool = False, cadence: bool = False
    ) -> dict[str, Any]:
        metrics = self.evaluate(final, cadence)
        row = {
            "iteration": self.iteration,
            "wall_time": round(self.train_seconds, 4),
            "eval_seconds": round(self.eval_seconds, 4),
            "phase": self._ran_phase(),
            "n_gaussians": self.gaussians.num,
            "loss": losses,
            "skipped_steps": self.skipped_steps,
            **metrics,
        }
        if self.budget is not None:
            row["time_left"] = round(self.time_left() or 0.0, 3)
            row["planned_iterations"] = self.sched.iterations
        self.metrics.append(row)
        self.last_eval = row
        self.on_event({"type": "eval", **row})
        return row

    def _ran_phase(self) -> str:
        """The phase of the last step run (a budget's refit may since have moved the
        marks, so the schedule can name another phase for that iteration now)."""
        if self._step_phase is not None:
            return self._step_phase
        return self.current_phase(self.iteration - 1).name

    def _maybe_plan_view_dependence(self) -> None:
        """At the end of the RGB-only phase, decide on the env map from evidence."""
        if self.plan.envmap.pending and self.iteration >= self.marks.geometry_start:
            evidence = probe_view_dependence(
                self._targets, self.gaussians, self.cfg, self.radius, iteration=self.iteration
            )
            decide_envmap(self.plan, evidence, self.cfg)
            if not self.plan.envmap.value:
                self.envmap = None
                for k in ENVMAP_OPTIMIZERS:
                    self.optimizers.pop(k, None)
            if not self.plan.roughness_possible(self.cfg):  # nothing to blur: costs nothing
                drop_roughness_state(self.gaussians)
                self.optimizers.pop(ROUGH_KEY, None)
            self.plan.save(self.out / "plan.json")
            self.on_event({"type": "plan", "plan": self.plan.to_dict()})

    def _overhead(self, n: int, steps_seconds: float) -> float:
        """Seconds of evaluation and checkpoints a run of ``n`` iterations still makes
        from here (``steps_seconds`` of training), at their measured mean cost: cadence
        evaluations (at most EVAL_SHARE of the training), one per phase change and the
        last, the Chamfer probes left, and checkpoints. The time budget pays for them."""
        left = max(n - self.iteration, 0)
        every_eval = self.cfg.eval.every or max(1, n // 20)
        every_ckpt = self.cfg.checkpoint_every or max(1, n // 5)
        c = self._costs
        marks = Marks.of(self.cfg.model_copy(update={"iterations": n})).boundaries()
        fixed = sum(m > self.iteration for m in marks) + 1  # phase changes ahead + the end
        cadence = min(left / every_eval * c.get("eval", 0.0), EVAL_SHARE * steps_seconds)
        probes = 0
        if self.evaluator.gt_points is not None:
            probes = len(CHAMFER_FRACTIONS) - self.chamfer_probes + 1
        return (
            cadence
            + fixed * c.get("eval", 0.0)
            + probes * c.get("chamfer", 0.0)
            + (left / every_ckpt + fixed) * c.get("checkpoint", 0.0)
        )

    def _note_cost(self, kind: str, seconds: float) -> None:
        old = self._costs.get(kind)
        self._costs[kind] = seconds if old is None else 0.7 * old + 0.3 * seconds

    def _replan(self, force: bool = False) -> None:
        """Fit the schedule to the time left (a time-budgeted run, every 2% of it, and
        when it reaches its planned end with time to spare)."""
        b = self.budget
        if b is None or not b.due(self.used_seconds, force=force):
            return
        planned = b.plan(
            self.cfg, self.iteration, self.used_seconds, self.gaussians.num, self._overhead
        )
        self._resize_schedule(planned)

    def _budget_spent(self) -> bool:
        """Whether the next step, the final evaluation and checkpoint would overrun."""
        left = self.time_left()
        if left is None or self.budget is None:
            return False
        step = self.budget.step_cost(self.current_phase().name, self.gaussians.num) or 0.0
        final = self._costs.get("eval", 0.0) + self._costs.get("checkpoint", 0.0)
        if self.evaluator.gt_points is not None:
            final += self._costs.get("chamfer", 0.0)
        return left <= step + final

    def _eta(self) -> float:
        it, total = self.iteration, self.sched.iterations
        rate = it / self.train_seconds if self.train_seconds > 0 else 0.0
        eta = (total - it) / rate if rate > 0 else math.nan
        left = self.time_left()
        return eta if left is None else (left if math.isnan(eta) else min(eta, left))

    def train(self) -> TrainResult:
        bar = None
        if self.progress:
            from tqdm import tqdm

            bar = tqdm(
                total=self.sched.iterations, initial=self.iteration, desc="train", unit="it",
                dynamic_ncols=True,
            )  # fmt: skip
        if self.iteration == 0:
            self._record({})
        status, stopped_by = "succeeded", "iterations"
        while True:
            if self.iteration >= self.sched.iterations:
                self._replan(force=True)  # time left over: the estimate was cautious
                if self.iteration >= self.sched.iterations:
                    if self.budget is not None and self.iteration < self.cfg.iterations:
                        stopped_by = "time"  # the plan for the time left ended it, not the cap
                    break
            if self.should_stop():
                status = "cancelled"
                break
            if self._budget_spent():
                stopped_by = "time"
                break
            self._maybe_plan_view_dependence()
            phase = self.current_phase().name
            t0 = time.perf_counter()
            losses = self.step()
            dt = time.perf_counter() - t0
            self.train_seconds += dt
            if self.budget is not None:
                self.budget.observe(phase, dt, self.gaussians.num)
                self._replan()
            self.last_losses = losses
            it, total = self.iteration, self.sched.iterations
            boundaries = set(self.marks.boundaries())
            self._step_phase = phase
            # a phase's end is always a row: at its mark, or where a time budget's refit
            # moved the mark past the step that ended it
            if it == total or it in boundaries or self.current_phase().name != phase:
                self._record(losses, final=it == total)
            elif it % self._eval_every() == 0 and self._eval_affordable():
                self._record(losses, cadence=True)
            if it % self._ckpt_every() == 0 or it in boundaries:
                self.save()
            self.on_event(
                {
                    "type": "progress",
                    "iteration": it,
                    "total": total,
                    "phase": phase,
                    "n_gaussians": self.gaussians.num,
                    "loss": losses.get("total"),
                    "elapsed": self.train_seconds,
                    "eta": self._eta(),
                    "time_left": self.time_left(),
                    "psnr": self.last_eval.get("psnr"),
                }
            )
            if bar is not None:
                if bar.total != total:
                    bar.total = total
                bar.update(1)
                bar.set_postfix(
                    phase=phase,
                    n=self.gaussians.num,
                    psnr=f"{self.last_eval.get('psnr', float('nan')):.2f}",
                )
        if status == "succeeded" and self.last_eval.get("iteration") != self.iteration:
            self._record(self.last_losses, final=True)  # the run's end is always a row
        if bar is not None:
            bar.close()
        self.save()
        return TrainResult(
            status, self.iteration, self.train_seconds, dict(self.last_eval), stopped_by,
            self.skipped_steps,
        )  # fmt: skip
