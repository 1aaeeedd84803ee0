"""Compile Glint's numba kernels once, into their on-disk cache, before the tests.

Every kernel is ``@njit(cache=True)``: the first process that calls one compiles it
(seconds each) and writes ``__pycache__/*.nbi``; later processes load it. On a fresh
clone both pytest workers, and every server and worker process the tests start, would
otherwise compile the same kernels at the same time, on the same two cores, inside
tests that time out. A tiny training run through every phase, its outputs (mesh,
renders) and one frame of every viewer channel reach them all.

The float64 variants (the stability and parity tests render, shade and compare in
float64: another signature of each kernel, ~25 s of compiling inside those tests) are
compiled at the same time in a second process, on the core the first one leaves idle
(numba compiles on one thread; its cache writes are atomic, so the two never clash).

    .venv/bin/python scripts/warm_kernels.py
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch

from core.config import TrainConfig
from core.model.channels import CHANNELS
from core.model.frame import to_display
from core.model.trained import CHECKPOINT_NAME, TrainedModel
from core.scene.synthetic import make_scene
from core.training.run import train_scene


def float64_paths() -> None:
    """A float64 G-buffer pass with its backward on the compiled CPU backend, the cube
    map lookups (sharp and mip-mapped), the multi-view loss and SSIM's blur: the float64
    signatures the tests use."""
    from core.evaluation.ssim import ssim
    from core.render.envmap import sample_cube
    from core.render.envmap_mips import sample_cube_lod
    from core.render.gbuffer import render_gbuffer_tensors
    from core.scene.cameras import Camera, Intrinsics
    from core.training.losses import multi_view_loss

    f64 = torch.float64
    gen = torch.Generator().manual_seed(0)
    n, size = 64, 24
    cam = Camera(Intrinsics(24.0, 24.0, 12.0, 12.0, size, size), torch.eye(4, dtype=f64))
    means = torch.randn(n, 3, generator=gen, dtype=f64) * 0.3 + torch.tensor([0, 0, 2.0], dtype=f64)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen, dtype=f64), dim=-1)
    scales = torch.rand(n, 3, generator=gen, dtype=f64) * 0.1 + 0.02
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=f64), dim=-1)
    leaves = [
        t.requires_grad_(True)
        for t in (means, quats, scales, torch.full((n,), 0.8, dtype=f64),
                  torch.rand(n, 3, generator=gen, dtype=f64), normals,
                  torch.full((n,), 0.3, dtype=f64))
    ]  # fmt: skip
    gb, _ = render_gbuffer_tensors(*leaves, cam, backend="cpu")
    loss = gb.depth.sum() + gb.normal.sum() + gb.plane_dist.sum() + gb.center_depth.sum()
    (loss + gb.base.sum() + gb.alpha.sum()).backward()
    tex = torch.rand(6, 4, 4, 3, generator=gen, dtype=f64).requires_grad_(True)
    dirs = torch.randn(32, 3, generator=gen, dtype=f64).requires_grad_(True)
    sample_cube(tex, dirs).sum().backward()
    lod = torch.rand(32, generator=gen, dtype=f64).requires_grad_(True)
    sample_cube_lod(tex, dirs, lod).sum().backward()
    nb = Camera(cam.intrinsics, torch.tensor(
        [[1, 0, 0, -0.2], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=f64))  # fmt: skip
    d_ref = torch.full((size, size), 2.0, dtype=f64, requires_grad=True)
    d_nb = torch.full((size, size), 2.0, dtype=f64)
    ones = torch.ones(size, size, dtype=torch.bool)
    loss, _ = multi_view_loss(d_ref, ones, cam, d_nb, ones, nb)
    loss.backward()
    img = torch.rand(size, size, 3, generator=gen, dtype=f64).requires_grad_(True)
    ssim(img, torch.rand(size, size, 3, generator=gen, dtype=f64)).backward()


def main() -> int:
    t0 = time.perf_counter()
    torch.set_num_threads(1)
    if sys.argv[1:] == ["--float64"]:
        float64_paths()
        return 0
    other = subprocess.Popen([sys.executable, __file__, "--float64"])
    scene = make_scene("sphere", "glossy", n_train=6, n_test=2, size=32, samples=1)
    cfg = TrainConfig(  # L_multi kept (a masked scene's plan drops it) and given neighbours
        iterations=60,
        init_points=400,
        plan_overrides={"multi_view": True},
        loss={"multiview_max_angle_deg": 90.0},
    )
    with tempfile.TemporaryDirectory() as tmp:
        train_scene(scene, tmp, cfg)  # every phase, then the outputs (mesh, renders)
        model = TrainedModel.open(Path(tmp) / CHECKPOINT_NAME, device="cpu").freeze()
        frame = model.render(scene.train[0].camera, CHANNELS)  # the viewer's frame path
        for ch in CHANNELS:
            to_display(frame.image(ch))
    if other.wait() != 0:
        print("the float64 warm-up failed (its kernels compile in the tests instead)")
    print(f"numba kernels compiled and cached in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
