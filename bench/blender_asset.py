"""Does the relightable asset look like the photos in Blender? (issue 39, point 3)

Renders the asset of a trained run (``glint export RUN --asset DIR``: ``asset.glb`` +
``asset_env.exr``) in Blender's Cycles from every held-out view of its scene, renders
the same views with Glint itself, and scores both against the held-out photos::

    bash scripts/blender_venv.sh                 # once: .venv-blender with PyPI bpy 4.5
    python -m bench.blender_asset --run RUN --scene ../shared/data/sphere_mirror
    python -m bench.blender_asset --standin --scene ../shared/data/sphere_mirror

Acceptance (issue 39): PSNR(Blender vs photo) >= PSNR(Glint vs photo) - 3 dB.

How it works: this side (Glint's venv) writes a job file and runs
``bench/blender_render.py`` in the Blender venv as a subprocess (bpy is never imported
here, nor a dependency of Glint); that script renders linear RGBA EXRs with a
transparent film, and this side scores them.

Scoring, as ``core.evaluation`` does for Glint's own renders: every image is
composited over a **white** background in linear light (photos: sRGB PNG with straight
alpha, decoded to linear, ``rgb * a + (1 - a)``; Blender: premultiplied EXR,
``rgb + (1 - a)``; Glint: its ``final`` channel rendered with a white background), then
PSNR and SSIM (``core.evaluation.metrics.psnr``/``ssim_srgb``) on sRGB values clipped to
[0, 1]. Also the silhouette IoU (alpha > 0.5) of the Blender render against the photo:
a rotated or mirrored asset shows there first.

Conventions (checked by ``--standin``, see below):

- World frame: Glint's = the scene's (Blender convention, +Z up). ``asset.glb`` holds
  glTF (x, y, z) = world (x, z, -y); Blender's glTF importer maps glTF back with Blender
  (x, y, z) = glTF (x, -z, y), so the imported object sits in the world frame.
- Cameras: each held-out view's camera as Glint loaded it, converted back to an
  OpenGL/Blender camera-to-world (``Camera.to_opengl_c2w``: for NeRF-synthetic scenes
  exactly ``transform_matrix``) and set as the Blender camera's ``matrix_world``;
  horizontal sensor fit, ``lens = fx * sensor_width / W`` (= ``0.5 * W / tan(0.5 *
  camera_angle_x)`` pixels), principal point through ``shift_x = (W/2 - cx) / W`` and
  ``shift_y = (cy - H/2) / W`` (zero for the dev scenes), square pixels, the view's size.
- World: ``asset_env.exr`` as an Environment Texture with default mapping (centre
  column faces +X, column W/4 faces +Y, top row +Z: for direction d, u = 0.5 -
  atan2(d.y, d.x) / 2pi), strength 1. The dev scenes' ``envmap.exr`` follows the same
  convention, times ``meta.json:envmap.scale``.
- Cycles on the CPU, box pixel filter 1 px (the photos are box-filtered), no sample
  clamping, view transform Standard (the EXRs are linear anyway), transparent film.

``--standin`` renders, instead of an exported asset, the scene's true mesh
(``gt_mesh.ply``, turned to glTF's +Y up as above and exported with trimesh) with the
scene's true material as a glTF metallic-roughness material (conductors: metallic 1,
base colour = the metal's linear F0, roughness = sqrt(GGX alpha); constant-colour
plastics: metallic 0) under the scene's own ``envmap.exr`` at its exposure. On
``sphere_mirror`` it gives 47.6 dB against the photos (16 views at 64 spp, 44.6-50.3 dB
each; the same renders mirrored left-right: 14-21 dB), on the asymmetric ``teapot_gold``
39.0 dB with silhouette IoU 0.999: the camera, world-texture and glTF axis conventions
above are the ones the photos were made with.

Writes ``OUT/blender_bench.md``, ``OUT/blender_bench.json`` and, for the first
``--pictures`` views, ``OUT/<view>.png``: photo | Glint | Blender | |Blender - photo| x4
(the stand-in: photo | Blender | difference); Blender's EXRs, job file and log go to
``OUT/renders/`` (git-ignored under docs/bench/issue39_blender/).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import shlex
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
import torch

from core.errors import GlintError
from core.evaluation.metrics import psnr, ssim_srgb, to_display
from core.scene.imageio import write_image

ROOT = Path(__file__).resolve().parents[1]
BLENDER_VENV = ROOT / ".venv-blender"
RENDER_SCRIPT = Path(__file__).with_name("blender_render.py")
MAKE_VENV = "bash scripts/blender_venv.sh"
WHITE = torch.ones(3)
ACCEPT_DB = 3.0

# Linear-RGB reflectance at normal incidence (F0) of the dev scenes' metals, for the
# stand-in's glTF base colour (Real-Time Rendering, 4th ed., table 9.2).
CONDUCTOR_F0 = {
    "Ag": (0.972, 0.960, 0.915),
    "Au": (1.000, 0.766, 0.336),
    "Cu": (0.955, 0.638, 0.538),
    "Cr": (0.549, 0.556, 0.554),
    "Al": (0.913, 0.922, 0.924),
}


class BenchError(Exception):
    """A problem with the inputs that the message explains."""


# -- inputs ------------------------------------------------------------------------------


def blender_python(venv: Path) -> Path:
    py = venv / "bin" / "python"
    if not py.is_file():
        raise BenchError(
            f"no Blender venv at {venv} (Blender's bpy lives apart from Glint's venv); "
            f"create it with: {MAKE_VENV}"
        )
    return py


def ensure_asset(
    run: Path, scene_dir: Path, asset_dir: Path, device: str | None, **options: Any
) -> tuple[dict[str, Any], float | None]:
    """asset.json of ``asset_dir``, exporting the run's asset there first when missing;
    returns it and the export's wall time (None when it was there already)."""
    if (asset_dir / "asset.glb").is_file():
        meta_path = asset_dir / "asset.json"
        return (json.loads(meta_path.read_text()) if meta_path.is_file() else {}), None
    try:
        from core.asset.export import asset_run
    except ImportError as e:
        raise BenchError(
            f"{asset_dir / 'asset.glb'} is missing and this checkout cannot export one "
            f"(core.asset.export.asset_run: {e}); run `glint export {run} --asset "
            f"{asset_dir}` where it can, or pass --asset"
        ) from e
    print(f"exporting the asset of {run} into {asset_dir} ...", flush=True)
    t0 = time.perf_counter()
    info = asset_run(
        run, asset_dir, scene_dir=scene_dir, device=device, on_event=_print_event, **options
    )
    return info, time.perf_counter() - t0


