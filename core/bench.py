"""Evaluation of a run (``glint eval``) and the ablation benchmark (``glint bench``).

``evaluate_run`` scores one trained run the way the paper reports (Sect. 5): PSNR,
SSIM and LPIPS on every test view, Chamfer distance ×10² and F-score of the TSDF
mesh against ``gt_points.ply`` (the data README's recipe), normal and depth error
against the GT maps, rendering speed, Gaussian count and training time. It writes
``eval.json`` (atomically: its presence marks a finished benchmark cell) and adds
an "Evaluation" section to ``report.md``.

``run_bench`` trains the full model and the Table 3 ablations (plus an SH-only
baseline) on each scene at one iteration budget, evaluates each run and writes
``bench.md`` (Table 3 layout, one table per scene and their mean) and
``error_vs_time.png``. Cells are run folders ``OUT/<scene>/<config>``; a cell with
an ``eval.json`` is finished and skipped, an interrupted one resumes from its
checkpoint.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from core.config import TrainConfig, config_from_dict, saved_config
from core.report import plot_error_vs_time, read_metrics, write_report

if TYPE_CHECKING:
    import trimesh

    from core.scene import Scene, View
    from core.trainer import Trainer

EVAL_FILE = "eval.json"
DEFAULT_CHAMFER_POINTS = 1_000_000  # the data README's sampling floor is stated for 1M

# name -> ablation switches (the paper's Table 3, plus the SH-only baseline)
CONFIGS: dict[str, dict[str, bool]] = {
    "full": {},
    "no_deferred": {"deferred_shading": False},
    "eq5_depth": {"planar_depth": False},
    "no_single": {"single_view": False},
    "no_multi": {"multi_view": False},
    "sh_only": {"deferred_shading": False, "single_view": False, "multi_view": False},
}
LABELS = {
    "full": "Full model",
    "no_deferred": "w/o deferred shading",
    "eq5_depth": "w/o depth compute (Eq. 5 depth)",
    "no_single": "w/o L_single",
    "no_multi": "w/o L_multi",
    "sh_only": "SH only (no deferred, no L_single, no L_multi)",
}
# rows in the order of the paper's Table 3 (full model last), the baseline first
TABLE_ORDER = ("sh_only", "no_deferred", "eq5_depth", "no_single", "no_multi", "full")


# -- evaluation of one run ----------------------------------------------------------


def _atomic_json(path: Path, data: dict[str, Any]) -> None:
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


def eval_views(scene: Scene) -> list[View]:
    """All held-out views (the paper's test split), or the training views if none."""
    return list(scene.test or scene.train)


@torch.no_grad()
def image_metrics(trainer: Trainer, views: Sequence[View]) -> dict[str, Any]:
    """PSNR/SSIM (and LPIPS when its weights are here) of the deferred renders."""
    from core.metrics import lpips_distance, lpips_unavailable_reason, psnr, ssim_srgb
    from core.trainer import eval_background, render_view

    bg = eval_background(trainer.cfg, trainer.device)
    phase = trainer.current_phase(max(trainer.iteration - 1, 0))
    reason = lpips_unavailable_reason()
    rows = []
    for v in views:
        vv = trainer._to_device(v)
        _, shade, _ = render_view(
            trainer.gaussians, trainer.envmap, vv.camera, phase, bg, trainer.cfg.backend
        )
        target = vv.composited(bg)
        row: dict[str, Any] = {
            "view": v.name,
            "psnr": psnr(shade.final, target),
            "ssim": ssim_srgb(shade.final, target),
        }
        if reason is None:
            row["lpips"] = lpips_distance(shade.final, target)
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
    trainer: Trainer, views: Sequence[View], *, frames: int | None = None, warmup: int = 3
) -> dict[str, Any]:
    """FPS of the full deferred renderer (G-buffer + shading) at the test resolution."""
    from core.kernel_pool import kernel_threads
    from core.metrics import time_renders
    from core.raster import resolve_backend
    from core.trainer import eval_background, render_view

    bg = eval_background(trainer.cfg, trainer.device)
    phase = trainer.current_phase(max(trainer.iteration - 1, 0))
    cams = [v.camera for v in views]
    # a few passes over the views: short windows are at the mercy of a shared machine
    n = frames if frames is not None else max(3 * len(cams), 24)

    def render(i: int) -> object:
        return render_view(
            trainer.gaussians, trainer.envmap, cams[i % len(cams)], phase, bg, trainer.cfg.backend
        )[1].final

    out = time_renders(render, n, warmup=warmup, device=trainer.device)
    out.update(
        resolution=[cams[0].width, cams[0].height],
        device=str(trainer.device),
        backend=resolve_backend(trainer.cfg.backend, trainer.device),
        threads=kernel_threads(),
    )
    return out


