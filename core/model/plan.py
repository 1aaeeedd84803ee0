"""The scene plan as data: which parts of the method a run uses, and why.

The decisions themselves are made by ``core.training.planner`` (before training, and
at the end of the RGB-only phase); this module holds what they produce, so that
everything that reads a trained model (outputs, meshing, evaluation, the viewer) can
read its plan without importing training.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from core.config import TrainConfig

# Parts a user may override with ``plan_overrides``; every decision of a plan.
OVERRIDABLE = (
    "envmap", "sh_degree", "multi_view", "mesh", "silhouette", "roughness", "hull",
    "oblique_depth",
)  # fmt: skip
DECISION_KEYS = (
    "envmap",
    "envmap_resolution",
    "sh_degree",
    "multi_view",
    "background",
    "mesh",
    "silhouette",
    "roughness",
    "hull",
    "oblique_depth",
)
# The paper's cube-map face size (6 × 128 × 128).
PAPER_ENVMAP_RESOLUTION = 128


@dataclass
class Decision:
    """One part of the plan: its value, the reason, the measurements behind it."""

    value: Any
    reason: str
    evidence: dict[str, Any] = field(default_factory=dict)
    overridden: bool = False
    pending: bool = False


@dataclass
class ScenePlan:
    """Every decision of one run, the multi-view neighbour of each training view, and
    how the Gaussians were initialised."""

    envmap: Decision
    sh_degree: Decision
    multi_view: Decision
    background: Decision
    mesh: Decision
    neighbours: list[int | None] = field(default_factory=list)
    init: dict[str, Any] = field(default_factory=dict)
    envmap_resolution: Decision = field(
        default_factory=lambda: Decision(PAPER_ENVMAP_RESOLUTION, "the paper's default")
    )
    silhouette: Decision = field(
        default_factory=lambda: Decision(False, "not planned (a run from before it existed)")
    )
    roughness: Decision = field(
        default_factory=lambda: Decision(False, "not planned (a run from before it existed)")
    )
    # meshes bounded by the masks' hull (core.training.mask_agreement says when)
    hull: Decision = field(
        default_factory=lambda: Decision(False, "not planned (a run from before it existed)")
    )
    # L_single also on oblique pixels, where some side is never faced (core.training.planner)
    oblique_depth: Decision = field(
        default_factory=lambda: Decision(False, "not planned (a run from before it existed)")
    )

    def neighbour_of(self, view_index: int) -> int | None:
        if not self.multi_view.value or view_index >= len(self.neighbours):
            return None
        return self.neighbours[view_index]

    def envmap_possible(self, cfg: TrainConfig) -> bool:
        return cfg.ablation.deferred_shading and bool(self.envmap.value)

    def roughness_possible(self, cfg: TrainConfig) -> bool:
        return self.envmap_possible(cfg) and bool(self.roughness.value)

    # -- persistence --------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "decisions": {k: asdict(getattr(self, k)) for k in DECISION_KEYS},
            "neighbours": list(self.neighbours),
            "init": dict(self.init),
        }

    @staticmethod
    def from_dict(d: dict[str, Any]) -> ScenePlan:
        # a decision this version does not know (a plan written by a later one) is
        # dropped rather than refusing to open the run
        dec = {k: Decision(**v) for k, v in d["decisions"].items() if k in DECISION_KEYS}
        return ScenePlan(
            neighbours=list(d.get("neighbours", [])), init=dict(d.get("init", {})), **dec
        )

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=2, default=float))
        tmp.replace(path)
        return path
