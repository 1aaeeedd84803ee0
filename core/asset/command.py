"""``glint export RUN --asset DIR``: the relightable asset of a run, from the command line."""

from __future__ import annotations

import argparse
from pathlib import Path


def _power_of_two(text: str) -> int:
    value = int(text)
    if value < 16 or value > 8192 or value & (value - 1):
        raise argparse.ArgumentTypeError(f"{text} is not a power of two in 16..8192")
    return value


def _cmd_export(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from core.asset.export import STEPS, asset_run

    bar = tqdm(total=len(STEPS), unit="step", desc="asset", disable=args.quiet)
    last = {"overall": 0}

    def on_event(event: dict) -> None:
        if event.get("name") != "asset":
            bar.set_postfix_str(f"mesh: {event.get('step')}")
            return
        bar.set_postfix_str(f"{event['step']} {event['done']}/{event['total']}")
        overall = int(event["overall_done"])
        if overall > last["overall"]:
            bar.update(overall - last["overall"])
            last["overall"] = overall

    if args.threads:
        from core.kernels.threads import configure_cpu_threads

        configure_cpu_threads(args.threads)
    try:
        info = asset_run(
            args.run,
            args.asset,
            args.scene,
            device=args.device,
            on_event=on_event,
            faces=args.faces,
            texture_size=args.texture_size,
            views=args.views,
            occlusion=not args.no_occlusion,
        )
    finally:
        bar.close()
    out = Path(args.asset)
    sizes = info["size_bytes"]
    total = sum(sizes.values()) / 1e6
    print(
        f"asset of iteration {info['iteration']}: {info['mesh']['faces']} faces "
        f"({info['mesh']['source_faces']} before simplifying), "
        f"{info['textures']['size']}² textures from {info['textures']['views_baked']} views, "
        f"mean metallic {info['material']['mean_metallic']:.2f}, "
        f"mean roughness {info['material']['mean_roughness']:.2f}, {total:.1f} MB"
    )
    if not info["environment"]["present"]:
        print(f"no environment map: {info['environment']['reason']}")
    names = ", ".join(sorted(v for v in info["files"].values()))
    print(f"wrote {names} and asset.json in {out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="export a relightable asset (textured glTF with a PBR material + env map HDR)",
        description="Makes a relightable asset of a run: its TSDF mesh simplified to a face "
        "budget and UV-unwrapped, base colour / metallic-roughness / normal / occlusion "
        "textures baked from the model, in one glTF 2.0 .glb (+Y up), and the learned "
        "environment as equirectangular .exr and .hdr (see docs/asset.md).",
    )
    p.add_argument("run", help="run folder (with checkpoint.pt)")
    p.add_argument("--asset", required=True, metavar="DIR", help="folder to write the asset to")
    p.add_argument("--scene", help="the run's scene folder (default: from scene.json)")
    p.add_argument(
        "--faces", type=int, default=100_000, help="face budget of the mesh (default 100000)"
    )
    p.add_argument(
        "--texture-size",
        type=_power_of_two,
        default=1024,
        help="texture width and height, a power of two (default 1024)",
    )
    p.add_argument(
        "--views", type=int, default=32, help="training views the textures are baked from"
    )
    p.add_argument("--no-occlusion", action="store_true", help="no ambient-occlusion map")
    p.add_argument("--device", help="cpu or cuda (default: the run's, if available)")
    p.add_argument("--threads", type=int, help="CPU threads for the compiled kernels")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_export)
