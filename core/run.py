"""Train a scene folder into a run folder: the one entry the CLI and the worker share."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from core.config import TrainConfig
from core.scene import Scene
from core.scene_io import load_scene
from core.trainer import Trainer, TrainResult, check_runnable


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
    out.mkdir(parents=True, exist_ok=True)
    if not isinstance(scene, Scene):
        from core.outputs import record_scene

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
        from core.outputs import export_run

        summary = export_run(trainer)
        if on_event:
            on_event({"type": "exported", **summary})
    return result, summary