def _print_event(event: dict[str, Any]) -> None:
    """One line per finished step of the export (its events come per item)."""
    if event.get("done") == event.get("total"):
        print(f"  {event.get('name')}: {event.get('step')} done", flush=True)


def env_file(asset_dir: Path) -> Path:
    for name in ("asset_env.exr", "asset_env.hdr"):
        if (asset_dir / name).is_file():
            return asset_dir / name
    raise BenchError(f"{asset_dir}: no asset_env.exr or asset_env.hdr (the asset's world)")


def pick_views(views: list, n: int | None) -> list:
    """All views, or ``n`` of them evenly spread over the list."""
    if n is None or n >= len(views):
        return list(views)
    idx = np.unique(np.round(np.linspace(0, len(views) - 1, max(n, 1))).astype(int))
    return [views[i] for i in idx]


def slug(name: str) -> str:
    """A view name ("test/r_0") as a file name ("test_r_0")."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "view"


def view_job(view: Any) -> dict[str, Any]:
    cam = view.camera
    i = cam.intrinsics
    return {
        "name": slug(view.name),
        "c2w": cam.to_opengl_c2w().double().tolist(),
        "width": int(i.width),
        "height": int(i.height),
        "fx": float(i.fx),
        "fy": float(i.fy),
        "cx": float(i.cx),
        "cy": float(i.cy),
    }


# -- Blender -----------------------------------------------------------------------------


def run_blender(py: Path, job: dict[str, Any], work: Path, timeout: float) -> dict[str, Any]:
    """Render ``job`` with bench/blender_render.py in the Blender venv; its result.json."""
    work.mkdir(parents=True, exist_ok=True)
    job_path = work / "job.json"
    job_path.write_text(json.dumps(job, indent=2))
    log = work / "blender.log"
    cmd = [str(py), str(RENDER_SCRIPT), str(job_path)]
    print(f"blender: {len(job['views'])} views, log in {log}", flush=True)
    with log.open("w") as fh:
        try:
            proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, timeout=timeout)
        except subprocess.TimeoutExpired as e:
            raise BenchError(f"Blender took over {timeout:.0f} s; see {log}") from e
    if proc.returncode != 0:
        tail = "\n".join(log.read_text(errors="replace").splitlines()[-15:])
        raise BenchError(f"Blender failed (exit {proc.returncode}); end of {log}:\n{tail}")
    return json.loads((Path(job["out_dir"]) / "result.json").read_text())


def read_exr(path: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """A Blender EXR as (premultiplied linear RGB (H, W, 3), alpha (H, W))."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise BenchError(f"{path}: cannot read the Blender render ({oiio.geterror()})")
    try:
        spec = inp.spec()
        px = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, "float"), np.float32)
    finally:
        inp.close()
    if px.ndim != 3 or px.shape[2] < 4:
        raise BenchError(f"{path}: expected RGBA, got shape {px.shape}")
    return torch.from_numpy(px[..., :3].copy()), torch.from_numpy(px[..., 3].copy())


