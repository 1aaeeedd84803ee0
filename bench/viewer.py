"""Viewer benchmark: time to first frame, moving frame rate, full-resolution frame time.

A synthetic model of ~100k flat Gaussians on a sphere (glossy, with an env map) is
saved as a checkpoint, served by the real viewer stack (uvicorn + WebSocket) and
driven by a Python client::

    .venv/bin/python -m bench.viewer [--gaussians 100000] [--size 512] [--seconds 6] [--one-sided]

Prints one JSON object. "moving" streams cameras at 60 Hz along an orbit (the
server renders the newest, at the resolution its governor picks); "still" asks for
full-resolution frames of a resting camera.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
import uvicorn
from fastapi import FastAPI
from websockets.sync.client import connect

import viewer_web
from core.config import TrainConfig
from core.kernels.pool import kernel_threads
from core.kernels.threads import configure_cpu_threads
from core.model.checkpoint import save_checkpoint
from core.render import orientation as ori
from core.render.envmap import EnvMap, texel_directions
from core.render.gaussians import PARAM_SHAPES, Gaussians, scalar_logit
from core.render.sh import rgb_to_sh0
from core.scene.synthetic import albedo, default_env, surface_points
from viewer_web.protocol import unpack_frame


def sphere_model(n: int, seed: int = 0) -> Gaussians:
    """n flat discs tangent to a sphere of radius 0.6, covering it about twice over."""
    pts, nrm = surface_points("sphere", n, seed)
    radius = float(pts.norm(dim=-1).mean())
    s = 2.0 * radius * math.sqrt(4 * math.pi / n)  # disc radius ~ 2× the point spacing
    # Quaternion (w, x, y, z) turning +z onto the normal: (1 + n_z, -n_y, n_x, 0).
    q = torch.stack([1 + nrm[:, 2], -nrm[:, 1], nrm[:, 0], torch.zeros(n)], dim=-1)
    q = F.normalize(torch.where(q[:, :1] < 1e-6, torch.tensor([0.0, 1.0, 0.0, 0.0]), q), dim=-1)
    g = torch.Generator().manual_seed(seed)
    params = {
        "means": pts.float(),
        "log_scales": torch.log(torch.tensor([s, s, s * 0.01])).repeat(n, 1),
        "quats": q.float(),
        "opacity_logits": torch.full((n,), scalar_logit(0.9)),
        "sh_dc": rgb_to_sh0(albedo(pts).float().clamp(0, 1))[:, None, :],
        "sh_rest": torch.zeros(n, *PARAM_SHAPES["sh_rest"]),
        "refl_logits": torch.logit(torch.rand(n, generator=g) * 0.5 + 0.2),
    }
    return Gaussians(params, sh_degree=0)


def seen_from_outside(g: Gaussians, views: float = 5.0) -> None:
    """Record every disc as seen along its outward normal from ``views`` views, as
    training's visibility record would for a closed surface: one-sided culling then
    hides the discs facing away from a camera."""
    ori.add_orientation_state(g)
    g.params[ori.SEEN_DIR].data[:] = views * g.normals().detach()
    g.params[ori.SEEN_COUNT].data[:] = views


def write_run(run_dir: Path, n: int, one_sided: bool = False) -> Path:
    """The checkpoint; ``one_sided`` also records each disc as seen from outside (as
    training records it), so that the far half is culled in every view."""
    env = EnvMap(64)
    env.set_texels(default_env(texel_directions(64)))
    cfg = TrainConfig(sh_degree=0, envmap_resolution=64)
    extra = {
        "iteration": cfg.iterations,
        "config": cfg.model_dump(mode="json"),
        "envmap": env.state_dict(),
    }
    g = sphere_model(n)
    if one_sided:
        seen_from_outside(g)
    return save_checkpoint(run_dir / "checkpoint.pt", g, extra)


def serve(run_dir: Path) -> tuple[uvicorn.Server, str, str]:
    app = FastAPI()
    service = viewer_web.ViewerService(
        lambda job_id, owner: viewer_web.JobView(
            run_dir, None, {"id": job_id, "state": "succeeded", "version": 1}
        )
    )
    viewer_web.mount(app, service)
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    threading.Thread(target=server.run, daemon=True).start()
    while not server.started:
        time.sleep(0.02)
    token, _ = service.issue_token("job_bench", "bench")
    return (
        server,
        f"ws://127.0.0.1:{port}/v1/jobs/job_bench/viewer/ws?token={token}",
        str(service.device),
    )


def camera(seq: int, angle: float, size: int, still: bool) -> str:
    eye = [2.2 * math.cos(angle), 2.2 * math.sin(angle), 0.6]
    return json.dumps(
        {
            "type": "camera",
            "seq": seq,
            "width": size,
            "height": size,
            "eye": eye,
            "target": [0, 0, 0],
            "up": [0, 0, 1],
            "fov_y": 40.0,
            "still": still,
        }
    )


def frame(ws: Any, timeout: float = 120) -> dict[str, Any]:
    while True:
        msg = ws.recv(timeout=timeout)
        if isinstance(msg, bytes):
            return unpack_frame(msg)[0]


def run(
    n: int, size: int, seconds: float, one_sided: bool = False, stills: int = 9
) -> dict[str, Any]:
    """Serve a sphere model of ``n`` Gaussians and time it: first frame, ``seconds`` of
    moving cameras, then ``stills`` full-resolution frames (their median and range:
    three frames left the median to one noisy frame)."""
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp)
        write_run(run_dir, n, one_sided)
        server, url, device = serve(run_dir)
        try:
            t0 = time.perf_counter()
            with connect(url, max_size=None) as ws:
                ws.recv(timeout=120)  # hello (the model is loaded by now)
                ws.send(camera(1, 0.0, size, still=True))
                first = frame(ws)
                ttff = time.perf_counter() - t0

                # Moving: a camera per display frame (60 Hz), as the browser sends one per
                # animation frame while it moves; frames arrive as fast as renders allow.
                stop = threading.Event()
                sent = [1]

                def sender() -> None:
                    while not stop.is_set():
                        sent[0] += 1
                        ws.send(camera(sent[0], sent[0] * 0.02, size, still=False))
                        time.sleep(1 / 60)

                th = threading.Thread(target=sender)
                moving: list[dict[str, Any]] = []
                th.start()
                t1 = time.perf_counter()
                while time.perf_counter() - t1 < seconds:
                    moving.append(frame(ws))
                stop.set()
                th.join()
                elapsed = time.perf_counter() - t1
                moving = [f for f in moving if f["reason"] == "camera"]

                # Still: full resolution frames of resting cameras.
                still_ms, still_rt, still_render, still_encode = [], [], [], []
                seq = sent[0] + 100
                for i in range(stills):
                    seq += 1
                    t = time.perf_counter()
                    ws.send(camera(seq, 1.0 + i, size, still=True))
                    while (h := frame(ws))["seq"] != seq or not h["full"]:
                        pass
                    still_rt.append((time.perf_counter() - t) * 1000)
                    still_ms.append(h["render_ms"] + h["encode_ms"])
                    still_render.append(h["render_ms"])
                    still_encode.append(h["encode_ms"])
        finally:
            server.should_exit = True
    steady = moving[len(moving) // 3 :] or moving
    return {
        "gaussians": n,
        "one_sided": one_sided,
        "size": size,
        "device": device,
        "torch_threads": torch.get_num_threads(),
        "kernel_threads": kernel_threads(),
        "time_to_first_frame_s": round(ttff, 3),
        "first_frame_render_ms": first["render_ms"],
        "moving": {
            "cameras_sent": sent[0] - 1,
            "frames": len(moving),
            "fps": round(len(moving) / elapsed, 2),
            "median_scale": statistics.median(f["scale"] for f in steady),
            "median_resolution": f"{statistics.median(f['width'] for f in steady):.0f}px wide",
            "median_render_ms": statistics.median(f["render_ms"] for f in steady),
        },
        "still_full_res": {
            "frames": len(still_ms),
            "render_plus_encode_ms_median": round(statistics.median(still_ms), 1),
            "render_plus_encode_ms_range": [round(min(still_ms), 1), round(max(still_ms), 1)],
            "render_ms_median": round(statistics.median(still_render), 1),
            "encode_ms_median": round(statistics.median(still_encode), 1),
            "round_trip_ms_median": round(statistics.median(still_rt), 1),
        },
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument(
        "--one-sided", action="store_true",
        help="record the discs as seen from outside, as a trained model's are: the far "
        "half is culled in every view (default: two-sided, every disc drawn)",
    )  # fmt: skip
    ap.add_argument(
        "--stills", type=int, default=9,
        help="full-resolution frames of resting cameras, each at its own angle",
    )  # fmt: skip
    a = ap.parse_args()
    if a.stills < 1:
        ap.error("--stills must be at least 1 (the still frame's median needs a frame)")
    configure_cpu_threads()  # as `glint serve` does
    print(json.dumps(run(a.gaussians, a.size, a.seconds, a.one_sided, a.stills), indent=2))


if __name__ == "__main__":
    main()
