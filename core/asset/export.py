"""``glint export RUN --asset DIR``: a relightable asset from a trained run.

The run's TSDF mesh, simplified to a face budget and UV-unwrapped, with textures baked
from the model seen from its training views (core.asset.bake), Eq. 9's material mapped
to glTF's metallic-roughness (core.asset.material), a tangent-space normal map of the
model's normals against the mesh's, an ambient-occlusion map, and the learned env map
as an equirectangular HDR. Files (flat names, so they can sit in a run folder):

- ``asset.glb``: glTF 2.0, +Y up (Glint's +Z-up world turned by :data:`GLTF_FROM_WORLD`;
  Blender's importer turns it back, so the object lands in the capture's frame).
- ``asset_env.exr`` / ``asset_env.hdr``: linear radiance, 2:1, in Blender's world
  texture convention (+Z up; World > Environment Texture, default mapping, strength 1).
  three.js's equirect convention for the Y-up glb is the same map with no rotation
  (``environment.three_rotation_y`` = 0 in asset.json). Absent for a diffuse plan.
- ``asset.json``: what was made, how (options, mapping, what is lost), sizes, timings.
- ``asset_preview.png``: the three textures side by side.
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from core.asset.bake import bake_memory_bytes, bake_views, pick_views
from core.asset.glb import GLTF_FROM_WORLD, GlbMesh, GlbTextures, write_glb
from core.asset.material import fresnel_averaged, gltf_material, irradiance_sh
from core.asset.occlusion import ambient_occlusion, embree_available
from core.asset.texels import TexelSamples, fill_unknown, rasterize_atlas
from core.asset.uv_mesh import simplify_to_budget, unwrap
from core.errors import AssetError
from core.meshing.mesh import MeshCancelledError
from core.model.trained import TrainedModel
from core.render.envmap_io import save_equirect
from core.render.roughness import has_roughness
from core.scene.imageio import linear_to_srgb
from core.scene.views import View

__all__ = [
    "ASSET_FILES",
    "AssetCancelledError",
    "AssetError",
    "AssetOptions",
    "asset_run",
    "export_asset",
]

ASSET_FILES = ("asset.glb", "asset.json", "asset_env.exr", "asset_env.hdr", "asset_preview.png")
STEPS = ("simplify", "unwrap", "bake", "occlusion", "material", "write")
Progress = Callable[[str, int, int], None]

MAPPING_NOTE = (
    "per texel, base colour c and metallic m are the least-squares fit of "
    "|(1-m)·c·I - base|² + |(F - w_r/s)·I|², I = Irr(n)·AO the exported map's diffuse "
    "irradiance times occlusion, F = F0·(1-κ)+κ glTF's Schlick reflectance averaged over "
    "the baked views, F0 = 0.04·(1-m) + m·c (fit_rms_relative: what the fit missed); the "
    "map is the learned one times the exposure s that fits best (environment.exposure); "
    "roughness is Glint's ρ (glTF perceptual roughness, GGX α = ρ²). Lost: a mostly-mirror "
    "texel's base colour, Fresnel at angles the capture did not see, base brighter than the "
    "light explains (clipped), inter-reflections."
)


class AssetCancelledError(MeshCancelledError):
    """The export stopped because the caller asked it to (a cancelled job)."""


@dataclass
class AssetOptions:
    """What to make: face budget, texture size (power of two), views baked, AO."""

    faces: int = 100_000
    texture_size: int = 1024
    views: int = 32
    occlusion: bool = True
    env_height: int = 512

    def check(self) -> None:
        if int(self.faces) < 100:
            raise AssetError(f"faces: {self.faces} is too small; expected at least 100")
        t = int(self.texture_size)
        if t < 16 or t > 8192 or t & (t - 1):
            raise AssetError(
                f"texture_size: {self.texture_size} is not a power of two in 16..8192 "
                "(e.g. 512, 1024, 2048)"
            )
        if int(self.views) < 1:
            raise AssetError(f"views: {self.views}; expected at least 1 view to bake from")
        if int(self.env_height) < 8:
            raise AssetError(f"env_height: {self.env_height}; expected at least 8 rows")


def _png(image: np.ndarray, srgb: bool) -> bytes:
    """8-bit PNG bytes of a linear float image (H, W, 3) in [0, 1]."""
    from PIL import Image

    x = np.clip(image, 0.0, 1.0)
    if srgb:
        x = np.asarray(linear_to_srgb(x))
    buf = io.BytesIO()
    Image.fromarray(np.round(x * 255).astype(np.uint8)).save(buf, format="PNG", optimize=False)
    return buf.getvalue()


def _tangent_space(texels: TexelSamples, normals: np.ndarray) -> np.ndarray:
    """Model normals (M, 3, world) in each texel's (tangent, bitangent, normal) frame."""
    ts = np.stack(
        [
            np.sum(normals * texels.tangents, 1),
            np.sum(normals * texels.bitangents, 1),
            np.sum(normals * texels.normals, 1),
        ],
        1,
    )
    ts[:, 2] = np.maximum(ts[:, 2], 1e-3)  # never below the mesh's surface
    return ts / np.linalg.norm(ts, axis=1, keepdims=True)


