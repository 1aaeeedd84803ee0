"""A PGSR-DR training step and a deferred render against a plain 3DGS step.

    python -m bench.train_step --device cuda --size 800 --n 300000     # issue 5's GPU case
    python -m bench.train_step --device cpu --size 64 --n 4000 --threads 2

All cases run in one process on the same Gaussians, side by side:

* ``plain render`` / ``plain step``: the 3DGS baseline, a 3-channel render of SH
  colours (degree 3), then L1 + D-SSIM, backward and Adam. On CUDA it is a bare
  ``gsplat.rasterization`` call with gsplat's own SH; elsewhere the same rasteriser
  backend as ours with 3 channels.
* ``G-buffer``: our 9-channel pass (base, normal, plane distance, w_r, centre z).
* ``deferred render``: G-buffer + env-map shading, no gradients (the viewer's frame).
* ``full step``: the multi-view phase, the heaviest, composited in the default
  ``splat_order`` (plane order on CPU, centre order on CUDA; ``--compare-order`` times
  another order beside it): G-buffer, deferred shading, RGB,
  scale, single-view and multi-view losses (a second, depth-only G-buffer for the
  neighbour, at the pixels the multi-view loss reads), backward and Adam; and the
  same step without L_multi, as the scene plan runs a capture whose every view is
  masked (``--compare-fresnel`` times that one without Fresnel beside it).

Targets (issue 5, on an H100, where ``auto`` is centre order): full step ≤ 1.3 × plain
step; deferred ≥ 200 FPS. On CPU the full step composites in plane order, which gathers
and sorts each pixel's splats, so it does not compare with that target.
Peak memory is CUDA's allocator peak per case, or the process's peak RSS on CPU.

Timing is interleaved: each of ``--repeat`` rounds runs every case once, so a machine
whose speed drifts minute to minute (a shared VM moved a sequential run's ratio by
±20%) slows the plain and the full step alike. The ratios are medians of the rounds'
own ratios, printed with their range; a range that straddles a target means the run
cannot tell (repeat more).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from collections.abc import Callable

import torch

from bench.common import bench_camera, interleaved_times, machine_line, peak_rss_mib
from core.config import TrainConfig
from core.render.envmap import EnvMap
from core.render.gaussians import Gaussians
from core.render.gbuffer import geometry_depth, render_gbuffer
from core.render.raster import rasterize, resolve_backend
from core.render.roughness import add_roughness_state
from core.render.shading import deferred_shade
from core.scene.cameras import Camera
from core.training.losses import (
    multi_view_footprint,
    multi_view_loss,
    multi_view_pixels,
    rgb_loss,
    scale_loss,
    single_view_loss,
)
from core.training.optim import make_optimizers

MASKED_STEP = "full step, masked capture (plan: no L_multi)"


def neighbour_camera(cam: Camera, degrees: float = 10.0) -> Camera:
    """The same camera orbited ``degrees`` about the world z axis (a multi-view pair)."""
    a = math.radians(degrees)
    rot = torch.eye(4, dtype=torch.float64)
    rot[:2, :2] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return Camera(cam.intrinsics, cam.world_to_cam @ rot, "neighbour")


def make_gaussians(n: int, device: torch.device, seed: int = 0) -> Gaussians:
    """n flat, SH-3 Gaussians in the ball the bench camera looks at."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(n, 3, generator=g) * 0.45
    cols = torch.rand(n, 3, generator=g)
    gs = Gaussians.from_points(pts, cols, sh_degree=3, radius=1.0)
    with torch.no_grad():
        gs.params["sh_rest"].normal_(0.0, 0.05, generator=g)
        gs.params["opacity_logits"].uniform_(-1.0, 2.0, generator=g)
        gs.params["log_scales"][:, 2] -= 3.0
    return gs.to(device)


