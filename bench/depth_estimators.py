"""Planar (Eq. 8) against blended-centre (Eq. 5) depth of one trained model, each against
the true depth of the test views (issue 36, item 4: why planar depth does or does not
move the Chamfer distance).

Both depths come from the same G-buffer (one render per view), so the difference is the
estimator alone, not the training. Pixels: both valid, alpha > 0.9, a true surface::

    .venv/bin/python -m bench.depth_estimators RUN [RUN ...] --scene SCENE

Prints per run the mean |error| and the signed bias (model − truth; negative = in front
of the true surface) of each estimator, and their mean distance from each other.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from core.model.run_folder import open_run
from core.scene.groundtruth import load_ground_truth


def depth_estimators(run: Path, scene_dir: Path | None) -> dict[str, Any]:
    model, scene = open_run(run, scene_dir)
    root = Path(scene_dir) if scene_dir else scene.root
    rows = []
    for v in scene.test or scene.train:
        gt = load_ground_truth(root, v)
        if gt is None:
            continue
        gb = model.render(v.camera, ("depth",)).gbuffer
        d8, d5 = gb.depth, gb.center_depth
        g = gt.depth.to(d8)
        m = gb.depth_valid & (gb.alpha > 0.9) & (g > 0) & (d5 > 0)
        if not m.any():
            continue
        e8, e5 = d8[m] - g[m], d5[m] - g[m]
        gap = (d8[m] - d5[m]).abs().mean().item()
        rows.append(
            [
                e8.abs().mean().item(),
                e5.abs().mean().item(),
                gap,
                e8.mean().item(),
                e5.mean().item(),
            ]
        )
    if not rows:
        raise SystemExit(f"{run}: no test view with ground-truth depth")
    r = np.array(rows).mean(0)
    keys = ("abs_err_eq8", "abs_err_eq5", "eq8_minus_eq5", "bias_eq8", "bias_eq5")
    return {
        "run": str(run),
        "views": len(rows),
        **{k: float(x) for k, x in zip(keys, r, strict=True)},
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="run folders")
    p.add_argument("--scene", help="scene folder with *_gt/ maps (default: the run's)")
    args = p.parse_args(argv)
    print("| run | abs err Eq. 8 | abs err Eq. 5 | abs Eq. 8 − Eq. 5 | bias Eq. 8 | bias Eq. 5 |")
    print("|---|---:|---:|---:|---:|---:|")
    out = []
    for run in args.runs:
        r = depth_estimators(Path(run), Path(args.scene) if args.scene else None)
        out.append(r)
        cells = [f"{r[k]:.4f}" for k in ("abs_err_eq8", "abs_err_eq5", "eq8_minus_eq5")]
        cells += [f"{r[k]:+.4f}" for k in ("bias_eq8", "bias_eq5")]
        print(f"| {run} | " + " | ".join(cells) + " |")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
