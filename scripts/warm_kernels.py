"""Compile Glint's numba kernels once, into their on-disk cache, before the tests.

Every kernel is ``@njit(cache=True)``: the first process that calls one compiles it
(seconds each) and writes ``__pycache__/*.nbi``; later processes load it. On a fresh
clone both pytest workers, and every server and worker process the tests start, would
otherwise compile the same kernels at the same time, on the same two cores, inside
tests that time out. A tiny training run through every phase, its outputs (mesh,
renders) and one frame of every viewer channel reach them all.

    .venv/bin/python scripts/warm_kernels.py
"""

from __future__ import annotations

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


def main() -> int:
    t0 = time.perf_counter()
    torch.set_num_threads(1)
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
    print(f"numba kernels compiled and cached in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