def _preview(images: Sequence[np.ndarray], out: Path, tile: int = 256) -> None:
    from PIL import Image

    tiles = []
    for img in images:
        pic = Image.fromarray(np.round(np.clip(img, 0, 1) * 255).astype(np.uint8))
        tiles.append(pic.resize((tile, tile), Image.Resampling.BILINEAR))
    sheet = Image.new("RGB", (tile * len(tiles), tile), (255, 255, 255))
    for i, t in enumerate(tiles):
        sheet.paste(t, (i * tile, 0))
    sheet.save(out)


def export_asset(
    model: TrainedModel,
    views: Sequence[View],
    out: str | Path,
    mesh: trimesh.Trimesh,
    *,
    options: AssetOptions | None = None,
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> dict[str, Any]:
    """Make the asset of ``model`` from its TSDF ``mesh`` and training ``views`` into
    ``out``; returns what asset.json records. Bad input raises :class:`AssetError`."""
    opt = options or AssetOptions()
    opt.check()
    if not views:
        raise AssetError("no views to bake the textures from")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stop = should_stop or (lambda: False)
    times: dict[str, float] = {}
    clock = time.perf_counter()

    def step(name: str, done: int = 1, total: int = 1) -> None:
        nonlocal clock
        if stop():
            raise AssetCancelledError(f"asset export cancelled during {name}")
        if progress is not None:
            progress(name, done, total)
        if done == total:
            now = time.perf_counter()
            times[name] = round(times.get(name, 0.0) + now - clock, 3)
            clock = now

    source_faces = len(mesh.faces)
    simple = simplify_to_budget(mesh, int(opt.faces))
    step("simplify")
    uvm = unwrap(simple, int(opt.texture_size))
    texels = rasterize_atlas(uvm, int(opt.texture_size))
    if texels.count == 0:
        raise AssetError("the UV atlas covers no texel centre; raise texture_size")
    step("unwrap")
    baked_views = pick_views(views, int(opt.views))
    baked = bake_views(
        model, baked_views, texels, progress=lambda d, t: step("bake", d, t) if d < t else None
    )
    step("bake")
    occlusion = None
    occlusion_note = "off (options.occlusion = false)"
    if opt.occlusion:
        if embree_available():
            occlusion = ambient_occlusion(simple, texels.points, texels.normals)
            occlusion_note = "16 cosine-weighted rays per texel against the mesh (Embree)"
        else:
            occlusion_note = "skipped: embreex is not installed"
    step("occlusion")
    env_sh = None if model.envmap is None else irradiance_sh(model.envmap.texels())
    base, w_r = baked.base, baked.w_r
    if model.phase.fresnel and model.envmap is not None:  # it rises as glTF's does
        f0 = float(model.envmap.fresnel_f0.detach())
        base, w_r = fresnel_averaged(base, w_r, baked.roughness, baked.grazing, f0)
    color, metallic, residual, exposure = gltf_material(
        base, w_r, baked.normal, occlusion, env_sh, baked.grazing
    )
    known = texels.mask()
    seen_img = texels.mask(baked.seen)
    gutter = 2 * 8  # enough passes to cover the atlas padding and small unseen islands

    def texture(values: np.ndarray, fill: float) -> np.ndarray:
        img = texels.to_image(values, fill)
        return fill_unknown(img, seen_img, iterations=gutter + 48)

    base_img = texture(color, 0.0)
    rough_img = texture(baked.roughness[:, None], 0.5)[..., 0]
    metal_img = texture(metallic[:, None], 0.0)[..., 0]
    ao_img = (
        fill_unknown(texels.to_image(occlusion[:, None], 1.0), known, gutter)[..., 0]
        if occlusion is not None
        else np.ones_like(rough_img)
    )
    ts = _tangent_space(texels, baked.normal)
    normal_img = fill_unknown(texels.to_image(ts * 0.5 + 0.5), known, gutter)
    orm_img = np.stack([ao_img, rough_img, metal_img], -1)
    step("material")
    glb_mesh = GlbMesh(uvm.positions, uvm.normals, uvm.tangents, uvm.uvs, uvm.faces)
    textures = GlbTextures(
        base_color=_png(base_img, srgb=True),
        orm=_png(orm_img, srgb=False),
        normal=_png(normal_img, srgb=False),
        has_occlusion=occlusion is not None,
    )
    files = {"glb": "asset.glb"}
    glb_bytes = write_glb(out / "asset.glb", glb_mesh, textures)
    env: dict[str, Any] = {"present": False, "reason": "the scene plan has no env map (diffuse)"}
    for stale in ("asset_env.exr", "asset_env.hdr"):
        (out / stale).unlink(missing_ok=True)
    if model.envmap is not None:
        texels_env = model.envmap.texels().detach().float().cpu() * exposure
        for ext in ("exr", "hdr"):
            save_equirect(out / f"asset_env.{ext}", texels_env, int(opt.env_height))
            files[f"env_{ext}"] = f"asset_env.{ext}"
        env = {
            "present": True,
            "files": [files["env_exr"], files["env_hdr"]],
            "size": [2 * int(opt.env_height), int(opt.env_height)],
            "convention": "equirectangular, linear radiance, +Z up (Blender world texture); "
            "for the Y-up glb three.js reads it with no rotation",
            "three_rotation_y": 0.0,
            "exposure": exposure,
            "exposure_note": "the learned map times this factor (Eq. 9 fixes only w_r · E; "
            "this is the scale at which the glTF material reproduces the model best)",
            "blender": "World > Environment Texture with this file, default mapping, strength 1",
        }
    _preview([np.asarray(linear_to_srgb(base_img)), orm_img, normal_img], out / "asset_preview.png")
    files["preview"] = "asset_preview.png"
    step("write")
    seen = baked.seen
    info: dict[str, Any] = {
        "iteration": model.iteration,
        "files": files,
        "options": asdict(opt),
        "mesh": {
            "source_faces": int(source_faces),
            "faces": len(uvm.faces),
            "vertices": len(uvm.positions),
        },
        "orientation": {
            "gltf_from_world": GLTF_FROM_WORLD.tolist(),
            "note": "glTF (x, y, z) = world (x, z, -y): +Y up in the file; Blender's "
            "importer restores the capture's +Z-up frame",
        },
        "textures": {
            "size": int(opt.texture_size),
            "covered_texels": int(texels.count),
            "seen_fraction": float(seen.mean()) if len(seen) else 0.0,
            "views_baked": baked.views,
            "occlusion": occlusion_note,
            "normal_map": "tangent space, glTF convention (+Y = −v, up in the image)",
        },
        "material": {
            "mapping": MAPPING_NOTE,
            "roughness": "learned per Gaussian"
            if has_roughness(model.gaussians)
            else "none learned: 0 (the env map was read as a mirror)",
            "mean_metallic": float(metallic[seen].mean()) if seen.any() else 0.0,
            "fit_rms_relative": float(np.sqrt(residual[seen].mean())) if seen.any() else 0.0,
            "mean_roughness": float(baked.roughness[seen].mean()) if seen.any() else 0.0,
        },
        "environment": env,
        "size_bytes": {"glb": int(glb_bytes)},
        "bake_memory_bytes_estimate": bake_memory_bytes(
            texels.count, views[0].camera.height, views[0].camera.width
        ),
        "seconds": times,
    }
    for key in ("env_exr", "env_hdr"):
        if key in files:
            info["size_bytes"][key] = (out / files[key]).stat().st_size
    (out / "asset.json").write_text(json.dumps(info, indent=2))
    return info


def load_run_mesh(run_dir: Path, iteration: int) -> trimesh.Trimesh | None:
    """The run's mesh.ply when mesh.json says it is of ``iteration``, else None."""
    meta, ply = run_dir / "mesh.json", run_dir / "mesh.ply"
    if not (meta.is_file() and ply.is_file()):
        return None
    try:
        if int(json.loads(meta.read_text()).get("iteration", -1)) != int(iteration):
            return None
    except (OSError, ValueError, TypeError):
        return None
    mesh = trimesh.load(ply, force="mesh", process=False)
    return mesh if isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) else None


