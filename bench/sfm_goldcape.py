"""Structure from motion measured against known poses (issue 23): goldcape_llff by default.

    python -m bench.sfm_goldcape [--scene ../shared/data/goldcape_llff] [--out runs/sfm_bench]
                                 [--configs baseline,glint] [--repeat 1] [--subset N | --first N]

Runs each configuration on the scene's photos alone, each in a child process (so its
peak memory is its own: the parent never loads pixels or torch, whose peak a child
would inherit across exec on Linux), in alternation when ``--repeat`` > 1 (machine
drift hits all alike), then aligns the recovered cameras of the largest model to the scene's own
poses with a similarity transform (Umeyama, on camera centres) and prints one
Markdown row per run: images registered (and models found), median/max rotation
error (degrees), median/max camera-centre error (% of the rig's extent: the largest
distance between two true camera centres), wall time, CPU time (user + system of the
child: steadier than wall time on a shared machine), stage times and peak RSS.

Configurations:

* ``baseline``: plain pycolmap defaults, as the issue describes its reference: SIFT
  (one camera per image), exhaustive matching, incremental mapping;
* ``glint``: ``run_sfm`` as ``glint sfm IMAGES --masks MASKS`` runs it (defaults);
  its peak RSS includes the ~300 MB that importing Glint (torch) costs, reported apart;
* ``glint_feature_masks``: the same with keypoints kept off the object (``--feature-masks``);
* ``glint_exhaustive`` / ``glint_retrieval``: the matching forced either way;
* ``glint_global``: the global mapper.

Any scene Glint loads works (``--scene``): its photos are linked into one folder under
their view names, its masks (or alpha) written beside them. ``--subset N`` uses N
photos spread evenly over the set, ``--first N`` the first N in name order (the same
density of viewpoints: for the matching threshold).
Rows and the full per-run records are also written to ``OUT/results.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from datetime import date
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_SCENE = Path(__file__).resolve().parents[2] / "shared" / "data" / "goldcape_llff"
CONFIGS = (
    "baseline",
    "glint",
    "glint_feature_masks",
    "glint_exhaustive",
    "glint_retrieval",
    "glint_global",
)


# -- child: one SfM run ------------------------------------------------------------------


def _baseline(images: Path, out: Path) -> dict[str, Any]:
    import pycolmap

    pycolmap.logging.minloglevel = 2
    db = out / "database.db"
    t: dict[str, float] = {}
    t0 = time.perf_counter()
    pycolmap.extract_features(db, images)
    t["features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pycolmap.match_exhaustive(db)
    t["matching"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    recs = pycolmap.incremental_mapping(db, images, out / "sparse")
    t["mapping"] = time.perf_counter() - t0
    sizes = sorted((r.num_reg_images() for r in recs.values()), reverse=True)
    best = max(recs, key=lambda k: recs[k].num_reg_images()) if recs else None
    return {
        "seconds": t,
        "models": sizes,
        "model_dir": str(out / "sparse" / str(best)) if best is not None else None,
        "reprojection_px": recs[best].compute_mean_reprojection_error() if recs else None,
    }


def _glint(images: Path, masks: Path | None, out: Path, config: str) -> dict[str, Any]:
    from core.scene.sfm import SfmOptions, run_sfm

    imports_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # torch et al.

    kw: dict[str, Any] = {}
    if config == "glint_feature_masks":
        kw["feature_masks"] = True
    elif config in ("glint_exhaustive", "glint_retrieval"):
        kw["matching"] = config.removeprefix("glint_")
    elif config == "glint_global":
        kw["mapper"] = "global"
    res = run_sfm(images, out / "scene", masks=masks, options=SfmOptions(**kw))
    r = res.report
    return {
        "seconds": r["seconds"],
        "models": r["models"],
        "model_dir": str(out / "scene" / "sparse" / "0"),
        "reprojection_px": r["mean_reprojection_error_px"],
        "imports_rss_mb": imports_mb,
        "report": r,
    }


def child(config: str, images: Path, masks: Path | None, out: Path, truth: Path) -> None:
    """One SfM run, measured, then scored (scoring loads torch: after the measurement)."""
    t0 = time.perf_counter()
    failed = None
    try:
        rec = _baseline(images, out) if config == "baseline" else _glint(images, masks, out, config)
    except Exception as exc:  # a configuration that fails is a row, not a crash
        failed = f"{type(exc).__name__}: {str(exc)[:300]}"
        rec = {"seconds": {}, "models": [], "model_dir": None}
    ru = resource.getrusage(resource.RUSAGE_SELF)
    rec.update(
        wall=time.perf_counter() - t0, cpu=ru.ru_utime + ru.ru_stime, maxrss_mb=ru.ru_maxrss / 1024
    )
    poses = {k: np.array(v) for k, v in json.loads(truth.read_text()).items()}
    rec.update(score(rec, poses, len(poses)), failed=failed)
    print("RESULT " + json.dumps(rec, default=float))


def prepare(scene: Path, out: Path, n: int | None, first: int | None) -> None:
    """The input folders and ``truth.json`` (in a child: loading the scene's pixels must
    not raise the peak memory that the configurations' children inherit)."""
    truth = scene_inputs(scene, out, n, first)[2]
    (out / "truth.json").write_text(json.dumps({k: v.tolist() for k, v in truth.items()}))


# -- inputs, truth, scoring, table -------------------------------------------------------


def scene_inputs(
    scene: Path, out: Path, n: int | None, first: int | None = None
) -> tuple[Path, Path | None, dict]:
    """A folder of the scene's photos (and one of masks), linked under flat view names,
    and each view's true world-to-camera 4x4 by that name; ``n``: an even subset,
    ``first``: the first ones.

    Masks are the scene's mask files, or its alpha written out (rendered scenes).
    """
    from core.scene.formats import load_scene
    from core.scene.formats.common import evenly
    from core.scene.formats.writers import flat_name
    from core.scene.imageio import write_image

    views = load_scene(scene, test_every=0).views
    views = sorted(views, key=lambda v: v.path.name if v.path else v.name)
    if n:
        views = evenly(views, n)
    if first:
        views = views[:first]
    for sub in ("images", "masks"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    truth = {}
    has_masks = all(v.mask is not None for v in views)
    for v in views:
        name = flat_name(v.name)
        os.symlink(v.path.resolve(), out / "images" / f"{name}{v.path.suffix}")
        if has_masks:
            write_image(out / "masks" / f"{name}.png", v.mask, encode_srgb=False)
        truth[name] = v.camera.world_to_cam.numpy()
    return out / "images", (out / "masks" if has_masks else None), truth


def recovered_poses(model_dir: Path) -> dict[str, np.ndarray]:
    from core.scene.formats.colmap import image_pose, read_model

    model = read_model(model_dir)
    return {
        Path(im.name).stem: image_pose(im, file=model.files["images"])
        for im in model.images.values()
    }


def score(rec: dict[str, Any], truth: dict[str, np.ndarray], n_images: int) -> dict[str, Any]:
    from core.scene.sfm.align import pose_errors

    got = recovered_poses(Path(rec["model_dir"])) if rec.get("model_dir") else {}
    row: dict[str, Any] = {"registered": len(got), "images": n_images}
    if len(got) >= 3:
        s = pose_errors(got, truth).summary()
        row.update(
            rot_med=s["rotation_deg_median"],
            rot_max=s["rotation_deg_max"],
            ctr_med_pct=100 * s["center_rel_median"],
            ctr_max_pct=100 * s["center_rel_max"],
        )
    return row


def fmt_row(config: str, rec: dict[str, Any]) -> str:
    row = rec
    if rec.get("failed"):
        return (
            f"| {config} | failed: {rec['failed']} | | | {rec['wall']:.1f} | {rec['cpu']:.1f} | | |"
        )

    def f(k: str, d: int) -> str:
        return f"{row[k]:.{d}f}" if k in row else "–"

    stages = ", ".join(f"{k} {v:.0f}" for k, v in rec["seconds"].items() if k != "total")
    return (
        f"| {config} | {row['registered']}/{row['images']} {rec['models']} | "
        f"{f('rot_med', 3)} / {f('rot_max', 2)} | {f('ctr_med_pct', 3)} / {f('ctr_max_pct', 2)} | "
        f"{rec['wall']:.1f} | {rec['cpu']:.1f} | {stages} | {rec['maxrss_mb']:.0f}"
        + (f" ({rec['imports_rss_mb']:.0f} imports)" if "imports_rss_mb" in rec else "")
        + " |"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    ap.add_argument("--out", type=Path, default=Path("runs/sfm_bench"))
    ap.add_argument("--configs", default="baseline,glint")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--subset", type=int, default=None)
    ap.add_argument("--first", type=int, default=None)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args()
    inputs = a.out / "input"
    if a.child == "prepare":
        prepare(a.scene, inputs, a.subset, a.first)
        return
    masks = inputs / "masks" if any((inputs / "masks").glob("*")) else None
    if a.child:
        child(a.child, inputs / "images", masks, a.out / a.child, inputs / "truth.json")
        return
    configs = [c.strip() for c in a.configs.split(",") if c.strip()]
    for c in configs:
        if c not in CONFIGS:
            raise SystemExit(f"unknown config {c!r}; expected some of {', '.join(CONFIGS)}")
    shutil.rmtree(a.out, ignore_errors=True)
    a.out.mkdir(parents=True)
    base = [sys.executable, "-m", "bench.sfm_goldcape", "--scene", str(a.scene)]
    base += ["--out", str(a.out)] + (["--subset", str(a.subset)] if a.subset else [])
    base += ["--first", str(a.first)] if a.first else []
    subprocess.run([*base, "--child", "prepare"], check=True)
    n_images = len(json.loads((inputs / "truth.json").read_text()))
    print(
        f"# SfM on {a.scene.name} ({n_images} photos), {date.today()}, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at start\n"
    )
    print(
        "| config | registered [models] | rotation error median / max (deg) | "
        "centre error median / max (% of rig) | wall (s) | CPU (s) | stages (s) | peak RSS (MB) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    results = []
    for r in range(a.repeat):
        for c in configs:
            shutil.rmtree(a.out / c, ignore_errors=True)
            (a.out / c).mkdir(parents=True)
            proc = subprocess.run([*base, "--child", c], capture_output=True, text=True)
            line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
            if proc.returncode or not line:
                print(f"| {c} | crashed: {proc.stderr.strip().splitlines()[-1:]} |")
                continue
            rec = json.loads(line[0].removeprefix("RESULT "))
            print(fmt_row(c, rec), flush=True)
            results.append({"config": c, "repeat": r, **rec})
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")
    (a.out / "results.json").write_text(json.dumps(results, indent=2, default=float))


if __name__ == "__main__":
    main()
