"""Error against run time: the metrics log, the Markdown table and the plot.

Every run appends one JSON line per evaluation (wall time excludes evaluation), so
two configurations can be compared at equal training time.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

ERROR_NOTE = (
    "Held-out views; train time excludes evaluation. Geometry: with ground truth, normal "
    "and depth error against the GT maps (same render as PSNR) and the Chamfer distance "
    "×10² of the rendered surface points (16 training views' depth, 150k points) against "
    "gt_points at 1/16, 1/8, 1/4, 1/2 of the run and its end — a quick stand-in for "
    "`glint eval`'s TSDF-mesh figure; without ground truth, depth–normal consistency and "
    "multi-view consistency (named so: they are not errors against truth)."
)


class MetricsLog:
    """Append-only ``metrics.jsonl``; truncatable to a checkpoint's iteration on resume."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def append(self, row: dict[str, Any]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a") as f:
            f.write(json.dumps(row, allow_nan=True) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def rows(self) -> list[dict[str, Any]]:
        return read_metrics(self.path)

    def truncate_after(self, iteration: int) -> None:
        """Drop rows past ``iteration`` (a resumed run re-records them); -1 clears."""
        if not self.path.exists():
            return
        keep = [r for r in self.rows() if iteration >= 0 and r.get("iteration", 0) <= iteration]
        tmp = self.path.with_suffix(".jsonl.tmp")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in keep))
        tmp.replace(self.path)


def read_metrics(path: str | Path) -> list[dict[str, Any]]:
    """The rows of a metrics log; a last line still being written is left out."""
    rows = []
    p = Path(path)
    if not p.exists():
        return rows
    lines = [x.strip() for x in p.read_text().splitlines()]
    lines = [x for x in lines if x]
    for k, line in enumerate(lines):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            if k == len(lines) - 1:  # a reader caught the run mid-append
                break
            raise
    return rows


