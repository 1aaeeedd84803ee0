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
from core.errors import GlintError

Handler = Callable[[argparse.Namespace], int]


def _cmd_info(args: argparse.Namespace) -> int:
    import torch

    from core.raster import BACKENDS

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    info = {
        "glint": __version__,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "devices": devices,
        "backends": {
            name: {d: (ok(torch.device(d)) or "available") for d in devices}
            for name, (ok, _) in BACKENDS.items()
        },
    }
    print(json.dumps(info, indent=2))
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from core.scene_io import load_scene

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
    print(f"outputs in {out} (report.md, error_vs_time.png, point_cloud.ply, renders/)")


def _add_train_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="YAML or JSON training config")
    p.add_argument("--iterations", type=int, help="total iterations (phase marks scale with it)")
    p.add_argument("--device", help="cpu or cuda")
    p.add_argument("--backend", choices=["auto", "reference", "cpu", "cuda"])
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a config field, e.g. loss.scale=50",
    )
    p.add_argument(
        "--no-resume", action="store_true", help="start over even if a checkpoint exists"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _cmd_train(args: argparse.Namespace) -> int:
    from core.run import train_scene

    cfg = _train_config(args)
    result, summary = train_scene(
        args.scene, args.out, cfg, progress=not args.quiet, resume=not args.no_resume
    )
    _print_summary(args.out, result, summary)
    return 0 if result.status == "succeeded" else 3


DEMO_DEFAULTS = {
    "iterations": 1500,
    "init_points": 3000,
    "envmap_resolution": 32,
    "densify.max_gaussians": 12000,
}


def _cmd_demo(args: argparse.Namespace) -> int:
    from core.run import train_scene
    from core.synthetic import write_synthetic_scene

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
        description="Renders an analytic glossy sphere (48 + 4 views), then trains on it with "
        "the full method at a CPU budget. Needs no GPU, no network and no data files.",
    )
    p.add_argument("--out", default="runs/demo", help="folder for the scene and the run")
    p.add_argument("--size", type=int, default=64, help="image size of the generated views")
    _add_train_args(p)
    p.set_defaults(func=_cmd_demo)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="glint",
        description="Glint: reconstruct shiny objects with planar Gaussian splatting and "
        "deferred reflection (PGSR-DR).",
    )
    parser.add_argument("--version", action="version", version=f"glint {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _register_core(sub)
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
        return int(args.func(args) or 0)
    except GlintError as exc:
        print(f"glint {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"glint {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
