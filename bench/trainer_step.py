"""Seconds per training step of the real trainer, resumed from a run's checkpoint.

Times ``Trainer.step`` (every loss, densification hooks, the step's bookkeeping) on a
copy of a finished run, so two versions of Glint can be timed on the same model in one
sitting: run this once from each checkout (``git worktree``) with the same run.

    python -m bench.trainer_step runs/teapot --scene ../shared/data/teapot_gold --steps 60

Prints the median and quartiles of the step times after ``--warmup`` steps, and the
phase the steps were in. The copy is trained ``--steps`` past its end, in a temporary
folder; the run itself is not touched.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import torch

from core.config import saved_config
from core.scene.formats import load_scene
from core.training.trainer import Trainer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a finished run folder (config.json + checkpoint.pt)")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (CLI default: 1)")
    ap.add_argument("--json", help="write the figures here too")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    run = Path(a.run)
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "run"
        shutil.copytree(run, copy, ignore=shutil.ignore_patterns("renders", "mesh*"))
        cfg = saved_config(json.loads((copy / "config.json").read_text()), str(copy))
        scene = load_scene(a.scene, downscale=1.0 / cfg.resolution_scale)
        trainer = Trainer(scene, cfg, copy)
        trainer.setup(resume=True)
        start = trainer.iteration
        trainer._resize_schedule(start + a.warmup + a.steps + 1)
        times = []
        for i in range(a.warmup + a.steps):
            t0 = time.perf_counter()
            trainer.step()
            if i >= a.warmup:
                times.append(time.perf_counter() - t0)
        q = statistics.quantiles(times, n=4)
        out = {
            "run": str(run),
            "from_iteration": start,
            "phase": trainer.current_phase().name,
            "gaussians": trainer.gaussians.num,
            "steps": a.steps,
            "median_s": statistics.median(times),
            "q1_s": q[0],
            "q3_s": q[2],
        }
    print(
        f"{run}: {a.steps} steps from iteration {start} ({out['phase']}, "
        f"{out['gaussians']} Gaussians): median {out['median_s'] * 1000:.1f} ms "
        f"(quartiles {out['q1_s'] * 1000:.1f}-{out['q3_s'] * 1000:.1f})"
    )
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
