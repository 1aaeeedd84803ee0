"""The ``sfm`` phase of a training job on an images-only scene: photos in, a COLMAP scene
out (``core.scene.sfm.run_sfm``), then training on it as on any scene.

**Per job.** The recovered scene lives at ``jobs/{id}/scene`` beside the run folder, not
with the uploaded scene: its options are the job's, it goes when the job is deleted, and
two jobs on one capture never write the same objects, so no runner waits for another
or cleans up after one. A second job on the same photos runs SfM again (a minute or two
for ~100 photos on a CPU; docs/api.md).

**Idempotent** (delivery is at least once; the database decides): the job row's
``sfm.result`` is written only after the scene is whole in the store. A runner that
finds it set fetches that scene and trains; one that does not runs SfM again, replacing
whatever a crashed run left under the key.

**Artifacts**: the run folder gets copies of ``sfm_report.json``, ``sfm_report.txt`` and
``sparse/0/*.bin``; a failed SfM leaves its report there (when mapping ran) and fails
the job with the engine's message (which names the photos left out), made relative to
the upload. The uploaded photos are only ever read.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, TypeVar

from api.service.photos import find_photos
from api.service.store import ArtifactStore, job_scene_key, scene_files_key

log = logging.getLogger("glint.runner")

T = TypeVar("T")
Patiently = Callable[[str, Callable[[], T]], T]
SPARSE = "sparse/0"
REPORTS = ("sfm_report.json", "sfm_report.txt")  # core.scene.sfm.report's names
SUMMARY_KEYS = ("images", "registered", "unregistered", "rescued", "points3D", "warnings")


class PhaseReporter(Protocol):
    """What the phase needs of the runner's job reporter."""

    def update(self, values: dict[str, Any], *, now: bool = False) -> None: ...
    def should_stop(self) -> bool: ...


def scene_key(job_id: str, scene_id: str, sfm: dict[str, Any] | None) -> str:
    """The store key of the scene a training job trains on: its own SfM scene for an
    images-only scene, else the uploaded files."""
    return job_scene_key(job_id) if sfm is not None else scene_files_key(scene_id)


class SfmProgress:
    """SfM events → the job row: ``phase: "sfm"`` and a ``stage`` with the step's
    progress, throttled like training progress (each step's end is written at once)."""

    def __init__(self, reporter: PhaseReporter) -> None:
        self.reporter = reporter

    def __call__(self, event: dict[str, Any]) -> None:
        kind = event.get("type")
        if kind == "sfm":
            stage = {
                "name": "sfm",
                "step": str(event["stage"]),
                "done": int(event["done"]),
                "total": int(event["total"]),
                "elapsed_s": round(float(event["elapsed"]), 1),
            }
            self.reporter.update({"phase": "sfm", "stage": stage})
        elif kind == "sfm_stage":
            seconds = round(float(event["seconds"]), 2)
            step = {"name": "sfm", "step": str(event["stage"]), "seconds": seconds}
            self.reporter.update({"phase": "sfm", "stage": step}, now=True)


def recover_scene(
    store: ArtifactStore,
    job_id: str,
    scene_id: str,
    sfm: dict[str, Any],
    run_dir: Path,
    reporter: PhaseReporter,
    patiently: Patiently[Path],
) -> Path | None:
    """The job's COLMAP scene folder on this host, running SfM unless an earlier run of
    this job finished it; None when SfM was cancelled (or the runner is shutting down).

    Raises :class:`core.errors.GlintError` saying why SfM gave no scene.
    """
    key = job_scene_key(job_id)
    if sfm.get("result"):
        scene = patiently("fetch the SfM scene", lambda: store.local(key))
        if (scene / REPORTS[0]).is_file():
            copy_artifacts(scene, run_dir)
            return scene
        log.warning("job %s: the SfM scene is recorded but not in the store; again", job_id)
    reporter.update({"phase": "sfm", "stage": {"name": "sfm", "step": "start"}}, now=True)
    uploads = patiently("fetch the scene", lambda: store.local(scene_files_key(scene_id)))
    out = patiently("fetch the SfM scene", lambda: store.local(key))
    report = _run(uploads, out, sfm["options"], run_dir, reporter)
    if report is None:
        return None
    patiently("send the SfM scene", lambda: store.push(key))  # whole in the store, then
    copy_artifacts(out, run_dir)
    result = {**sfm, "result": summary(report)}  # ... recorded: the phase is done
    reporter.update({"phase": None, "stage": None, "sfm": result}, now=True)
    return out


def _run(
    uploads: Path, out: Path, options: dict[str, Any], run_dir: Path, reporter: PhaseReporter
) -> dict[str, Any] | None:
    """``run_sfm`` on the uploaded photos into ``out``; its report, or None if cancelled."""
    from core.errors import GlintError, SceneError
    from core.scene.sfm import SfmCancelledError, SfmError, SfmOptions, run_sfm
    from core.scene.sfm.report import write_report

    photos = find_photos(uploads)
    if photos is None:
        raise GlintError("the scene holds no photos for structure from motion")
    _clear_leftovers(out)
    for name in REPORTS:  # an earlier failed attempt's: this one writes its own
        (run_dir / name).unlink(missing_ok=True)
    try:
        result = run_sfm(
            photos.images,
            out,
            masks=photos.masks,
            options=SfmOptions(**options, overwrite=True),  # what is there is a crash's
            on_event=SfmProgress(reporter),
            should_stop=reporter.should_stop,
        )
    except SfmCancelledError:
        return None
    except (SfmError, SceneError) as exc:
        report = getattr(exc, "report", None)
        if report:
            write_report(run_dir, report)
        raise GlintError(_relative(str(exc), uploads)) from exc
    return result.report


def _clear_leftovers(out: Path) -> None:
    """Remove the temporary folders a killed SfM left beside ``out`` (``.scene.*``): the
    job's folder holds nothing else of that name."""
    if out.parent.is_dir():
        for p in out.parent.glob(f".{out.name}.*"):
            shutil.rmtree(p, ignore_errors=True)


def _relative(message: str, uploads: Path) -> str:
    """``message`` with the upload's local path cut to the paths users uploaded."""
    for root in (str(uploads.resolve()), str(uploads)):
        message = message.replace(root + os.sep, "").replace(root, "the upload")
    return message


def copy_artifacts(scene: Path, run_dir: Path) -> None:
    """The registration report and the sparse model into the run folder, as artifacts
    (each file whole before it appears: ``*.tmp`` is never listed nor pushed)."""
    names = list(REPORTS)
    names += [f"{SPARSE}/{p.name}" for p in sorted((scene / SPARSE).glob("*")) if p.is_file()]
    for name in names:
        src, dst = scene / name, run_dir / name
        if not src.is_file():
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        tmp = dst.with_name(dst.name + ".tmp")
        shutil.copyfile(src, tmp)
        os.replace(tmp, dst)


def summary(report: dict[str, Any]) -> dict[str, Any]:
    """What the job row keeps of the registration report (the rest is the artifact)."""
    out: dict[str, Any] = {k: report.get(k) for k in SUMMARY_KEYS}
    out["cameras"] = len(report.get("cameras") or [])
    out["mean_reprojection_error_px"] = report.get("mean_reprojection_error_px")
    out["seconds"] = (report.get("seconds") or {}).get("total")
    return _finite(out)


def _finite(values: dict[str, Any]) -> dict[str, Any]:
    """Floats that JSON columns accept (NaN/Inf → None)."""
    return {
        k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in values.items()
    }
