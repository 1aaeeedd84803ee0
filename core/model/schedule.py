"""Which parts of the method are active at an iteration (paper Sect. 5, phases), and
when opacity resets fall (the geometric losses pause after one)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from core.config import TrainConfig

# An opacity reset needs ~200 Adam steps to recover (logit 0.01 → 0.5 at lr 0.025);
# resets closer than this keep every Gaussian transparent, so short runs space
# them at least this far apart (and runs shorter than this get none).
MIN_RESET_INTERVAL = 1000


def opacity_reset_every(cfg: TrainConfig) -> int:
    """Iterations between opacity resets in this run (0: none)."""
    d = cfg.densify
    if not d.enabled or d.opacity_reset_interval <= 0:
        return 0
    return max(MIN_RESET_INTERVAL, cfg.scaled(d.opacity_reset_interval))


def last_opacity_reset(cfg: TrainConfig, iteration: int, every: int | None = None) -> int | None:
    """The latest iteration before ``iteration`` that ended with an opacity reset
    (``every``: the run's reset interval when it differs from the config's, as in a
    time-budgeted run that fixed it when its first reset passed)."""
    every = opacity_reset_every(cfg) if every is None else every
    stop = cfg.scaled(cfg.densify.stop)
    if every == 0 or iteration <= every:
        return None
    last = min(iteration - 1, stop - 1) // every * every
    return last if last > 0 else None


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
    antialiased: bool = True
    silhouette: bool = False  # the silhouette-point depth loss (core.training.silhouette)
    one_sided: bool = False  # cull splats seen from behind (core.render.orientation)
    grazing: bool = False  # learned edge-on opacity fade (core.render.grazing)
    lowpass: float = 0.3  # px² added to each splat's 2D covariance (TrainConfig.lowpass_2d)
    splat_order: str = "centre"  # compositing order (TrainConfig.splat_order)
    fresnel: bool = False  # reflection rising at grazing angles (core.render.fresnel)


@dataclass(frozen=True)
class Marks:
    """Phase marks in this run's iterations (the 30k marks scaled)."""

    geometry_start: int
    multiview_start: int
    sh_full_start: int
    # the first iteration without the silhouette term (phases.silhouette_until; the run's
    # length when it stays on); not a boundary: ending one loss needs no evaluation
    silhouette_stop: int

    @staticmethod
    def of(cfg: TrainConfig) -> Marks:
        """Scaled marks, with floors on the first two phases in short runs.

        Why floors: Adam needs a number of *steps*, not a fraction of the run, to settle
        the densifying point cloud before the geometric losses pull on it. Scaled
        proportionally, a 1500-iteration run would switch them on at iteration 150,
        and on the dev scenes that cost 2-3 dB of test PSNR and 3° of normal error
        against starting at 500 (docs/benchmarks.md). The floors never bind at the
        paper's 30k and are capped at a third (a sixth) of the run so short runs keep
        every phase. A mark set to 0 (or equal to the previous one) is left alone.
        """
        p, n = cfg.phases, cfg.iterations
        geo = cfg.scaled(p.geometry_start)
        if p.geometry_start > 0:
            geo = max(geo, min(p.min_rgb_iterations, n // 3))
        mv = max(cfg.scaled(p.multiview_start), geo)
        if p.multiview_start > p.geometry_start:
            mv = max(mv, geo + min(p.min_geometry_iterations, n // 6))
        return Marks(geo, mv, cfg.scaled(p.sh_full_start), math.ceil(p.silhouette_until * n))

    def boundaries(self) -> list[int]:
        """Iterations at which the phase changes (checkpoint and evaluation points)."""
        return sorted({self.geometry_start, self.multiview_start, self.sh_full_start} - {0})


def geometry_paused(cfg: TrainConfig, iteration: int, reset_every: int | None = None) -> bool:
    """True for ``phases.geometry_pause_after_reset`` iterations after an opacity reset.

    Why: right after a reset every opacity is ≤ 0.01, so the blended depth and normals
    are a faint average of many layers. Left on, L_single and L_multi pull on that
    noise and their gradients swamp the RGB loss's push to restore opacity in Adam's
    moments: on spot_plastic (3000-iteration checkpoint, reset re-applied) the full
    model was at 29.2 dB 200 steps later with them on and 34.5 dB with a 100-step pause
    (33.97 before the reset); RGB alone recovers in ~50 steps.
    """
    pause = cfg.phases.geometry_pause_after_reset
    if pause <= 0:
        return False
    last = last_opacity_reset(cfg, iteration, reset_every)
    return last is not None and iteration - last <= pause


def phase_at(
    cfg: TrainConfig,
    iteration: int,
    *,
    envmap_planned: bool = True,
    multi_view_planned: bool = True,
    max_sh_degree: int | None = None,
    reset_every: int | None = None,
    silhouette_planned: bool = True,
) -> Phase:
    """Phase of ``iteration`` (0-based): RGB → + single view & env map → + multi view."""
    m = Marks.of(cfg)
    ab = cfg.ablation
    geo = iteration >= m.geometry_start
    mv = iteration >= m.multiview_start
    name = "multiview" if mv else ("geometry" if geo else "rgb")
    paused = geometry_paused(cfg, iteration, reset_every)
    top = cfg.sh_degree if max_sh_degree is None else min(cfg.sh_degree, max_sh_degree)
    return Phase(
        name=name,
        single_view=geo and ab.single_view and not paused,
        envmap=geo and ab.deferred_shading and envmap_planned,
        multi_view=mv and ab.multi_view and multi_view_planned and not paused,
        sh_degree=top if iteration >= m.sh_full_start else 0,
        planar_depth=ab.planar_depth,
        scale_loss=ab.planar,
        antialiased=cfg.antialiased,
        silhouette=geo
        and ab.silhouette
        and silhouette_planned
        and not paused
        and iteration < m.silhouette_stop,
        one_sided=ab.one_sided,
        grazing=ab.grazing_opacity,
        lowpass=cfg.lowpass_2d,
        splat_order=cfg.splat_order,
        fresnel=ab.fresnel,
    )
