"""Train a scene folder into a run folder: the one entry the CLI and the worker share."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from core.config import ConfigError, TrainConfig, config_changes, saved_config
from core.evaluation.geometry import geometry_errors
from core.meshing.mesh import MeshCancelledError, mesh_model, mesh_section, stage_progress
from core.model.run_folder import record_scene
from core.model.trained import CHECKPOINT_NAME
from core.outputs.export import export_run
from core.scene.formats import load_scene
from core.scene.views import Scene
from core.training.trainer import Trainer, TrainResult, check_runnable

RENDERED_VIEWS = 4  # test views whose every channel an export writes to renders/


def train_scene(
    scene: str | Path | Scene,
    out_dir: str | Path,
    cfg: TrainConfig,
    *,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    progress: bool = False,
    resume: bool = True,
    export: bool = True,
) -> tuple[TrainResult, dict[str, Any] | None]:
    """Load (if a path), train or resume, and export artifacts when training finished."""
    check_runnable(cfg)  # a missing GPU or backend fails here, before the run folder is made
    out = Path(out_dir)
    if resume:
        check_same_config(out, cfg)
    out.mkdir(parents=True, exist_ok=True)
    if not isinstance(scene, Scene):
        record_scene(out, scene)  # so `glint mesh/eval RUN` find the scene again
        scene = load_scene(scene, downscale=1.0 / cfg.resolution_scale)
    (out / "config.json").write_text(json.dumps(cfg.model_dump(mode="json"), indent=2))
    trainer = Trainer(
        scene, cfg, out, on_event=on_event, should_stop=should_stop, progress=progress
    )
    trainer.setup(resume=resume)
    result = trainer.train()
    summary = None
    if export and result.status == "succeeded":
        try:
            summary = export_trained(trainer, on_event=on_event, should_stop=should_stop)
        except MeshCancelledError:  # stopped while meshing: resuming redoes export and mesh
            return TrainResult("cancelled", result.iteration, result.train_seconds), None
        if on_event:
            on_event({"type": "exported", **summary})
    return result, summary


def check_same_config(out: Path, cfg: TrainConfig) -> None:
    """Refuse to resume (or report) a run folder trained with another configuration.

    Without this, ``glint train scene --out runs/x --set ...`` on a folder holding a
    finished run printed that old run's figures as if they were the new configuration's.
    """
    path = out / "config.json"
    if not (out / CHECKPOINT_NAME).is_file() or not path.is_file():
        return
    try:
        old = saved_config(json.loads(path.read_text()), source=str(path))
    except (OSError, ValueError, ConfigError):
        return  # unreadable: the checkpoint's own copy decides when it is loaded
    changes = config_changes(old, cfg)
    if changes:
        shown = "; ".join(changes[:8]) + (
            f"; and {len(changes) - 8} more" if len(changes) > 8 else ""
        )
        raise ConfigError(
            f"{out} holds a run trained with another configuration ({shown}); "
            "use another --out, or --overwrite to train again from the start there"
        )


def export_trained(
    trainer: Trainer,
    *,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> dict[str, Any]:
    """Export a trainer's model into its run folder, with its geometry error when the
    scene ships ground-truth maps and its mesh when the plan asks for one."""
    model = trainer.model
    scene = trainer.scene
    cfg = trainer.cfg
    geo = geometry_errors(model, scene.test or scene.train, scene.root)
    sections = []
    mesh_info = None
    mesh = None
    if trainer.plan.mesh.value or cfg.outputs.asset:  # the asset is made from the mesh
        mesh, mesh_info = mesh_model(
            model,
            scene.train,
            trainer.out,
            resolution=cfg.outputs.mesh_resolution,
            color=cfg.outputs.mesh_color,
            progress=stage_progress(on_event, len(scene.train)),
            should_stop=should_stop,
        )
        sections.append(mesh_section(mesh_info))
    asset = None
    if cfg.outputs.asset and mesh is not None:
        asset = export_run_asset(trainer, mesh, on_event, should_stop)
        sections.append(asset_section(asset))
    views = trainer.progress_views()[:RENDERED_VIEWS]
    summary = export_run(model, trainer.out, views, geometry=geo, sections=sections)
    if mesh_info is not None:
        summary["mesh"] = {k: mesh_info[k] for k in ("vertices", "faces", "color", "files")}
    if asset is not None:
        summary["asset"] = asset
    return summary


def export_run_asset(
    trainer: Trainer,
    mesh: Any,
    on_event: Callable[[dict[str, Any]], None] | None,
    should_stop: Callable[[], bool] | None,
) -> dict[str, Any]:
    """The run's relightable asset (outputs.asset) into its folder; an input the asset
    cannot be made from is reported in the summary, not a failed run."""
    from core.asset.export import AssetOptions, asset_progress, export_asset
    from core.errors import AssetError

    out = trainer.cfg.outputs
    options = AssetOptions(faces=out.asset_faces, texture_size=out.asset_texture_size)
    try:
        info = export_asset(
            trainer.model,
            trainer.scene.train,
            trainer.out,
            mesh,
            options=options,
            progress=asset_progress(on_event),
            should_stop=should_stop,
        )
    except AssetError as exc:  # a cancel (AssetCancelledError) is not one: it goes up
        return {"error": str(exc)}
    return {"files": sorted(info["files"].values()), "faces": info["mesh"]["faces"]}


def asset_section(asset: dict[str, Any]) -> str:
    if "error" in asset:
        return f"## Relightable asset\n\nNot made: {asset['error']}."
    files = ", ".join(f"`{f}`" for f in asset["files"])
    return (
        f"## Relightable asset\n\n{asset['faces']} faces, with PBR textures and the "
        f"environment (docs/asset.md): {files}, and `asset.json`."
    )