def _fmt(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


# Geometry columns, first present wins for the plot: (row key, label, digits).
GEOMETRY_SERIES = (
    ("cd_x100", "Chamfer distance ×10² (surface points vs GT)", 3),
    ("normal_error_deg", "normal error vs GT (°)", 2),
    ("depth_normal_consistency_deg", "depth–normal inconsistency (°, no GT)", 2),
)


def geometry_series(rows: list[dict[str, Any]]) -> tuple[str, str] | None:
    """The geometry measure a run recorded (key, label): error when it had ground
    truth, consistency otherwise; None for runs from before geometry was recorded."""
    for key, label, _ in GEOMETRY_SERIES:
        if any(r.get(key) is not None for r in rows):
            return key, label
    return None


def metrics_table(rows: list[dict[str, Any]]) -> str:
    cols = [
        (key, label.split(" (")[0] if key != "cd_x100" else "CD ×10²", digits)
        for key, label, digits in GEOMETRY_SERIES
        if any(r.get(key) is not None for r in rows)
    ]
    if any(r.get("depth_abs_error") is not None for r in rows):
        at = 1 if cols and cols[0][0] == "cd_x100" else 0
        cols.insert(at, ("depth_abs_error", "depth error", 4))
        if any(r.get("depth_bias") is not None for r in rows):
            cols.insert(at + 1, ("depth_bias", "depth bias", 4))
    head = (
        "| iteration | train time (s) | eval time (s) | phase | Gaussians | loss "
        "| PSNR (dB) | SSIM |"
    )
    head += "".join(f" {label} |" for _, label, _ in cols)
    lines = [head, "|---:|---:|---:|---|---:|---:|---:|---:|" + "---:|" * len(cols)]
    for r in rows:
        loss = (r.get("loss") or {}).get("total")
        line = (
            f"| {r['iteration']} | {_fmt(r.get('wall_time'), 1)} "
            f"| {_fmt(r.get('eval_seconds'), 1)} "
            f"| {r.get('phase', '')} | {r.get('n_gaussians', '')} | {_fmt(loss, 4)} "
            f"| {_fmt(r.get('psnr'))} | {_fmt(r.get('ssim'), 4)} |"
        )
        line += "".join(f" {_fmt(r.get(key), digits)} |" for key, _, digits in cols)
        lines.append(line)
    return "\n".join(lines)


def _phase_changes(rows: list[dict[str, Any]]) -> list[float]:
    out, prev = [], None
    for r in rows:
        if prev is not None and r.get("phase") != prev:
            out.append(r["wall_time"])
        prev = r.get("phase")
    return out


def plot_error_vs_time(
    curves: dict[str, list[dict[str, Any]]],
    path: str | Path,
    title: str = "Held-out error vs training time",
) -> Path:
    """Image error (PSNR) and geometry error against training time, one panel each,
    one curve per run (label → metrics rows); phase changes marked as dashed lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    geo = None
    for rows in curves.values():
        geo = geo or geometry_series(rows)
    panels = 2 if geo else 1
    fig, axes = plt.subplots(1, panels, figsize=(6.2 * panels, 4.2), dpi=110, squeeze=False)
    ax_img = axes[0][0]
    ax_geo = axes[0][1] if geo else None
    for label, rows in curves.items():
        pts = [(r["wall_time"], r["psnr"]) for r in rows if r.get("psnr") is not None]
        if not pts:
            continue
        t, p = zip(*pts, strict=True)
        (line,) = ax_img.plot(t, p, marker="o", ms=3, label=label)
        color = line.get_color()
        if ax_geo is not None and geo is not None:
            g = [(r["wall_time"], r[geo[0]]) for r in rows if _finite(r.get(geo[0]))]
            if g:
                tg, vg = zip(*g, strict=True)
                ax_geo.plot(tg, vg, marker="s", ms=4, color=color, label=label)
        for x in _phase_changes(rows):
            for ax in (ax_img, ax_geo):
                if ax is not None:
                    ax.axvline(x, color=color, alpha=0.25, ls="--")
    ax_img.set_ylabel("held-out PSNR (dB)")
    ax_img.set_title("image error")
    if ax_geo is not None and geo is not None:
        ax_geo.set_ylabel(geo[1])
        ax_geo.set_title(
            "geometry error" if geo[0] != "depth_normal_consistency_deg" else "geometry consistency"
        )
        if geo[0] == "cd_x100":
            ax_geo.set_yscale("log")
    for ax in (ax_img, ax_geo):
        if ax is not None:
            ax.set_xlabel("training wall time (s, evaluation excluded)")
            ax.grid(alpha=0.3)
            if len(curves) > 1:
                ax.legend(fontsize=8)
    fig.suptitle(title + " (dashed: phase changes)")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and math.isfinite(v)


def write_report(run_dir: str | Path, extra_sections: list[str] | None = None) -> Path:
    """``report.md`` + ``error_vs_time.png`` from ``metrics.jsonl`` (and plan.json if present)."""
    run = Path(run_dir)
    rows = read_metrics(run / "metrics.jsonl")
    plot_error_vs_time({"run": rows}, run / "error_vs_time.png")
    parts = ["# Glint training report", ""]
    if rows:
        last = rows[-1]
        parts += [
            f"Final: iteration {last['iteration']}, "
            f"{_fmt(last.get('wall_time'), 1)} s of training "
            f"(+ {_fmt(last.get('eval_seconds'), 1)} s evaluating while training), "
            f"{last.get('n_gaussians')} Gaussians, held-out PSNR {_fmt(last.get('psnr'))} dB, "
            f"SSIM {_fmt(last.get('ssim'), 4)}"
            + (f", CD ×10² {_fmt(last.get('cd_x100'), 3)}" if _finite(last.get("cd_x100")) else "")
            + ".",
            "",
        ]
    parts += ["## Error against run time", "", "![error vs time](error_vs_time.png)", ""]
    parts += [ERROR_NOTE, "", metrics_table(rows), ""]
    plan = run / "plan.json"
    if plan.exists():
        data = json.loads(plan.read_text())
        parts += ["## Scene plan", "", "| part | decision | why |", "|---|---|---|"]
        for name, d in data.get("decisions", {}).items():
            parts.append(f"| {name} | {d.get('value')} | {d.get('reason', '')} |")
        parts.append("")
    for s in extra_sections or []:
        parts += [s, ""]
    out = run / "report.md"
    out.write_text("\n".join(parts))
    return out
