"""Fitting a run to a time budget: how many iterations fit, so the phases keep their shape.

A run sized in iterations scales its phase marks with ``iterations`` (``TrainConfig.scaled``).
A run sized in time does the same with a *planned* iteration count: the number of
iterations that fit in the time left, predicted from the measured cost of a step.

Cost model: a step costs ``k · factor[phase] · n_gaussians`` seconds. ``k`` is measured
(an average over recent steps, per phase) and the factor of a phase not reached yet
comes from :data:`PHASE_COST`, measured on the dev scenes: per Gaussian, a
single-view step costs about 1.4× an RGB step (normals, depth and Eq. 11) and a
multi-view step about 2× (a second G-buffer for the neighbour). The count itself is
expected to grow while densification is still ahead (:data:`DENSIFY_GROWTH`). The evaluations
and checkpoints a run of a given length still makes are charged at their measured
cost (the trainer's ``overhead``). The plan is redone every :data:`REPLAN_FRACTION` of the budget,
so it follows the Gaussian count as densification changes it.

A new plan never moves a phase mark that the run has passed back past the current
iteration (the run would fall back into an earlier phase); it may move later marks
earlier, which is what happens when steps turn out dearer than predicted.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from core.config import REFERENCE_ITERATIONS, TrainConfig
from core.model.schedule import Marks

# Per-Gaussian step cost relative to the RGB phase (teapot_gold 128², CPU backend:
# about 4.0, 5.5 and 7.8 µs per Gaussian per step).
PHASE_COST = {"rgb": 1.0, "geometry": 1.4, "multiview": 2.0}
# How much densification grows the Gaussian count over its whole window (start to stop):
# about 2× on the dev scenes at 1500 iterations (teapot_gold 20k → 39k, spot_plastic
# 20k → 41k). A step's cost follows the count, so the plan charges the growth ahead.
DENSIFY_GROWTH = 1.0
WARMUP_STEPS = 5  # the first steps after a start or resume carry one-off costs
REPLAN_FRACTION = 0.02  # re-plan every 2% of the budget
EMA = 0.1  # weight of the newest step in a phase's cost average


def _phase_marks(cfg: TrainConfig, n: int) -> list[int]:
    m = Marks.of(cfg.model_copy(update={"iterations": n}))
    return [m.geometry_start, m.multiview_start]


def _growth(cfg: TrainConfig, n: int, iteration: int, at: float) -> float:
    """Expected Gaussian count at step ``at`` over the count at ``iteration``: densification
    still ahead grows it, by DENSIFY_GROWTH over a whole densification window."""
    d = cfg.densify
    if not d.enabled:
        return 1.0
    scale = n / REFERENCE_ITERATIONS
    start, stop = d.start * scale, d.stop * scale
    if stop <= start or iteration >= stop:
        return 1.0
    ahead = max(0.0, min(at, stop) - max(iteration, start)) / (stop - start)
    return 1.0 + DENSIFY_GROWTH * ahead


@dataclass
class TimeBudget:
    """The planned iteration count of a time-budgeted run, re-planned as it goes."""

    seconds: float
    cap: int  # ``iterations`` of the config: whichever comes first ends the run
    planned: int  # the iteration count the schedule is scaled to now
    cost: dict[str, float] = field(default_factory=dict)  # seconds per step per Gaussian
    steps_seen: int = 0  # steps measured since this process started the run
    last_plan_used: float = -math.inf  # budget seconds used at the last plan

    @classmethod
    def of(cls, cfg: TrainConfig) -> TimeBudget | None:
        if cfg.time_budget is None:
            return None
        # Until the first steps are measured the schedule is the cap's (only the
        # first few RGB steps run under it; no mark is that early).
        return cls(seconds=float(cfg.time_budget), cap=cfg.iterations, planned=cfg.iterations)

    # -- measuring -----------------------------------------------------------
    def observe(self, phase: str, seconds: float, n_gaussians: int) -> None:
        """One training step's wall time (without evaluation or checkpoints)."""
        self.steps_seen += 1
        if self.steps_seen <= WARMUP_STEPS or n_gaussians <= 0 or not math.isfinite(seconds):
            return
        k = seconds / n_gaussians
        old = self.cost.get(phase)
        self.cost[phase] = k if old is None else (1 - EMA) * old + EMA * k

    def step_cost(self, phase: str, n_gaussians: int) -> float | None:
        """Predicted seconds of one step of ``phase`` at ``n_gaussians``."""
        if phase in self.cost:
            return self.cost[phase] * n_gaussians
        if not self.cost:
            return None
        # scale from the most expensive phase measured (the latest, in practice)
        ref = max(self.cost, key=lambda p: PHASE_COST[p])
        return self.cost[ref] * PHASE_COST[phase] / PHASE_COST[ref] * n_gaussians

    # -- planning ------------------------------------------------------------
    def due(self, used: float, *, force: bool = False) -> bool:
        """Whether to re-plan now (warm-up done, and the first plan or 2% later)."""
        measured = self.steps_seen > WARMUP_STEPS and bool(self.cost)
        return measured and (force or used - self.last_plan_used >= REPLAN_FRACTION * self.seconds)

    def predict(
        self,
        cfg: TrainConfig,
        n: int,
        iteration: int,
        n_gaussians: int,
        overhead: Callable[[int, float], float],
    ) -> float:
        """Seconds from ``iteration`` to ``n`` when the schedule is scaled to ``n``:
        the steps of each phase plus ``overhead(n, steps_seconds)``, the evaluations
        and checkpoints a run of that length still makes."""
        marks = _phase_marks(cfg, n)
        bounds = [iteration, *[min(max(m, iteration), n) for m in marks], n]
        total = 0.0
        for name, a, b in zip(("rgb", "geometry", "multiview"), bounds, bounds[1:], strict=False):
            if b > a:
                count = n_gaussians * _growth(cfg, n, iteration, (a + b) / 2)
                cost = self.step_cost(name, round(count))
                total += (b - a) * (cost or 0.0)
        return total + overhead(n, total)

    def plan(
        self,
        cfg: TrainConfig,
        iteration: int,
        used: float,
        n_gaussians: int,
        overhead: Callable[[int, float], float],
    ) -> int:
        """The largest iteration count that fits in the time left and keeps every
        passed phase mark behind the last trained step (no step falls back into an
        earlier phase); sets and returns ``planned``."""
        self.last_plan_used = used
        left = self.seconds - used
        lo = iteration + 1
        if left <= 0:
            self.planned = max(iteration, 1)
            return self.planned
        old = _phase_marks(cfg, self.planned)

        def fits(n: int) -> bool:
            marks = _phase_marks(cfg, n)
            last = iteration - 1  # the last trained step
            if any(m_old <= last < m for m_old, m in zip(old, marks, strict=True)):
                return False
            return self.predict(cfg, n, iteration, n_gaussians, overhead) <= left

        if not fits(lo):
            self.planned = lo
            return lo
        hi = self.cap
        if fits(hi):
            self.planned = hi
            return hi
        while hi - lo > 1:  # fits(lo) and not fits(hi)
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if fits(mid) else (lo, mid)
        self.planned = lo
        return lo

    # -- persistence -----------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {"seconds": self.seconds, "planned": self.planned, "cost": dict(self.cost)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """A resumed run keeps its plan and costs; the time left is the checkpoint's."""
        self.planned = int(state.get("planned", self.planned))
        self.cost = {str(k): float(v) for k, v in (state.get("cost") or {}).items()}