# -- scoring -------------------------------------------------------------------------------


def scores(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None) -> dict[str, float]:
    """PSNR/SSIM as ``glint eval``, and the mean signed difference ``img - ref`` of the
    display (sRGB, clipped) values over the photo's object pixels (alpha > 0.5): a too
    dark or too bright asset."""
    inside = mask > 0.5 if mask is not None else torch.ones(img.shape[:2], dtype=torch.bool)
    diff = to_display(img) - to_display(ref)
    bias = float(diff[inside].mean()) if bool(inside.any()) else math.nan
    return {"psnr": psnr(img, ref), "ssim": ssim_srgb(img, ref), "bias": bias}


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a > 0.5, b > 0.5
    union = int((a | b).sum())
    return float(int((a & b).sum()) / union) if union else 1.0


def side_by_side(images: list[torch.Tensor], path: Path) -> None:
    """Linear (H, W, 3) images in a row (display values), |last two - first| x4 after."""
    disp = [to_display(x.float().cpu()) for x in images]
    disp.append(((disp[-1] - disp[0]).abs() * 4.0).clamp(0.0, 1.0))
    h = disp[0].shape[0]
    gap = torch.full((h, 4, 3), 0.5)
    row = torch.cat([t for x in disp for t in (x, gap)][:-1], dim=1)
    if h < 256:  # small dev views: twice the size, nearest
        row = row.repeat_interleave(2, 0).repeat_interleave(2, 1)
    write_image(path, row, encode_srgb=False)


def mean(rows: list[dict], key: str, sub: str | None = None) -> float:
    """Mean of ``row[key]`` (or ``row[key][sub]``) over the rows."""
    vals = [r[key] if sub is None else r[key][sub] for r in rows]
    return float(np.mean(vals)) if vals else math.nan


# -- the two modes -------------------------------------------------------------------------


