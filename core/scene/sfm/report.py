"""The registration report: what SfM recovered, what it left out, what it cost.

Written beside the scene as ``sfm_report.json`` (for programs: the service stores
it as an artifact) and ``sfm_report.txt`` (for people), and carried by
:class:`~core.scene.sfm.errors.SfmError` when SfM fails.
"""

from __future__ import annotations

import json
import resource
import sys
from pathlib import Path
from typing import Any

REPORT_JSON = "sfm_report.json"
REPORT_TEXT = "sfm_report.txt"


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / (1024 * 1024) if sys.platform == "darwin" else r / 1024  # bytes vs KiB


def list_names(names: list[str], limit: int = 20) -> str:
    """``a, b, c`` — at most ``limit`` names, then how many more."""
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def report_text(r: dict[str, Any]) -> str:
    """The report as a few readable lines."""
    lines = [
        f"registered {r['registered']} of {r['images']} images "
        f"({100 * r['registered'] / max(1, r['images']):.1f} %)",
    ]
    if r.get("unregistered"):
        lines.append(f"not registered: {list_names(r['unregistered'])}")
    if r.get("rescued"):
        lines.append(f"registered in the second pass (weaker evidence): {list_names(r['rescued'])}")
    if len(r.get("models", [])) > 1:
        lines.append(
            f"the first mapping pass found {len(r['models'])} separate models (images each: "
            f"{r['models']}); the largest was kept and continued"
        )
    m = r.get("matching", {})
    lines.append(
        f"matching: {m.get('strategy')} ({m.get('pairs')} pairs tried, "
        f"{m.get('verified_pairs')} verified), mapper: {r.get('mapper')}, feature masks: "
        f"{'on (object excluded)' if r.get('feature_masks') else 'off'}"
    )
    if r.get("mean_reprojection_error_px") is not None:
        lines.append(
            f"mean reprojection error {r['mean_reprojection_error_px']:.3f} px, "
            f"{r.get('points3D', 0)} 3D points"
            + (
                f" ({r['background_points_dropped']} background points dropped)"
                if r.get("background_points_dropped")
                else ""
            )
        )
    for c in r.get("cameras", []):
        p = c["params"]
        lines.append(
            f"camera {c['id']}: {c['width']}x{c['height']} fx {p[0]:.2f} fy {p[1]:.2f} "
            f"cx {p[2]:.2f} cy {p[3]:.2f} (undistorted pinhole)"
        )
    lines += [f"warning: {w}" for w in r.get("warnings", [])]
    s = r.get("seconds", {})
    parts = ", ".join(f"{k} {v:.1f} s" for k, v in s.items() if k != "total")
    rss = r["peak_rss_mb"]
    lines.append(f"time {s.get('total', 0):.1f} s ({parts}); process peak memory {rss:.0f} MB")
    return "\n".join(lines) + "\n"


def write_report(folder: Path, r: dict[str, Any]) -> None:
    """``sfm_report.json`` and ``sfm_report.txt`` in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / REPORT_JSON).write_text(json.dumps(r, indent=2) + "\n")
    (folder / REPORT_TEXT).write_text(report_text(r))
