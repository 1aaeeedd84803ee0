"""Which parts of the method are active at an iteration (paper Sect. 5, phases)."""

from __future__ import annotations

from dataclasses import dataclass

from core.config import TrainConfig


@dataclass(frozen=True)
class Phase:
    """The active parts at one iteration (after ablations and the scene plan)."""

    name: str  # "rgb" | "geometry" | "multiview"
    single_view: bool
    envmap: bool
    multi_view: bool
    sh_degree: int
    planar_depth: bool
    scale_loss: bool


@dataclass(frozen=True)
class Marks:
    """Phase marks in this run's iterations (the 30k marks scaled)."""

    geometry_start: int
    multiview_start: int
    sh_full_start: int

    @staticmethod
    def of(cfg: TrainConfig) -> Marks:
        p = cfg.phases
        return Marks(
            cfg.scaled(p.geometry_start), cfg.scaled(p.multiview_start), cfg.scaled(p.sh_full_start)
        )

    def boundaries(self) -> list[int]:
        """Iterations at which the phase changes (checkpoint and evaluation points)."""
        return sorted({self.geometry_start, self.multiview_start, self.sh_full_start} - {0})


def phase_at(
    cfg: TrainConfig,
    iteration: int,
    *,
    envmap_planned: bool = True,
    multi_view_planned: bool = True,
    max_sh_degree: int | None = None,
) -> Phase:
    """Phase of ``iteration`` (0-based): RGB → + single view & env map → + multi view."""
    m = Marks.of(cfg)
    ab = cfg.ablation
    geo = iteration >= m.geometry_start
    mv = iteration >= m.multiview_start
    name = "multiview" if mv else ("geometry" if geo else "rgb")
    top = cfg.sh_degree if max_sh_degree is None else min(cfg.sh_degree, max_sh_degree)
    return Phase(
        name=name,
        single_view=geo and ab.single_view,
        envmap=geo and ab.deferred_shading and envmap_planned,
        multi_view=mv and ab.multi_view and multi_view_planned,
        sh_degree=top if iteration >= m.sh_full_start else 0,
        planar_depth=ab.planar_depth,
        scale_loss=ab.planar,
    )