def ensure_mesh(
    trainer: Trainer,
    *,
    voxel: float | None = None,
    trunc: float | None = None,
    resolution: int | None = None,
    remesh: bool = False,
) -> tuple[trimesh.Trimesh, dict[str, Any]]:
    """The run's TSDF mesh: reuse mesh.ply when it was made from this checkpoint with
    the same settings, else extract it (and write mesh.ply/.obj/.glb)."""
    import trimesh

    from core.mesh import DEFAULT_RESOLUTION, mesh_run

    request = {"voxel": voxel, "trunc": trunc, "resolution": resolution or DEFAULT_RESOLUTION}
    info_path = trainer.out / "mesh.json"
    if not remesh and info_path.is_file() and (trainer.out / "mesh.ply").is_file():
        info = json.loads(info_path.read_text())
        if info.get("iteration") == trainer.iteration and info.get("request") == request:
            mesh = trimesh.load(trainer.out / "mesh.ply", process=False, force="mesh")
            return mesh, info
    mesh, info = mesh_run(trainer, voxel=voxel, trunc=trunc, resolution=request["resolution"])
    info["request"] = request
    info_path.write_text(json.dumps(info, indent=2))
    return mesh, info


def load_gt_points(scene_root: Path | None) -> dict[str, np.ndarray] | None:
    """``gt_points.ply`` (points, normals) and ``gt_points_seen.npy`` when present."""
    if scene_root is None or not (Path(scene_root) / "gt_points.ply").is_file():
        return None
    from plyfile import PlyData

    root = Path(scene_root)
    v = PlyData.read(str(root / "gt_points.ply"))["vertex"]
    out = {"points": np.stack([np.asarray(v[k], dtype=np.float64) for k in "xyz"], 1)}
    names = {p.name for p in v.properties}
    if {"nx", "ny", "nz"} <= names:
        out["normals"] = np.stack(
            [np.asarray(v[k], dtype=np.float64) for k in ("nx", "ny", "nz")], 1
        )
    seen = root / "gt_points_seen.npy"
    if seen.is_file():
        out["seen"] = np.load(seen).astype(bool)
    return out


def mesh_chamfer(
    mesh: trimesh.Trimesh,
    gt: dict[str, np.ndarray],
    *,
    n_points: int = DEFAULT_CHAMFER_POINTS,
    seed: int = 0,
) -> dict[str, Any]:
    """CD, F-score (all and seen GT) and normal consistency of a mesh vs GT points."""
    from core.metrics import chamfer_distance, sample_surface

    pts, face = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.faces), n_points, seed)
    normals = np.asarray(mesh.face_normals)[face] if len(face) else None
    res = chamfer_distance(
        pts,
        gt["points"],
        gt_seen=gt.get("seen"),
        pred_normals=normals,
        gt_normals=gt.get("normals"),
    )
    res["sampled"] = n_points
    return res


def train_time(run_dir: Path) -> float | None:
    """Training wall time (evaluation excluded) of the last metrics row."""
    rows = read_metrics(Path(run_dir) / "metrics.jsonl")
    return float(rows[-1]["wall_time"]) if rows else None


def evaluate_run(
    run_dir: str | Path,
    gt_scene: str | Path | None = None,
    *,
    trainer: Trainer | None = None,
    n_points: int = DEFAULT_CHAMFER_POINTS,
    voxel: float | None = None,
    trunc: float | None = None,
    mesh_resolution: int | None = None,
    remesh: bool = False,
    fps_frames: int | None = None,
    device: str | None = None,
    backend: str | None = None,
    notes: list[str] | None = None,
) -> dict[str, Any]:
    """Every metric of the paper for one run; writes eval.json and the report section.

    ``device``/``backend``/``notes``: where to reopen the run (see ``load_run``).
    """
    from core.outputs import export_sections, geometry_errors, load_run

    run = Path(run_dir)
    if trainer is None:
        trainer = load_run(run, gt_scene, device=device, backend=backend, notes=notes)
    t0 = time.perf_counter()
    views = eval_views(trainer.scene)
    ev: dict[str, Any] = {
        "run": str(run),
        "scene": str(trainer.scene.root) if trainer.scene.root else None,
        "iteration": trainer.iteration,
        "n_gaussians": trainer.gaussians.num,
        "train_seconds": train_time(run),
        "config": {
            "ablation": trainer.cfg.ablation.model_dump(),
            "iterations": trainer.cfg.iterations,
            "resolution_scale": trainer.cfg.resolution_scale,
        },
    }
    ev["image"] = image_metrics(trainer, views)
    ev["fps"] = render_speed(trainer, views, frames=fps_frames)
    ev["geometry"] = geometry_errors(trainer, views)
    gt = load_gt_points(trainer.scene.root)
    mesh, mesh_info = ensure_mesh(
        trainer, voxel=voxel, trunc=trunc, resolution=mesh_resolution, remesh=remesh
    )
    ev["mesh"] = {k: mesh_info.get(k) for k in ("vertices", "faces", "watertight", "components")}
    ev["mesh"]["fusion"] = mesh_info.get("fusion")
    ev["chamfer"] = None
    if gt is not None and len(mesh.faces):
        ev["chamfer"] = mesh_chamfer(mesh, gt, n_points=n_points)
    elif gt is not None:
        ev["chamfer"] = {"error": "the extracted mesh is empty"}
    ev["summary"] = summarize(ev)
    ev["eval_seconds"] = round(time.perf_counter() - t0, 2)
    _atomic_json(run / EVAL_FILE, ev)
    write_report(run, [*export_sections(trainer, ev["geometry"]), evaluation_section(ev)])
    return ev


def summarize(ev: dict[str, Any]) -> dict[str, Any]:
    """The headline numbers of an evaluation (one row of the benchmark table)."""
    ch = ev.get("chamfer") or {}
    geo = ev.get("geometry") or {}
    img = ev.get("image") or {}
    return {
        "cd_x100": ch.get("cd_x100"),
        "cd_x100_seen": ch.get("cd_x100_seen"),
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
        "n_gaussians": ev.get("n_gaussians"),
    }


def _f(v: Any, digits: int = 2) -> str:
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
        f"Iteration {ev['iteration']}, {_f(ev['n_gaussians'])} Gaussians, "
        f"{_f(ev['train_seconds'], 1)} s of training.",
        "",
        "| metric | value |",
        "|---|---:|",
        f"| PSNR (dB), {img['views']} test views | {_f(s['psnr'])} |",
        f"| SSIM | {_f(s['ssim'], 4)} |",
        f"| LPIPS | {_f(s['lpips'], 4)} |",
        f"| CD ×10² | {_f(s['cd_x100'], 3)} |",
        f"| CD ×10² (seen GT points) | {_f(s['cd_x100_seen'], 3)} |",
        f"| F-score @ 0.01 | {_f(s['fscore'], 3)} |",
        f"| normal error (°) | {_f(s['normal_error_deg'])} |",
        f"| depth error (abs) | {_f(s['depth_abs_error'], 4)} |",
        f"| FPS ({fps['resolution'][0]}×{fps['resolution'][1]}, {fps['device']}) "
        f"| {_f(fps['fps'], 1)} |",
        "",
    ]
    if img.get("lpips_reason"):
        lines.append(f"LPIPS unavailable: {img['lpips_reason']}.")
    ch = ev.get("chamfer")
    if ch and "cd" in ch:
        lines.append(
            f"Chamfer distance: {_f(ch['sampled'])} points sampled uniformly by area on the "
            f"TSDF mesh ({_f(ev['mesh']['faces'])} faces), {_f(ch['dropped'])} dropped beyond "
            f"r = {ch['max_radius']:g} from the origin, against {_f(ch['n_gt'])} GT points; "
            "CD = (d(P→G) + d(G→P)) / 2 (Euclidean, no alignment)."
        )
    elif ch is None:
        lines.append("No gt_points.ply in the scene: no Chamfer distance.")
    lines.append(
        f"FPS: median of {fps['frames']} timed frames after {fps['warmup']} warm-up frames "
        f"({fps['backend']} backend, {fps['threads']} threads)."
    )
    return "\n".join(lines)


# -- the benchmark ------------------------------------------------------------------


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


def parse_configs(text: str | Sequence[str]) -> list[str]:
    """Comma-separated configuration names, validated against :data:`CONFIGS`."""
    from core.errors import GlintError

    names = [n.strip() for n in text.split(",")] if isinstance(text, str) else list(text)
    names = [n for n in names if n]
    unknown = [n for n in names if n not in CONFIGS]
    if unknown or not names:
        raise GlintError(
            f"unknown configuration(s) {', '.join(unknown) or '(none)'}; "
            f"expected some of {', '.join(CONFIGS)}"
        )
    return list(dict.fromkeys(names))


