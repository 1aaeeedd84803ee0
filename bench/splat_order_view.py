"""A trained model's G-buffer, forward and backward, in each compositing order.

    python -m bench.splat_order_view RUN/checkpoint.pt SCENE [--repeat 7] [--threads 1]

``bench.train_step`` times a random ball of Gaussians, every pixel many layers deep: the
worst case for plane order, which gathers and sorts all of a pixel's contributors. This
times what training renders: the checkpoint's Gaussians seen from the scene's first
held-out view (its first training view if it has none), the G-buffer pass the training
step runs (``render_gbuffer``, every channel summed, ``backward``), in centre, slab and
plane order, interleaved round by round so machine drift hits all alike.
"""

from __future__ import annotations

import argparse
import statistics
from collections.abc import Callable

import torch

from bench.common import interleaved_times, machine_line
from core.config import TrainConfig
from core.kernels.threads import configure_cpu_threads
from core.model.checkpoint import load_checkpoint
from core.render.gbuffer import render_gbuffer
from core.scene.formats import load_scene

ORDERS = ("centre", "slab", "plane")


def order_cases(checkpoint: str, scene: str) -> dict[str, Callable[[], None]]:
    """Forward and forward+backward of the model's G-buffer in each order."""
    gs = load_checkpoint(checkpoint).gaussians
    views = load_scene(scene)
    cam = (views.test or views.train)[0].camera
    cfg = TrainConfig()
    kw = {"sh_degree": gs.sh_degree, "backend": "cpu", "antialiased": cfg.antialiased,
          "lowpass": cfg.lowpass_2d}  # fmt: skip
    params = list(gs.params.values())
    for p in params:
        p.requires_grad_(True)

    def forward(order: str) -> None:
        with torch.no_grad():
            render_gbuffer(gs, cam, splat_order=order, **kw)

    def step(order: str) -> None:
        gb, _ = render_gbuffer(gs, cam, splat_order=order, **kw)
        (gb.base.sum() + gb.normal.sum() + gb.plane_dist.sum() + gb.alpha.sum()).backward()
        for p in params:
            p.grad = None

    cases: dict[str, Callable[[], None]] = {}
    for order in ORDERS:
        cases[f"{order}: forward"] = lambda o=order: forward(o)
        cases[f"{order}: forward+backward"] = lambda o=order: step(o)
    return cases


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("checkpoint", help="a run's checkpoint.pt")
    ap.add_argument("scene", help="the scene folder it was trained on")
    ap.add_argument("--repeat", type=int, default=7, help="rounds (each runs every case once)")
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1, help="compiled-kernel threads")
    args = ap.parse_args(argv)
    configure_cpu_threads(args.threads)
    cases = order_cases(args.checkpoint, args.scene)
    for _ in range(args.warmup):
        for fn in cases.values():
            fn()
    times = interleaved_times(cases, args.repeat)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(machine_line())
    print("| case | ms (median) | × centre |\n|---|---:|---:|")
    for key, ms in med.items():
        what = key.split(": ")[1]
        print(f"| {key} | {ms:.1f} | {ms / med[f'centre: {what}']:.2f} |")


if __name__ == "__main__":
    main()
