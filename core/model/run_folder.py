"""A run folder on disk: its checkpoint, the scene it was trained on, and opening both.

``glint mesh``/``glint eval`` and the API's mesh jobs reopen a finished run: the model
from its checkpoint and the scene (views, masks, ground truth) from the folder it was
trained on, at the run's resolution.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from core.errors import GlintError
from core.model.trained import TrainedModel
from core.scene.formats import load_scene
from core.scene.views import Scene

# Written into a run folder by tools that know the scene a run was trained on
# (``glint train``, ``glint bench``, the service's runner), so ``glint mesh``/``glint
# eval`` can find it again. The path is relative to the run folder: a run folder is an
# artifact a service hands out, and must not tell where the server keeps its files.
SCENE_RECORD = "scene.json"


def record_scene(run_dir: str | Path, scene_dir: str | Path) -> Path:
    """Remember which scene folder a run belongs to, as a path relative to the run
    (absolute only where there is none: another drive on Windows)."""
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    scene = Path(scene_dir).resolve()
    try:
        where = Path(os.path.relpath(scene, run.resolve())).as_posix()
    except ValueError:
        where = str(scene)
    path = run / SCENE_RECORD
    path.write_text(json.dumps({"scene": where}, indent=2))
    return path


def find_run_scene(run_dir: str | Path, scene_dir: str | Path | None = None) -> Path:
    """The scene folder of a run: the one given, else ``scene.json``, else the
    ``scene/`` folder beside the run (the layout ``glint demo`` writes)."""
    run = Path(run_dir)
    if scene_dir is not None:
        return Path(scene_dir)
    rec = run / SCENE_RECORD
    if rec.is_file():  # relative to the run (older records: absolute, which joins as is)
        return (run.resolve() / json.loads(rec.read_text())["scene"]).resolve()
    demo = run.parent / "scene"
    if (demo / "transforms_train.json").is_file():
        return demo
    raise GlintError(f"{run}: no {SCENE_RECORD} in the run folder; pass the scene folder")


def open_run(
    run_dir: str | Path,
    scene_dir: str | Path | None = None,
    *,
    device: str | None = None,
    backend: str | None = None,
    notes: list[str] | None = None,
) -> tuple[TrainedModel, Scene]:
    """The trained model of a run folder (its latest checkpoint) and its scene, loaded
    at the run's resolution; raises if the run has no checkpoint.

    ``device``/``backend``/``notes``: see :meth:`TrainedModel.open`. The run's
    config.json is not changed.
    """
    run = Path(run_dir)
    model = TrainedModel.open(run, device=device, backend=backend, notes=notes)
    scene = load_scene(
        find_run_scene(run, scene_dir), downscale=1.0 / model.config.resolution_scale
    )
    return attach_scene(model, scene), scene


def attach_scene(model: TrainedModel, scene: Scene) -> TrainedModel:
    """Give a model opened from a checkpoint that predates the scene record its
    scene's box and training cameras (newer checkpoints carry both)."""
    if model.center is None or model.radius is None:
        model.center, model.radius = scene.center.float(), float(scene.radius)
    if not model.cameras:
        model.cameras = [v.camera for v in scene.train]
    return model
