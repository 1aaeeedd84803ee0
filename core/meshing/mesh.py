"""The mesh of a trained model: render its depth from the training views, fuse, extract.

Generic fusion and extraction live in ``core.meshing.tsdf``; this module feeds them
the depth the model itself uses (planar Eq. 8, or Eq. 5 in that ablation), one view
at a time (never every depth map at once), and writes mesh.ply (binary, vertex colours
and normals), mesh.glb, mesh.obj, mesh.json and a preview picture into a folder.

Colour: a shiny object's rendered radiance has the environment baked in (the
highlight of one view smeared over the surface by the others), so the default is
the *base* colour of Eq. 9, the material without the reflection; ``radiance`` keeps
the shaded colour.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
import trimesh

from core.errors import GlintError
from core.meshing.preview import render_mesh_preview
from core.meshing.tsdf import (
    DEFAULT_RESOLUTION,
    EMPTY_ALPHA,
    MASK_EMPTY,
    MASK_OBJECT,
    SURFACE_ALPHA,
    DepthFrame,
    TSDFVolume,
    extract_mesh,
    fuse_frames,
    keep_largest_components,
    mask_hull_distance,
    observation_weight,
)
from core.model.trained import TrainedModel
from core.render.depth_geometry import grazing_blend as grazing_blend_depth
from core.scene.imageio import linear_to_srgb
from core.scene.views import View

MESH_COLORS = ("base", "radiance")
MESH_FILES = ("mesh.ply", "mesh.obj", "mesh.glb")
PREVIEW_FILE = "mesh_preview.png"
BOUNDS_MIN_SIDE = 256  # views at least this large are fitted to the grid at ¼ resolution
# Eq. 8's depth counts fully where the surface faces the pixel within acos 0.6 (53°) and
# gives way linearly to Eq. 5's centre depth, wholly at acos 0.3 (73°). Why: on a held-out
# knot shot from above Eq. 8's depth error was 0.6× Eq. 5's at cos 0.6-0.8 and 1.5× it
# below cos 0.4, where such a capture sees the undersides (docs/benchmarks.md, 2026-11-30).
GRAZING_BLEND_COS = (0.3, 0.6)

Progress = Callable[[str, int, int], None]


class MeshCancelledError(GlintError):
    """Extraction stopped because the caller asked it to (nothing was written)."""


@torch.no_grad()
def model_depth_frame(
    model: TrainedModel,
    view: View,
    *,
    color: str | None = "base",
    scale: float = 1.0,
    weighted: bool = True,
    hull: bool = False,
    grazing_blend: bool = True,
) -> DepthFrame:
    """The depth the model uses and, unless ``color`` is None, the surface colour of one
    view (``base`` or ``radiance``, un-premultiplied), masked as fusion needs, with
    each pixel's fusion weight (incidence of the rendered normal, occlusion edges)
    unless ``weighted`` is False (a frame read only for its points: bounds, the narrow
    band, the run record's surface probe; ~50 ms a frame at 800² saved), and with
    ``hull`` its mask's hull distances (tsdf.mask_hull_distance) when it has a mask.
    ``grazing_blend``: a planar model's depth leans toward Eq. 5's at oblique pixels
    (:func:`core.render.depth_geometry.grazing_blend`, :data:`GRAZING_BLEND_COS`)."""
    camera = view.camera if scale == 1.0 else view.camera.scaled(scale)
    channels = {"base": ("base", "depth"), "radiance": ("final", "depth"), None: ("depth",)}
    if color not in channels:
        raise ValueError(f"unknown mesh colour {color!r}; expected one of {', '.join(MESH_COLORS)}")
    bg = model.background
    frame = model.render(camera, channels[color], background=bg)
    depth, valid = frame.depth()
    if grazing_blend and frame.planar_depth:
        gb = frame.gbuffer
        depth = grazing_blend_depth(
            depth, valid, gb.center_depth, gb.normal, camera, GRAZING_BLEND_COS
        )
    alpha = frame.gbuffer.alpha
    valid = valid & (alpha > SURFACE_ALPHA)
    if view.mask is not None:
        mask = view.mask.to(alpha.device, torch.float32)
        if mask.shape != alpha.shape:
            mask = F.interpolate(mask[None, None], size=tuple(alpha.shape), mode="area")[0, 0]
        valid = valid & (mask > MASK_OBJECT)
        empty = mask < MASK_EMPTY
        hull_dist = mask_hull_distance(empty) if hull else None
    else:
        empty = alpha < EMPTY_ALPHA
        hull_dist = None
    rgb = None
    a = alpha.clamp_min(1e-6)[..., None]
    if color == "base":  # G-buffer base colour is premultiplied by coverage
        rgb = (frame.gbuffer.base / a).clamp(0, 1)
    elif color == "radiance":  # remove the background the shading composited in
        fill = (1.0 - alpha)[..., None] * bg
        rgb = ((frame.image("final") - fill) / a).clamp(0, 1)
    weight = None
    if weighted:
        weight = observation_weight(depth.detach(), valid, frame.gbuffer.normal.detach(), camera)
    color_out = None if rgb is None else rgb.detach()
    return DepthFrame(camera, depth.detach(), valid, empty, color_out, weight, hull_dist)


def export_mesh(mesh: trimesh.Trimesh, out_dir: str | Path, stem: str = "mesh") -> list[Path]:
    """Write PLY (binary, vertex colours and normals), OBJ and GLB through trimesh."""
    from trimesh.exchange.ply import export_ply

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for ext in ("ply", "obj", "glb"):
        p = out / f"{stem}.{ext}"
        tmp = p.with_name(p.name + ".tmp")
        if ext == "ply":
            data = export_ply(mesh, encoding="binary", vertex_normal=len(mesh.faces) > 0)
        elif ext == "obj":
            data = _obj_bytes(mesh)
        else:
            data = mesh.export(file_type="glb")
        tmp.write_bytes(data)
        tmp.replace(p)
        paths.append(p)
    return paths


def _obj_bytes(mesh: trimesh.Trimesh) -> bytes:
    text = mesh.export(file_type="obj", include_color=True, include_normals=False)
    return text.encode() if isinstance(text, str) else text


def simplify_mesh(mesh: trimesh.Trimesh, vol: TSDFVolume, faces: int) -> trimesh.Trimesh:
    """Quadric decimation to about ``faces`` faces; colours re-read from the fused volume."""
    if len(mesh.faces) <= faces:
        return mesh
    out = mesh.simplify_quadric_decimation(face_count=int(faces))
    g = vol.grid
    ijk = (np.asarray(out.vertices) - np.asarray(g.origin)) / g.voxel
    colors = vol.vertex_colors(ijk)
    if colors is not None:
        srgb = np.asarray(linear_to_srgb(np.clip(colors, 0.0, 1.0)))
        out.visual.vertex_colors = np.concatenate(
            [np.round(srgb * 255), np.full((len(srgb), 1), 255)], 1
        ).astype(np.uint8)
    return out


def planned_hull(model: TrainedModel) -> bool:
    """Whether the run's plan bounds its meshes by the masks' hull (on where the masks
    agree with each other, core.training.mask_agreement); False for a run without that
    decision (older runs, checkpoints of other tools)."""
    return bool(model.plan is not None and model.plan.hull.value)


def mesh_model(
    model: TrainedModel,
    views: Sequence[View],
    out: str | Path,
    *,
    voxel: float | None = None,
    trunc: float | None = None,
    resolution: int = DEFAULT_RESOLUTION,
    carve: bool = True,
    hull: bool | None = None,
    keep_fraction: float = 0.1,
    color: str = "base",
    simplify: int | None = None,
    max_resolution: int | None = None,
    preview: bool = True,
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
    grazing_blend: bool = True,
) -> tuple[trimesh.Trimesh, dict[str, Any]]:
    """Mesh of a trained model seen from ``views`` (its training views): fuse, extract,
    clean, and write into ``out`` (the run folder), all files or none.

    ``progress(stage, done, total)`` follows the passes over the views (``bounds``,
    ``band``, ``integrate``) and the last steps (``extract``, ``write``);
    ``should_stop()`` is asked between views and raises :class:`MeshCancelledError`.
    ``hull``: bound the distance field by the masks' hull; None: as the run's plan says
    (:func:`planned_hull`). ``grazing_blend``: see :func:`model_depth_frame`.
    """
    hull = planned_hull(model) if hull is None else hull
    if model.center is None or model.radius is None:
        raise ValueError("the model has no scene box: open it with its scene (open_run)")
    if color not in MESH_COLORS:
        raise ValueError(f"unknown mesh colour {color!r}; expected one of {', '.join(MESH_COLORS)}")
    if not views:
        raise ValueError("no views to mesh from")
    out = Path(out)
    views = list(views)
    stop = should_stop or (lambda: False)
    model = model.frozen()  # three passes over every view: the per-splat work once

    def report(stage: str, done: int, total: int) -> None:
        if stop():
            raise MeshCancelledError(f"mesh extraction cancelled during {stage}")
        if progress is not None:
            progress(stage, done, total)

    small = min(views[0].camera.height, views[0].camera.width) < BOUNDS_MIN_SIDE
    bounds_scale = 1.0 if small else 0.25
    t0 = time.perf_counter()
    frame = partial(model_depth_frame, model, grazing_blend=grazing_blend)
    vol, params = fuse_frames(
        len(views),
        lambda i: frame(views[i], color=color, hull=hull),
        bounds_frame_at=lambda i: frame(views[i], color=None, scale=bounds_scale, weighted=False),
        band_frame_at=lambda i: frame(views[i], color=None, weighted=False),
        center=model.center,
        radius=float(model.radius),
        voxel=voxel,
        trunc=trunc,
        resolution=resolution,
        carve=carve,
        hull=hull,
        device=model.device,
        progress=report,
        max_resolution=max_resolution,
    )
    t1 = time.perf_counter()
    report("extract", 0, 1)
    mesh, comp = keep_largest_components(extract_mesh(vol), keep_fraction)
    if simplify is not None:
        mesh = simplify_mesh(mesh, vol, simplify)
    del vol
    t2 = time.perf_counter()
    report("write", 0, 1)
    info: dict[str, Any] = {
        "files": list(MESH_FILES) + ([PREVIEW_FILE] if preview else []),
        "iteration": model.iteration,
        "color": color,
        "grazing_blend_cos": list(GRAZING_BLEND_COS) if grazing_blend else None,
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "watertight": bool(mesh.is_watertight) if len(mesh.faces) else False,
        "components": comp,
        "simplified_to": simplify,
        "fusion": params.__dict__,
        "seconds": {"fuse": round(t1 - t0, 3), "extract": round(t2 - t1, 3)},
    }
    staging = out / ".mesh-staging.tmp"
    shutil.rmtree(staging, ignore_errors=True)
    try:
        export_mesh(mesh, staging)
        if preview:
            render_mesh_preview(mesh, staging / PREVIEW_FILE)
        info["seconds"]["write"] = round(time.perf_counter() - t2, 3)
        (staging / "mesh.json").write_text(json.dumps(info, indent=2))
        for p in sorted(staging.iterdir()):  # mesh.json last: it marks a complete mesh
            if p.name != "mesh.json":
                p.replace(out / p.name)
        (staging / "mesh.json").replace(out / "mesh.json")
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return mesh, info


def mesh_section(info: dict[str, Any]) -> str:
    """The report's "Mesh" section: figures and the preview picture."""
    comp = info.get("components") or {}
    sec = info.get("seconds") or {}
    fu = info.get("fusion") or {}
    total = sum(v for v in sec.values() if isinstance(v, (int, float)))
    lines = [
        "## Mesh",
        "",
        f"TSDF fusion of the rendered depth of {fu.get('frames', '?')} training views "
        f"(voxel {fu.get('voxel', float('nan')):.4g}, grid "
        f"{'×'.join(str(x) for x in fu.get('shape', []))}), marching cubes, largest "
        f"components kept: {info['vertices']:,} vertices, {info['faces']:,} faces, "
        f"{comp.get('kept', 0)}/{comp.get('components', 0)} components kept, "
        f"{total:.1f} s. Vertex colour: {info.get('color', 'radiance')}"
        + (" (the material without reflections)." if info.get("color") == "base" else "."),
        "",
        "Files: " + ", ".join(f"`{f}`" for f in MESH_FILES) + ".",
    ]
    if PREVIEW_FILE in info.get("files", []):
        lines += ["", f"![mesh: normals and colour, two viewpoints]({PREVIEW_FILE})"]
    return "\n".join(lines)


STEPS = ("bounds", "band", "integrate", "extract", "write")


def stage_progress(
    on_event: Callable[[dict[str, Any]], None] | None, n_views: int
) -> Progress | None:
    """A ``progress`` callback that emits ``stage`` events for the mesh phase, with the
    position over the whole extraction (three passes over the views, then two steps)."""
    if on_event is None:
        return None
    total = 3 * n_views + 2

    def progress(step: str, done: int, of: int) -> None:
        i = STEPS.index(step)
        overall = i * n_views + done if i < 3 else 3 * n_views + (i - 3)
        on_event(
            {
                "type": "stage",
                "name": "mesh",
                "step": step,
                "done": done,
                "total": of,
                "overall_done": overall,
                "overall_total": total,
            }
        )

    return progress


def mesh_run(
    run_dir: str | Path,
    out: str | Path,
    scene_dir: str | Path | None = None,
    *,
    device: str | None = None,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    **kwargs: Any,
) -> tuple[trimesh.Trimesh, dict[str, Any]]:
    """Mesh a finished run folder into ``out`` (another folder, or the run's own):
    the checkpoint reopened on ``device`` with its scene; ``kwargs`` go to
    :func:`mesh_model`; progress as ``stage`` events through ``on_event``."""
    from core.model.run_folder import open_run

    model, scene = open_run(run_dir, scene_dir, device=device)
    views = scene.train
    return mesh_model(model, views, out, progress=stage_progress(on_event, len(views)), **kwargs)