def bench_config(
    name: str, budget: int, resolution_scale: float, base: dict[str, Any] | None = None
) -> TrainConfig:
    """The training config of one benchmark cell: ``base`` + budget + ablation switches.

    Where deferred shading is on, the env map is forced on (``plan_overrides.envmap``):
    the scene planner would drop it on scenes it measures as only mildly
    view-dependent, and the "full model" row would silently become the
    no-deferred-shading row. A ``base`` that sets ``plan_overrides.envmap`` wins.
    """
    data = json.loads(json.dumps(base or {}))
    data["iterations"] = int(budget)
    data["resolution_scale"] = float(resolution_scale)
    data.setdefault("ablation", {}).update(CONFIGS[name])
    if data["ablation"].get("deferred_shading", True):
        data.setdefault("plan_overrides", {}).setdefault("envmap", True)
    return config_from_dict(data, f"bench config {name}")


def plan_cells(scenes: Sequence[str | Path], configs: Sequence[str], out: Path) -> list[Cell]:
    cells = []
    names: set[str] = set()
    for sd in scenes:
        sd = Path(sd)
        name = sd.resolve().name
        if name in names:
            from core.errors import GlintError

            raise GlintError(f"two scenes are named {name!r}; the run folders would collide")
        names.add(name)
        cells += [Cell(sd, name, c, out / name / c) for c in configs]
    return cells


def check_cell_config(cell: Cell, cfg: TrainConfig) -> None:
    """Refuse to reuse or resume a cell that was started with another configuration
    (another budget, resolution or override): its numbers would be mislabelled."""
    from core.errors import GlintError

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