def plain_render(gs: Gaussians, cam: Camera, backend: str) -> torch.Tensor:
    """The 3DGS baseline image (H, W, 3) over a white background."""
    if backend == "cuda":
        from core.render.raster.cuda import camera_matrices, gsplat_rasterization

        viewmats, Ks = camera_matrices(cam, torch.float32, gs.device)
        sh = torch.cat([gs.params["sh_dc"], gs.params["sh_rest"]], dim=1)
        img, alpha, _ = gsplat_rasterization()(
            gs.params["means"], gs.unit_quats, gs.scales, gs.opacities, sh, viewmats, Ks,
            cam.width, cam.height, sh_degree=3, packed=True,
        )  # fmt: skip
        return img[0] + (1.0 - alpha[0])
    r = rasterize(
        gs.params["means"], gs.unit_quats, gs.scales, gs.opacities, gs.colors(cam, 3), cam,
        backend=backend,
    )  # fmt: skip
    return r.features + (1.0 - r.alpha)[..., None]


def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    if args.split_threads:
        from core.kernels.threads import configure_cpu_threads

        configure_cpu_threads(args.threads or None)
    elif args.threads:
        torch.set_num_threads(args.threads)
    backend = resolve_backend(args.backend, device)
    cfg = TrainConfig(device=args.device, backend=backend)
    aa = cfg.antialiased  # render the way training does
    cam, cam_nb = bench_camera(args.size), neighbour_camera(bench_camera(args.size))
    gs = make_gaussians(args.n, device)
    if not args.no_roughness:  # the full model reads the env map's mips at each splat's ρ
        add_roughness_state(gs, cfg.init_roughness)
    env = EnvMap(args.envmap).to(device)
    opts = make_optimizers(gs, cfg, 1.0)
    opts["envmap"] = torch.optim.Adam(env.parameters(), lr=cfg.lr.envmap)
    target = torch.rand(args.size, args.size, 3, generator=torch.Generator().manual_seed(1))
    target = target.to(device)
    white = torch.ones(3, device=device)
    gen = torch.Generator().manual_seed(2)

    def adam() -> None:
        for o in opts.values():
            o.step()
            o.zero_grad(set_to_none=True)

    def plain_fwd() -> None:
        with torch.no_grad():
            plain_render(gs, cam, backend)

    def plain_step() -> None:
        rgb_loss(plain_render(gs, cam, backend), target, 0.8).backward()
        adam()

    def gbuffer_fwd() -> None:
        with torch.no_grad():
            render_gbuffer(gs, cam, sh_degree=3, backend=backend, antialiased=aa)

    def gbuffer_fwd_bwd() -> None:
        gb, _ = render_gbuffer(gs, cam, sh_degree=3, backend=backend, antialiased=aa)
        (gb.base.sum() + gb.normal.sum() + gb.plane_dist.sum() + gb.alpha.sum()).backward()
        adam()

    def deferred() -> None:
        with torch.no_grad():
            gb, _ = render_gbuffer(gs, cam, sh_degree=3, backend=backend, antialiased=aa)
            deferred_shade(gb, env, white, fresnel=cfg.ablation.fresnel)

    def full_step(
        multi_view: bool = True, order: str = cfg.splat_order, fresnel: bool = cfg.ablation.fresnel
    ) -> None:
        gb, _ = render_gbuffer(
            gs, cam, sh_degree=3, backend=backend, antialiased=aa, splat_order=order
        )
        shade = deferred_shade(gb, env, white, fresnel=fresnel)
        loss = rgb_loss(shade.final, target, 0.8) + 100.0 * scale_loss(gs.scales)
        depth, valid = geometry_depth(gb, True)
        loss = loss + 0.2 * single_view_loss(gb.normal, depth, valid, cam)
        if multi_view:  # the neighbour is read for its depth, where the loss reads it,
            # as training does
            pixels = multi_view_pixels(valid, cfg.loss.multiview_pixels, gen)
            footprint = multi_view_footprint(depth.detach(), pixels, cam, cam_nb)
            gb_n, _ = render_gbuffer(
                gs, cam_nb, sh_degree=0, backend=backend, antialiased=aa, geometry_only=True,
                splat_order=order, pixels=footprint,
            )  # fmt: skip
            d_n, v_n = geometry_depth(gb_n, True)
            mv, _ = multi_view_loss(depth, valid, cam, d_n, v_n, cam_nb, pixels=pixels)
            loss = loss + 0.1 * mv
        loss.backward()
        adam()

    cases: list[tuple[str, Callable[[], None]]] = [
        ("plain render", plain_fwd),
        ("plain step", plain_step),
        ("G-buffer forward", gbuffer_fwd),
        ("G-buffer forward+backward", gbuffer_fwd_bwd),
        ("deferred render", deferred),
        ("full step (multi-view phase)", full_step),
        # the plan drops L_multi where every view is masked (core/training/planner.py)
        (MASKED_STEP, lambda: full_step(multi_view=False)),
    ]
    order_case = f"full step (multi-view phase), splat_order {args.compare_order}"
    if args.compare_order:  # TrainConfig.splat_order's cost, timed beside the default
        cases.append((order_case, lambda: full_step(order=args.compare_order)))
    fresnel_case = f"{MASKED_STEP}, without Fresnel"
    compare_fresnel = bool(getattr(args, "compare_fresnel", False))
    if compare_fresnel:  # Ablation.fresnel's cost, timed beside the default
        cases.append((fresnel_case, lambda: full_step(multi_view=False, fresnel=False)))
    times = time_rounds(cases, args.warmup, args.repeat, device)
    rows = []
    for name, _ in cases:
        ms = statistics.median(times[name]["ms"])
        rows.append({"case": name, "ms": ms, "fps": 1e3 / ms, "peak_mib": times[name]["peak_mib"]})
    plain = times["plain step"]["ms"]
    full, masked = (times[k]["ms"] for k in ("full step (multi-view phase)", MASKED_STEP))
    by = {r["case"]: r for r in rows}
    extra = {}
    if args.compare_order:
        extra = {
            "compare_order": args.compare_order,
            "order_over_full_range": paired_ratio(times[order_case]["ms"], full),
        }
    if compare_fresnel:
        extra["masked_over_no_fresnel_range"] = paired_ratio(masked, times[fresnel_case]["ms"])
    return {
        **extra,
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "backend": backend,
        "size": args.size,
        "n": args.n,
        "roughness": not args.no_roughness,
        "rounds": args.repeat,
        "rows": rows,
        "full_over_plain_step": paired_ratio(full, plain)["median"],
        "masked_full_over_plain_step": paired_ratio(masked, plain)["median"],
        "full_over_plain_range": paired_ratio(full, plain),
        "masked_full_over_plain_range": paired_ratio(masked, plain),
        "gbuffer_over_plain_render": paired_ratio(
            times["G-buffer forward"]["ms"], times["plain render"]["ms"]
        )["median"],
        "deferred_fps": by["deferred render"]["fps"],
    }


