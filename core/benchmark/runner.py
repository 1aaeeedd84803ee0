"""``glint bench``: train and evaluate every (scene, configuration) cell, resumably.

Cells are run folders ``OUT/<scene>/<config>``; a cell with an ``eval.json`` is
finished and skipped, an interrupted one resumes from its checkpoint. When every cell
is done, ``core.benchmark.tables`` writes bench.md and the error-vs-time plots.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from core.benchmark.cells import Cell, check_cell_config, plan_cells
from core.benchmark.configs import CONFIGS, bench_config
from core.config import TrainConfig, saved_config
from core.errors import GlintError
from core.evaluation.evaluate import (
    EVAL_FILE,
    atomic_json,
    evaluate_run,
    render_speed,
    summarize,
    test_views,
)
from core.model.run_folder import attach_scene, record_scene
from core.model.trained import TrainedModel
from core.scene.formats import load_scene
from core.scene.views import Scene
from core.training.run import train_scene


def run_cell(
    cell: Cell,
    cfg: TrainConfig,
    scene: Scene,
    *,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    eval_kwargs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train (or resume) one cell and evaluate it."""
    record_scene(cell.run_dir, cell.scene_dir)
    result, _ = train_scene(scene, cell.run_dir, cfg, on_event=on_event, resume=True)
    if result.status != "succeeded":
        raise RuntimeError(f"{cell.run_dir}: training {result.status}")
    return evaluate_run(cell.run_dir, scene=scene, **(eval_kwargs or {}))


def refresh_fps(cells: Sequence[Cell], *, frames: int | None = None) -> int:
    """Re-time the renderer of every finished cell, one after another in this process.

    Cells trained in parallel, or while the machine was busy, timed their renders
    under different loads; re-timing them back to back makes the FPS column
    comparable. Updates eval.json (``fps.refreshed``); returns how many were re-timed.
    """
    scenes: dict[Path, Scene] = {}
    n = 0
    for cell in cells:
        if not cell.done:
            continue
        cfg = saved_config(json.loads((cell.run_dir / "config.json").read_text()))
        key = cell.scene_dir.resolve()
        if key not in scenes:
            scenes.clear()
            scenes[key] = load_scene(cell.scene_dir, downscale=1.0 / cfg.resolution_scale)
        model = attach_scene(TrainedModel.open(cell.run_dir), scenes[key])
        ev = json.loads((cell.run_dir / EVAL_FILE).read_text())
        ev["fps"] = {**render_speed(model, test_views(scenes[key]), frames=frames)}
        ev["fps"]["refreshed"] = True
        ev["summary"] = summarize(ev)
        atomic_json(cell.run_dir / EVAL_FILE, ev)
        n += 1
    return n


def run_bench(
    scenes: Sequence[str | Path],
    budget: int | None,
    out: str | Path,
    *,
    time_budget: float | None = None,
    configs: Sequence[str] = tuple(CONFIGS),
    resolution_scale: float = 1.0,
    base: dict[str, Any] | None = None,
    progress: bool = True,
    eval_kwargs: dict[str, Any] | None = None,
    command: str | None = None,
    retime_fps: bool = False,
) -> Path:
    """Train and evaluate every (scene, config) cell not finished yet; write bench.md
    (``command``, when given, is quoted in it so the table can be reproduced;
    ``retime_fps`` re-times every finished cell's renderer back to back first).
    ``budget`` (iterations) and ``time_budget`` (seconds) size each run; with both,
    whichever comes first ends it. The progress bar counts iterations, or runs when
    the runs are sized by time."""
    if budget is None and time_budget is None:
        raise GlintError("give an iteration budget, a time budget, or both")
    from tqdm import tqdm

    from core.benchmark.tables import write_bench

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cells = plan_cells(scenes, configs, out)
    per_cell = budget if time_budget is None and budget is not None else 1
    bar = tqdm(
        total=len(cells) * per_cell,
        unit="it" if per_cell > 1 else "run",
        dynamic_ncols=True,
        disable=not progress,
        desc="bench",
    )
    loaded: dict[Path, Scene] = {}
    for cell in cells:
        bar.set_description(f"{cell.scene}/{cell.config}")
        cfg = bench_config(cell.config, budget, resolution_scale, base, time_budget)
        check_cell_config(cell, cfg)
        if cell.done:
            bar.update(per_cell)
            continue
        if cell.scene_dir not in loaded:
            loaded.clear()  # one scene in memory at a time
            loaded[cell.scene_dir] = load_scene(cell.scene_dir, downscale=1.0 / resolution_scale)
        start = bar.n
        state = {"it": 0}

        def on_event(e: dict[str, Any], state: dict[str, int] = state) -> None:
            if per_cell > 1 and e.get("type") in ("progress", "resumed"):
                it = int(e["iteration"])
                bar.update(it - state["it"])
                state["it"] = it
            elif e.get("type") == "exported":
                bar.set_postfix_str("evaluating")

        run_cell(cell, cfg, loaded[cell.scene_dir], on_event=on_event, eval_kwargs=eval_kwargs)
        bar.update(start + per_cell - bar.n)
        bar.set_postfix_str("")
    bar.close()
    if retime_fps:
        refresh_fps(cells)
    return write_bench(
        out,
        cells,
        budget=budget,
        resolution_scale=resolution_scale,
        command=command,
        time_budget=time_budget,
    )
