"""Compile Glint's numba kernels once, into their on-disk cache, before the tests.

Every kernel is ``@njit(cache=True)``: the first process that calls one compiles it
(seconds each) and writes ``__pycache__/*.nbi``; later processes load it. On a fresh
clone both pytest workers, and every server and worker process the tests start, would
otherwise compile the same kernels at the same time, on the same two cores, inside
tests that time out.

What to compile is the list a whole test run compiled (``scripts/kernel_signatures.tsv``,
``core.kernels.signatures``: 127 signatures, float32 and float64, contiguous and strided),
split into two shares of equal cost, one process per core (numba compiles on one thread;
its cache writes are atomic, so the two never clash). Then, as catch-alls, a tiny training
run through every phase with its outputs and one frame of every viewer channel, and the
float64 paths: they load what the list held and compile what it lacks (a kernel added
since). Without a list, the training run and the float64 paths run side by side instead.

    .venv/bin/python scripts/warm_kernels.py
    .venv/bin/python scripts/warm_kernels.py --record [CHECKOUT]  # after a test run there
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
from core.kernels import signatures
from core.model.channels import CHANNELS
from core.model.frame import to_display
from core.model.trained import CHECKPOINT_NAME, TrainedModel
from core.scene.synthetic import make_scene
from core.training.run import train_scene

ROOT = Path(__file__).resolve().parents[1]


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


def compile_part(part: int, parts: int, entries: list[signatures.Entry] | None = None) -> int:
    """Compile one of ``parts`` equal shares of the recorded signatures (``entries``:
    the list already read, else read here)."""
    entries = signatures.read() if entries is None else entries
    share = signatures.balance(entries, parts)[part]
    done, stale = signatures.compile_entries(share)
    for msg in stale:
        print(f"stale kernel signature (re-record with --record): {msg}")
    return 0 if done or not share else 1


def tiny_run() -> None:
    """A tiny training run through every phase, its outputs and the viewer's frame: it
    reaches any kernel the recorded list lacks (a new one, a changed one)."""
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


def main() -> int:
    t0 = time.perf_counter()
    torch.set_num_threads(1)
    args = sys.argv[1:]
    if args == ["--float64"]:
        float64_paths()
        return 0
    if args[:1] == ["--record"]:  # [--record [CHECKOUT]]: its caches, after a test run
        entries = signatures.record(Path(args[1]) if args[1:] else ROOT)
        signatures.write(entries)
        print(f"{len(entries)} kernel signatures recorded in {signatures.LIST}")
        return 0
    if len(args) == 2 and args[0] == "--part":
        return compile_part(int(args[1]), 2)
    entries = signatures.read()
    if entries:
        # the recorded signatures in two equal shares, one per core; then the catch-alls
        # (everything they reach is loaded from the cache unless the list lacks it)
        other = subprocess.Popen([sys.executable, __file__, "--part", "1"])
        compile_part(0, 2, entries)
        if other.wait() != 0:
            print("the second share of the recorded kernels failed to compile")
        tiny_run()
        float64_paths()
    else:
        other = subprocess.Popen([sys.executable, __file__, "--float64"])
        tiny_run()
        if other.wait() != 0:
            print("the float64 warm-up failed (its kernels compile in the tests instead)")
    print(f"numba kernels compiled and cached in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
