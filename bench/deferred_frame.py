"""One deferred frame on the CPU, stage by stage: the viewer's case of issue 5.

    python -m bench.deferred_frame [--gaussians 100000] [--size 512] [--threads 2]

A viewer frame is the G-buffer pass (per-Gaussian channels, projection, binning,
compositing) followed by deferred shading (Eq. 9). Both scenes of the rasteriser
benchmarks are timed: the viewer benchmark's glossy sphere of flat discs with an env
map, and bench.raster's random blob (shaded with a constant grey env map). Compiled
and PyTorch shading, and SIMD and numba compositing, run side by side in the same
process; every round times every stage once (interleaved), so ratios and stage sums
hold on a machine whose speed drifts. Prints a Markdown table and one JSON line per
scene; peak RSS is the process's.

Roughness: the shading of a second G-buffer of the same view with a per-splat roughness
channel (ρ uniform in [0.05, 0.6), seeded: LODs across the env map's mip chain) is
timed next to the sharp one (``shade_compiled_rough_ms``, ``shade_pytorch_rough_ms``):
what a viewer frame of a model with roughness pays for the trilinear lookup.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections.abc import Callable

import torch

from bench.common import bench_camera, machine_line, peak_rss_mib, random_gaussians
from bench.viewer import sphere_model
from core.kernels.pool import kernel_threads
from core.kernels.threads import configure_cpu_threads
from core.render.envmap import EnvMap, texel_directions
from core.render.gbuffer import gbuffer_features, near_plane, render_gbuffer_tensors
from core.render.raster import PROJECTORS, bin_gaussians, cpu_simd
from core.render.raster.cpu import rasterize_cpu
from core.render.shading import deferred_shade
from core.scene.cameras import Camera, Intrinsics
from core.scene.synthetic import default_env


def _interleaved(stages: dict[str, Callable[[], object]], repeat: int) -> dict[str, list[float]]:
    """Wall ms of each stage, ``repeat`` rounds after one warm-up round; every round
    runs every stage once, so a machine whose speed drifts slows all stages alike."""
    out: dict[str, list[float]] = {k: [] for k in stages}
    for r in range(repeat + 1):
        for name, fn in stages.items():
            t0 = time.perf_counter()
            fn()
            if r:
                out[name].append((time.perf_counter() - t0) * 1000.0)
    return out


def _sphere_scene(n: int, size: int) -> dict:
    g = sphere_model(n)
    env = EnvMap(64)
    env.set_texels(default_env(texel_directions(64)))
    fy = 0.5 * size / math.tan(math.radians(50.0) / 2)
    intr = Intrinsics(fy, fy, size / 2, size / 2, size, size)
    cam = Camera.look_at([0, 0.4, 2.0], [0, 0, 0], [0, 1, 0], intr)
    return {
        "means": g.params["means"],
        "covariances": g.covariances.detach(),
        "opacities": g.opacities.detach(),
        "colors": g.colors(cam, 0).detach(),
        "normals": g.normals().detach(),
        "w_r": g.w_r.detach(),
        "camera": cam,
        "env": env.requires_grad_(False),
    }


def _blob_scene(n: int, size: int) -> dict:
    from core.render.raster import covariances_from

    means, quats, scales, opac, feats = random_gaussians(n, channels=8)
    env = EnvMap(64, init_value=0.5).requires_grad_(False)
    return {
        "means": means,
        "covariances": covariances_from(quats, scales),
        "opacities": opac,
        "colors": feats[:, :3].contiguous(),
        "normals": torch.nn.functional.normalize(feats[:, 3:6] - 0.5, dim=-1),
        "w_r": feats[:, 6].contiguous(),
        "camera": bench_camera(size),
        "env": env,
    }


def bench_scene(name: str, s: dict, size: int, repeat: int) -> dict:
    cam, env = s["camera"], s["env"]
    bg = torch.ones(3)
    n = s["means"].shape[0]
    g = torch.Generator().manual_seed(0)
    rough = 0.05 + 0.55 * torch.rand(n, generator=g, dtype=s["means"].dtype)
    with torch.no_grad():

        def gbuf(roughness=None):
            return render_gbuffer_tensors(
                s["means"], None, None, s["opacities"], s["colors"], s["normals"], s["w_r"],
                cam, covariances=s["covariances"], backend="cpu", antialiased=True,
                roughness=roughness,
            )[0]  # fmt: skip

        feats = gbuffer_features(s["means"], s["colors"], s["normals"], s["w_r"], cam)
        near = near_plane(feats[:, 8])
        project = PROJECTORS["cpu"]
        covs = s["covariances"]

        def proj_fn():
            return project(s["means"], None, None, cam, covariances=covs, near=near)

        proj = proj_fn()
        bins = bin_gaussians(proj.means2d, proj.depths, proj.radii, size, size)
        opac = s["opacities"] * proj.compensation
        gb = gbuf()
        gb_rough = gbuf(rough)
        stages: dict[str, Callable[[], object]] = {
            "features_ms": lambda: gbuffer_features(
                s["means"], s["colors"], s["normals"], s["w_r"], cam
            ),
            "projection_ms": proj_fn,
            "binning_ms": lambda: bin_gaussians(proj.means2d, proj.depths, proj.radii, size, size),
            "compositing_ms": lambda: rasterize_cpu(proj, opac, feats, bins, size, size),
            "compositing_numba_ms": lambda: rasterize_cpu(
                proj, opac, feats, bins, size, size, simd=False
            ),
            "gbuffer_ms": gbuf,
            "shade_compiled_ms": lambda: deferred_shade(gb, env, bg),
            "shade_pytorch_ms": lambda: deferred_shade(gb, env, bg, compiled=False),
            "shade_compiled_rough_ms": lambda: deferred_shade(gb_rough, env, bg),
            "shade_pytorch_rough_ms": lambda: deferred_shade(gb_rough, env, bg, compiled=False),
            "frame_ms": lambda: deferred_shade(gbuf(), env, bg),
        }
        samples = _interleaved(stages, repeat)
    row: dict[str, object] = {
        "scene": name,
        "gaussians": int(s["means"].shape[0]),
        "size": size,
        "tile_pairs": int(bins.gauss_ids.numel()),
        "coverage": round(float(gb.alpha.mean()), 3),
    }
    row.update({k: statistics.median(v) for k, v in samples.items()})
    # The best frame (min) is also given: on a machine whose speed drifts it is the
    # steadier figure; the medians of all stages come from the same rounds.
    row["frame_best_ms"] = min(samples["frame_ms"])
    row["fps"] = round(1000.0 / row["frame_ms"], 2)
    row["fps_best"] = round(1000.0 / row["frame_best_ms"], 2)
    row["shade_speedup"] = round(row["shade_pytorch_ms"] / row["shade_compiled_ms"], 1)
    row["shade_rough_speedup"] = round(
        row["shade_pytorch_rough_ms"] / row["shade_compiled_rough_ms"], 1
    )
    row["composite_speedup"] = round(row["compositing_numba_ms"] / row["compositing_ms"], 1)
    row["compositing_kernel"] = "simd" if cpu_simd.why_unavailable() is None else "numba"
    row["peak_rss_mib"] = round(peak_rss_mib(), 1)
    return {k: round(v, 2) if isinstance(v, float) else v for k, v in row.items()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--threads", type=int, default=None, help="kernel threads (default: all)")
    ap.add_argument("--repeat", type=int, default=9)
    args = ap.parse_args(argv)
    configure_cpu_threads(args.threads)
    n, size, rep = args.gaussians, args.size, args.repeat
    rows = [
        bench_scene("sphere (viewer)", _sphere_scene(n, size), size, rep),
        bench_scene("random blob", _blob_scene(n, size), size, rep),
    ]
    print(f"{machine_line()}, {kernel_threads()} kernel threads; medians of {args.repeat}\n")
    cols = [
        "scene", "tile_pairs", "features_ms", "projection_ms", "binning_ms", "compositing_ms",
        "compositing_numba_ms", "gbuffer_ms", "shade_compiled_ms", "shade_compiled_rough_ms",
        "shade_pytorch_ms", "shade_pytorch_rough_ms", "frame_ms", "fps", "frame_best_ms",
        "fps_best", "peak_rss_mib",
    ]  # fmt: skip
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(str(r[c]) for c in cols) + " |")
    for r in rows:
        print(json.dumps(r))


if __name__ == "__main__":
    main()
