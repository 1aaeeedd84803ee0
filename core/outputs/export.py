"""What a finished (or checkpointed) run leaves behind for users.

point_cloud.ply (3DGS layout), the env map (EXR cross + lat-long + PNG preview),
renders of test views (final, base, specular, normal, depth, w_r, alpha), geometry
error against ground truth where the scene ships it, and report.md with the
error-vs-time plot.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from core.model.channels import CHANNELS
from core.model.trained import TrainedModel
from core.outputs.ply import save_ply
from core.outputs.report import write_report
from core.render.envmap_io import save_envmap
from core.scene.imageio import write_image
from core.scene.views import View


def export_sections(model: TrainedModel, geo: dict[str, Any] | None) -> list[str]:
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
    if model.skipped_steps:
        sections.append(f"Skipped {model.skipped_steps} steps with non-finite loss or gradients.")
    return sections


@torch.no_grad()
def export_run(
    model: TrainedModel,
    out: str | Path,
    render_views: Sequence[View],
    *,
    geometry: dict[str, Any] | None = None,
    sections: Sequence[str] = (),
) -> dict[str, Any]:
    """Write every artifact of the run into ``out``; returns a summary.

    ``render_views``: the views whose channels are written to ``renders/``;
    ``geometry``: the error against ground-truth maps, when the caller measured it;
    ``sections``: more report sections (the mesh's).
    """
    out = Path(out)
    save_ply(model.gaussians.detach(), out / "point_cloud.ply")
    files: dict[str, Any] = {"ply": "point_cloud.ply"}
    if model.envmap is not None:
        paths = save_envmap(model.envmap.texels().detach().cpu(), out)
        files["envmap"] = {k: Path(p).name for k, p in paths.items()}
    render_dir = out / "renders"
    for v in render_views:
        stem = (v.name or "view").replace("/", "_")
        frame = model.render(v.camera, CHANNELS)
        for ch, img in frame.images(CHANNELS).items():
            write_image(render_dir / f"{stem}_{ch}.png", img)
    files["renders"] = sorted(p.name for p in render_dir.glob("*.png"))
    if geometry is not None:
        (out / "geometry.json").write_text(json.dumps(geometry, indent=2))
    write_report(out, [*export_sections(model, geometry), *sections])
    files["report"] = "report.md"
    summary: dict[str, Any] = {"files": files, "geometry": geometry, "iteration": model.iteration}
    if model.center is not None and model.radius is not None:
        summary["scene_box"] = {
            "center": [float(v) for v in model.center],
            "radius": float(model.radius),
        }
    (out / "outputs.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary
