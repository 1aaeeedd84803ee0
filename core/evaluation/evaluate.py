"""Evaluation of one run (``glint eval``): every metric the paper reports, in one file.

``evaluate_run`` scores a trained run the way the paper does (Sect. 5): PSNR, SSIM
and LPIPS on every test view, Chamfer distance ×10² and F-score of the TSDF mesh
against ``gt_points.ply`` (the data README's recipe), normal and depth error against
the GT maps, rendering speed, Gaussian count and training time. It writes
``eval.json`` (atomically: its presence marks a finished benchmark cell) and adds an
"Evaluation" section to ``report.md``.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from core.evaluation.envmap_accuracy import (
    envmap_accuracy,
    specular_share,
)
from core.evaluation.geometry import (
    DEFAULT_CHAMFER_POINTS,
    chamfer_floor_x100,
    geometry_errors,
    load_gt_points,
    mesh_chamfer,
)
from core.model.run_folder import attach_scene, open_run
from core.model.trained import TrainedModel
from core.outputs.export import export_sections
from core.outputs.report import read_metrics, write_report

if TYPE_CHECKING:
    import trimesh

    from core.scene.views import Scene, View

EVAL_FILE = "eval.json"


def atomic_json(path: Path, data: dict[str, Any]) -> None:
    """Write JSON so that a reader sees the old file or the new one, never half of one."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, default=_json_default))
    tmp.replace(path)


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serialisable: {type(x)}")


def test_views(scene: Scene) -> list[View]:
    """All held-out views (the paper's test split), or the training views if none."""
    return list(scene.test or scene.train)


@torch.no_grad()
def image_metrics(model: TrainedModel, views: Sequence[View]) -> dict[str, Any]:
    """PSNR/SSIM (and LPIPS when its weights are here) of the deferred renders."""
    from core.evaluation.metrics import lpips_distance, lpips_unavailable_reason, psnr, ssim_srgb

    bg = model.background
    reason = lpips_unavailable_reason()
    rows = []
    for v in views:
        final = model.render(v.camera, ("final",), background=bg).image("final")
        target = v.composited(bg.cpu()).to(model.device)
        row: dict[str, Any] = {
            "view": v.name,
            "psnr": psnr(final, target),
            "ssim": ssim_srgb(final, target),
        }
        if reason is None:
            row["lpips"] = lpips_distance(final, target)
        rows.append(row)
    out: dict[str, Any] = {
        "views": len(rows),
        "psnr": float(np.mean([r["psnr"] for r in rows])),
        "ssim": float(np.mean([r["ssim"] for r in rows])),
        "lpips": float(np.mean([r["lpips"] for r in rows])) if reason is None else "unavailable",
        "per_view": rows,
    }
    if reason is not None:
        out["lpips_reason"] = reason
    return out


@torch.no_grad()
def render_speed(
    model: TrainedModel, views: Sequence[View], *, frames: int | None = None, warmup: int = 3
) -> dict[str, Any]:
    """FPS of the full deferred renderer (G-buffer + shading) at the test resolution."""
    from core.evaluation.metrics import time_renders
    from core.kernels.pool import kernel_threads
    from core.render.raster import resolve_backend

    bg = model.background
    cams = [v.camera for v in views]
    # a few passes over the views: short windows are at the mercy of a shared machine
    n = frames if frames is not None else max(3 * len(cams), 24)

    def render(i: int) -> object:
        return model.render(cams[i % len(cams)], ("final",), background=bg).image("final")

    out = time_renders(render, n, warmup=warmup, device=model.device)
    out.update(
        resolution=[cams[0].width, cams[0].height],
        device=str(model.device),
        backend=resolve_backend(model.backend, model.device),
        threads=kernel_threads(),
    )
    return out


def ensure_mesh(
    model: TrainedModel,
    views: Sequence[View],
    out: Path,
    *,
    voxel: float | None = None,
    trunc: float | None = None,
    resolution: int | None = None,
    hull: bool | None = None,
    remesh: bool = False,
    grazing_blend: bool = True,
) -> tuple[trimesh.Trimesh, dict[str, Any]]:
    """The run's TSDF mesh: reuse mesh.ply when it was made from this checkpoint with
    the same settings, else extract it from ``views`` (and write mesh.ply/.obj/.glb);
    ``hull``: bound it by the masks' hull (tsdf.hull_bound); None: as the run's plan says."""
    import trimesh

    from core.meshing.mesh import mesh_model, planned_hull
    from core.meshing.tsdf import DEFAULT_RESOLUTION

    hull = planned_hull(model) if hull is None else hull
    request = {
        "voxel": voxel, "trunc": trunc, "resolution": resolution or DEFAULT_RESOLUTION,
        "hull": hull, "grazing_blend": grazing_blend,
    }  # fmt: skip
    info_path = out / "mesh.json"
    if not remesh and info_path.is_file() and (out / "mesh.ply").is_file():
        info = json.loads(info_path.read_text())
        # older records: no hull, planar depth at every angle
        made = {"hull": False, "grazing_blend": False, **(info.get("request") or {})}
        if info.get("iteration") == model.iteration and made == request:
            mesh = trimesh.load(out / "mesh.ply", process=False, force="mesh")
            return mesh, info
    mesh, info = mesh_model(
        model, views, out, voxel=voxel, trunc=trunc, resolution=request["resolution"],
        hull=hull, grazing_blend=grazing_blend,
    )  # fmt: skip
    info["request"] = request
    info_path.write_text(json.dumps(info, indent=2))
    return mesh, info


def train_time(run_dir: Path) -> float | None:
    """Training wall time (evaluation excluded) of the last metrics row."""
    rows = read_metrics(Path(run_dir) / "metrics.jsonl")
    return float(rows[-1]["wall_time"]) if rows else None


def evaluate_run(
    run_dir: str | Path,
    gt_scene: str | Path | None = None,
    *,
    scene: Scene | None = None,
    n_points: int = DEFAULT_CHAMFER_POINTS,
    voxel: float | None = None,
    trunc: float | None = None,
    mesh_resolution: int | None = None,
    hull: bool | None = None,
    remesh: bool = False,
    grazing_blend: bool = True,
    fps_frames: int | None = None,
    device: str | None = None,
    backend: str | None = None,
    notes: list[str] | None = None,
) -> dict[str, Any]:
    """Every metric of the paper for one run; writes eval.json and the report section.

    ``scene``: the run's scene when the caller has it loaded (else it is read from
    ``gt_scene`` or the run's record); ``device``/``backend``/``notes``: where to
    reopen the run (see ``TrainedModel.open``).
    """
    run = Path(run_dir)
    if scene is None:
        model, scene = open_run(run, gt_scene, device=device, backend=backend, notes=notes)
    else:
        model = TrainedModel.open(run, device=device, backend=backend, notes=notes)
        attach_scene(model, scene)
    t0 = time.perf_counter()
    views = test_views(scene)
    ev: dict[str, Any] = {
        "run": str(run),
        "scene": str(scene.root) if scene.root else None,
        "iteration": model.iteration,
        "n_gaussians": model.gaussians.num,
        "train_seconds": train_time(run),
        "config": {
            "ablation": model.config.ablation.model_dump(),
            "iterations": model.config.iterations,
            "resolution_scale": model.config.resolution_scale,
        },
    }
    ev["image"] = image_metrics(model, views)
    ev["fps"] = render_speed(model, views, frames=fps_frames)
    ev["geometry"] = geometry_errors(model, views, scene.root)
    gt = load_gt_points(scene.root)
    mesh, mesh_info = ensure_mesh(
        model, scene.train, run, voxel=voxel, trunc=trunc, resolution=mesh_resolution,
        hull=hull, remesh=remesh, grazing_blend=grazing_blend,
    )  # fmt: skip
    ev["mesh"] = {k: mesh_info.get(k) for k in ("vertices", "faces", "watertight", "components")}
    ev["mesh"]["fusion"] = mesh_info.get("fusion")
    ev["chamfer"] = None
    if gt is not None and len(mesh.faces):
        ev["chamfer"] = mesh_chamfer(mesh, gt, n_points=n_points)
        ev["chamfer"]["floor_x100"] = chamfer_floor_x100(scene.root, n_points)
    elif gt is not None:
        ev["chamfer"] = {"error": "the extracted mesh is empty"}
    ev["envmap"] = envmap_accuracy(model, scene.train, scene.root, run)
    ev["specular_share"] = specular_share(model, views)
    ev["summary"] = summarize(ev)
    ev["eval_seconds"] = round(time.perf_counter() - t0, 2)
    atomic_json(run / EVAL_FILE, ev)
    write_report(run, [*export_sections(model, ev["geometry"]), evaluation_section(ev)])
    return ev


def summarize(ev: dict[str, Any]) -> dict[str, Any]:
    """The headline numbers of an evaluation (one row of the benchmark table)."""
    ch = ev.get("chamfer") or {}
    geo = ev.get("geometry") or {}
    img = ev.get("image") or {}
    env = ev.get("envmap") or {}
    return {
        "cd_x100": ch.get("cd_x100"),
        "cd_x100_seen": ch.get("cd_x100_seen"),
        "cd_floor_x100": ch.get("floor_x100"),
        "fscore": ch.get("fscore"),
        "fscore_seen": ch.get("fscore_seen"),
        "dropped": ch.get("dropped"),
        "psnr": img.get("psnr"),
        "ssim": img.get("ssim"),
        "lpips": img.get("lpips"),
        "fps": (ev.get("fps") or {}).get("fps"),
        "train_seconds": ev.get("train_seconds"),
        "normal_error_deg": geo.get("normal_error_deg"),
        "depth_abs_error": geo.get("depth_abs_error"),
        "depth_bias": geo.get("depth_bias"),
        "n_gaussians": ev.get("n_gaussians"),
        "envmap_psnr": env.get("psnr"),
        "envmap_log_correlation": env.get("log_correlation"),
        "envmap_psnr_channel_gains": env.get("psnr_channel_gains"),
        "specular_share": ev.get("specular_share"),
    }


def fmt_value(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, str):
        return v
    if isinstance(v, int):
        return f"{v:,}"
    return f"{v:.{digits}f}"


def evaluation_section(ev: dict[str, Any]) -> str:
    """Markdown for report.md: what was measured, how, and the numbers."""
    s = ev["summary"]
    img, fps = ev["image"], ev["fps"]
    lines = [
        "## Evaluation",
        "",
        f"Iteration {ev['iteration']}, {fmt_value(ev['n_gaussians'])} Gaussians, "
        f"{fmt_value(ev['train_seconds'], 1)} s of training.",
        "",
        "| metric | value |",
        "|---|---:|",
        f"| PSNR (dB), {img['views']} test views | {fmt_value(s['psnr'])} |",
        f"| SSIM | {fmt_value(s['ssim'], 4)} |",
        f"| LPIPS | {fmt_value(s['lpips'], 4)} |",
        f"| CD ×10² (a perfect surface: {fmt_value(s.get('cd_floor_x100'), 3)}) "
        f"| {fmt_value(s['cd_x100'], 3)} |",
        f"| CD ×10² (seen GT points) | {fmt_value(s['cd_x100_seen'], 3)} |",
        f"| F-score @ 0.01 | {fmt_value(s['fscore'], 3)} |",
        f"| normal error (°) | {fmt_value(s['normal_error_deg'])} |",
        f"| depth error (abs) | {fmt_value(s['depth_abs_error'], 4)} |",
        f"| depth bias (median of rendered − true; + is behind) "
        f"| {fmt_value(s.get('depth_bias'), 4)} |",
        f"| env map PSNR after exposure fit (dB) | {fmt_value(s.get('envmap_psnr'))} |",
        f"| env map log-luminance correlation | {fmt_value(s.get('envmap_log_correlation'), 3)} |",
        f"| specular share of the colour | {fmt_value(s.get('specular_share'), 3)} |",
        f"| FPS ({fps['resolution'][0]}×{fps['resolution'][1]}, {fps['device']}) "
        f"| {fmt_value(fps['fps'], 1)} |",
        "",
    ]
    if img.get("lpips_reason"):
        lines.append(f"LPIPS unavailable: {img['lpips_reason']}.")
    ch = ev.get("chamfer")
    if ch and "cd" in ch:
        lines.append(
            f"Chamfer distance: {fmt_value(ch['sampled'])} points sampled uniformly by area "
            f"on the TSDF mesh ({fmt_value(ev['mesh']['faces'])} faces), "
            f"{fmt_value(ch['dropped'])} dropped beyond r = {ch['max_radius']:g} from the "
            f"origin, against {fmt_value(ch['n_gt'])} GT points; "
            "CD = (d(P→G) + d(G→P)) / 2 (Euclidean, no alignment)."
        )
    elif ch is None:
        lines.append("No gt_points.ply in the scene: no Chamfer distance.")
    env = ev.get("envmap")
    if env and "psnr" in env:
        lines.append(
            f"Env map: the learned map against the scene's envmap.exr over the "
            f"{fmt_value(env['directions'])} directions the training views reflect "
            f"({env['normals']} normals; {env['seen_fraction']:.0%} of the sphere), after "
            f"one exposure factor ({env['exposure']:.3g}); PSNR in display space "
            f"(sRGB of radiance clipped at 1). Picture: {env.get('picture', '–')}."
        )
    lines.append(
        f"FPS: median of {fps['frames']} timed frames after {fps['warmup']} warm-up frames "
        f"({fps['backend']} backend, {fps['threads']} threads)."
    )
    return "\n".join(lines)