def run_cell(
    cell: Cell,
    cfg: TrainConfig,
    scene: Scene,
    *,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    eval_kwargs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train (or resume) one cell and evaluate it."""
    from core.outputs import record_scene
    from core.run import train_scene
    from core.trainer import Trainer

    record_scene(cell.run_dir, cell.scene_dir)
    result, _ = train_scene(scene, cell.run_dir, cfg, on_event=on_event, resume=True)
    if result.status != "succeeded":
        raise RuntimeError(f"{cell.run_dir}: training {result.status}")
    trainer = Trainer(scene, cfg, cell.run_dir)
    trainer.setup(resume=True)
    return evaluate_run(cell.run_dir, trainer=trainer, **(eval_kwargs or {}))


def refresh_fps(cells: Sequence[Cell], *, frames: int | None = None) -> int:
    """Re-time the renderer of every finished cell, one after another in this process.

    Cells trained in parallel, or while the machine was busy, timed their renders
    under different loads; re-timing them back to back makes the FPS column
    comparable. Updates eval.json (``fps.refreshed``); returns how many were re-timed.
    """
    from core.scene_io import load_scene
    from core.trainer import Trainer

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
        trainer = Trainer(scenes[key], cfg, cell.run_dir)
        trainer.setup(resume=True)
        ev = json.loads((cell.run_dir / EVAL_FILE).read_text())
        ev["fps"] = {**render_speed(trainer, eval_views(trainer.scene), frames=frames)}
        ev["fps"]["refreshed"] = True
        ev["summary"] = summarize(ev)
        _atomic_json(cell.run_dir / EVAL_FILE, ev)
        n += 1
    return n


def run_bench(
    scenes: Sequence[str | Path],
    budget: int,
    out: str | Path,
    *,
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
    ``retime_fps`` re-times every finished cell's renderer back to back first)."""
    from tqdm import tqdm

    from core.scene_io import load_scene

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cells = plan_cells(scenes, configs, out)
    bar = tqdm(
        total=len(cells) * budget, unit="it", dynamic_ncols=True, disable=not progress, desc="bench"
    )
    loaded: dict[Path, Scene] = {}
    for cell in cells:
        bar.set_description(f"{cell.scene}/{cell.config}")
        cfg = bench_config(cell.config, budget, resolution_scale, base)
        check_cell_config(cell, cfg)
        if cell.done:
            bar.update(budget)
            continue
        if cell.scene_dir not in loaded:
            loaded.clear()  # one scene in memory at a time
            loaded[cell.scene_dir] = load_scene(cell.scene_dir, downscale=1.0 / resolution_scale)
        start = bar.n
        state = {"it": 0}

        def on_event(e: dict[str, Any], state: dict[str, int] = state) -> None:
            if e.get("type") in ("progress", "resumed"):
                it = int(e["iteration"])
                bar.update(it - state["it"])
                state["it"] = it
            elif e.get("type") == "exported":
                bar.set_postfix_str("evaluating")

        run_cell(cell, cfg, loaded[cell.scene_dir], on_event=on_event, eval_kwargs=eval_kwargs)
        bar.update(start + budget - bar.n)
        bar.set_postfix_str("")
    bar.close()
    if retime_fps:
        refresh_fps(cells)
    return write_bench(
        out, cells, budget=budget, resolution_scale=resolution_scale, command=command
    )


# -- the benchmark report -----------------------------------------------------------

# (key, header, digits, better: +1 higher, -1 lower, 0 neither)
COLUMNS: tuple[tuple[str, str, int, int], ...] = (
    ("cd_x100", "CD×10² ↓", 3, -1),
    ("cd_x100_seen", "CD×10² seen ↓", 3, -1),
    ("fscore", "F@0.01 ↑", 3, 1),
    ("psnr", "PSNR ↑", 2, 1),
    ("ssim", "SSIM ↑", 4, 1),
    ("lpips", "LPIPS ↓", 4, -1),
    ("fps", "FPS ↑", 1, 1),
    ("train_seconds", "train time (s)", 0, 0),
    ("normal_error_deg", "normal err (°) ↓", 2, -1),
    ("depth_abs_error", "depth err ↓", 4, -1),
    ("n_gaussians", "#Gaussians", 0, 0),
    ("dropped", "dropped > 1.1", 0, 0),
)


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(v) else None


def results_table(rows: dict[str, dict[str, Any]], columns=COLUMNS) -> str:
    """A Markdown table, one row per configuration (Table 3 order), best in bold."""
    names = [n for n in TABLE_ORDER if n in rows] + [n for n in rows if n not in TABLE_ORDER]
    best: dict[str, float] = {}
    for key, _, _, better in columns:
        vals = [x for n in names if (x := _num(rows[n].get(key))) is not None]
        if better and len(vals) > 1:
            best[key] = max(vals) if better > 0 else min(vals)
    lines = [
        "| Model settings | " + " | ".join(h for _, h, _, _ in columns) + " |",
        "|---|" + "---:|" * len(columns),
    ]
    for n in names:
        cells = []
        for key, _, digits, _ in columns:
            v = rows[n].get(key)
            text = _f(int(v) if digits == 0 and _num(v) is not None else v, digits)
            if key in best and _num(v) is not None and _num(v) == best[key]:
                text = f"**{text}**"
            cells.append(text)
        lines.append(f"| {LABELS.get(n, n)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def mean_rows(per_scene: dict[str, dict[str, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """Per configuration, the mean of each numeric column over the scenes that have it."""
    configs = {c for rows in per_scene.values() for c in rows}
    out: dict[str, dict[str, Any]] = {}
    for c in configs:
        vals: dict[str, list[float]] = {}
        for rows in per_scene.values():
            for key, v in rows.get(c, {}).items():
                if (x := _num(v)) is not None:
                    vals.setdefault(key, []).append(x)
        n = len([1 for rows in per_scene.values() if c in rows])
        out[c] = {k: float(np.mean(v)) for k, v in vals.items() if len(v) == n}
    return out


def mean_curve(curves: Sequence[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Held-out PSNR and wall time averaged over scenes at the iterations all share."""
    if not curves:
        return []
    common = set.intersection(*[{r["iteration"] for r in rows} for rows in curves])
    out = []
    for it in sorted(common):
        rs = [next(r for r in rows if r["iteration"] == it) for rows in curves]
        out.append(
            {
                "iteration": it,
                "wall_time": float(np.mean([r["wall_time"] for r in rs])),
                "psnr": float(np.mean([r["psnr"] for r in rs])),
                "phase": rs[0].get("phase"),
            }
        )
    return out


def write_bench(
    out: Path,
    cells: Sequence[Cell],
    *,
    budget: int,
    resolution_scale: float,
    command: str | None = None,
) -> Path:
    """bench.md + error_vs_time.png (and one plot per scene) from the cells' results."""
    per_scene: dict[str, dict[str, dict[str, Any]]] = {}
    curves: dict[str, dict[str, list[dict[str, Any]]]] = {}
    evals: dict[tuple[str, str], dict[str, Any]] = {}
    for c in cells:
        if not c.done:
            continue
        ev = json.loads((c.run_dir / EVAL_FILE).read_text())
        evals[(c.scene, c.config)] = ev
        per_scene.setdefault(c.scene, {})[c.config] = ev["summary"]
        curves.setdefault(c.scene, {})[c.config] = read_metrics(c.run_dir / "metrics.jsonl")
    configs = list(dict.fromkeys(c.config for c in cells))
    for scene, by_cfg in curves.items():
        plot_error_vs_time(
            {LABELS[k]: v for k, v in by_cfg.items()},
            out / f"error_vs_time_{scene}.png",
            title=f"{scene}: held-out PSNR vs training time",
        )
    mean_curves = {
        LABELS[c]: mean_curve([curves[s][c] for s in curves if c in curves[s]])
        for c in configs
        if any(c in curves[s] for s in curves)
    }
    plot_error_vs_time(
        mean_curves,
        out / "error_vs_time.png",
        title=f"Held-out PSNR vs training time, mean over {len(curves)} scene(s)",
    )
    # the preamble describes the protocol from a run that has every part of it
    any_ev = next((e for e in evals.values() if e.get("chamfer")), next(iter(evals.values()), None))
    parts = ["# Glint ablation benchmark (paper Table 3 layout)", ""]
    if command:
        parts += [f"Command: `{command}`", ""]
    parts += _bench_preamble(any_ev, budget, resolution_scale, len(cells), len(evals))
    for scene, rows in per_scene.items():
        parts += [f"## {scene}", "", results_table(rows), ""]
        parts += [f"![{scene}: error vs time](error_vs_time_{scene}.png)", ""]
    if len(per_scene) > 1:
        parts += [f"## Mean over {len(per_scene)} scenes", "", results_table(mean_rows(per_scene))]
        parts += [""]
    parts += ["## Error against training time", "", "![error vs time](error_vs_time.png)", ""]
    path = out / "bench.md"
    path.write_text("\n".join(parts))
    return path


def _bench_preamble(
    ev: dict[str, Any] | None, budget: int, resolution_scale: float, n_cells: int, n_done: int
) -> list[str]:
    lines = [
        f"{n_done}/{n_cells} runs finished. Budget: {budget:,} iterations per run (the "
        f"paper's 30k-iteration phase marks scaled to it), images at resolution scale "
        f"{resolution_scale:g}.",
        "",
    ]
    if ev is not None:
        fps = ev["fps"]
        ch = ev.get("chamfer") or {}
        fu = (ev.get("mesh") or {}).get("fusion") or {}
        lines += [
            f"- Device: {fps['device']}, rasteriser backend `{fps['backend']}`, "
            f"{fps['threads']} kernel threads; FPS of the deferred renderer at "
            f"{fps['resolution'][0]}×{fps['resolution'][1]} (median over {fps['frames']} frames "
            "after warm-up"
            + ("; re-timed back to back in one process" if fps.get("refreshed") else "")
            + "). Train time is wall time with evaluation excluded, under whatever load "
            "the machine had while each run trained.",
            "- Deferred shading (env map) is forced on wherever the configuration has it, "
            "whatever the scene planner would decide.",
            "- Geometry: TSDF fusion of the planar depth (Eq. 5 depth in that ablation) of "
            "every training view on a grid fitted to each run's surface (voxel = its largest "
            f"side / resolution, e.g. {_f(fu.get('voxel'), 4)} in "
            f"{'/'.join(Path(ev['run']).parts[-2:])}; truncation 4 voxels), marching cubes, "
            "largest components kept.",
        ]
        if ch:
            lines.append(
                f"- Chamfer distance: {_f(ch.get('sampled'))} points sampled on the mesh against "
                "gt_points.ply, points beyond r = 1.1 dropped (column 'dropped'), "
                "CD = (d(P→G) + d(G→P)) / 2 ×10²; 'seen' uses only the GT points visible in a "
                "training view. Sampling floor of a perfect surface at 1M points (data README): "
                "0.18 / 0.19 / 0.29 (teapot / spot / sphere)."
            )
        lines.append(
            "- Normal error (degrees) and depth error (absolute z) against the GT maps of the "
            "test views, over pixels both cover."
        )
        if ev["image"].get("lpips_reason"):
            lines.append(f"- LPIPS: unavailable ({ev['image']['lpips_reason']}).")
        lines.append("")
    return lines
