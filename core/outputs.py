"""What a finished (or checkpointed) run leaves behind for users.

point_cloud.ply (3DGS layout), the env map (EXR cross + lat-long + PNG preview),
renders of test views (final, base, specular, normal, depth, w_r, alpha), geometry
error against ground truth where the scene ships it, and report.md with the
error-vs-time plot.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from core.channels import CHANNELS  # noqa: F401  (re-exported)
from core.envmap_io import save_envmap
from core.gbuffer import geometry_depth, render_gbuffer
from core.groundtruth import load_ground_truth
from core.imageio import srgb_to_linear, write_image
from core.metrics import depth_error, normal_angle_error_deg
from core.ply import save_ply
from core.report import write_report

if TYPE_CHECKING:
    from core.trainer import Trainer


def colormap(x: Tensor, valid: Tensor, name: str = "turbo") -> Tensor:
    """Map a scalar image to RGB (linear) with a matplotlib colormap; invalid → black."""
    import matplotlib

    v = x[valid]
    lo, hi = (float(v.min()), float(v.max())) if v.numel() else (0.0, 1.0)
    t = ((x - lo) / max(hi - lo, 1e-12)).clamp(0, 1).cpu().numpy()
    rgb = matplotlib.colormaps[name](t)[..., :3].astype(np.float32)
    out = torch.from_numpy(rgb)
    out[~valid.cpu()] = 0.0
    # Colormaps are defined in display space; store linear so write_image's sRGB encode round-trips.
    return srgb_to_linear(out)


@torch.no_grad()
def channel_images(trainer: Trainer, camera) -> dict[str, Tensor]:
    """Every viewer/report channel of one view as linear RGB (H, W, 3) on the CPU."""
    from core.trainer import eval_background, render_view

    bg = eval_background(trainer.cfg, trainer.device)
    phase = trainer.current_phase(max(trainer.iteration - 1, 0))
    gb, shade, _ = render_view(
        trainer.gaussians, trainer.envmap, camera, phase, bg, trainer.cfg.backend
    )
    R = camera.R.to(gb.normal)
    n_world = gb.normal @ R
    n_world = n_world / n_world.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    normal_rgb = (n_world * 0.5 + 0.5) * gb.alpha[..., None]
    normal_lin = srgb_to_linear(normal_rgb)
    depth, valid = geometry_depth(gb, phase.planar_depth)
    return {
        "final": shade.final.cpu(),
        "base": (gb.base + (1 - gb.alpha[..., None]) * bg).cpu(),
        "specular": shade.specular.cpu(),
        "normal": normal_lin.cpu(),
        "depth": colormap(depth.cpu(), valid.cpu()),
        "w_r": gb.w_r[..., None].expand(-1, -1, 3).cpu(),
        "alpha": gb.alpha[..., None].expand(-1, -1, 3).cpu(),
    }


@torch.no_grad()
def geometry_errors(trainer: Trainer, views) -> dict[str, Any] | None:
    """Mean normal angle and depth error vs GT maps over pixels both cover."""
    root = trainer.scene.root
    if root is None:
        return None
    angles, abs_err, rel_err, n = [], [], [], 0
    phase = trainer.current_phase(max(trainer.iteration - 1, 0))
    planar = phase.planar_depth
    for v in views:
        gt = load_ground_truth(root, v)
        if gt is None:
            continue
        gb, _ = render_gbuffer(
            trainer.gaussians, v.camera, sh_degree=0, backend=trainer.cfg.backend,
            antialiased=phase.antialiased,
        )  # fmt: skip
        depth, valid = geometry_depth(gb, planar)
        mask = gt.mask.to(depth.device) & valid & (gb.alpha > 0.5)
        R = v.camera.R.to(gb.normal)
        n_world = gb.normal @ R
        angles.append(normal_angle_error_deg(n_world, gt.normal_world.to(n_world), mask))
        de = depth_error(depth, gt.depth.to(depth), mask)
        abs_err.append(de["abs"])
        rel_err.append(de["rel"])
        n += 1
    if n == 0:
        return None

    def mean(xs):
        xs = [x for x in xs if not math.isnan(x)]
        return float(np.mean(xs)) if xs else math.nan

    return {
        "views": n,
        "normal_error_deg": mean(angles),
        "depth_abs_error": mean(abs_err),
        "depth_rel_error": mean(rel_err),
    }


def export_sections(trainer: Trainer, geo: dict[str, Any] | None) -> list[str]:
    """The report sections of an export; later writers of report.md (``glint eval``)
    repeat them so that rewriting the report keeps them."""
    sections = []
    if geo is not None:
        sections.append(
            "## Geometry against ground truth\n\n"
            f"Over {geo['views']} views: mean normal error {geo['normal_error_deg']:.2f}°, "
            f"depth error {geo['depth_abs_error']:.4f} (abs), "
            f"{100 * geo['depth_rel_error']:.2f}% (rel)."
        )
    if trainer.skipped_steps:
        sections.append(f"Skipped {trainer.skipped_steps} steps with non-finite loss or gradients.")
    return sections


# Written into a run folder by tools that know the scene a run was trained on
# (``glint bench``), so ``glint mesh``/``glint eval`` can find it again.
SCENE_RECORD = "scene.json"


def record_scene(run_dir: str | Path, scene_dir: str | Path) -> Path:
    """Remember which scene folder a run belongs to (absolute path)."""
    path = Path(run_dir) / SCENE_RECORD
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"scene": str(Path(scene_dir).resolve())}, indent=2))
    return path


def find_run_scene(run_dir: str | Path, scene_dir: str | Path | None = None) -> Path:
    """The scene folder of a run: the one given, else ``scene.json``, else the
    ``scene/`` folder beside the run (the layout ``glint demo`` writes)."""
    from core.errors import GlintError

    run = Path(run_dir)
    if scene_dir is not None:
        return Path(scene_dir)
    rec = run / SCENE_RECORD
    if rec.is_file():
        return Path(json.loads(rec.read_text())["scene"])
    demo = run.parent / "scene"
    if (demo / "transforms_train.json").is_file():
        return demo
    raise GlintError(f"{run}: no {SCENE_RECORD} in the run folder; pass the scene folder")


def load_run(
    run_dir: str | Path,
    scene_dir: str | Path | None = None,
    *,
    device: str | None = None,
    backend: str | None = None,
    notes: list[str] | None = None,
) -> Trainer:
    """The trained model of a run folder (its latest checkpoint), with its scene loaded
    at the run's resolution; raises if the run has no checkpoint.

    ``device``/``backend`` replace the run's own; without them, a device or backend
    this machine lacks (a GPU worker's run opened on a laptop) gives way to the CPU
    and a backend that runs there, with a line appended to ``notes`` for each.
    The run's config.json is not changed.
    """
    from core.config import saved_config
    from core.devices import reopen_placement
    from core.errors import GlintError
    from core.raster import resolve_backend
    from core.scene_io import load_scene
    from core.trainer import CHECKPOINT_NAME, Trainer

    run = Path(run_dir)
    if not (run / CHECKPOINT_NAME).is_file():
        raise GlintError(f"{run}: no {CHECKPOINT_NAME}: not a (started) training run")
    cfg_path = run / "config.json"
    if not cfg_path.is_file():
        raise GlintError(f"{run}: no config.json")
    cfg = saved_config(json.loads(cfg_path.read_text()), str(cfg_path))
    place = reopen_placement(
        cfg.device, cfg.backend, device_override=device, backend_override=backend
    )
    if notes is not None:
        notes.extend(place.notes)
    cfg = cfg.model_copy(update={"device": place.device, "backend": place.backend})
    if cfg.densify.absgrad and resolve_backend(cfg.backend, cfg.device) != "cuda":
        # AbsGS only changes how a run densifies; reading one back never densifies
        cfg = cfg.model_copy(update={"densify": cfg.densify.model_copy(update={"absgrad": False})})
    scene = load_scene(find_run_scene(run, scene_dir), downscale=1.0 / cfg.resolution_scale)
    trainer = Trainer(scene, cfg, run)
    trainer.setup(resume=True)
    return trainer


def export_run(trainer: Trainer, max_renders: int = 4) -> dict[str, Any]:
    """Write every artifact of the run into its folder; returns a summary."""
    out = trainer.out
    save_ply(trainer.gaussians.detach(), out / "point_cloud.ply")
    files: dict[str, Any] = {"ply": "point_cloud.ply"}
    if trainer.envmap is not None:
        paths = save_envmap(trainer.envmap.texels().detach().cpu(), out)
        files["envmap"] = {k: Path(p).name for k, p in paths.items()}
    render_dir = out / "renders"
    views = trainer.eval_views()[:max_renders]
    for v in views:
        stem = (v.name or "view").replace("/", "_")
        for ch, img in channel_images(trainer, v.camera).items():
            write_image(render_dir / f"{stem}_{ch}.png", img)
    files["renders"] = sorted(p.name for p in render_dir.glob("*.png"))
    geo_views = trainer.scene.test or trainer.scene.train
    geo = geometry_errors(trainer, geo_views)
    if geo is not None:
        (out / "geometry.json").write_text(json.dumps(geo, indent=2))
    write_report(out, export_sections(trainer, geo))
    files["report"] = "report.md"
    summary = {"files": files, "geometry": geo, "iteration": trainer.iteration}
    (out / "outputs.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary
