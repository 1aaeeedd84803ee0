"""The mesh of a trained model: render its depth from the training views, fuse, extract.

Generic fusion and extraction live in ``core.meshing.tsdf``; this module feeds them
the depth the model itself uses (planar Eq. 8, or Eq. 5 in that ablation) and writes
mesh.ply/.obj/.glb and mesh.json into the run folder.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import trimesh

from core.meshing.tsdf import (
    DEFAULT_RESOLUTION,
    EMPTY_ALPHA,
    MASK_EMPTY,
    MASK_OBJECT,
    SURFACE_ALPHA,
    DepthFrame,
    extract_mesh,
    fuse_depth_frames,
    keep_largest_components,
)
from core.model.trained import TrainedModel
from core.scene.views import View


@torch.no_grad()
def model_depth_frames(model: TrainedModel, views: Sequence[View]) -> list[DepthFrame]:
    """Render the depth the trained model uses and the shaded colour of each view,
    masked as fusion needs."""
    bg = model.background
    frames = []
    for v in views:
        frame = model.render(v.camera, ("final", "depth"), background=bg)
        depth, valid = frame.depth()
        alpha = frame.gbuffer.alpha
        valid = valid & (alpha > SURFACE_ALPHA)
        if v.mask is not None:
            mask = v.mask.to(alpha.device)
            valid = valid & (mask > MASK_OBJECT)
            empty = mask < MASK_EMPTY
        else:
            empty = alpha < EMPTY_ALPHA
        # un-premultiply: the colour of the surface itself, without the background
        fill = (1.0 - alpha)[..., None] * bg
        color = ((frame.image("final") - fill) / alpha.clamp_min(1e-6)[..., None]).clamp(0, 1)
        frames.append(DepthFrame(v.camera, depth.detach(), valid, empty, color.detach()))
    return frames


MESH_FILES = ("mesh.ply", "mesh.obj", "mesh.glb")


def export_mesh(mesh: trimesh.Trimesh, out_dir: str | Path, stem: str = "mesh") -> list[Path]:
    """Write PLY (binary, vertex colours), OBJ and GLB through trimesh."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for ext in ("ply", "obj", "glb"):
        p = out / f"{stem}.{ext}"
        tmp = p.with_name(p.name + ".tmp")
        tmp.write_bytes(mesh.export(file_type=ext) if ext != "obj" else _obj_bytes(mesh))
        tmp.replace(p)
        paths.append(p)
    return paths


def _obj_bytes(mesh: trimesh.Trimesh) -> bytes:
    text = mesh.export(file_type="obj", include_color=True, include_normals=False)
    return text.encode() if isinstance(text, str) else text


def mesh_model(
    model: TrainedModel,
    views: Sequence[View],
    out: str | Path,
    *,
    voxel: float | None = None,
    trunc: float | None = None,
    resolution: int = DEFAULT_RESOLUTION,
    carve: bool = True,
    keep_fraction: float = 0.1,
) -> tuple[trimesh.Trimesh, dict[str, Any]]:
    """Mesh of a trained model seen from ``views`` (its training views): fuse, extract,
    clean, and export into ``out`` (the run folder)."""
    if model.center is None or model.radius is None:
        raise ValueError("the model has no scene box: open it with its scene (open_run)")
    out = Path(out)
    t0 = time.perf_counter()
    frames = model_depth_frames(model, views)
    t1 = time.perf_counter()
    vol, params = fuse_depth_frames(
        frames,
        center=model.center,
        radius=float(model.radius),
        voxel=voxel,
        trunc=trunc,
        resolution=resolution,
        carve=carve,
        device=model.device,
    )
    t2 = time.perf_counter()
    raw = extract_mesh(vol)
    mesh, comp = keep_largest_components(raw, keep_fraction)
    t3 = time.perf_counter()
    export_mesh(mesh, out)
    info: dict[str, Any] = {
        "files": list(MESH_FILES),
        "iteration": model.iteration,
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "watertight": bool(mesh.is_watertight) if len(mesh.faces) else False,
        "components": comp,
        "fusion": params.__dict__,
        "seconds": {
            "render": round(t1 - t0, 3),
            "fuse": round(t2 - t1, 3),
            "extract": round(t3 - t2, 3),
        },
    }
    (out / "mesh.json").write_text(json.dumps(info, indent=2))
    return mesh, info
