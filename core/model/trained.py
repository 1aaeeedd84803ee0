"""A trained model: what every reader of a run renders through.

Outputs, mesh extraction, evaluation, the benchmark and the viewer all need the same
thing: the Gaussians, the env map, the config and plan that say which phase the run
ended in (SH degree, deferred shading, planar depth, antialiasing), the cameras and
scene box, and one way to render a set of channels for a camera. The trainer hands
out its live state as one (``Trainer.model``); everything else opens one from a run
folder or checkpoint with :meth:`TrainedModel.open`, without importing training.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from core.config import TrainConfig, saved_config
from core.model.checkpoint import CheckpointError, load_checkpoint
from core.model.frame import COLOURED, DEPTH, ROUGH, SHADED, Frame
from core.model.placement import reopen_placement
from core.model.plan import ScenePlan
from core.model.schedule import Phase, phase_at
from core.render.envmap import EnvMap
from core.render.gaussians import Gaussians
from core.render.gbuffer import near_plane, render_gbuffer, render_gbuffer_tensors
from core.render.raster import resolve_backend
from core.render.raster.plane_order import plane_reach
from core.render.roughness import roughness as splat_roughness
from core.render.shading import deferred_shade
from core.render.view_opacity import view_opacity_scale, visible_index
from core.scene.cameras import Camera, Intrinsics
from core.stages import stage

CHECKPOINT_NAME = "checkpoint.pt"


def eval_background(cfg: TrainConfig, device: torch.device | str) -> Tensor:
    """Renders for people and metrics use a fixed background (random → white)."""
    if cfg.background == "black":
        return torch.zeros(3, device=device)
    if isinstance(cfg.background, list):
        return torch.tensor(cfg.background, dtype=torch.float32, device=device)
    return torch.ones(3, device=device)


def envmap_from_state(state: Any, device: torch.device | str) -> EnvMap | None:
    """The env map stored in a checkpoint (``EnvMap.state_dict()``), or None."""
    if not isinstance(state, dict):
        return None
    texels = state.get("log_radiance", state.get("raw"))  # "raw": before log radiance
    if texels is None:
        return None
    envmap = EnvMap(texels.shape[1], texels.shape[-1]).to(device)
    envmap.load_state_dict(state)
    return envmap


def scene_record(center: Tensor, radius: float, cameras: Iterable[Camera]) -> dict[str, Any]:
    """The scene box and cameras as checkpoint data (what a reader cannot get elsewhere)."""
    return {
        "center": [float(v) for v in center],
        "radius": float(radius),
        "cameras": [c.to_dict() for c in cameras],
    }


@dataclass
class TrainedModel:
    """A model to render: Gaussians, env map, config, plan, cameras and scene box."""

    gaussians: Gaussians
    envmap: EnvMap | None
    config: TrainConfig
    plan: ScenePlan | None
    iteration: int
    device: torch.device
    backend: str
    cameras: list[Camera] = field(default_factory=list)
    center: Tensor | None = None  # the scene box (None for checkpoints that predate it)
    radius: float | None = None
    train_seconds: float = 0.0
    skipped_steps: int = 0
    path: Path | None = None  # the checkpoint it was read from
    # the iteration count its schedule was scaled to, when not config.iterations (a
    # run sized by a time budget): its phases are placed on this length
    schedule_iterations: int | None = None
    _static: dict[str, Tensor] | None = field(default=None, repr=False)

    # -- opening ----------------------------------------------------------------
    @staticmethod
    def open(
        path: str | Path,
        *,
        device: str | None = None,
        backend: str | None = None,
        notes: list[str] | None = None,
    ) -> TrainedModel:
        """The model in a run folder (its ``checkpoint.pt``) or a checkpoint file.

        ``device``/``backend`` replace the run's own; without them a device or backend
        this machine lacks (a GPU worker's run opened on a laptop) gives way to one that
        works here, with a line appended to ``notes``. Raises CheckpointError (naming
        the file) when there is no readable checkpoint.
        """
        path = Path(path)
        ck_path = path / CHECKPOINT_NAME if path.is_dir() else path
        if not ck_path.is_file():
            raise CheckpointError(
                f"no {CHECKPOINT_NAME}: not a (started) training run", file=ck_path
            )
        ck = load_checkpoint(ck_path, "cpu")
        x = ck.extra
        cfg = _recorded_config(ck_path, x.get("config"), prefer_folder=path.is_dir())
        place = reopen_placement(
            cfg.device, cfg.backend, device_override=device, backend_override=backend
        )
        if notes is not None:
            notes.extend(place.notes)
        g = ck.gaussians.to(place.device) if place.device != "cpu" else ck.gaussians
        for p in g.params.values():
            p.requires_grad_(False)
        envmap = envmap_from_state(x.get("envmap"), place.device)
        if envmap is not None:
            envmap.requires_grad_(False)
        scene = x.get("scene") if isinstance(x.get("scene"), dict) else {}
        center = scene.get("center")
        return TrainedModel(
            gaussians=g,
            envmap=envmap,
            config=cfg,
            plan=ScenePlan.from_dict(x["plan"]) if isinstance(x.get("plan"), dict) else None,
            iteration=int(x.get("iteration", cfg.iterations)),
            device=torch.device(place.device),
            backend=resolve_backend(place.backend, place.device),
            cameras=[Camera.from_dict(c) for c in scene.get("cameras", [])],
            center=None if center is None else torch.tensor(center, dtype=torch.float32),
            radius=None if scene.get("radius") is None else float(scene["radius"]),
            train_seconds=float(x.get("train_seconds", 0.0)),
            skipped_steps=int(x.get("skipped_steps", 0)),
            path=ck_path,
            schedule_iterations=x.get("schedule_iterations"),
        )

    # -- what the run was doing ---------------------------------------------------
    @property
    def phase(self) -> Phase:
        """The phase of the last trained iteration (what its renders looked like).

        A checkpoint written by another tool may carry no plan: then the env map is used
        if the file holds one, and the model's own SH degree.
        """
        if self.plan is not None:
            env = bool(self.plan.envmap.value)
            mv = bool(self.plan.multi_view.value)
            sh = int(self.plan.sh_degree.value)
        else:
            env, mv, sh = self.envmap is not None, False, self.gaussians.sh_degree
        cfg = self.config
        if self.schedule_iterations and self.schedule_iterations != cfg.iterations:
            cfg = cfg.model_copy(update={"iterations": int(self.schedule_iterations)})
        return phase_at(
            cfg,
            max(self.iteration - 1, 0),
            envmap_planned=env,
            multi_view_planned=mv,
            max_sh_degree=sh,
        )

    @property
    def background(self) -> Tensor:
        return eval_background(self.config, self.device)

    def framing(self) -> tuple[list[float], float]:
        """Where a viewer first looks: the median Gaussian and a 90% radius around it."""
        means = self.gaussians.params["means"].detach().float()
        if means.numel() == 0:
            return [0.0, 0.0, 0.0], 1.0
        center = means.median(dim=0).values
        dist = (means - center).norm(dim=-1)
        radius = float(torch.quantile(dist[:100_000].cpu(), 0.9))
        return [float(v) for v in center.cpu()], max(radius, 1e-6)

    # -- rendering ------------------------------------------------------------------
    def freeze(self) -> TrainedModel:
        """Precompute the view-independent per-Gaussian inputs for repeated renders.

        Covariances and normals each cost a quaternion → matrix pass over every
        Gaussian, about a third of a CPU frame on a 100k model; colours too while the
        run has not reached view-dependent SH (degree 0). Only for a model that no
        longer changes (the viewer's); the trainer's live model never freezes.
        """
        g = self.gaussians
        static = {
            "means": g.params["means"].detach(),
            "covariances": g.covariances.detach(),
            "opacities": g.opacities.detach(),
            "normals": g.normals().detach(),
            "w_r": g.w_r.detach(),
            # plane order's reach, from the scales as the live model's: not from each
            # frame's covariances (their eigenvalues: ~0.1 s a frame at 134k splats)
            "plane_reach": plane_reach(g.scales),
        }
        rough = splat_roughness(g)
        if rough is not None:
            static["roughness"] = rough.detach()
        if self.phase.sh_degree == 0:
            dummy = Camera.look_at([0, 0, 1], [0, 0, 0], [0, 1, 0], Intrinsics(1, 1, 0, 0, 1, 1))
            static["colors"] = g.colors(dummy, 0).detach()
        self._static = static
        return self

    def frozen(self) -> TrainedModel:
        """This model frozen (:meth:`freeze`), as a copy sharing its tensors when it is
        not frozen yet: for a caller that renders many views of a model someone else
        holds (mesh fusion, 3 passes over every training view). The same frames."""
        return self if self._static is not None else replace(self).freeze()

    @torch.no_grad()
    def render(
        self,
        camera: Camera,
        channels: Iterable[str] = ("final",),
        *,
        background: Tensor | None = None,
        compact: bool = True,
    ) -> Frame:
        """Render one view with the settings of the run's phase.

        Only what ``channels`` need is computed: the SH colours toward the camera for
        colour channels (geometry channels splat degree 0), deferred shading (env map
        lookups) for ``final`` and ``specular`` only, the depth's two channels for
        ``depth`` only (``Frame.depth`` needs it). A frozen model also drops the
        Gaussians this view cannot show (``visible_index``) before projecting them;
        ``compact=False`` keeps them all, the reference it is tested against.
        """
        wanted = set(channels)
        phase = self.phase
        bg = self.background if background is None else background
        sh_degree = phase.sh_degree if wanted & COLOURED else 0
        with_rough = bool(wanted & ROUGH)
        with_depth = bool(wanted & DEPTH)
        if self._static is not None:
            st = self._static
            with stage("view_opacity"):
                cull = view_opacity_scale(
                    self.gaussians, camera, one_sided=phase.one_sided, grazing=phase.grazing,
                    normals=st["normals"],
                )  # fmt: skip
                opacities = st["opacities"] if cull is None else st["opacities"] * cull
            with stage("near_plane"):
                # the near plane of every Gaussian, as an unfrozen render computes it
                z_cam = st["means"] @ camera.R[2].to(st["means"]) + float(camera.t[2])
                near = near_plane(z_cam)
            with stage("visible"):
                keep = visible_index(opacities) if compact else None

                def pick(t: Tensor | None) -> Tensor | None:
                    return t if t is None or keep is None else t.index_select(0, keep)

                colors = pick(st.get("colors"))
                keys = ("means", "normals", "w_r", "covariances", "plane_reach")
                means, normals, w_r, covs, reach = (pick(st[k]) for k in keys)
                opacities = pick(opacities)
                rough = pick(st.get("roughness")) if with_rough else None
            if colors is None:
                with stage("sh_colors"):
                    colors = self.gaussians.colors(camera, sh_degree, subset=keep)
            with stage("gbuffer"):
                gb, _ = render_gbuffer_tensors(
                    means, None, None, opacities, colors, normals, w_r, camera,
                    covariances=covs, backend=self.backend, antialiased=phase.antialiased,
                    lowpass=phase.lowpass, roughness=rough, near=near, depth=with_depth,
                    splat_order=phase.splat_order, plane_reach=reach,
                )  # fmt: skip
        else:
            cull = view_opacity_scale(
                self.gaussians, camera, one_sided=phase.one_sided, grazing=phase.grazing
            )
            gb, _ = render_gbuffer(
                self.gaussians, camera, sh_degree=sh_degree, backend=self.backend,
                antialiased=phase.antialiased, lowpass=phase.lowpass, opacity_scale=cull,
                with_roughness=with_rough, depth=with_depth, splat_order=phase.splat_order,
            )  # fmt: skip
        shade = None
        if wanted & SHADED:
            enabled = phase.envmap and self.envmap is not None
            with stage("deferred_shading"):
                shade = deferred_shade(gb, self.envmap, bg, enabled=enabled, fresnel=phase.fresnel)
        return Frame(camera, gb, shade, bg, phase.planar_depth)

    def summary(self) -> dict[str, Any]:
        """What a client shows about the model."""
        return {
            "iteration": self.iteration,
            "n_gaussians": self.gaussians.num,
            "phase": self.phase.name,
            "envmap": self.envmap is not None,
            "device": str(self.device),
            "backend": self.backend,
        }


def _recorded_config(ck_path: Path, saved: Any, *, prefer_folder: bool) -> TrainConfig:
    """The run's config as recorded (left as it was: the placement says where it
    renders now). A run folder's config.json is its record (``glint train`` writes
    it; an operator may edit it); a checkpoint file opened alone carries its own copy.
    Either falls back to the other, then to the defaults."""
    cfg_path = ck_path.parent / "config.json"
    has_file, has_folder = isinstance(saved, dict), cfg_path.is_file()
    if has_folder and (prefer_folder or not has_file):
        return saved_config(json.loads(cfg_path.read_text()), str(cfg_path))
    if has_file:
        return saved_config(dict(saved), f"{ck_path}: extra.config")
    return saved_config({}, str(ck_path))
