"""Mesh extraction: wall time and peak memory at several grid resolutions.

    python -m bench.mesh_extraction --run RUN_DIR [--resolutions 256 512]
    python -m bench.mesh_extraction --scene SCENE_DIR --iterations 1000

Each resolution runs in a process of its own (peak RSS is per process), with the model
loaded and the rasteriser's kernels compiled (one view rendered) when the clock starts;
the figures are the extraction's wall time and the peak resident memory over that
baseline. Without ``--run`` a run is
trained first (``--scene``, default: a generated glossy sphere).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _status_mib(field: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _reset_peak() -> bool:
    """Start the peak-RSS high-water mark afresh (Linux: /proc/self/clear_refs)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _peak_mib() -> float:
    hwm = _status_mib("VmHWM")
    return hwm if hwm == hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def one(run: Path, resolution: int, color: str) -> dict:
    """Extract once in this process; the figures as a dict."""
    from core.meshing.mesh import mesh_model, model_depth_frame
    from core.model.run_folder import open_run

    model, scene = open_run(run)
    model_depth_frame(model, scene.train[0], color=color)  # compile the kernels first
    base = _status_mib("VmRSS")
    reset = _reset_peak()  # the peak of loading the scene is not the extraction's
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        _, info = mesh_model(model, scene.train, out, resolution=resolution, color=color)
        wall = time.perf_counter() - t0
    fu = info["fusion"]
    return {
        "resolution": resolution,
        "views": len(scene.train),
        "view_size": [scene.train[0].width, scene.train[0].height],
        "grid": fu["shape"],
        "band_voxels": fu["band_voxels"],
        "faces": info["faces"],
        "seconds": round(wall, 2),
        "stages": info["seconds"],
        "baseline_rss_mib": round(base, 1),
        "peak_rss_mib": round(_peak_mib(), 1),
        "peak_over_baseline_mib": round(_peak_mib() - base, 1),
        "peak_reset": reset,
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--run", type=Path, help="a finished run folder")
    p.add_argument("--scene", type=Path, help="scene to train first when --run is not given")
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("--resolutions", type=int, nargs="+", default=[256, 512])
    p.add_argument("--color", default="base", choices=("base", "radiance"))
    p.add_argument("--one", type=int, help=argparse.SUPPRESS)  # child process mode
    args = p.parse_args(argv)
    if args.one is not None:
        print(json.dumps(one(args.run, args.one, args.color)))
        return
    run = args.run
    if run is None:
        from core.config import config_from_dict
        from core.scene.synthetic import write_synthetic_scene
        from core.training.run import train_scene

        tmp = Path(tempfile.mkdtemp(prefix="glint-mesh-bench-"))
        scene = args.scene or write_synthetic_scene(tmp / "scene", "sphere", "glossy", size=128)
        run = tmp / "run"
        cfg = config_from_dict({"iterations": args.iterations, "outputs": {"mesh": False}})
        train_scene(scene, run, cfg, progress=True)
    rows = []
    for res in args.resolutions:
        cmd = [sys.executable, "-m", "bench.mesh_extraction", "--run", str(run)]
        cmd += ["--one", str(res), "--color", args.color]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    print()
    print("| resolution | grid | band voxels | faces | seconds | peak RSS MiB (over model) |")
    print("|---:|---|---:|---:|---:|---:|")
    for r in rows:
        grid = "×".join(str(x) for x in r["grid"])
        print(
            f"| {r['resolution']} | {grid} | {r['band_voxels']:,} | {r['faces']:,} | "
            f"{r['seconds']} | {r['peak_rss_mib']} ({r['peak_over_baseline_mib']:+}) |"
        )


if __name__ == "__main__":
    main()
