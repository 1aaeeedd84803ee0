"""Where a training step's time goes: each stage of the real ``Trainer.step``, forward
and backward, in milliseconds per step and as a share of the step.

    python -m bench.step_breakdown ../shared/data/spot_plastic --phase multiview \\
        --init-points 20000 --steps 20 --threads 2 --markdown docs/bench/step_breakdown.md

The trainer, the rasteriser and the shading mark their stages with
:func:`core.stages.stage` (profiler ranges named ``glint::…``). The steps run under
``torch.profiler`` (CPU activity):

* **forward** of a stage is the wall time inside its range, less the ranges nested in
  it (``gbuffer`` holds ``project``, ``bin``, ``composite``; so does
  ``neighbour_gbuffer``, as ``neighbour_gbuffer/composite``, ...);
* **backward** of a stage is the time the autograd engine spent on the nodes that
  stage's operations created, matched by the profiler's sequence numbers (the rest of
  ``backward`` is the engine's own: ``backward/engine``);
* ``(outside stages)`` is the step's time in no range: choosing the view, summing the
  losses, zeroing gradients, the learning-rate update.

The profiler slows small operations down, so the step time is also measured without
it (``step, unprofiled``), and the shares are the ones to read. Without ``--run`` the
trainer starts fresh on the scene (``--init-points`` points; the visual hull or the
scene's points) and jumps to the first iteration of ``--phase``; with ``--run`` it
resumes a finished run's checkpoint, as ``bench.trainer_step`` does.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from bisect import bisect_right
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile, record_function

from core.cli import _parse_overrides as parse_overrides
from core.config import load_config, saved_config
from core.kernels.threads import configure_cpu_threads
from core.scene.formats import load_scene
from core.stages import PREFIX
from core.training.trainer import Trainer

STEP = "bench_step"
ENGINE = "autograd::engine::evaluate_function: "
RASTER_STAGES = ("project", "bin", "composite")


def _first_iteration_of(trainer: Trainer, phase: str) -> int:
    for it in range(trainer.sched.iterations):
        if trainer.current_phase(it).name == phase:
            return it
    names = sorted({trainer.current_phase(i).name for i in range(trainer.sched.iterations)})
    raise SystemExit(f"this run has no phase {phase!r}; its phases are {', '.join(names)}")


def _range(evt: Any) -> tuple[float, float]:
    return float(evt.time_range.start), float(evt.time_range.end)


def _inside(inner: tuple[float, float], outer: tuple[float, float]) -> bool:
    return outer[0] <= inner[0] and inner[1] <= outer[1]


def breakdown(events: list[Any], steps: int) -> list[dict[str, Any]]:
    """Per stage path: forward and backward milliseconds per step (see the module doc)."""
    ranges = [e for e in events if e.name.startswith(PREFIX) or e.name == STEP]
    by_thread: dict[Any, list[Any]] = defaultdict(list)
    for e in ranges:
        by_thread[e.thread].append(e)
    path_of: dict[int, str] = {}  # id(range event) -> "a/b" (without the step itself)
    parents: dict[int, Any] = {}
    for evs in by_thread.values():
        evs.sort(key=lambda e: (_range(e)[0], -_range(e)[1]))
        stack: list[Any] = []
        for e in evs:
            while stack and not _inside(_range(e), _range(stack[-1])):
                stack.pop()
            parents[id(e)] = stack[-1] if stack else None
            names = [s.name.removeprefix(PREFIX) for s in stack if s.name != STEP]
            if e.name != STEP:
                names.append(e.name.removeprefix(PREFIX))
            path_of[id(e)] = "/".join(names)
            stack.append(e)

    nested: dict[int, float] = defaultdict(float)  # id(range) -> time of the ranges in it
    for e in ranges:
        parent = parents.get(id(e))
        if parent is not None:
            nested[id(parent)] += _range(e)[1] - _range(e)[0]
    forward: dict[str, float] = defaultdict(float)
    for e in ranges:
        if e.name != STEP:
            start, end = _range(e)
            forward[path_of[id(e)]] += end - start - nested[id(e)]
    step_total = sum(_range(e)[1] - _range(e)[0] for e in ranges if e.name == STEP)
    top = sum(
        _range(e)[1] - _range(e)[0]
        for e in ranges
        if e.name != STEP and (parents.get(id(e)) is None or parents[id(e)].name == STEP)
    )
    forward["(outside stages)"] += step_total - top

    # the stage each forward operation ran in, by the sequence number of its node
    spans = {
        t: [(*_range(r), path_of[id(r)]) for r in evs if r.name != STEP]
        for t, evs in by_thread.items()
    }  # sorted by start, outer before inner
    starts = {t: [a for a, _, _ in sp] for t, sp in spans.items()}

    def innermost(evt: Any) -> str | None:
        # ranges nest: walking back from the last one started, the first that still
        # holds the moment is the innermost
        s, sp = _range(evt)[0], spans.get(evt.thread, [])
        for i in range(bisect_right(starts.get(evt.thread, []), s) - 1, -1, -1):
            if sp[i][1] >= s:
                return sp[i][2]
        return None

    seq_stage: dict[int, tuple[float, str | None]] = {}
    for e in events:
        if e.name.startswith((ENGINE, PREFIX)) or e.name == STEP or e.sequence_nr < 0:
            continue
        where = innermost(e)
        if where is not None and where.split("/")[0] == "backward":
            continue  # an op the engine ran for a node: it carries the node's number
        start = _range(e)[0]
        known = seq_stage.get(e.sequence_nr)
        if known is None or start > known[0]:  # the op that made the node is the last
            seq_stage[e.sequence_nr] = (start, where)
    backward: dict[str, float] = defaultdict(float)
    engine_time = 0.0
    for e in events:
        if not e.name.startswith(ENGINE):
            continue
        dur = _range(e)[1] - _range(e)[0]
        engine_time += dur
        seq = e.sequence_nr
        if seq < 0:  # a Python autograd Function's node: its number is on the child
            seq = next((c.sequence_nr for c in e.cpu_children if c.sequence_nr >= 0), -1)
        where = seq_stage.get(seq, (0.0, None))[1]
        if where is None:
            where = "backward/" + ("accumulate_grad" if "AccumulateGrad" in e.name else "other")
        backward[where] += dur
    if "backward" in forward:  # the range's own time beyond the nodes: the engine's
        forward["backward/engine"] = max(forward.pop("backward") - engine_time, 0.0)

    rows = []
    for path in sorted(set(forward) | set(backward)):
        f, b = forward.get(path, 0.0) / steps / 1000.0, backward.get(path, 0.0) / steps / 1000.0
        rows.append({"stage": path, "forward_ms": f, "backward_ms": b, "total_ms": f + b})
    total = sum(r["total_ms"] for r in rows) or 1.0
    for r in rows:
        r["share"] = r["total_ms"] / total
    rows.sort(key=lambda r: -r["total_ms"])
    return rows


def markdown(rows: list[dict[str, Any]], head: dict[str, Any]) -> str:
    out = [
        f"Step breakdown: {head['scene']} ({head['width']}x{head['height']}), phase "
        f"{head['phase']}, {head['gaussians']} Gaussians, {head['steps']} steps, "
        f"{head['threads']} kernel threads, device {head.get('device', 'cpu')}; "
        f"step {head['step_ms']:.1f} ms unprofiled "
        f"(median), {head['profiled_ms']:.1f} ms under the profiler.",
        "",
        "| stage | forward ms | backward ms | total ms | share |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        out.append(
            f"| {r['stage']} | {r['forward_ms']:.2f} | {r['backward_ms']:.2f} | "
            f"{r['total_ms']:.2f} | {100 * r['share']:.1f}% |"
        )
    raster = sum(r["share"] for r in rows if r["stage"].split("/")[-1] in RASTER_STAGES)
    out += ["", f"The rasteriser (project, bin, composite) is {100 * raster:.0f}% of the step."]
    return "\n".join(out) + "\n"


def _trainer(args: argparse.Namespace, out: Path) -> Trainer:
    overrides = parse_overrides(args.set or [])
    if args.run:
        run = Path(args.run)
        shutil.copytree(run, out, ignore=shutil.ignore_patterns("renders", "mesh*"))
        cfg = saved_config(json.loads((out / "config.json").read_text()), str(out))
    else:
        base = {"iterations": args.iterations, "init_points": args.init_points}
        cfg = load_config(None, {**base, **overrides})
    scene = load_scene(args.scene, downscale=1.0 / cfg.resolution_scale)
    trainer = Trainer(scene, cfg, out)
    trainer.setup(resume=bool(args.run))
    if not args.run:
        trainer.iteration = _first_iteration_of(trainer, args.phase)
    trainer._resize_schedule(trainer.iteration + 2 * (args.warmup + args.steps) + 1)
    return trainer


def _synchronizer(trainer: Trainer) -> Callable[[], None]:
    """Waits for the device's queue, so a GPU step is timed to its end, not its launch."""
    device = torch.device(trainer.device)
    if device.type == "cuda":
        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def measure(args: argparse.Namespace) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="glint-breakdown-") as tmp:
        trainer = _trainer(args, Path(tmp) / "run")
        for _ in range(args.warmup):
            trainer.step()
        sync = _synchronizer(trainer)
        plain = []
        for _ in range(args.steps):
            sync()
            t0 = time.perf_counter()
            trainer.step()
            sync()
            plain.append(time.perf_counter() - t0)
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(args.steps):
                with record_function(STEP):  # the step's own range (no glint:: prefix)
                    trainer.step()
        events = list(prof.events())
        rows = breakdown(events, args.steps)
        spans = [_range(e) for e in events if e.name == STEP]
        profiled = sum(b - a for a, b in spans) / len(spans) / 1e6
        cam = trainer.scene.train[0].camera
        head = {
            "scene": Path(args.scene).name,
            "width": cam.width,
            "height": cam.height,
            "phase": trainer.current_phase().name,
            "gaussians": trainer.gaussians.num,
            "steps": args.steps,
            "threads": args.threads,
            "device": str(trainer.device),
            "step_ms": 1000 * statistics.median(plain),
            "profiled_ms": 1000 * profiled,
        }
    return rows, head


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawTextHelpFormatter
    )
    ap.add_argument("scene", help="scene folder")
    ap.add_argument("--run", help="resume this finished run's checkpoint instead")
    ap.add_argument("--phase", default="multiview", help="rgb, geometry or multiview")
    ap.add_argument("--init-points", type=int, default=20_000)
    ap.add_argument("--iterations", type=int, default=3000, help="the run length it plans")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2, help="compiled-kernel threads")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override")
    ap.add_argument("--json", help="write rows and header here")
    ap.add_argument("--markdown", help="write the table here")
    args = ap.parse_args(argv)
    configure_cpu_threads(args.threads)
    rows, head = measure(args)
    text = markdown(rows, head)
    print(text)
    if args.markdown:
        Path(args.markdown).write_text(text)
    if args.json:
        Path(args.json).write_text(json.dumps({"head": head, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
