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
    rows = []
    p = Path(path)
    if not p.exists():
        return rows
    for line in p.read_text().splitlines():
        line = line.strip()
        if line:
            rows.append(json.loads(line))
    return rows


def _fmt(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def metrics_table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| iteration | train time (s) | phase | Gaussians | loss | PSNR (dB) | SSIM |",
        "|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        loss = (r.get("loss") or {}).get("total")
        lines.append(
            f"| {r['iteration']} | {_fmt(r.get('wall_time'), 1)} | {r.get('phase', '')} "
            f"| {r.get('n_gaussians', '')} | {_fmt(loss, 4)} | {_fmt(r.get('psnr'))} "
            f"| {_fmt(r.get('ssim'), 4)} |"
        )
    return "\n".join(lines)


def plot_error_vs_time(
    curves: dict[str, list[dict[str, Any]]],
    path: str | Path,
    title: str = "Held-out error vs training time",
) -> Path:
    """One PSNR-vs-time curve per run (label → metrics rows); phase changes marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=110)
    for label, rows in curves.items():
        pts = [(r["wall_time"], r["psnr"]) for r in rows if r.get("psnr") is not None]
        if not pts:
            continue
        t, p = zip(*pts, strict=True)
        (line,) = ax.plot(t, p, marker="o", ms=3, label=label)
        prev = None
        for r in rows:
            if prev is not None and r.get("phase") != prev:
                ax.axvline(r["wall_time"], color=line.get_color(), alpha=0.25, ls="--")
            prev = r.get("phase")
    ax.set_xlabel("training wall time (s, evaluation excluded)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if len(curves) > 1:
        ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


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
            f"{_fmt(last.get('wall_time'), 1)} s of training, "
            f"{last.get('n_gaussians')} Gaussians, held-out PSNR {_fmt(last.get('psnr'))} dB, "
            f"SSIM {_fmt(last.get('ssim'), 4)}.",
            "",
        ]
    parts += ["## Error against run time", "", "![error vs time](error_vs_time.png)", ""]
    parts += [metrics_table(rows), ""]
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