def bench_run(args: argparse.Namespace, py: Path) -> dict[str, Any]:
    """Exported asset of a trained run vs Glint's own render vs the photos."""
    from core.model.run_folder import open_run

    run: Path = args.run
    if not (run / "checkpoint.pt").is_file():
        raise BenchError(f"{run}: no checkpoint.pt, not a trained run folder")
    torch.set_grad_enabled(False)
    model, scene = open_run(run, args.scene, device=args.device)
    views = pick_views(list(scene.test), args.views)
    if not views:
        raise BenchError(f"{args.scene}: the scene has no held-out (test) views to score")
    asset_dir: Path = args.asset or run / "asset"
    options = {"faces": args.faces, "texture_size": args.texture_size}
    options = {k: v for k, v in options.items() if v is not None}
    asset, export_s = ensure_asset(run, args.scene, asset_dir, args.device, **options)
    env = env_file(asset_dir)
    out: Path = args.out or default_out(args.scene)
    job = blender_job(args, asset_dir / "asset.glb", env, 1.0, views, out)
    result = run_blender(py, job, out / "renders", args.timeout)
    blender_s = {v["name"]: v["seconds"] for v in result["views"]}
    model.render(views[0].camera, ("final",), background=WHITE.to(model.device))  # warm-up
    rows = []
    for k, v in enumerate(views):
        photo = v.composited(WHITE)
        t0 = time.perf_counter()
        glint = model.render(v.camera, ("final",), background=WHITE.to(model.device))
        glint = glint.image("final").float().cpu()
        glint_s = time.perf_counter() - t0
        rgb, alpha = read_exr(out / "renders" / f"{job['views'][k]['name']}.exr")
        blender = rgb + (1.0 - alpha)[..., None]
        row = {
            "view": v.name,
            "blender_vs_photo": scores(blender, photo, v.mask),
            "glint_vs_photo": scores(glint, photo, v.mask),
            "blender_vs_glint": scores(blender, glint, v.mask),
            "silhouette_iou": iou(alpha, v.mask) if v.mask is not None else None,
            "blender_seconds": blender_s[job["views"][k]["name"]],
            "glint_seconds": glint_s,
        }
        rows.append(row)
        if k < args.pictures:
            side_by_side([photo, glint, blender], out / f"{slug(v.name)}.png")
    summary = summarise(rows, glint=True)
    return {
        "mode": "asset",
        "run": str(run),
        "scene": str(args.scene),
        "asset": str(asset_dir),
        "asset_exported_seconds": export_s,
        "asset_json": asset,
        "split": scene.meta.get("split"),
        "iteration": model.iteration,
        "glint_device": str(model.device),
        "blender": result,
        "summary": summary,
        "per_view": rows,
        "pictures": [slug(v.name) for v in views[: args.pictures]],
        "out": str(out),
    }


def bench_standin(args: argparse.Namespace, py: Path) -> dict[str, Any]:
    """The scene's true mesh and material in Blender vs the photos: the conventions."""
    from core.scene.formats import load_scene

    scene_dir: Path = args.scene
    meta = json.loads((scene_dir / "meta.json").read_text())
    scene = load_scene(scene_dir)
    views = pick_views(list(scene.test), args.views)
    if not views:
        raise BenchError(f"{scene_dir}: the scene has no held-out (test) views to score")
    out: Path = args.out or default_out(scene_dir, "standin")
    out.mkdir(parents=True, exist_ok=True)
    (out / "renders").mkdir(parents=True, exist_ok=True)
    glb, material = standin_glb(scene_dir, meta, out / "renders" / "standin.glb")
    env = scene_dir / "envmap.exr"
    strength = float(meta["envmap"]["scale"])
    job = blender_job(args, glb, env, strength, views, out)
    result = run_blender(py, job, out / "renders", args.timeout)
    blender_s = {v["name"]: v["seconds"] for v in result["views"]}
    rows = []
    for k, v in enumerate(views):
        photo = v.composited(WHITE)
        name = job["views"][k]["name"]
        rgb, alpha = read_exr(out / "renders" / f"{name}.exr")
        blender = rgb + (1.0 - alpha)[..., None]
        rows.append({
            "view": v.name,
            "blender_vs_photo": scores(blender, photo, v.mask),
            "mirrored_x_vs_photo": scores(torch.flip(blender, [1]), photo, v.mask),
            "silhouette_iou": iou(alpha, v.mask) if v.mask is not None else None,
            "blender_seconds": blender_s[name],
        })  # fmt: skip
        if k < args.pictures:
            side_by_side([photo, blender], out / f"{slug(v.name)}.png")
    return {
        "mode": "standin",
        "scene": str(scene_dir),
        "standin": {"glb": str(glb), "material": material, "env": str(env)},
        "env_strength": strength,
        "blender": result,
        "summary": summarise(rows, glint=False),
        "per_view": rows,
        "pictures": [slug(v.name) for v in views[: args.pictures]],
        "out": str(out),
    }


