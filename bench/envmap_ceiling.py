"""What the env-map score can reach at all (issue 36): the true map itself, stored as a cube map.

The env-map score (``core.evaluation.envmap_accuracy``) compares a run's learned cube map
with the scene's full-resolution ``envmap.exr`` over the directions the training views
reflect. Two things cap it before any learning happens:

- **resolution**: a cube map of face size R cannot hold detail finer than its texels.
  Scored here: the true map box-filtered into an R cube (``sharp``), for several R;
- **roughness**: a GGX surface of roughness α shows each view the map averaged over its
  lobe, so images of it pin the map only at the mip level the lobe spans
  (``core.render.envmap_mips.roughness_to_lod``, ρ = √α). Scored here: the true map
  read at that level (``blurred``), what a run learns if nothing deconvolves the lobe.

A learned map near ``blurred`` has taken from the images what a one-level lookup lets
through; between ``blurred`` and ``sharp`` lies what would need the lobe undone.

    python -m bench.envmap_ceiling ../shared/data/teapot_gold ../shared/data/fandisk_copper
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from core.config import TrainConfig
from core.evaluation.envmap_accuracy import (
    TrueEnvmap,
    compare_envmaps,
    load_true_envmap,
    reflected_directions,
)
from core.render.envmap import EnvMap, texel_directions
from core.render.envmap_mips import mip_sizes, roughness_to_lod, sample_cube_lod
from core.scene.formats import load_scene
from core.training.planner import plan_envmap_resolution

SUPERSAMPLE = 8  # true-map samples per texel side when box-filtering into a cube


def true_cube(truth: TrueEnvmap, resolution: int, supersample: int = SUPERSAMPLE) -> torch.Tensor:
    """(6, R, R, 3) texels: the true map averaged over each texel (``supersample``² taps)."""
    r, s = resolution, supersample
    d = texel_directions(r * s).reshape(-1, 3)
    return truth.sample(d).reshape(6, r, s, r, s, 3).mean(dim=(2, 4)).float()


def material_lod(roughness: float, resolution: int) -> float:
    """The mip level a roughness ρ reads in a cube of this face size."""
    rho = torch.tensor(float(roughness))
    return float(roughness_to_lod(rho, resolution, len(mip_sizes(resolution))))


def blurred_cube(texels: torch.Tensor, roughness: float) -> torch.Tensor:
    """The cube read at the LOD ``roughness`` gives, at every texel's own direction."""
    r = texels.shape[1]
    dirs = texel_directions(r).reshape(-1, 3)
    lod = torch.full((dirs.shape[0],), material_lod(roughness, r), dtype=texels.dtype)
    out = sample_cube_lod(texels, dirs, lod, compiled=False)
    return out.reshape(texels.shape)


def scene_ceiling(root: Path, resolutions: list[int]) -> dict[str, object]:
    """Scores of the true map as a cube at each resolution, sharp and blurred."""
    meta = json.loads((root / "meta.json").read_text())
    spec = meta.get("spec", {})
    alpha = float(spec.get("material", {}).get("alpha", 0.0))
    scene = load_scene(root)
    truth = load_true_envmap(root)
    if truth is None:
        raise SystemExit(f"{root}: no {root / 'envmap.exr'} to score against")
    dirs, _ = reflected_directions(scene.train, root)
    focals = [float(v.camera.intrinsics.fx) for v in scene.train]
    auto = int(plan_envmap_resolution(focals, TrainConfig()).value)  # what a run gets
    rows = []
    for r in sorted(set(resolutions) | {auto}):
        sharp = true_cube(truth, r)
        env = EnvMap(r)
        env.set_texels(sharp)
        s = compare_envmaps(env, truth, dirs)["psnr"]
        env.set_texels(blurred_cube(sharp, math.sqrt(alpha)))
        b = compare_envmaps(env, truth, dirs)["psnr"]
        lod = material_lod(math.sqrt(alpha), r)
        rows.append({"resolution": r, "auto": r == auto, "lod": lod, "sharp": s, "blurred": b})
    return {"scene": root.name, "ggx_alpha": alpha, "rows": rows}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("scenes", type=Path, nargs="+", help="scene folders with envmap.exr")
    ap.add_argument("--resolutions", type=int, nargs="+", default=[16, 32, 64, 128])
    args = ap.parse_args(argv)
    torch.set_grad_enabled(False)
    print("| scene | GGX α | cube face R | LOD of α | true map, sharp | true map at the LOD |")
    print("|---|---:|---:|---:|---:|---:|")
    for root in args.scenes:
        res = scene_ceiling(root, args.resolutions)
        for row in res["rows"]:  # type: ignore[union-attr]
            mark = " (auto)" if row["auto"] else ""
            print(
                f"| {res['scene']} | {res['ggx_alpha']:g} | {row['resolution']}{mark} | "
                f"{row['lod']:.2f} | {row['sharp']:.2f} | {row['blurred']:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