def time_rounds(
    cases: list[tuple[str, Callable[[], None]]], warmup: int, rounds: int, device: torch.device
) -> dict[str, dict]:
    """Each case's ms per round (every round runs every case once, in order) and its
    peak memory (taken during its own warm-up runs, before the rounds mix the cases)."""
    cuda = device.type == "cuda"
    peaks: dict[str, float] = {}
    for name, fn in cases:
        if cuda:
            torch.cuda.reset_peak_memory_stats(device)
        for _ in range(max(warmup, 1)):  # at least once: the memory peak needs a run
            fn()
        if cuda:
            torch.cuda.synchronize(device)
        peaks[name] = torch.cuda.max_memory_allocated(device) / 2**20 if cuda else peak_rss_mib()
    sync = torch.cuda.synchronize if cuda else None
    times = interleaved_times(dict(cases), rounds, sync)
    return {name: {"ms": times[name], "peak_mib": peaks[name]} for name, _ in cases}


def paired_ratio(num: list[float], den: list[float]) -> dict[str, float]:
    """min / median / max over rounds of num[i] / den[i] (both timed in round i)."""
    r = sorted(a / b for a, b in zip(num, den, strict=True))
    return {"min": r[0], "median": statistics.median(r), "max": r[-1]}


def format_table(res: dict) -> str:
    mem = "peak CUDA MiB" if res["device"].startswith("cuda") else "peak RSS MiB (process)"
    lines = [
        f"Machine: {machine_line()}; device {res['device_name']}, backend `{res['backend']}`, "
        f"{res['size']}², {res['n']:,} Gaussians",
        "",
        f"| case | median ms | per second | {mem} |",
        "|---|---:|---:|---:|",
    ]
    for r in res["rows"]:
        lines.append(f"| {r['case']} | {r['ms']:.2f} | {r['fps']:.1f} | {r['peak_mib']:.0f} |")
    fr, mr = res["full_over_plain_range"], res["masked_full_over_plain_range"]
    lines += [
        "",
        f"Medians over {res['rounds']} interleaved rounds; ratios are the median of the "
        "rounds' own ratios [min–max].",
        "",
        f"full step / plain step: {res['full_over_plain_step']:.2f}× "
        f"[{fr['min']:.2f}–{fr['max']:.2f}] (target ≤ 1.3× on an H100, in centre order), "
        f"on a masked capture {res['masked_full_over_plain_step']:.2f}× "
        f"[{mr['min']:.2f}–{mr['max']:.2f}]; "
        f"G-buffer / plain render: {res['gbuffer_over_plain_render']:.2f}×; "
        f"deferred render: {res['deferred_fps']:.0f} FPS (target ≥ 200 on an H100)",
    ]
    if "compare_order" in res:
        o = res["order_over_full_range"]
        lines += [
            "",
            f"full step with splat_order {res['compare_order']} / full step: "
            f"{o['median']:.2f}× [{o['min']:.2f}–{o['max']:.2f}]",
        ]
    if "masked_over_no_fresnel_range" in res:
        o = res["masked_over_no_fresnel_range"]
        lines += [
            "",
            f"masked full step / the same without Fresnel: {o['median']:.3f}× "
            f"[{o['min']:.3f}–{o['max']:.3f}]",
        ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--size", type=int, default=800)
    ap.add_argument("--n", type=int, default=300_000)
    ap.add_argument("--envmap", type=int, default=128, help="cube face size")
    ap.add_argument("--repeat", type=int, default=10, help="rounds (each runs every case once)")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: default)")
    ap.add_argument(
        "--split-threads",
        action="store_true",
        help="Glint's process layout (core.kernels.threads): torch on one thread, the compiled "
        "kernels on --threads (default: every usable CPU)",
    )
    ap.add_argument(
        "--no-roughness",
        action="store_true",
        help="the model without per-splat roughness (mirror lookups, as before issue 36)",
    )
    ap.add_argument(
        "--compare-order",
        choices=["centre", "slab", "plane"],
        help="also time the full step with this TrainConfig.splat_order, beside the default "
        "('auto': plane order on the cpu backend, centre order on cuda)",
    )
    ap.add_argument(
        "--compare-fresnel",
        action="store_true",
        help="also time the masked full step without Fresnel (Ablation.fresnel), beside it",
    )
    ap.add_argument("--json", help="also write the results here")
    args = ap.parse_args(argv)
    if args.repeat < 1 or args.warmup < 0:
        ap.error(f"--repeat must be >= 1 and --warmup >= 0, got {args.repeat} and {args.warmup}")
    res = run(args)
    print(format_table(res))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=2)


if __name__ == "__main__":
    main()
