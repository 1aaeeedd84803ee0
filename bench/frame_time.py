"""A viewer frame's render time without the server: the model the viewer benchmark serves,
rendered through the viewer's own call (``viewer_web.renderer.render_channel``).

    python -m bench.frame_time [--gaussians 100000] [--sizes 102 384 512] [--repeat 30]

``bench.viewer`` times the whole stream (WebSocket, governor, JPEG), whose figures move
with the machine's load by as much as a change is worth; this times the render alone,
many times, and prints min and median per size (the min is the figure to compare
between two trees run one after the other). 102 px is what the governor streams at on
a slow machine (scale 0.2 of 512), 384 the issue's scale 0.75.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import tempfile
import time
from pathlib import Path

import torch

from bench.viewer import write_run
from core.kernels.threads import configure_cpu_threads
from core.scene.cameras import Camera, Intrinsics
from viewer_web.renderer import load_model, render_channel


def frame_camera(size: int, fov_deg: float = 50.0) -> Camera:
    """A square view of the sphere model from outside, ``size`` pixels wide."""
    intr = Intrinsics.from_fov_x(math.radians(fov_deg), size, size)
    return Camera.look_at((0.0, -3.0, 1.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), intr)


def time_frames(model, size: int, channel: str, repeat: int, warmup: int = 3) -> list[float]:
    cam = frame_camera(size)
    for _ in range(warmup):
        render_channel(model, cam, channel)
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        render_channel(model, cam, channel)
        out.append(1000.0 * (time.perf_counter() - t0))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--sizes", type=int, nargs="+", default=[102, 384, 512])
    ap.add_argument("--channel", default="final")
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--threads", type=int, default=None, help="kernel threads (default: all)")
    args = ap.parse_args(argv)
    configure_cpu_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="glint-frame-") as tmp:
        run = write_run(Path(tmp), args.gaussians, one_sided=True)
        model = load_model(run, torch.device("cpu"))
        rows = []
        for size in args.sizes:
            ms = time_frames(model, size, args.channel, args.repeat)
            rows.append({"size": size, "min_ms": round(min(ms), 2),
                         "median_ms": round(statistics.median(ms), 2)})  # fmt: skip
    print(json.dumps({"gaussians": args.gaussians, "channel": args.channel, "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