def standin_glb(scene_dir: Path, meta: dict, path: Path) -> tuple[Path, dict[str, Any]]:
    """gt_mesh.ply with the scene's material, as glTF (+Y up) the way an asset is."""
    import trimesh

    spec = meta.get("material", {}).get("spec", {})
    kind = spec.get("type", "")
    rough = math.sqrt(float(spec.get("alpha", 0.0)))  # Blender/glTF: GGX alpha = r^2
    if kind in ("conductor", "roughconductor") and spec.get("material") in CONDUCTOR_F0:
        base, metallic = CONDUCTOR_F0[spec["material"]], 1.0
    elif kind in ("plastic", "roughplastic") and isinstance(spec.get("diffuse_reflectance"), list):
        base, metallic = tuple(spec["diffuse_reflectance"]), 0.0
    else:
        raise BenchError(
            f"{scene_dir}: no stand-in for the material {spec} "
            "(metals and constant-colour plastics only)"
        )
    mesh = trimesh.load(scene_dir / "gt_mesh.ply", process=False, force="mesh")
    normals = np.asarray(mesh.vertex_normals, np.float64)
    to_gltf = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], np.float64)  # (x, z, -y)
    mesh = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices) @ to_gltf.T,
        faces=mesh.faces,
        vertex_normals=normals @ to_gltf.T,
        process=False,
    )
    mat = trimesh.visual.material.PBRMaterial(
        baseColorFactor=[*base, 1.0], metallicFactor=metallic, roughnessFactor=rough
    )
    mesh.visual = trimesh.visual.TextureVisuals(material=mat)
    mesh.export(path, file_type="glb", include_normals=True)
    material = {"base_color_linear": list(base), "metallic": metallic, "roughness": rough}
    return path, {"from": spec, **material}


def blender_job(
    args: argparse.Namespace, glb: Path, env: Path, strength: float, views: list, out: Path
) -> dict[str, Any]:
    return {
        "glb": str(glb.resolve()),
        "env": str(env.resolve()),
        "env_strength": strength,
        "samples": args.samples,
        "denoise": args.denoise,
        "threads": args.threads,
        "glossy_bounces": args.glossy_bounces,
        "seed": 0,
        "out_dir": str((out / "renders").resolve()),
        "views": [view_job(v) for v in views],
    }


def summarise(rows: list[dict], *, glint: bool) -> dict[str, Any]:
    s: dict[str, Any] = {"views": len(rows)}
    pairs = ["blender_vs_photo"] + (["glint_vs_photo", "blender_vs_glint"] if glint else [])
    pairs += [] if glint else ["mirrored_x_vs_photo"]
    for p in pairs:
        s[p] = {k: mean(rows, p, k) for k in ("psnr", "ssim", "bias")}
    ious = [r["silhouette_iou"] for r in rows if r["silhouette_iou"] is not None]
    s["silhouette_iou"] = float(np.mean(ious)) if ious else None
    s["blender_seconds_per_view"] = mean(rows, "blender_seconds")
    if glint:
        s["glint_seconds_per_view"] = mean(rows, "glint_seconds")
        gap = s["glint_vs_photo"]["psnr"] - s["blender_vs_photo"]["psnr"]
        s["psnr_gap_db"] = gap
        s["accepted"] = bool(gap <= ACCEPT_DB)
    return s


# -- report --------------------------------------------------------------------------------


def default_out(scene_dir: Path, suffix: str = "") -> Path:
    name = Path(scene_dir).resolve().name + (f"_{suffix}" if suffix else "")
    return ROOT / "docs" / "bench" / "issue39_blender" / name


def machine() -> str:
    import os

    return (
        f"{platform.machine()}, {os.cpu_count()} CPUs ({platform.processor() or 'cpu'}), "
        f"{platform.system()} {platform.release()}, Python {platform.python_version()}"
    )


