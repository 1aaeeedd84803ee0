"""``run_sfm``: a folder of photos in, a COLMAP scene folder out, all or nothing.

Everything happens in a temporary folder beside the output and is renamed into
place at the end, so a failure or a cancel leaves no half-written scene, and the
input photos are only ever read. Progress goes to ``on_event`` as plain dicts, like
training's events, so the CLI draws a bar and the service forwards them.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from core.scene.exposure import exposure_warning
from core.scene.sfm.colmap_lib import pycolmap
from core.scene.sfm.errors import SfmCancelledError, SfmError
from core.scene.sfm.export import drop_background_points, write_colmap_scene
from core.scene.sfm.features import extract, keypoint_counts, write_feature_masks
from core.scene.sfm.inputs import InputImage, collect_images
from core.scene.sfm.mapping import MAPPERS, map_images
from core.scene.sfm.matching import STRATEGIES, choose_strategy, match_pairs, plan_pairs
from core.scene.sfm.pairs import pairs_with
from core.scene.sfm.report import list_names, peak_rss_mb, report_text, write_report

Event = dict[str, Any]
STAGES = ("features", "matching", "mapping", "undistort")


@dataclass
class SfmOptions:
    """The choices of one SfM run (defaults: what docs/benchmarks.md measured best).

    ``matching``: ``auto`` (exhaustive up to 40 images, retrieval above), or forced.
    ``feature_masks``: keep keypoints off the object (needs masks); see
    docs/benchmarks.md for the measurement that decides its default.
    ``min_registered``: the fraction of images that must register, else SfmError.
    """

    matching: str = "auto"
    mapper: str = "incremental"
    feature_masks: bool = False
    min_registered: float = 0.8
    seed: int = 0
    overwrite: bool = False
    verbose: bool = False

    def __post_init__(self) -> None:
        if self.matching not in STRATEGIES:
            raise ValueError(f"matching must be one of {STRATEGIES}, got {self.matching!r}")
        if self.mapper not in MAPPERS:
            raise ValueError(f"mapper must be one of {MAPPERS}, got {self.mapper!r}")
        if not 0.0 <= self.min_registered <= 1.0:
            raise ValueError(f"min_registered must be in [0, 1], got {self.min_registered}")


@dataclass
class SfmResult:
    """Where the scene was written and its registration report."""

    scene: Path
    report: dict[str, Any] = field(default_factory=dict)

    def text(self) -> str:
        return report_text(self.report)


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise SfmError(f"output {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise SfmError(
            f"output folder {out} is not empty (glint sfm --overwrite, or "
            "SfmOptions(overwrite=True), replaces it)"
        )


def _stage_inputs(images: list[InputImage], folder: Path) -> dict[str, InputImage]:
    """Links with plain unique names (COLMAP's pair lists split on spaces) → inputs."""
    folder.mkdir(parents=True)
    staged = {}
    for k, im in enumerate(images):
        name = f"{k:06d}{im.path.suffix.lower()}"
        try:
            os.symlink(im.path.resolve(), folder / name)
        except OSError:  # no symlinks here (some Windows setups): copy instead
            shutil.copyfile(im.path, folder / name)
        staged[name] = im
    return staged


def _place(tmp_scene: Path, out: Path) -> None:
    """Move the finished scene into ``out`` (replacing what ``overwrite`` allowed)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists():
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        out.rename(old)
        tmp_scene.rename(out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp_scene.rename(out)


class _Progress:
    """Stage timing, events, cancellation checks."""

    def __init__(
        self, on_event: Callable[[Event], None] | None, should_stop: Callable[[], bool] | None
    ) -> None:
        self.on_event = on_event or (lambda e: None)
        self.should_stop = should_stop
        self.t0 = time.perf_counter()
        self.seconds: dict[str, float] = {}
        self.stage = ""
        self.started = self.t0

    def begin(self, stage: str) -> None:
        self.check()
        self.stage, self.started = stage, time.perf_counter()

    def step(self, done: int, total: int) -> None:
        self.on_event(
            {
                "type": "sfm",
                "stage": self.stage,
                "done": min(done, total),
                "total": total,
                "elapsed": time.perf_counter() - self.t0,
            }
        )
        self.check()

    def end(self, **details: Any) -> None:
        dt = time.perf_counter() - self.started
        self.seconds[self.stage] = self.seconds.get(self.stage, 0.0) + dt
        self.on_event({"type": "sfm_stage", "stage": self.stage, "seconds": dt, **details})

    def check(self) -> None:
        if self.should_stop and self.should_stop():
            where = self.stage or "start"
            raise SfmCancelledError(f"structure from motion cancelled during {where}")


def run_sfm(
    images: str | Path,
    out: str | Path,
    *,
    masks: str | Path | None = None,
    options: SfmOptions | None = None,
    on_event: Callable[[Event], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> SfmResult:
    """Recover cameras for the photos in ``images`` and write a COLMAP scene to ``out``.

    ``masks``: a folder of object masks named like the images; they are undistorted
    into ``out/masks`` for training and, with ``options.feature_masks``, keep keypoints
    off the object. Raises SceneError (an unreadable image or mask, named), SfmError
    (too few images, no overlap, too few registered: the report names the images
    left out) or SfmCancelledError; in every case ``out`` is left as it was.
    """
    opts = options or SfmOptions()
    out = Path(out)
    _check_out(out, opts.overwrite)
    inputs = collect_images(images, masks)
    if opts.feature_masks and masks is None:
        raise SfmError("feature masks need a mask folder (--masks)")
    prog = _Progress(on_event, should_stop)
    old_level = pycolmap.logging.minloglevel
    if not opts.verbose:
        pycolmap.logging.minloglevel = 2  # errors only: the events carry the progress
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with tempfile.TemporaryDirectory(prefix=f".{out.name}.sfm-", dir=out.parent) as tmp:
            return _run(inputs, out, Path(tmp), opts, prog, masks is not None)
    finally:
        pycolmap.logging.minloglevel = old_level


def _run(
    inputs: list[InputImage],
    out: Path,
    tmp: Path,
    opts: SfmOptions,
    prog: _Progress,
    has_masks: bool,
) -> SfmResult:
    work, scene = tmp / "work", tmp / "scene"
    staged = _stage_inputs(inputs, work / "images")
    names = list(staged)
    db = work / "database.db"

    prog.begin("features")
    fmask = None
    if opts.feature_masks:  # COLMAP looks feature masks up by the staged name
        fmask = write_feature_masks(_renamed(staged), work / "feature_masks")
    extract(db, work / "images", _renamed(staged), feature_mask_dir=fmask, on_step=prog.step)
    kp = keypoint_counts(db)
    prog.end(images=len(names))

    prog.begin("matching")
    strategy = choose_strategy(len(names), opts.matching)
    pairs, sim = plan_pairs(db, names, strategy)
    match_pairs(db, names, pairs, work / "pairs", on_step=prog.step)
    matched = set(pairs)
    prog.end(strategy=strategy, pairs=len(pairs))

    def match_more(missing: list[str]) -> None:
        if strategy == "exhaustive":
            return
        missing_idx = [names.index(n) for n in missing]
        # each left-out image against every other, within the first round's cost
        extra = pairs_with(missing_idx, len(names), matched, sim=sim, budget=len(pairs))
        match_pairs(db, names, extra, work / "pairs")
        matched.update(extra)

    prog.begin("mapping")
    registered_count = [0]

    def on_image() -> None:
        registered_count[0] += 1
        prog.step(registered_count[0], len(names))

    mapping = map_images(
        db,
        work / "images",
        names,
        work / "mapping",
        mapper=opts.mapper,
        seed=opts.seed,
        match_more=match_more,
        on_image=on_image,
        should_stop=prog.should_stop,
    )
    rec = mapping.reconstruction
    dropped = 0
    if has_masks and rec.num_reg_images() > 0:
        dropped = drop_background_points(
            rec, {n: im.mask for n, im in staged.items() if im.mask is not None}
        )
    prog.end(registered=rec.num_reg_images())

    report = _report(inputs, staged, mapping, db, kp, strategy, len(matched), opts, dropped)
    report["seconds"] = {**{k: round(v, 2) for k, v in prog.seconds.items()}}
    _check_registered(report, opts)

    prog.begin("undistort")
    written = write_colmap_scene(rec, staged, work / "images", scene, work, on_step=prog.step)
    prog.end()
    report.update(cameras=written["cameras"], points3D=written["points3D"])
    report["seconds"] = {k: round(v, 2) for k, v in prog.seconds.items()}
    report["seconds"]["total"] = round(time.perf_counter() - prog.t0, 2)
    report["peak_rss_mb"] = round(peak_rss_mb(), 1)
    write_report(scene, report)
    prog.check()
    _place(scene, out)
    prog.on_event({"type": "sfm_done", "scene": str(out), "report": report})
    return SfmResult(out, report)


def _renamed(staged: dict[str, InputImage]) -> list[InputImage]:
    """The inputs under their staged names (what COLMAP reads)."""
    return [InputImage(n, im.path, im.size, im.camera, im.mask) for n, im in staged.items()]


def _verified_pairs(db: Path) -> int:
    d = pycolmap.Database.open(db)
    try:
        _, inliers = d.read_two_view_geometry_num_inliers()
        return int(sum(1 for n in inliers if n > 0))
    finally:
        d.close()


def _report(
    inputs: list[InputImage],
    staged: dict[str, InputImage],
    mapping: Any,
    db: Path,
    keypoints: dict[str, int],
    strategy: str,
    n_pairs: int,
    opts: SfmOptions,
    dropped: int,
) -> dict[str, Any]:
    import numpy as np

    rec = mapping.reconstruction
    reg = mapping.registered
    kp = np.array([keypoints.get(n, 0) for n in staged], dtype=float)
    return {
        "images": len(inputs),
        "registered": len(reg),
        "unregistered": sorted(staged[n].name for n in staged if n not in reg),
        "rescued": sorted(staged[n].name for n in mapping.rescued),
        "models": mapping.model_sizes,
        "matching": {
            "strategy": strategy,
            "pairs": n_pairs,
            "verified_pairs": _verified_pairs(db),
        },
        "mapper": opts.mapper,
        "feature_masks": opts.feature_masks,
        "keypoints": {"min": int(kp.min()), "median": float(np.median(kp))},
        "points3D": int(rec.num_points3D()),
        "background_points_dropped": dropped,
        "mean_reprojection_error_px": (
            float(rec.compute_mean_reprojection_error()) if rec.num_reg_images() else None
        ),
        "warnings": [w for w in [exposure_warning([im.path for im in inputs])] if w],
        "pycolmap": pycolmap.__version__,
    }


def _check_registered(report: dict[str, Any], opts: SfmOptions) -> None:
    n, k = report["images"], report["registered"]
    report["peak_rss_mb"] = round(peak_rss_mb(), 1)
    miss = report["unregistered"]
    if report["matching"]["verified_pairs"] == 0:
        raise SfmError(
            f"no overlap: no two of the {n} images share enough matching features "
            "(photograph the object from viewpoints that overlap, ~60-80 % per step)",
            unregistered=miss,
            report=report,
        )
    if k == 0:
        raise SfmError(
            f"no reconstruction could start: none of the {report['matching']['verified_pairs']} "
            f"matching image pairs among the {n} images sees enough of the scene from far "
            "enough apart; the photos overlap too little (take more, ~10-20° apart)",
            unregistered=miss,
            report=report,
        )
    if k < 3 or k < opts.min_registered * n:
        raise SfmError(
            f"registered {k} of {n} images (at least {opts.min_registered:.0%} needed); "
            f"not registered: {list_names(miss)}",
            unregistered=miss,
            report=report,
        )
