"""Env map lookup throughput and deferred-shading time per frame; prints a Markdown table.

    python -m bench.bench_envmap [--device cpu|cuda] [--repeat 7]

Sampling: a 6×128×128×3 map looked up at 128² and 512² random directions, forward
only (no autograd) and forward + backward (gradients for texels and directions).
Shading: ``deferred_shade`` of a mirror-sphere G-buffer at 256² and 800², same two
modes. The padded mip chain every training step rebuilds (R = 32 and 128), forward +
backward, torch ops against the compiled pass (``envmap_pack_compiled``; CPU only).
Median of ``--repeat`` runs after a warm-up; torch's default thread count.
"""

from __future__ import annotations

import argparse
import dataclasses

import torch

from bench.common import machine_line, median_time
from core.render.envmap import EnvMap
from core.render.gbuffer import GBuffer
from core.render.shading import deferred_shade
from core.scene.cameras import Camera, Intrinsics


def sphere_gbuffer(size: int, device: str) -> GBuffer:
    """A unit mirror sphere filling most of a size² view (normals analytic, w_r = alpha)."""
    cam = Camera.look_at(
        [0.0, -3.0, 0.5], [0, 0, 0], [0, 0, 1], Intrinsics.from_fov_x(0.8, size, size)
    )
    o, d = cam.world_rays(torch.float64)
    b = d @ o
    disc = b * b - (o @ o - 1.0)
    hit = disc > 0
    t = -b - disc.clamp_min(0).sqrt()
    n_world = torch.where(hit[..., None], o + t[..., None] * d, torch.zeros_like(d))
    n_cam = (n_world @ cam.R.T).float().to(device)
    alpha = hit.float().to(device)
    z = torch.zeros(size, size, device=device)
    return GBuffer(
        base=0.1 * alpha[..., None].expand(size, size, 3).clone(),
        normal=n_cam,
        plane_dist=z,
        w_r=0.8 * alpha,
        alpha=alpha,
        camera=cam,
    )


def chain_rows(repeat: int) -> list[tuple[str, str, float, str]]:
    """The packed, padded mip chain forward + backward: torch ops, then compiled."""
    from core.render.envmap_mips import _packed_levels, cube_mip_chain
    from core.render.envmap_pack_compiled import packed_cube_levels

    rows = []
    for r in (32, 128):
        texels = torch.rand(6, r, r, 3, requires_grad=True)

        def torch_ops(texels=texels):
            _packed_levels(cube_mip_chain(texels))[0].sum().backward()

        def compiled(texels=texels):
            packed_cube_levels(texels, mips=True)[0].sum().backward()

        t_ref = median_time(torch_ops, warmup=3, repeat=repeat)
        t_new = median_time(compiled, warmup=3, repeat=repeat)
        rows.append((f"mip chain R={r}", "fwd+bwd, torch ops", t_ref * 1e3, ""))
        rows.append((f"mip chain R={r}", "fwd+bwd, compiled", t_new * 1e3, f"{t_ref / t_new:.2f}×"))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    dev = args.device
    sync = torch.cuda.synchronize if dev.startswith("cuda") else None
    env = EnvMap(resolution=128, channels=3).to(dev)
    with torch.no_grad():
        env.log_radiance.normal_()
    bg = torch.ones(3, device=dev)
    rows = []

    for side in (128, 512):
        n = side * side
        dirs = torch.randn(n, 3, device=dev)

        def fwd(dirs=dirs):
            with torch.no_grad():
                env.sample(dirs)

        def fwd_bwd(dirs=dirs):
            d = dirs.clone().requires_grad_(True)
            env.zero_grad(set_to_none=True)
            env.sample(d).sum().backward()

        for mode, fn in (("forward", fwd), ("forward+backward", fwd_bwd)):
            t = median_time(fn, warmup=2, repeat=args.repeat, sync=sync)
            rows.append(
                (f"sample {side}×{side} dirs", mode, t * 1e3, f"{n / t / 1e6:.2f} M dirs/s")
            )

    for size in (256, 800):
        gb = sphere_gbuffer(size, dev)

        def shade(gb=gb):
            with torch.no_grad():
                deferred_shade(gb, env, bg)

        def shade_bwd(gb=gb):
            normal = gb.normal.clone().requires_grad_(True)
            w_r = gb.w_r.clone().requires_grad_(True)
            g = dataclasses.replace(gb, normal=normal, w_r=w_r)
            env.zero_grad(set_to_none=True)
            deferred_shade(g, env, bg).final.sum().backward()

        for mode, fn in (("forward", shade), ("forward+backward", shade_bwd)):
            t = median_time(fn, warmup=2, repeat=args.repeat, sync=sync)
            rows.append((f"deferred_shade {size}×{size}", mode, t * 1e3, f"{1 / t:.1f} frames/s"))

    if not dev.startswith("cuda"):
        rows += chain_rows(args.repeat)

    print(f"Env map 6×128×128×3 on {dev}: {machine_line()}\n")
    print("| case | mode | median ms | throughput |")
    print("|---|---|---:|---:|")
    for case, mode, ms, thr in rows:
        print(f"| {case} | {mode} | {ms:.2f} | {thr} |")


if __name__ == "__main__":
    main()