def write_report(report: dict[str, Any], argv: list[str]) -> Path:
    out = Path(report["out"])
    out.mkdir(parents=True, exist_ok=True)
    report["command"] = "python -m bench.blender_asset " + shlex.join(argv)
    report["machine"] = machine()
    report["date"] = datetime.now().isoformat(timespec="seconds")
    (out / "blender_bench.json").write_text(json.dumps(report, indent=2, default=str))
    (out / "blender_bench.md").write_text(markdown(report))
    return out


def markdown(r: dict[str, Any]) -> str:
    s = r["summary"]
    b = r["blender"]
    st = b["settings"]
    glint = r["mode"] == "asset"
    lines = [f"# Blender render of the {'asset' if glint else 'stand-in'} vs the photos", ""]
    if glint:
        lines += [
            f"Run `{r['run']}` (iteration {r['iteration']}), asset `{r['asset']}`, "
            f"scene `{r['scene']}`, {s['views']} held-out views.",
        ]
    else:
        m = r["standin"]["material"]
        lines += [
            f"Scene `{r['scene']}`: its `gt_mesh.ply` as glTF with base colour "
            f"{tuple(round(c, 3) for c in m['base_color_linear'])}, metallic {m['metallic']}, "
            f"roughness {m['roughness']:.3f} (from {m['from']}), world = its `envmap.exr` x "
            f"{r['env_strength']}; {s['views']} held-out views.",
        ]
    lines += [
        "",
        "Everything composited over white in linear light; PSNR/SSIM on sRGB [0, 1] "
        "(as `glint eval`). IoU: silhouette (alpha > 0.5) of the Blender render vs the photo.",
        "",
    ]
    if glint:
        lines += [
            *pair_table(s, ("blender_vs_photo", "glint_vs_photo", "blender_vs_glint")),
            "",
            f"- PSNR gap Glint - Blender: **{s['psnr_gap_db']:+.2f} dB** (acceptance: <= "
            f"{ACCEPT_DB:g} dB): **{'pass' if s['accepted'] else 'FAIL'}**",
            f"- silhouette IoU {s['silhouette_iou']:.4f}" if s["silhouette_iou"] else "",
            f"- time per view: Blender {s['blender_seconds_per_view']:.2f} s "
            f"(Cycles, {st['samples']} spp, {st['threads']} threads), Glint "
            f"{s['glint_seconds_per_view']:.3f} s ({r['glint_device']})",
        ]
        if r.get("asset_exported_seconds"):
            lines.append(f"- asset exported by this bench in {r['asset_exported_seconds']:.1f} s")
        lines += [
            "",
            "| view | Blender vs photo | Glint vs photo | Blender vs Glint | IoU | Blender s |",
            "|---|---|---|---|---|---|",
        ]
        for row in r["per_view"]:
            cells = [
                f"{row[p]['psnr']:.2f} / {row[p]['ssim']:.3f}"
                for p in ("blender_vs_photo", "glint_vs_photo", "blender_vs_glint")
            ]
            cells.append(f"{row['silhouette_iou']:.3f}" if row["silhouette_iou"] else "-")
            cells.append(f"{row['blender_seconds']:.2f}")
            lines.append(f"| {row['view']} | {' | '.join(cells)} |")
        pics = "photo, Glint, Blender, |Blender - photo| x4"
    else:
        lines += [
            *pair_table(s, ("blender_vs_photo", "mirrored_x_vs_photo")),
            "",
            f"- silhouette IoU {s['silhouette_iou']:.4f}" if s["silhouette_iou"] else "",
            f"- time per view: Blender {s['blender_seconds_per_view']:.2f} s "
            f"(Cycles, {st['samples']} spp, {st['threads']} threads)",
            "",
            "| view | PSNR (dB) | SSIM | mirrored PSNR | IoU |",
            "|---|---|---|---|---|",
        ]
        for row in r["per_view"]:
            bp = row["blender_vs_photo"]
            lines.append(
                f"| {row['view']} | {bp['psnr']:.2f} | {bp['ssim']:.4f} | "
                f"{row['mirrored_x_vs_photo']['psnr']:.2f} | {row['silhouette_iou']:.4f} |"
            )
        pics = "photo, Blender, |Blender - photo| x4"
    lines += [
        "",
        f"Pictures, left to right: {pics}.",
        "",
        *(f"![{name}]({name}.png)" for name in r["pictures"]),
        "",
        f"Blender {b['blender']}: {st['engine']} on {st['device']}, {st['samples']} samples, "
        f"adaptive sampling {st['adaptive_sampling']}, denoise {st['denoise']}, pixel filter "
        f"{st['pixel_filter']}, bounces {st['max_bounces']} (glossy {st['glossy_bounces']}), "
        f"view transform {st['view_transform']}, look {st['look']}, transparent film, "
        f"world strength {st['env_strength']:g}; import: {b['import']['faces']} faces, "
        f"{b['import']['vertices']} vertices, bbox {fmt_vec(b['import']['bbox_min'])} .. "
        f"{fmt_vec(b['import']['bbox_max'])}.",
        "",
        f"Command: `{r['command']}`  ",
        f"Machine: {r['machine']}  ",
        f"Date: {r['date']}",
        "",
    ]
    return "\n".join(lines)