def asset_run(
    run_dir: str | Path,
    out: str | Path,
    scene_dir: str | Path | None = None,
    *,
    device: str | None = None,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    **options: Any,
) -> dict[str, Any]:
    """Asset of a run folder into ``out``: the checkpoint reopened with its scene, the
    run's mesh (extracted into ``out`` when the run has none of its last iteration);
    ``options`` are :class:`AssetOptions` fields; progress as ``stage`` events."""
    from core.meshing.mesh import mesh_model, stage_progress
    from core.model.run_folder import open_run

    unknown = set(options) - set(AssetOptions.__dataclass_fields__)
    if unknown:
        raise AssetError(f"unknown asset option(s): {', '.join(sorted(unknown))}")
    opt = AssetOptions(**options)
    opt.check()
    run = Path(run_dir)
    model, scene = open_run(run, scene_dir, device=device)
    mesh = load_run_mesh(run, model.iteration)
    if mesh is None:
        mesh, _ = mesh_model(
            model,
            scene.train,
            out,
            progress=stage_progress(on_event, len(scene.train)),
            should_stop=should_stop,
        )
    return export_asset(
        model,
        scene.train,
        out,
        mesh,
        options=opt,
        progress=asset_progress(on_event),
        should_stop=should_stop,
    )


def asset_progress(on_event: Callable[[dict[str, Any]], None] | None) -> Progress | None:
    """A ``progress`` callback that emits ``stage`` events named ``asset``."""
    if on_event is None:
        return None

    def progress(step: str, done: int, of: int) -> None:
        on_event(
            {
                "type": "stage",
                "name": "asset",
                "step": step,
                "done": done,
                "total": of,
                "overall_done": STEPS.index(step) + int(done >= of),
                "overall_total": len(STEPS),
            }
        )

    return progress
