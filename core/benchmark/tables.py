"""bench.md: the benchmark's tables (paper Table 3 layout) and error-vs-time plots."""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from core.benchmark.configs import LABELS, TABLE_ORDER
from core.config import format_duration
from core.evaluation.evaluate import EVAL_FILE
from core.evaluation.evaluate import fmt_value as _f
from core.outputs.report import plot_error_vs_time, read_metrics

if TYPE_CHECKING:
    from core.benchmark.cells import Cell

# (key, header, digits, better: +1 higher, -1 lower, 0 neither)
COLUMNS: tuple[tuple[str, str, int, int], ...] = (
    ("cd_x100", "CD×10² ↓", 3, -1),
    ("cd_floor_x100", "perfect CD×10²", 3, 0),
    ("cd_x100_seen", "CD×10² seen ↓", 3, -1),
    ("fscore", "F@0.01 ↑", 3, 1),
    ("psnr", "PSNR ↑", 2, 1),
    ("ssim", "SSIM ↑", 4, 1),
    ("lpips", "LPIPS ↓", 4, -1),
    ("fps", "FPS ↑", 1, 1),
    ("train_seconds", "train time (s)", 0, 0),
    ("normal_error_deg", "normal err (°) ↓", 2, -1),
    ("depth_abs_error", "depth err ↓", 4, -1),
    ("depth_bias", "depth bias", 4, 0),
    ("envmap_psnr", "env map PSNR ↑", 2, 1),
    ("envmap_psnr_channel_gains", "env map PSNR, RGB gains ↑", 2, 1),
    ("envmap_log_correlation", "env map corr ↑", 3, 1),
    ("specular_share", "specular share", 3, 0),
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


CURVE_KEYS = ("psnr", "cd_x100", "normal_error_deg", "depth_normal_consistency_deg")


def mean_curve(curves: Sequence[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Wall time and each error averaged over scenes at the iterations all share (a
    geometry value only where every scene has it)."""
    if not curves:
        return []
    common = set.intersection(*[{r["iteration"] for r in rows} for rows in curves])
    out = []
    for it in sorted(common):
        rs = [next(r for r in rows if r["iteration"] == it) for rows in curves]
        row: dict[str, Any] = {
            "iteration": it,
            "wall_time": float(np.mean([r["wall_time"] for r in rs])),
            "phase": rs[0].get("phase"),
        }
        for key in CURVE_KEYS:
            vals = [_num(r.get(key)) for r in rs]
            if all(v is not None for v in vals):
                row[key] = float(np.mean(vals))
        out.append(row)
    return out


def value_at(rows: list[dict[str, Any]], key: str, t: float) -> float | None:
    """``key`` at training time ``t``, linearly interpolated between the rows that
    recorded it (None outside them)."""
    pts = [(r["wall_time"], x) for r in rows if (x := _num(r.get(key))) is not None]
    if not pts or t < pts[0][0] - 1e-9 or t > pts[-1][0] + 1e-9:
        return None
    ts, vs = zip(*pts, strict=True)
    return float(np.interp(t, ts, vs))


def time_to_reach(rows: list[dict[str, Any]], key: str, target: float) -> float | None:
    """Training seconds until ``key`` (an error) first falls to ``target``, linearly
    interpolated between the recorded points; None when it never does."""
    pts = [(r["wall_time"], x) for r in rows if (x := _num(r.get(key))) is not None]
    for (t0, v0), (t1, v1) in itertools.pairwise(pts):
        if v0 <= target:
            return t0
        if v1 <= target:
            return t0 + (t1 - t0) * (v0 - target) / (v0 - v1)
    if pts and pts[-1][1] <= target:
        return pts[-1][0]
    return None


# (key, header, digits, better) of the equal-wall-time table: the run record's figures
TIME_COLUMNS: tuple[tuple[str, str, int, int], ...] = (
    ("cd_x100", "CD×10² (surface points) ↓", 3, -1),
    ("psnr", "PSNR ↑", 2, 1),
    ("normal_error_deg", "normal err (°) ↓", 2, -1),
    ("depth_abs_error", "depth err ↓", 4, -1),
    ("depth_bias", "depth bias", 4, 0),
    ("envmap_psnr", "env map PSNR ↑", 2, 1),
    ("envmap_psnr_channel_gains", "env map PSNR, RGB gains ↑", 2, 1),
    ("envmap_log_correlation", "env map corr ↑", 3, 1),
    ("specular_share", "specular share", 3, 0),
)


def equal_time_rows(
    curves: dict[str, list[dict[str, Any]]],
) -> tuple[float, dict[str, dict[str, Any]]]:
    """Each configuration's recorded errors at the wall time the fastest one finished."""
    ends = [rows[-1]["wall_time"] for rows in curves.values() if rows]
    t = min(ends) if ends else 0.0
    out = {}
    for name, rows in curves.items():
        out[name] = {key: value_at(rows, key, t) for key, _, _, _ in TIME_COLUMNS}
    return t, out


def reach_table(curves: dict[str, list[dict[str, Any]]], target: float | None) -> str | None:
    """Time each configuration needs to bring its Chamfer distance down to ``target``
    (default: the worst final figure, which every configuration reaches)."""
    finals = [x for rows in curves.values() for r in rows[-1:] if (x := _num(r.get("cd_x100")))]
    if not finals:
        return None
    target = max(finals) if target is None else target
    names = [n for n in TABLE_ORDER if n in curves] + [n for n in curves if n not in TABLE_ORDER]
    lines = [
        f"Training seconds until CD×10² (surface points) ≤ {target:.3f}:",
        "",
        "| Model settings | seconds ↓ |",
        "|---|---:|",
    ]
    for n in names:
        t = time_to_reach(curves[n], "cd_x100", target)
        lines.append(f"| {LABELS.get(n, n)} | {_f(t, 1) if t is not None else 'not reached'} |")
    return "\n".join(lines)


def write_bench(
    out: Path,
    cells: Sequence[Cell],
    *,
    budget: int | None,
    resolution_scale: float,
    command: str | None = None,
    time_budget: float | None = None,
    target_cd: float | None = None,
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
            title=f"{scene}: held-out error vs training time",
        )
    mean_curves = {
        LABELS[c]: mean_curve([curves[s][c] for s in curves if c in curves[s]])
        for c in configs
        if any(c in curves[s] for s in curves)
    }
    plot_error_vs_time(
        mean_curves,
        out / "error_vs_time.png",
        title=f"Held-out error vs training time, mean over {len(curves)} scene(s)",
    )
    # the preamble describes the protocol from a run that has every part of it
    any_ev = next((e for e in evals.values() if e.get("chamfer")), next(iter(evals.values()), None))
    parts = ["# Glint ablation benchmark (paper Table 3 layout)", ""]
    if command:
        parts += [f"Command: `{command}`", ""]
    parts += _bench_preamble(any_ev, budget, resolution_scale, len(cells), len(evals), time_budget)
    for scene, rows in per_scene.items():
        parts += [f"## {scene}", "", "At the end of each run (`glint eval`):", ""]
        parts += [results_table(rows), ""]
        t, at_t = equal_time_rows(curves[scene])
        parts += [
            f"At equal wall time: each run's recorded errors at {t:.1f} s of training, when "
            "the fastest finished (interpolated between its evaluations):",
            "",
            results_table(at_t, TIME_COLUMNS),
            "",
        ]
        reach = reach_table(curves[scene], target_cd)
        if reach:
            parts += [reach, ""]
        parts += [f"![{scene}: error vs time](error_vs_time_{scene}.png)", ""]
    if len(per_scene) > 1:
        parts += [f"## Mean over {len(per_scene)} scenes", "", results_table(mean_rows(per_scene))]
        parts += [""]
    parts += ["## Error against training time", "", "![error vs time](error_vs_time.png)", ""]
    path = out / "bench.md"
    path.write_text("\n".join(parts))
    return path


def _bench_preamble(
    ev: dict[str, Any] | None,
    budget: int | None,
    resolution_scale: float,
    n_cells: int,
    n_done: int,
    time_budget: float | None = None,
) -> list[str]:
    sized = []
    if budget is not None:
        sized.append(f"{budget:,} iterations")
    if time_budget is not None:
        sized.append(f"{format_duration(time_budget)} of run time (training, evaluation)")
    lines = [
        f"{n_done}/{n_cells} runs finished. Budget per run: {' or '.join(sized)}, whichever "
        "comes first (the paper's 30k-iteration phase marks scaled to the run's length), "
        f"images at resolution scale {resolution_scale:g}.",
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
            "- L_multi is used as the scene plan decides: a capture whose every view has a "
            "mask drops it (its silhouette points pin the surface), so there 'w/o L_multi' "
            "repeats the full model; `--set plan_overrides.multi_view=true` gives the paper's.",
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
