"""Asset bench: export a run's relightable asset and check that it renders like the run.

For each run: ``glint export`` at the given options into RUN/asset (reused when made
with the same options; time per step, file sizes), then on the held-out views the asset
read back from its .glb and shaded as glTF prescribes (core.asset.reference_render: no
Fresnel, Glint's env lookup) against the photos and against Glint's own renders, with
and without the normal map; a picture per run
(photo | Glint | asset | asset without normal map)::

    .venv/bin/python -m bench.asset_check --run runs/teapot [--run ...] \
        [--faces 100000] [--texture-size 1024] [--views 32] [--out docs/bench/issue39_asset]

Blender's render of the same asset is ``bench.blender_asset`` (docs/blender_bench.md).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from datetime import date
from pathlib import Path
from typing import Any

import numpy as np
import torch

from core.asset.export import asset_run
from core.asset.reference_render import read_glb, render_asset
from core.evaluation.evaluate import test_views
from core.evaluation.metrics import psnr, ssim_srgb
from core.model.run_folder import open_run
from core.scene.imageio import write_image


def existing_asset(asset_dir: Path, options: dict[str, Any], iteration: int) -> dict | None:
    """asset.json of an asset made with these options from this iteration, else None."""
    try:
        info = json.loads((asset_dir / "asset.json").read_text())
    except (OSError, ValueError):
        return None
    same = all(info["options"].get(k) == v for k, v in options.items())
    return info if same and info.get("iteration") == iteration else None


def check_run(run: Path, out: Path, options: dict[str, Any], views: int | None) -> dict[str, Any]:
    """Export (or reuse RUN/asset made with the same options) and score one run."""
    asset_dir = run / "asset"
    model, scene = open_run(run)
    info = existing_asset(asset_dir, options, model.iteration)
    if info is None:
        t0 = time.perf_counter()
        info = asset_run(run, asset_dir, **options)
        seconds = time.perf_counter() - t0
    else:
        seconds = sum(info["seconds"].values())
    asset = read_glb(asset_dir / "asset.glb")
    env = None if model.envmap is None else model.envmap.texels()
    bg = model.background.cpu()
    rows = []
    pictures = []
    for i, v in enumerate(test_views(scene)[:views]):
        glint = model.render(v.camera, ("final",)).image("final").cpu().float()
        photo = v.composited(bg).float()
        mine, _ = render_asset(asset, env, v.camera, bg.numpy())
        flat, _ = render_asset(asset, env, v.camera, bg.numpy(), use_normal_map=False)
        mine_t, flat_t = torch.from_numpy(mine).float(), torch.from_numpy(flat).float()
        rows.append(
            {
                "view": v.name,
                "glint_vs_photo": psnr(glint, photo),
                "asset_vs_photo": psnr(mine_t, photo),
                "asset_vs_glint": psnr(mine_t, glint),
                "asset_no_normal_map_vs_photo": psnr(flat_t, photo),
                "ssim_glint": ssim_srgb(glint, photo),
                "ssim_asset": ssim_srgb(mine_t, photo),
            }
        )
        if i < 3:
            pictures.append(torch.cat([photo, glint, mine_t, flat_t], 1))
    write_image(out / f"{run.name}_views.png", torch.cat(pictures, 0))
    keys = [k for k in rows[0] if k != "view"]
    return {
        "run": str(run),
        "export_seconds": round(seconds, 1),
        "steps": info["seconds"],
        "faces": info["mesh"]["faces"],
        "source_faces": info["mesh"]["source_faces"],
        "size_mb": round(sum(info["size_bytes"].values()) / 1e6, 2),
        "sizes": info["size_bytes"],
        "mean_metallic": info["material"]["mean_metallic"],
        "mean_roughness": info["material"]["mean_roughness"],
        "seen_fraction": info["textures"]["seen_fraction"],
        "views": len(rows),
        **{k: float(np.mean([r[k] for r in rows])) for k in keys},
        "per_view": rows,
    }


def table(results: list[dict[str, Any]]) -> str:
    head = (
        "| run | faces | MB | export s | PSNR Glint | PSNR asset | asset vs Glint | "
        "asset, no normal map | SSIM Glint | SSIM asset | metallic | ρ |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = [
        f"| {Path(r['run']).name} | {r['faces']} | {r['size_mb']} | {r['export_seconds']} | "
        f"{r['glint_vs_photo']:.2f} | {r['asset_vs_photo']:.2f} | {r['asset_vs_glint']:.2f} | "
        f"{r['asset_no_normal_map_vs_photo']:.2f} | {r['ssim_glint']:.4f} | "
        f"{r['ssim_asset']:.4f} | {r['mean_metallic']:.2f} | {r['mean_roughness']:.2f} |"
        for r in results
    ]
    return head + "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", action="append", required=True, help="run folder (repeatable)")
    p.add_argument("--faces", type=int, default=100_000)
    p.add_argument("--texture-size", type=int, default=1024)
    p.add_argument("--views", type=int, default=32, help="training views baked")
    p.add_argument("--test-views", type=int, default=None, help="held-out views scored")
    p.add_argument("--out", default="docs/bench/issue39_asset")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    opts = {"faces": args.faces, "texture_size": args.texture_size, "views": args.views}
    results = [check_run(Path(r), out, opts, args.test_views) for r in args.run]
    cmd = (
        "python -m bench.asset_check "
        + " ".join(f"--run {r}" for r in args.run)
        + f" --faces {args.faces} --texture-size {args.texture_size} --views {args.views}"
    )
    md = (
        f"# Asset check ({date.today()}, {platform.machine()}, {platform.processor() or 'cpu'})\n\n"
        f"`{cmd}`\n\nPSNR in dB over the held-out views (sRGB, composited on the run's "
        "background). 'asset' = the .glb read back and shaded as glTF prescribes without "
        "Fresnel, under the learned map (core.asset.reference_render).\n\n" + table(results)
    )
    (out / "asset_check.md").write_text(md)
    (out / "asset_check.json").write_text(json.dumps(results, indent=2))
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
