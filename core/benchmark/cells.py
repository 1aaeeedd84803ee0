"""Benchmark cells: one (scene, configuration) run folder each, and their bookkeeping."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from core.config import TrainConfig
from core.errors import GlintError
from core.evaluation.evaluate import EVAL_FILE


@dataclass(frozen=True)
class Cell:
    """One (scene, configuration) run of the benchmark."""

    scene_dir: Path
    scene: str
    config: str
    run_dir: Path

    @property
    def done(self) -> bool:
        return (self.run_dir / EVAL_FILE).is_file()


def plan_cells(scenes: Sequence[str | Path], configs: Sequence[str], out: Path) -> list[Cell]:
    cells = []
    names: set[str] = set()
    for sd in scenes:
        sd = Path(sd)
        name = sd.resolve().name
        if name in names:
            raise GlintError(f"two scenes are named {name!r}; the run folders would collide")
        names.add(name)
        cells += [Cell(sd, name, c, out / name / c) for c in configs]
    return cells


def check_cell_config(cell: Cell, cfg: TrainConfig) -> None:
    """Refuse to reuse or resume a cell that was started with another configuration
    (another budget, resolution or override): its numbers would be mislabelled."""
    path = cell.run_dir / "config.json"
    if not path.is_file():
        return
    old = json.loads(path.read_text())
    new = json.loads(json.dumps(cfg.model_dump(mode="json")))
    if old != new:
        diff = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
        raise GlintError(
            f"{cell.run_dir} was run with a different configuration ({', '.join(diff)}); "
            "use another --out, or delete that folder to redo it"
        )
