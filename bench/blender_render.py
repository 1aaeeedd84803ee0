"""Blender side of ``bench.blender_asset``: render a glTF asset under an equirect world.

Runs in the Blender venv (``bash scripts/blender_venv.sh`` makes ``.venv-blender``, PyPI
``bpy``), never in Glint's: it imports only bpy, numpy and the standard library.

    .venv-blender/bin/python bench/blender_render.py JOB.json

The job file (written by ``bench.blender_asset``)::

    {"glb": "asset.glb", "env": "asset_env.exr", "env_strength": 1.0,
     "samples": 64, "denoise": false, "threads": 2, "seed": 0,
     "glossy_bounces": 4, "max_bounces": 12, "out_dir": "renders/",
     "views": [{"name": "r_0", "c2w": [[...4x4...]], "width": 128, "height": 128,
                "fx": 177.8, "fy": 177.8, "cx": 64.0, "cy": 64.0}, ...]}

``c2w`` is camera-to-world in the OpenGL/Blender camera convention (the camera looks
down its -Z, +Y up in the image), which is exactly a Blender camera object's
``matrix_world``. Intrinsics are in pixels (pixel centres at +0.5, ``cy`` from the top).

Set-up: factory settings with an empty scene; ``import_scene.gltf`` (the importer turns
glTF's +Y up into Blender's +Z up: Blender (x, y, z) = glTF (x, -z, y)); the world is
one Environment Texture node (default mapping: equirectangular, centre column facing
+X, top row +Z) into a Background of strength ``env_strength``; Cycles on the CPU, box
pixel filter of 1 px (the dev scenes' photos are box-filtered), view transform
Standard, look None, exposure 0, gamma 1, transparent film. Each view is written as
``<name>.exr``: RGBA float32, linear scene radiance, **premultiplied** alpha (Blender's
EXR convention; composite as ``rgb + bg * (1 - a)``). ``result.json`` beside them
records the Blender version, timings per view and what the import brought in.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix


def reset_scene() -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def configure(scene: bpy.types.Scene, job: dict) -> None:
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.samples = int(job.get("samples", 64))
    cy.use_adaptive_sampling = bool(job.get("adaptive", False))
    cy.use_denoising = bool(job.get("denoise", False))
    cy.seed = int(job.get("seed", 0))
    cy.pixel_filter_type = "BOX"
    cy.filter_width = 1.0
    cy.max_bounces = int(job.get("max_bounces", 12))
    cy.glossy_bounces = int(job.get("glossy_bounces", 4))
    cy.diffuse_bounces = int(job.get("diffuse_bounces", 4))
    cy.transmission_bounces = int(job.get("transmission_bounces", 12))
    cy.transparent_max_bounces = int(job.get("transparent_bounces", 8))
    cy.sample_clamp_direct = 0.0
    cy.sample_clamp_indirect = 0.0  # no clamping: it would darken reflected highlights
    threads = int(job.get("threads", 0))
    scene.render.threads_mode = "FIXED" if threads > 0 else "AUTO"
    if threads > 0:
        scene.render.threads = threads
    scene.render.film_transparent = True
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    scene.display_settings.display_device = "sRGB"
    vs = scene.view_settings
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure = 0.0
    vs.gamma = 1.0
    vs.use_curve_mapping = False
    im = scene.render.image_settings
    im.file_format = "OPEN_EXR"
    im.color_mode = "RGBA"
    im.color_depth = "32"
    im.exr_codec = "ZIP"


def import_asset(glb: str) -> dict:
    before = set(bpy.data.objects)
    bpy.ops.import_scene.gltf(filepath=glb)
    objs = [o for o in bpy.data.objects if o not in before]
    meshes = [o for o in objs if o.type == "MESH"]
    if not meshes:
        raise SystemExit(f"{glb}: the import brought in no mesh")
    bpy.context.view_layer.update()
    corners = np.array(
        [o.matrix_world @ v.co for o in meshes for v in o.data.vertices], dtype=np.float64
    )
    mats = sorted({s.material.name for o in meshes for s in o.material_slots if s.material})
    return {
        "objects": [o.name for o in objs],
        "meshes": len(meshes),
        "vertices": int(sum(len(o.data.vertices) for o in meshes)),
        "faces": int(sum(len(o.data.polygons) for o in meshes)),
        "materials": mats,
        "bbox_min": corners.min(0).tolist(),
        "bbox_max": corners.max(0).tolist(),
    }


def make_world(scene: bpy.types.Scene, env: str, strength: float) -> None:
    world = bpy.data.worlds.new("env")
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    tex = nt.nodes.new("ShaderNodeTexEnvironment")
    tex.image = bpy.data.images.load(env, check_existing=False)
    tex.image.colorspace_settings.name = "Linear Rec.709"  # radiance, not colour data
    tex.projection = "EQUIRECTANGULAR"
    tex.interpolation = "Linear"
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = float(strength)
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    scene.world = world


def make_camera(scene: bpy.types.Scene) -> bpy.types.Object:
    cam = bpy.data.objects.new("bench_camera", bpy.data.cameras.new("bench_camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.data.type = "PERSP"
    cam.data.sensor_fit = "HORIZONTAL"
    cam.data.sensor_width = 36.0
    cam.data.clip_start = 0.01
    cam.data.clip_end = 1000.0
    return cam


def place_camera(scene: bpy.types.Scene, cam: bpy.types.Object, view: dict) -> None:
    """Camera pose and pinhole intrinsics of one view (square pixels)."""
    w, h = int(view["width"]), int(view["height"])
    fx, fy = float(view["fx"]), float(view["fy"])
    if abs(fx - fy) > 1e-3 * fx:
        raise SystemExit(f"view {view['name']}: fx != fy ({fx}, {fy}); square pixels only")
    scene.render.resolution_x, scene.render.resolution_y = w, h
    cam.matrix_world = Matrix(view["c2w"])
    # horizontal sensor fit: lens / sensor_width = fx / W; the shift is in units of W
    cam.data.lens = fx * cam.data.sensor_width / w
    cam.data.shift_x = (0.5 * w - float(view["cx"])) / w
    cam.data.shift_y = (float(view["cy"]) - 0.5 * h) / w


def main(job_path: str) -> None:
    job = json.loads(Path(job_path).read_text())
    out_dir = Path(job["out_dir"])
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene = reset_scene()
    configure(scene, job)
    imported = import_asset(str(job["glb"]))
    make_world(scene, str(job["env"]), float(job.get("env_strength", 1.0)))
    cam = make_camera(scene)
    setup_s = time.perf_counter() - t0
    views = []
    for view in job["views"]:
        place_camera(scene, cam, view)
        path = out_dir / f"{view['name']}.exr"
        scene.render.filepath = str(path)
        t = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        dt = time.perf_counter() - t
        fov = 2.0 * math.degrees(math.atan(0.5 * view["width"] / view["fx"]))
        views.append({"name": view["name"], "file": path.name, "seconds": dt, "fov_x_deg": fov})
        print(f"blender: {view['name']} {dt:.2f} s", flush=True)
    result = {
        "blender": bpy.app.version_string,
        "setup_seconds": setup_s,
        "import": imported,
        "views": views,
        "settings": {
            "engine": scene.render.engine,
            "device": scene.cycles.device,
            "samples": scene.cycles.samples,
            "adaptive_sampling": scene.cycles.use_adaptive_sampling,
            "denoise": scene.cycles.use_denoising,
            "pixel_filter": f"{scene.cycles.pixel_filter_type} {scene.cycles.filter_width} px",
            "max_bounces": scene.cycles.max_bounces,
            "glossy_bounces": scene.cycles.glossy_bounces,
            "threads": scene.render.threads,
            "view_transform": scene.view_settings.view_transform,
            "look": scene.view_settings.look,
            "film_transparent": scene.render.film_transparent,
            "env_strength": float(job.get("env_strength", 1.0)),
        },
    }
    (out_dir / "result.json").write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: blender_render.py JOB.json")
    main(sys.argv[1])
