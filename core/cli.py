"""The ``glint`` command line.

Core commands live here; the service layers (api, worker) add theirs through the
``glint.commands`` entry-point group, so ``core`` never imports them.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path

from core import __version__
from core.asset.command import register as register_export
from core.errors import GlintError

Handler = Callable[[argparse.Namespace], int]


def _cmd_info(args: argparse.Namespace) -> int:
    import torch

    from core.devices import device_problem
    from core.kernels.pool import kernel_threads
    from core.render.raster import BACKENDS, cpu_simd

    no_cuda = device_problem("cuda")
    devices = ["cpu"] + ([] if no_cuda else ["cuda"])
    gpus = [] if no_cuda else [
        f"cuda:{i} {torch.cuda.get_device_name(i)}" for i in range(torch.cuda.device_count())
    ]  # fmt: skip
    info = {
        "glint": __version__,
        "torch": torch.__version__,
        "threads": {"torch": torch.get_num_threads(), "kernels": kernel_threads()},
        "devices": devices,
        "cuda": no_cuda or gpus,
        "backends": {
            name: {d: (ok(torch.device(d)) or "available") for d in devices}
            for name, (ok, _) in BACKENDS.items()
        },
        "cpu_compositing": cpu_simd.status(),
    }
    print(json.dumps(info, indent=2))
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from core.scene.formats import load_scene

    scene = load_scene(args.scene, downscale=args.downscale)
    print(json.dumps(scene.summary(), indent=2))
    return 0


def _parse_overrides(items: list[str]) -> dict:
    """``--set loss.scale=50`` → {"loss.scale": 50} (values parsed as YAML scalars)."""
    import yaml

    out = {}
    for item in items or []:
        if "=" not in item:
            raise GlintError(f"--set expects KEY=VALUE, got '{item}'")
        k, v = item.split("=", 1)
        out[k.strip()] = yaml.safe_load(v)
    return out


def _train_config(args: argparse.Namespace, defaults: dict | None = None):
    from core.config import load_config

    overrides = dict(defaults or {})
    if args.iterations is not None:
        overrides["iterations"] = args.iterations
    if getattr(args, "time", None) is not None:
        from core.config import parse_duration

        try:
            overrides["time_budget"] = parse_duration(args.time)
        except ValueError as exc:
            raise GlintError(f"--time: {exc}") from None
    if args.device is not None:
        overrides["device"] = args.device
    if getattr(args, "backend", None) is not None:
        overrides["backend"] = args.backend
    overrides.update(_parse_overrides(args.set))
    return load_config(args.config, overrides)


def _print_summary(out, result, summary) -> None:
    print(
        f"status: {result.status} at iteration {result.iteration} "
        f"({result.train_seconds:.1f} s of training)"
        + (", time budget spent" if result.stopped_by == "time" else "")
    )
    m = result.last_metrics
    if m:
        print(
            f"held-out PSNR {m.get('psnr', float('nan')):.2f} dB, "
            f"SSIM {m.get('ssim', float('nan')):.4f}, "
            f"{m.get('n_gaussians')} Gaussians"
        )
    if summary and summary.get("geometry"):
        g = summary["geometry"]
        print(
            f"normal error {g['normal_error_deg']:.2f} deg, "
            f"depth error {g['depth_rel_error'] * 100:.2f}%"
        )
    if summary and summary.get("mesh"):
        ms = summary["mesh"]
        print(f"mesh: {ms['faces']:,} faces, vertex colour {ms['color']} (mesh.ply/.glb/.obj)")
    print(f"outputs in {out} (report.md, error_vs_time.png, point_cloud.ply, renders/)")


def _add_train_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="YAML or JSON training config")
    p.add_argument("--iterations", type=int, help="total iterations (phase marks scale with it)")
    p.add_argument(
        "--time",
        metavar="DURATION",
        help="time budget, e.g. 90s, 5m, 1h: the phases are fitted to it and the run ends "
        "with complete outputs when it is spent (with --iterations: whichever comes first)",
    )
    p.add_argument("--device", help="cpu or cuda")
    p.add_argument("--backend", choices=["auto", "reference", "cpu", "cuda"])
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a config field, e.g. loss.scale=50",
    )
    p.add_argument(
        "--overwrite",
        "--no-resume",
        dest="no_resume",
        action="store_true",
        help="start over even if the folder holds a run (by default a run is resumed, and "
        "one made with another configuration is refused)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _cmd_train(args: argparse.Namespace) -> int:
    from core.training.run import train_scene

    cfg = _train_config(args)
    result, summary = train_scene(
        args.scene, args.out, cfg, progress=not args.quiet, resume=not args.no_resume
    )
    _print_summary(args.out, result, summary)
    return 0 if result.status == "succeeded" else 3


DEMO_DEFAULTS = {
    "iterations": 1500,
    "init_points": 3000,
    "densify.max_gaussians": 12000,
    # Antialiased splatting fades discs seen edge-on; the analytic sphere's rim is
    # nothing but such discs, and it scored 34.2 dB with it vs 36.9 dB without
    # (1500 iterations, 64 px; 34.8 vs 37.3 at 96 px). On the rendered dev scenes it
    # pays (spot_plastic +1.7 dB, teapot_gold -0.4 dB, depth error -25 %), so it stays
    # the default; see docs/benchmarks.md.
    "antialiased": False,
}


def _cmd_demo(args: argparse.Namespace) -> int:
    from core.scene.synthetic import write_synthetic_scene
    from core.training.run import train_scene

    out = Path(args.out)
    scene_dir = out / "scene"
    if not (scene_dir / "transforms_train.json").exists():
        print(f"generating a glossy test scene in {scene_dir} ...")
        write_synthetic_scene(
            scene_dir, "sphere", "glossy", n_train=24, n_test=4, size=args.size, seed=0
        )
    cfg = _train_config(args, DEMO_DEFAULTS)
    result, summary = train_scene(
        scene_dir, out / "run", cfg, progress=not args.quiet, resume=not args.no_resume
    )
    _print_summary(out / "run", result, summary)
    return 0 if result.status == "succeeded" else 3


def _cmd_sfm(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from core.scene.sfm import SfmError, SfmOptions, run_sfm

    try:
        opts = SfmOptions(
            matching=args.matching,
            mapper=args.mapper,
            feature_masks=args.feature_masks,
            min_registered=args.min_registered,
            overwrite=args.overwrite,
            verbose=args.verbose,
        )
    except ValueError as exc:
        raise GlintError(str(exc)) from None
    bars: dict[str, tqdm] = {}

    def on_event(e: dict) -> None:
        if e["type"] == "sfm":
            bar = bars.get(e["stage"])
            if bar is None:
                for b in bars.values():
                    b.close()
                bar = bars[e["stage"]] = tqdm(
                    total=e["total"], desc=e["stage"], unit="step", disable=args.quiet
                )
            bar.total = e["total"]
            bar.update(e["done"] - bar.n)

    try:
        result = run_sfm(args.images, args.out, masks=args.masks, options=opts, on_event=on_event)
    except SfmError as exc:
        if exc.report is not None:
            from core.scene.sfm.report import report_text

            print(report_text(exc.report), file=sys.stderr, end="")
        if len(exc.unregistered) > 20:  # the message names 20
            print(f"not registered (all): {', '.join(exc.unregistered)}", file=sys.stderr)
        raise
    finally:
        for b in bars.values():
            b.close()
    print(result.text(), end="")
    print(
        f"wrote the scene to {result.scene} (sfm_report.json, sfm_report.txt); "
        f"train it with: glint train {result.scene} --out RUN"
    )
    return 0


def _register_core(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="versions, devices and rasteriser backends available here")
    p.set_defaults(func=_cmd_info)
    p = sub.add_parser(
        "validate",
        help="load a scene folder (format auto-detected) and print its summary",
        description="Load SCENE (Blender/NeRF, nerfstudio, COLMAP, LLFF or NeRO) and report "
        "views, resolution, intrinsics, split and masks; exits 2 with the file and field "
        "at fault when the scene is malformed.",
    )
    p.add_argument("scene", help="scene folder")
    p.add_argument(
        "--downscale", type=float, default=1.0, help="divide image size by this on load (>= 1)"
    )
    p.set_defaults(func=_cmd_validate)
    p = sub.add_parser(
        "sfm",
        help="recover cameras for a folder of photos (structure from motion, pycolmap)",
        description="Extracts SIFT features, matches image pairs (all pairs up to 40 images, "
        "retrieved neighbours above), maps incrementally, undistorts, and writes a COLMAP "
        "scene (images/, masks/, sparse/0) with sfm_report.json/.txt into --out. Fails "
        "(exit 2, --out untouched) when too few images register, naming them.",
    )
    p.add_argument("images", help="folder of photos (JPEG, PNG, TIFF, ...)")
    p.add_argument("--out", required=True, help="scene folder to write (must be new or empty)")
    p.add_argument("--masks", help="folder of object masks named like the images (white = object)")
    p.add_argument(
        "--matching",
        choices=["auto", "exhaustive", "retrieval"],
        default="auto",
        help="which pairs to match (auto: exhaustive up to 40 images, retrieval above)",
    )
    p.add_argument("--mapper", choices=["incremental", "global"], default="incremental")
    p.add_argument(
        "--feature-masks",
        action="store_true",
        help="keep keypoints off the object (needs --masks; off by default, see docs/capture.md)",
    )
    p.add_argument(
        "--min-registered",
        type=float,
        default=0.8,
        help="fail unless at least this fraction of the images registers (default 0.8)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty --out")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's own log")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_sfm)
    p = sub.add_parser(
        "train",
        help="train PGSR-DR on a scene folder",
        description="Phased PGSR-DR training. Writes checkpoint.pt, point_cloud.ply, the env map, "
        "renders/, plan.json, metrics.jsonl, report.md and error_vs_time.png into --out. "
        "Re-running with the same --out resumes from the last checkpoint.",
    )
    p.add_argument("scene", help="scene folder (format auto-detected)")
    p.add_argument("--out", required=True, help="run folder")
    _add_train_args(p)
    p.set_defaults(func=_cmd_train)
    p = sub.add_parser(
        "demo",
        help="generate a small glossy scene and train on it (CPU, a few minutes)",
        description="Renders an analytic glossy sphere (24 + 4 views), then trains on it with "
        "the full method at a CPU budget. Needs no GPU, no network and no data files.",
    )
    p.add_argument("--out", default="runs/demo", help="folder for the scene and the run")
    p.add_argument("--size", type=int, default=64, help="image size of the generated views")
    _add_train_args(p)
    p.set_defaults(func=_cmd_demo)


def _add_reopen_args(p: argparse.ArgumentParser) -> None:
    """Where ``glint mesh/eval`` reopen a run (its own device may be another machine's)."""
    p.add_argument(
        "--device",
        help="cpu or cuda[:N] (default: the run's, or cpu when this machine lacks it)",
    )
    p.add_argument(
        "--backend",
        choices=["auto", "reference", "cpu", "cuda"],
        help="rasteriser (default: the run's, or auto when this machine lacks it)",
    )


def _add_mesh_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--voxel", type=float, help="TSDF voxel size (default: 2·radius/resolution)")
    p.add_argument("--trunc", type=float, help="TSDF truncation distance (default: 4 voxels)")
    p.add_argument(
        "--mesh-resolution", type=int, default=None, help="voxels across the box (default 256)"
    )
    p.add_argument(
        "--hull",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="bound the distance field by the masks' hull, or not (default: the run's plan, "
        "which turns it on where the masks agree with each other: docs/benchmarks.md)",
    )
    p.add_argument(
        "--grazing-blend",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="fuse Eq. 5's centre depth where the surface is seen obliquely (cos 0.6 to 0.3 "
        "ramp, default), or Eq. 8's planar depth at every angle (--no-grazing-blend)",
    )


def _set_threads(n: int | None) -> None:
    """``--threads N``: the compiled kernels' thread count (torch stays on one)."""
    if n:
        from core.kernels.threads import configure_cpu_threads

        configure_cpu_threads(n)


def _cmd_mesh(args: argparse.Namespace) -> int:
    from core.meshing.mesh import mesh_model
    from core.meshing.tsdf import DEFAULT_RESOLUTION
    from core.model.run_folder import open_run

    _set_threads(args.threads)
    notes: list[str] = []
    model, scene = open_run(
        args.run, args.scene, device=args.device, backend=args.backend, notes=notes
    )
    _print_notes(notes)
    from tqdm import tqdm

    n = len(scene.train)
    bar = tqdm(total=3 * n + 2, unit="step", desc="mesh", disable=args.quiet)

    def progress(step: str, done: int, total: int) -> None:
        bar.set_postfix_str(step)
        bar.update(1)

    try:
        _, info = mesh_model(
            model,
            scene.train,
            args.run,
            voxel=args.voxel,
            trunc=args.trunc,
            resolution=args.mesh_resolution or DEFAULT_RESOLUTION,
            carve=not args.no_carve,
            hull=args.hull,
            grazing_blend=args.grazing_blend,
            keep_fraction=args.keep_fraction,
            color=args.color,
            simplify=args.simplify,
            progress=progress,
        )
    finally:
        bar.close()
    fu = info["fusion"]
    print(
        f"mesh of iteration {info['iteration']}: {info['vertices']} vertices, "
        f"{info['faces']} faces, {info['components']['kept']}/"
        f"{info['components']['components']} components kept, voxel {fu['voxel']:.4g}, "
        f"truncation {fu['trunc']:.4g}, vertex colour: {info['color']}"
    )
    print(f"wrote mesh.ply, mesh.obj, mesh.glb, mesh.json and mesh_preview.png in {args.run}")
    return 0


def _print_notes(notes: list[str]) -> None:
    for note in notes:
        print(f"note: {note}", file=sys.stderr)


def _cmd_eval(args: argparse.Namespace) -> int:
    from core.evaluation.evaluate import evaluate_run

    _set_threads(args.threads)
    notes: list[str] = []
    ev = evaluate_run(
        args.run,
        args.gt,
        n_points=args.points,
        voxel=args.voxel,
        trunc=args.trunc,
        mesh_resolution=args.mesh_resolution,
        hull=args.hull,
        grazing_blend=args.grazing_blend,
        remesh=args.remesh,
        device=args.device,
        backend=args.backend,
        notes=notes,
    )
    _print_notes(notes)
    print(json.dumps(ev["summary"], indent=2))
    print(f"wrote eval.json and the Evaluation section of report.md in {args.run}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from core.benchmark.configs import parse_configs
    from core.benchmark.runner import run_bench

    _set_threads(args.threads)
    from core.config import parse_duration

    if args.budget is None and args.time is None:
        raise GlintError("give --budget ITERATIONS, --time DURATION, or both")
    try:
        time_budget = None if args.time is None else parse_duration(args.time)
    except ValueError as exc:
        raise GlintError(f"--time: {exc}") from None
    path = run_bench(
        args.scenes,
        args.budget,
        args.out,
        time_budget=time_budget,
        configs=parse_configs(args.configs),
        resolution_scale=args.resolution_scale,
        base=_nested(_parse_overrides(args.set)),
        progress=not args.quiet,
        eval_kwargs={
            "n_points": args.points,
            "voxel": args.voxel,
            "trunc": args.trunc,
            "mesh_resolution": args.mesh_resolution,
            "hull": args.hull,
            "grazing_blend": args.grazing_blend,
        },
        command=_bench_command(args),
        retime_fps=args.retime_fps,
    )
    print(path.read_text())
    print(f"wrote {path} and {path.parent / 'error_vs_time.png'}")
    return 0


def _bench_command(args: argparse.Namespace) -> str:
    """The ``glint bench`` command line that reproduces this run (for bench.md)."""
    parts = ["glint bench", *args.scenes]
    parts += [f"--budget {args.budget}"] if args.budget is not None else []
    parts += [f"--time {args.time}"] if args.time is not None else []
    parts += [f"--resolution-scale {args.resolution_scale:g}", f"--configs {args.configs}"]
    parts += [f"--set {s}" for s in args.set or []]
    for flag, value in (
        ("--points", args.points),
        ("--voxel", args.voxel),
        ("--trunc", args.trunc),
        ("--mesh-resolution", args.mesh_resolution),
        ("--threads", args.threads),
    ):
        if value is not None:
            parts.append(f"{flag} {value}")
    if args.hull is not None:
        parts.append("--hull" if args.hull else "--no-hull")
    if not args.grazing_blend:
        parts.append("--no-grazing-blend")
    if args.retime_fps:
        parts.append("--retime-fps")
    return " ".join(parts)


def _nested(flat: dict) -> dict:
    """{"loss.scale": 50} -> {"loss": {"scale": 50}}."""
    out: dict = {}
    for key, value in flat.items():
        node = out
        *parents, last = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[last] = value
    return out


def _register_eval(sub: argparse._SubParsersAction) -> None:
    from core.benchmark.configs import CONFIGS
    from core.evaluation import DEFAULT_CHAMFER_POINTS

    threads = {
        "type": int,
        "help": "CPU threads for the compiled kernels; torch's own ops run on one "
        "(default: GLINT_KERNEL_THREADS, else every usable CPU)",
    }
    p = sub.add_parser(
        "mesh",
        help="extract a mesh (TSDF of the planar depths) from a training run",
        description="Renders the planar depth of every training view from the run's latest "
        "checkpoint, fuses them into a TSDF, runs marching cubes, keeps the largest "
        "components and writes mesh.ply, mesh.obj, mesh.glb and mesh.json into RUN.",
    )
    p.add_argument("run", help="run folder (with checkpoint.pt)")
    p.add_argument("--scene", help="the run's scene folder (default: from scene.json)")
    _add_mesh_args(p)
    p.add_argument("--no-carve", action="store_true", help="do not carve empty pixels")
    p.add_argument(
        "--keep-fraction",
        type=float,
        default=0.1,
        help="keep components with at least this fraction of the largest one's faces",
    )
    p.add_argument(
        "--color",
        choices=("base", "radiance"),
        default="base",
        help="vertex colour: base (the material without reflections; default) or radiance "
        "(the rendered colour, environment baked in)",
    )
    p.add_argument(
        "--simplify", type=int, default=None, help="quadric decimation to about this many faces"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--threads", **threads)
    _add_reopen_args(p)
    p.set_defaults(func=_cmd_mesh)
    p = sub.add_parser(
        "eval",
        help="score a run: PSNR/SSIM/LPIPS, Chamfer distance, F-score, normal/depth error, FPS",
        description="Evaluates the run's latest checkpoint on every test view and, when the "
        "scene ships gt_points.ply, its TSDF mesh (extracted if needed). Writes eval.json and "
        "an Evaluation section in report.md.",
    )
    p.add_argument("run", help="run folder (with checkpoint.pt)")
    p.add_argument("--gt", help="scene folder with the ground truth (default: from scene.json)")
    p.add_argument(
        "--points",
        type=int,
        default=DEFAULT_CHAMFER_POINTS,
        help="points sampled on the mesh for the Chamfer distance",
    )
    _add_mesh_args(p)
    p.add_argument("--remesh", action="store_true", help="extract the mesh even if up to date")
    p.add_argument("--threads", **threads)
    _add_reopen_args(p)
    p.set_defaults(func=_cmd_eval)
    p = sub.add_parser(
        "bench",
        help="ablation benchmark (paper Table 3) over scenes at an iteration or time budget",
        description="Trains and evaluates the full model and each ablation on each scene, "
        "then writes bench.md (one table per scene, Table 3 layout) and error_vs_time.png "
        "into --out. Resumable: finished runs (with eval.json) are skipped, interrupted ones "
        "continue from their checkpoint.",
    )
    p.add_argument("scenes", nargs="+", help="scene folders")
    p.add_argument("--budget", type=int, help="training iterations per run")
    p.add_argument(
        "--time",
        metavar="DURATION",
        help="run time per run, e.g. 90s, 5m (with --budget: whichever comes first)",
    )
    p.add_argument("--out", default="runs/bench", help="benchmark folder")
    p.add_argument("--resolution-scale", type=float, default=1.0, help="image scale, (0, 1]")
    p.add_argument(
        "--configs",
        default=",".join(CONFIGS),
        help=f"comma-separated subset of {','.join(CONFIGS)}",
    )
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="base config override")
    p.add_argument(
        "--points",
        type=int,
        default=DEFAULT_CHAMFER_POINTS,
        help="points sampled on each mesh for the Chamfer distance",
    )
    _add_mesh_args(p)
    p.add_argument("--threads", **threads)
    p.add_argument(
        "--retime-fps",
        action="store_true",
        help="re-time every finished run's renderer back to back before writing bench.md "
        "(comparable FPS when runs were trained in parallel or under varying load)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_bench)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="glint",
        description="Glint: reconstruct shiny objects with planar Gaussian splatting and "
        "deferred reflection (PGSR-DR).",
    )
    parser.add_argument("--version", action="version", version=f"glint {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _register_core(sub)
    _register_eval(sub)
    register_export(sub)
    for ep in entry_points(group="glint.commands"):
        try:
            register = ep.load()
        except ImportError as exc:  # a broken service layer must not take down core commands
            print(f"glint: commands from '{ep.value}' unavailable: {exc}", file=sys.stderr)
            continue
        register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        # the thread layout imports torch (~2.5 s of a process's start); a command that
        # computes nothing (``compute=False`` in its parser's defaults: the key commands)
        # skips it
        if getattr(args, "compute", True):
            from core.kernels.threads import configure_cpu_threads

            try:
                configure_cpu_threads()
            except ValueError as exc:
                raise GlintError(str(exc)) from None
        return int(args.func(args) or 0)
    except GlintError as exc:
        print(f"glint {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"glint {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
