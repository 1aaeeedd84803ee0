"""Where a viewer frame's time goes: each stage of the viewer's own render call, in
milliseconds per frame and as a share of it.

    python -m bench.frame_breakdown [--run RUN] [--gaussians 100000] [--size 512] \\
        [--frames 18] [--threads 2] [--markdown FILE]

The frame is the viewer's own ``viewer_web.renderer.timed_frame`` (the frozen model's
render of one channel, its 8-bit display encoding, the JPEG) of ``bench.viewer``'s still
camera messages; without ``--run`` the model is ``bench.viewer``'s (a sphere of flat discs
with an env map, recorded as seen from outside so one-sided culling drops the far half).
Stages are the ``core.stages.stage`` ranges of the render (per-view opacity, near plane,
visibility and gathers, SH colours, the G-buffer's features, projection, binning,
compositing, deferred shading) and the viewer's ``display`` and ``jpeg``; each stage's
time is its own, less the ranges nested in it (``bench.step_breakdown.breakdown``), and
``(outside stages)`` is the rest of the frame (making the camera, the frame's header).
The frames are also timed without the profiler, whose ranges slow small operations down:
the shares are the figures to read.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile, record_function

from bench.common import machine_line
from bench.step_breakdown import RASTER_STAGES, STEP, breakdown
from bench.viewer import camera, write_run
from core.kernels.threads import configure_cpu_threads
from viewer_web.protocol import CameraMsg, ProtocolError, parse
from viewer_web.renderer import LoadedModel, load_model, timed_frame


def still_messages(size: int, count: int, channel: str = "final") -> list[CameraMsg]:
    """``bench.viewer``'s resting cameras asking for ``channel``, validated as the viewer
    validates a client's (a bad channel raises ``viewer_web.protocol.ProtocolError``)."""
    msgs = []
    for i in range(count):
        msg = json.loads(camera(i + 1, 1.0 + i, size, still=True))
        parsed = parse(json.dumps({**msg, "channel": channel}))
        assert isinstance(parsed, CameraMsg)
        msgs.append(parsed)
    return msgs


def frame(loaded: LoadedModel, spec: CameraMsg, quality: int) -> bytes:
    """One still frame at full resolution, as the viewer renders and encodes it."""
    return timed_frame(loaded, spec, 1.0, quality)[0]


def measure(
    loaded: LoadedModel, specs: list[CameraMsg], quality: int, warmup: int = 3
) -> tuple[list[dict[str, Any]], float, float]:
    """(rows, frame ms unprofiled (median), frame ms under the profiler (mean))."""
    for spec in specs[:warmup]:
        frame(loaded, spec, quality)
    plain = []
    for spec in specs:
        t0 = time.perf_counter()
        frame(loaded, spec, quality)
        plain.append(1000.0 * (time.perf_counter() - t0))
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for spec in specs:
            with record_function(STEP):
                frame(loaded, spec, quality)
    events = list(prof.events())
    spans = [e.time_range for e in events if e.name == STEP]
    profiled = sum(s.end - s.start for s in spans) / len(spans) / 1000.0
    rows = [r for r in breakdown(events, len(specs)) if r["total_ms"] > 0.0]
    return rows, statistics.median(plain), profiled


def markdown(rows: list[dict[str, Any]], head: dict[str, Any]) -> str:
    out = [
        f"Frame breakdown: {head['model']}, {head['size']}² `{head['channel']}`, "
        f"{head['frames']} still frames, {head['threads']} kernel threads; frame "
        f"{head['frame_ms']:.1f} ms unprofiled (median), {head['profiled_ms']:.1f} ms "
        "under the profiler.",
        "",
        "| stage | ms | share |",
        "|---|---:|---:|",
    ]
    out += [f"| {r['stage']} | {r['forward_ms']:.2f} | {100 * r['share']:.1f}% |" for r in rows]
    raster = sum(r["share"] for r in rows if r["stage"].split("/")[-1] in RASTER_STAGES)
    out += ["", f"The rasteriser (project, bin, composite) is {100 * raster:.0f}% of the frame."]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, help="a run folder (default: bench.viewer's model)")
    ap.add_argument("--gaussians", type=int, default=100_000, help="of bench.viewer's model")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--channel", default="final")
    ap.add_argument("--frames", type=int, default=18)
    ap.add_argument("--quality", type=int, default=85, help="JPEG quality")
    ap.add_argument("--threads", type=int, default=None, help="kernel threads (default: all)")
    ap.add_argument("--markdown", type=Path, help="also write the table to this file")
    a = ap.parse_args(argv)
    if a.frames < 1 or a.size < 16:
        ap.error("--frames must be at least 1 and --size at least 16")
    try:
        specs = still_messages(a.size, a.frames, a.channel)
    except ProtocolError as exc:
        ap.error(f"--channel {a.channel!r}: {exc}")
    threads = configure_cpu_threads(a.threads)
    with tempfile.TemporaryDirectory(prefix="glint-frame-") as tmp:
        run = a.run if a.run is not None else write_run(Path(tmp), a.gaussians, one_sided=True)
        loaded = load_model(run, torch.device("cpu"))
        rows, frame_ms, profiled = measure(loaded, specs, a.quality)
    head = {
        "model": str(a.run) if a.run else f"bench.viewer's sphere of {a.gaussians:,} discs",
        "size": a.size, "channel": a.channel, "frames": a.frames, "threads": threads,
        "frame_ms": frame_ms, "profiled_ms": profiled,
    }  # fmt: skip
    text = markdown(rows, head)
    print(machine_line())
    print(text)
    if a.markdown:
        a.markdown.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