def pair_table(s: dict[str, Any], pairs: tuple[str, ...]) -> list[str]:
    """Mean PSNR, SSIM and signed difference (A - B) of each pair, one row each."""
    rows = ["| pair | PSNR (dB) | SSIM | mean A - B on the object (sRGB) |", "|---|---|---|---|"]
    for p in pairs:
        name = p.replace("_vs_", " vs ").replace("_", " ")
        rows.append(f"| {name} | {s[p]['psnr']:.2f} | {s[p]['ssim']:.4f} | {s[p]['bias']:+.4f} |")
    return rows


def fmt_vec(v: list[float]) -> str:
    return "(" + ", ".join(f"{x:.3f}" for x in v) + ")"


# -- command line --------------------------------------------------------------------------


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m bench.blender_asset",
        description=__doc__.split("\n\n")[0],
        epilog=f"Needs the Blender venv: {MAKE_VENV}",
    )
    ap.add_argument("--run", type=Path, help="trained run folder (glint train ... --out RUN)")
    ap.add_argument("--scene", type=Path, required=True, help="scene folder with test views")
    ap.add_argument(
        "--asset", type=Path, help="asset folder (default RUN/asset, exported there if missing)"
    )
    ap.add_argument(
        "--standin",
        action="store_true",
        help="no run: render the scene's gt_mesh.ply with its true material and envmap.exr "
        "(checks the camera, world and glTF axis conventions against the photos)",
    )
    ap.add_argument("--faces", type=int, help="face budget when the asset is exported here")
    ap.add_argument("--texture-size", type=int, help="texture size when exported here")
    ap.add_argument("--views", type=int, help="score N test views, evenly spread (default all)")
    ap.add_argument("--pictures", type=int, default=4, help="side-by-side PNGs (default 4)")
    ap.add_argument("--samples", type=int, default=64, help="Cycles samples per pixel")
    ap.add_argument("--denoise", action="store_true", help="Cycles denoiser on (default off)")
    ap.add_argument("--threads", type=int, default=2, help="Cycles CPU threads (0: all)")
    ap.add_argument("--glossy-bounces", type=int, default=4)
    ap.add_argument("--device", help="Glint's render device (default: the run's or CPU)")
    ap.add_argument("--out", type=Path, help="default docs/bench/issue39_blender/<scene>/")
    ap.add_argument("--blender-venv", type=Path, default=BLENDER_VENV)
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds for Blender")
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser().parse_args(argv)
    try:
        if not (args.scene / "transforms_test.json").is_file() and not args.scene.is_dir():
            raise BenchError(f"{args.scene}: no such scene folder")
        py = blender_python(args.blender_venv)
        if args.standin:
            report = bench_standin(args, py)
        else:
            if args.run is None:
                raise BenchError("--run RUN is required (or --standin)")
            report = bench_run(args, py)
    except (BenchError, GlintError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out = write_report(report, argv)
    print((out / "blender_bench.md").read_text())
    print(f"wrote {out}/blender_bench.md, blender_bench.json and pictures")
    return 0


if __name__ == "__main__":
    sys.exit(main())
