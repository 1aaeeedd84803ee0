"""The one function that runs a training job: shared by the local queue and the worker.

``run_job(job_id, settings)`` is idempotent and safe under at-least-once delivery:

* **Claim**: one conditional ``UPDATE`` moves the job ``queued → running`` and stamps
  a fresh random ``lease``. Zero rows updated means someone else has it, or it is
  finished or cancelled: return without doing anything. A ``running`` job whose runner
  died (heartbeat older than ``stale_after_s``) is not claimed here: the reaper
  (``api.service.recovery``) counts the death, puts it back to ``queued`` and sends it.
* **Fencing**: every later write says ``WHERE id = :id AND lease = :lease``. A runner
  that lost its lease (it stalled and was taken over) writes nothing and stops at its
  next ``should_stop`` check.
* **Progress** goes to the database at most every ``progress_interval_s`` (≤ 2/s by
  default) plus the last iteration; a heartbeat thread keeps ``heartbeat_at`` fresh
  through loading and export, when no progress events come.
* **Cancel**: ``should_stop`` reads ``cancel_requested`` (at most every
  ``cancel_poll_s``); the trainer saves a checkpoint and the job ends ``cancelled``.
* **Shutdown**: a runner that must stop (``stop`` event set) gets the same
  checkpoint-and-return, but the job goes back to ``queued`` for the next runner.
* **Resume**: the run folder lives in the store (``jobs/{id}/run``); ``train_scene``
  always resumes from its checkpoint, so a re-queued job continues where it stopped.
* **Photos without poses**: a job whose row carries ``sfm`` first recovers the cameras
  into ``jobs/{id}/scene`` (:mod:`api.service.sfm_phase`; done once, recorded in the row).
* **Store**: the runner trains in a local copy of the run folder (the folder itself with
  a directory store; a copy in the cache with a bucket, fetched from it first, so a job
  resumed on another host finds its checkpoint) and sends it back at every checkpoint and
  evaluation and at the end. A store outage is ridden out with backoff (``store_retry_s``).
* **End**: the run folder is sent to the store, *then* its artifacts are registered and
  the state set to ``succeeded``, ``cancelled`` or ``failed`` (with the error) in one
  transaction: no artifact row names an object that is not whole in the store. The same
  transaction records the job's webhook event, if it has a webhook.
"""

from __future__ import annotations

import hashlib
import logging
import math
import mimetypes
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import Update, delete, func, select, update

from api.service.db import Database, database_for
from api.service.models import Artifact, Job, JobKind, JobState
from api.service.settings import Settings
from api.service.sfm_phase import recover_scene, scene_key
from api.service.store import (
    ArtifactStore,
    StoreUnavailableError,
    is_staging,
    job_run_key,
    job_scene_key,
    make_store,
    retrying,
    scene_files_key,
)
from api.service.webhooks import record_job_end

if TYPE_CHECKING:  # the engine is imported lazily, where a job needs it
    import trimesh

    from core.asset.export import AssetOptions
    from core.model.trained import TrainedModel
    from core.scene.views import View

log = logging.getLogger("glint.runner")

CONTENT_TYPES = {
    ".exr": "image/x-exr",
    ".ply": "application/x-ply",
    ".pt": "application/octet-stream",
    ".md": "text/markdown; charset=utf-8",
    ".jsonl": "application/jsonl",
    ".json": "application/json",
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".txt": "text/plain; charset=utf-8",
    ".obj": "model/obj",
    ".glb": "model/gltf-binary",
    ".hdr": "image/vnd.radiance",  # Radiance RGBE (the asset's environment)
}


def content_type(name: str) -> str:
    ext = os.path.splitext(name)[1].lower()
    return CONTENT_TYPES.get(ext) or mimetypes.guess_type(name)[0] or "application/octet-stream"


def json_safe(value: Any) -> Any:
    """``value`` with NaN/Inf replaced by None (JSON columns and responses reject them)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, int | str | bool) or value is None:
        return value
    try:  # numpy / torch scalars
        return json_safe(float(value))
    except (TypeError, ValueError):
        return str(value)


def _now() -> datetime:
    return datetime.now(UTC)


def claim(database: Database, job_id: str, worker: str) -> str | None:
    """Take the queued job for this runner; the new lease, or None if it is not claimable.

    ``error`` is kept: on a queued job it can only be the reaper's note on why its last
    runner is gone (``... requeued (attempt 2 of 3)``), which stays true while this run
    lasts; the run's end writes its own.
    """
    lease = uuid.uuid4().hex
    now = _now()
    with database.write() as s:
        res = s.execute(
            update(Job)
            .where(Job.id == job_id, Job.state == JobState.QUEUED)
            .values(
                state=JobState.RUNNING,
                lease=lease,
                worker=worker,
                heartbeat_at=now,
                attempts=Job.attempts + 1,
                started_at=func.coalesce(Job.started_at, now),
                updated_at=now,
                version=Job.version + 1,
            )
            .execution_options(synchronize_session=False)
        )
        if res.rowcount != 1:
            return None
        # the run folder is about to change: old registrations would describe other bytes
        s.execute(delete(Artifact).where(Artifact.job_id == job_id))
        return lease


class _JobReporter:
    """Turns trainer events into throttled, lease-fenced updates of the job row."""

    def __init__(
        self,
        database: Database,
        job_id: str,
        lease: str,
        settings: Settings,
        stop: threading.Event | None = None,
    ) -> None:
        self.database = database
        self.stop = stop
        self.interrupted = False  # stopped because this process is shutting down
        self.job_id = job_id
        self.lease = lease
        self.interval = settings.progress_interval_s
        self.cancel_poll = settings.cancel_poll_s
        self.pending: dict[str, Any] = {}
        self.last_write = 0.0
        self.last_poll = 0.0
        self.cancelled = False
        self.lost = False
        self.own_progress = False  # stage events drive iteration/total (mesh jobs)
        self.last_metrics: dict[str, Any] = {}  # the latest evaluation row
        self.sync: Callable[[], object] | None = None  # sends the run folder to the store
        self.lock = threading.Lock()

    def _fenced(self) -> Update:
        return update(Job).where(
            Job.id == self.job_id, Job.lease == self.lease, Job.state == JobState.RUNNING
        )

    def on_event(self, event: dict[str, Any]) -> None:
        kind = event.get("type")
        if kind == "progress":
            self.pending.update(
                iteration=int(event["iteration"]),
                total_iterations=int(event["total"]),
                phase=str(event["phase"]),
                n_gaussians=int(event["n_gaussians"]),
                loss=json_safe(event.get("loss")),
                elapsed_s=json_safe(event.get("elapsed")),
                eta_s=json_safe(event.get("eta")),
            )
            if event.get("time_left") is not None:  # a time-budgeted run: keep it current
                self.last_metrics["time_left"] = json_safe(event["time_left"])
                self.pending["metrics"] = dict(self.last_metrics)
            last = event["iteration"] >= event["total"]
            if last or time.monotonic() - self.last_write >= self.interval:
                self.flush()
        elif kind == "eval":
            m = {k: v for k, v in event.items() if k != "type"}
            self.last_metrics = json_safe(m)
            self.pending["metrics"] = dict(self.last_metrics)
        elif kind == "plan":
            self.pending["plan"] = json_safe(event.get("plan"))
        elif kind == "stage":
            stage = {k: event[k] for k in ("name", "step", "done", "total") if k in event}
            self.pending["stage"] = json_safe(stage)
            if self.own_progress:  # a mesh job: the stage is its progress
                self.pending.update(
                    phase=str(event.get("name")),
                    iteration=int(event.get("overall_done", 0)),
                    total_iterations=int(event.get("overall_total", 0)),
                )
            if time.monotonic() - self.last_write >= self.interval:
                self.flush()
        elif kind == "resumed":
            self.pending["iteration"] = int(event["iteration"])
            log.info("job %s: resumed from iteration %d", self.job_id, event["iteration"])
            self.flush()
        if kind in ("checkpoint", "eval") and self.sync is not None:
            self.sync()  # a new checkpoint or metrics row: into the store, for resumes/readers

    def update(self, values: dict[str, Any], *, now: bool = False) -> None:
        """Queue column values for the job row: written now, or once the interval passed
        (phases outside the trainer report through this: :mod:`api.service.sfm_phase`)."""
        with self.lock:
            self.pending.update(values)
        if now or time.monotonic() - self.last_write >= self.interval:
            self.flush()

    def flush(self) -> None:
        """Write pending progress now (a failed write is logged and retried next time)."""
        with self.lock:
            if not self.pending or self.lost:
                return
            values = dict(self.pending)
            now = _now()
            try:
                with self.database.write() as s:
                    res = s.execute(
                        self._fenced().values(
                            **values, heartbeat_at=now, updated_at=now, version=Job.version + 1
                        )
                    )
                    if res.rowcount == 0:
                        self.lost = True
            except Exception:
                log.exception("job %s: progress write failed", self.job_id)
                return
            self.pending.clear()
            self.last_write = time.monotonic()

    def heartbeat(self) -> None:
        with self.lock:
            try:
                with self.database.write() as s:
                    res = s.execute(self._fenced().values(heartbeat_at=_now()))
                    if res.rowcount == 0:
                        self.lost = True
            except Exception:
                log.exception("job %s: heartbeat failed", self.job_id)

    def should_stop(self) -> bool:
        """True on shutdown, once a cancel was requested, or the lease was lost."""
        if self.cancelled or self.lost or self.interrupted:
            return True
        if self.stop is not None and self.stop.is_set():
            self.interrupted = True
            return True
        now = time.monotonic()
        if now - self.last_poll < self.cancel_poll:
            return False
        self.last_poll = now
        try:
            with self.database.read() as s:
                row = s.execute(
                    select(Job.cancel_requested, Job.lease, Job.state).where(Job.id == self.job_id)
                ).one_or_none()
        except Exception:
            log.exception("job %s: cancel check failed", self.job_id)
            return False
        if row is None or row.lease != self.lease or row.state != JobState.RUNNING:
            self.lost = True
        elif row.cancel_requested:
            self.cancelled = True
        return self.cancelled or self.lost


class _Heartbeat(threading.Thread):
    def __init__(self, reporter: _JobReporter, period: float) -> None:
        super().__init__(name=f"glint-heartbeat-{reporter.job_id}", daemon=True)
        self.reporter = reporter
        self.period = period
        self.stopped = threading.Event()

    def run(self) -> None:
        while not self.stopped.wait(self.period):
            self.reporter.heartbeat()


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def collect_artifacts(run_dir: Path) -> list[dict[str, Any]]:
    """Every regular file in the run folder, with size, hash and content type."""
    out = []
    if not run_dir.is_dir():
        return out
    for p in sorted(run_dir.rglob("*")):
        rel = p.relative_to(run_dir)
        if p.is_file() and not p.is_symlink() and not is_staging(rel.as_posix()):
            name = rel.as_posix()
            out.append(
                {
                    "name": name,
                    "size": p.stat().st_size,
                    "sha256": _sha256(p),
                    "content_type": content_type(name),
                }
            )
    return out


def _finish(
    reporter: _JobReporter, state: str, error: str | None, artifacts: list[dict[str, Any]]
) -> bool:
    """Final state and artifacts in one fenced transaction; False if the lease was lost."""
    now = _now()
    values: dict[str, Any] = dict(reporter.pending)
    values.update(
        state=state,
        error=error,
        finished_at=now,
        updated_at=now,
        heartbeat_at=now,
        lease=None,
        version=Job.version + 1,
    )
    if state != JobState.CANCELLED:
        values["cancel_requested"] = False
    if state == JobState.SUCCEEDED:
        values["eta_s"] = 0.0
    with reporter.database.write() as s:
        res = s.execute(reporter._fenced().values(**values))
        if res.rowcount == 0:
            return False
        s.execute(delete(Artifact).where(Artifact.job_id == reporter.job_id))
        for a in artifacts:
            s.add(Artifact(job_id=reporter.job_id, **a))
        record_job_end(s, reporter.job_id)  # its webhook event, if it has one
    return True


def _release(reporter: _JobReporter) -> bool:
    """Hand an interrupted job back: ``queued`` again, to be resumed by the next runner."""
    now = _now()
    values: dict[str, Any] = dict(reporter.pending)
    values.update(state=JobState.QUEUED, lease=None, updated_at=now, version=Job.version + 1)
    with reporter.database.write() as s:
        return s.execute(reporter._fenced().values(**values)).rowcount == 1


def _public_error(exc: BaseException, *roots: Path) -> str:
    """The error for users: GlintErrors as they are, others with their type; no paths of
    the store or its local copies."""
    from core.errors import GlintError

    if isinstance(exc, StoreUnavailableError):
        msg = f"artifact store unavailable: {exc}"
    else:
        msg = str(exc) if isinstance(exc, GlintError) else f"{type(exc).__name__}: {exc}"
    for root in roots:
        for prefix in (str(root) + os.sep, str(root)):
            msg = msg.replace(prefix, "")
    return msg[:4000]


def placed_config(config: dict[str, Any], device: str | None) -> tuple[dict[str, Any], str | None]:
    """The job config this runner trains with, and a note when it changed the backend.

    ``device`` (a worker's ``--device``) replaces the config's: where a job trains is
    the runner's business. The backend follows the device: a job submitted with
    ``backend: cuda`` that lands on a CPU worker (or ``cpu`` on a GPU one) would
    otherwise fail on its first render, so such a backend gives way to ``auto``.
    """
    if not device:
        return config, None
    from core.render.raster import fallback_backend

    config = {**config, "device": device}
    _, why = fallback_backend(str(config.get("backend", "auto")), device)
    if why is None:
        return config, None
    config["backend"] = "auto"
    return config, f"{why}; this worker trains with 'auto' on {device}"


MAX_SKIPPED_FRACTION = 0.5  # a run that skipped more of its steps than this failed


def skipped_steps_error(skipped: int, steps: int) -> str | None:
    """Why a run that skipped most of its steps failed, or None when it trained."""
    if steps <= 0 or skipped <= steps * MAX_SKIPPED_FRACTION:
        return None
    return (
        f"{skipped} of {steps} steps were skipped (non-finite loss or gradients): the model "
        "did not train; lower the learning rates or loss weights, or check the scene's images"
    )


def _skipped_steps(last_metrics: dict[str, Any], iteration: int, run_dir: Path) -> tuple[int, int]:
    """(skipped steps, steps) of a finished run: from its last metrics, or, for a run
    resumed after it had finished (no step trained this time), from metrics.jsonl."""
    if "skipped_steps" not in last_metrics:
        from core.outputs.report import read_metrics

        rows = [r for r in read_metrics(run_dir / "metrics.jsonl") if "skipped_steps" in r]
        last_metrics = rows[-1] if rows else {}
    return int(last_metrics.get("skipped_steps") or 0), iteration


def _run_training(
    config: dict[str, Any], scene_dir: Path, run_dir: Path, reporter: _JobReporter
) -> str:
    """Train (or resume) into ``run_dir``: its export and mesh phase included.

    A run whose steps were mostly skipped by the trainer's NaN guard raises: its model
    is its initial state, and the job fails saying so instead of succeeding.
    """
    from core.config import config_from_dict
    from core.errors import GlintError
    from core.training.run import train_scene

    cfg = config_from_dict(config, source="job config")
    result, _summary = train_scene(
        scene_dir,
        run_dir,
        cfg,
        on_event=reporter.on_event,
        should_stop=reporter.should_stop,
        resume=True,
    )
    if result.status == "succeeded":
        why = skipped_steps_error(*_skipped_steps(result.last_metrics, result.iteration, run_dir))
        if why:
            raise GlintError(why)
    return result.status


def _run_mesh(
    config: dict[str, Any],
    parent_run: Path,
    scene_dir: Path,
    out: Path,
    reporter: _JobReporter,
    device: str | None,
    max_resolution: int,
) -> str:
    """Extract a mesh from the parent job's checkpoint into ``out`` (all files or none),
    then, when the request has an ``asset``, bake the relightable asset of that mesh.

    The asset is baked from the mesh this job just made (its resolution, colour,
    simplification), not from the parent's own mesh.ply, which ``asset_run`` would
    take; so the runner opens the run once and calls ``mesh_model`` and
    ``export_asset`` itself. A failed or cancelled bake keeps the finished mesh: its
    files stay this job's artifacts, and a failure's error says why there is no asset.
    """
    from core.asset.export import AssetOptions
    from core.meshing.mesh import MeshCancelledError, mesh_model, stage_progress
    from core.model.run_folder import open_run

    config = dict(config)
    asset = config.pop("asset", None)  # not a mesh_model parameter
    options = None if asset is None else AssetOptions(**asset)  # validated by the API
    if options is not None:
        options.check()  # before the mesh: a bad option costs nothing
    chain = _StageChain(reporter.on_event)
    out.mkdir(parents=True, exist_ok=True)
    model, scene = open_run(parent_run, scene_dir, device=device)
    views = scene.train
    try:
        mesh, _ = mesh_model(
            model,
            views,
            out,
            max_resolution=max_resolution,
            **config,  # the MeshCreate request the API validated: mesh_model's parameters
            progress=stage_progress(
                reporter.on_event if options is None else chain.first, len(views)
            ),
            should_stop=reporter.should_stop,
        )
    except MeshCancelledError:
        return "cancelled"
    if options is None:
        return "succeeded"
    return _bake_asset(model, views, out, mesh, options, chain, reporter)


def _bake_asset(
    model: TrainedModel,
    views: Sequence[View],
    out: Path,
    mesh: trimesh.Trimesh,
    options: AssetOptions,
    chain: _StageChain,
    reporter: _JobReporter,
) -> str:
    """The asset of the mesh just made into ``out`` (see :func:`_run_mesh`)."""
    from core.asset.export import ASSET_FILES, AssetError, asset_progress, export_asset
    from core.meshing.mesh import MeshCancelledError

    try:
        export_asset(
            model,
            views,
            out,
            mesh,
            options=options,
            progress=asset_progress(chain.second),
            should_stop=reporter.should_stop,
        )
    except Exception as exc:
        for name in ASSET_FILES:  # a half-written asset is no asset; the mesh stays
            (out / name).unlink(missing_ok=True)
        if isinstance(exc, MeshCancelledError):  # AssetCancelledError: the job was cancelled
            return "cancelled"
        if isinstance(exc, AssetError):
            raise AssetError(
                f"the mesh is made (its files are this job's artifacts), the asset is not: {exc}"
            ) from exc
        raise
    return "succeeded"


class _StageChain:
    """The stage events of a mesh job that also bakes an asset, as one progress.

    ``mesh_model`` and ``export_asset`` each count their own steps from zero: passed
    through as they are, the job's progress would reach 100 % at the mesh's end and then
    fall back. Here the mesh fills the first half of the job's count and the asset the
    second (its steps rescaled), so the progress only grows.
    """

    def __init__(self, on_event: Callable[[dict[str, Any]], None]) -> None:
        self.on_event = on_event
        self.span = 1  # the mesh's overall_total: the size of each half

    def first(self, event: dict[str, Any]) -> None:
        if event.get("overall_total"):
            self.span = int(event["overall_total"])
            event = {**event, "overall_total": 2 * self.span}
        self.on_event(event)

    def second(self, event: dict[str, Any]) -> None:
        if event.get("overall_total"):
            done = int(event.get("overall_done", 0)) * self.span // int(event["overall_total"])
            event = {**event, "overall_done": self.span + done, "overall_total": 2 * self.span}
        self.on_event(event)


# what a mesh job needs of its parent's run folder (not its renders, meshes, reports)
PARENT_FILES = ("checkpoint.pt", "config.json", "plan.json", "outputs.json", "scene.json")


def run_job(
    job_id: str,
    settings: Settings,
    *,
    database: Database | None = None,
    worker: str | None = None,
    stop: threading.Event | None = None,
    device: str | None = None,
    store: ArtifactStore | None = None,
) -> str | None:
    """Claim and run one job; returns its final state, or None if it was not ours to run.

    ``device`` (a worker's ``--device``) replaces the job config's torch device: where
    a job trains is the runner's business, not the submitter's.

    ``stop`` is the runner's shutdown signal: when it is set the trainer checkpoints
    and returns, and the job goes back to ``queued`` (not ``cancelled``: nobody asked)
    for the next runner to resume; the return value is then ``"queued"``.
    """
    database = database or database_for(settings.db_url)
    store = store or make_store(settings, "runner")
    worker = worker or f"{socket.gethostname()}:{os.getpid()}:{threading.get_ident()}"
    lease = claim(database, job_id, worker)
    if lease is None:
        log.info("job %s: not claimable (taken, finished or cancelled)", job_id)
        return None
    with database.read() as s:
        job = s.get(Job, job_id)
        assert job is not None
        config, scene_id = dict(job.config), job.scene_id
        kind, parent_id, sfm = job.kind, job.parent_id, job.sfm
        if parent_id is not None:  # a mesh job reads the scene its parent trained on
            parent_row = s.get(Job, parent_id)
            sfm = parent_row.sfm if parent_row is not None else None
    if kind == JobKind.TRAIN:
        config, note = placed_config(config, device)
        if note:
            log.warning("job %s: %s", job_id, note)
    reporter = _JobReporter(database, job_id, lease, settings, stop)
    reporter.own_progress = kind == JobKind.MESH
    heartbeat = _Heartbeat(reporter, settings.heartbeat_s)
    heartbeat.start()
    run_key = job_run_key(job_id)

    def patiently(what: str, op: Callable[[], Any]) -> Any:
        return retrying(
            op,
            what=f"job {job_id}: {what}",
            patience_s=settings.store_retry_s,
            give_up=lambda: reporter.lost,
        )

    state, error, store_down = JobState.FAILED, None, False
    run_dir: Path | None = None
    try:
        try:
            run_dir = patiently("fetch the run folder", lambda: store.local(run_key))
            reporter.sync = lambda: patiently("send the run folder", lambda: store.push(run_key))
            if kind == JobKind.MESH:
                assert parent_id is not None
                parent_key = job_run_key(parent_id)
                scene_dir = patiently(
                    "fetch the scene", lambda: store.local(scene_key(parent_id, scene_id, sfm))
                )
                parent = patiently(
                    "fetch the parent's checkpoint", lambda: store.local(parent_key, PARENT_FILES)
                )
                status = _run_mesh(
                    config,
                    parent,
                    scene_dir,
                    run_dir,
                    reporter,
                    device,
                    settings.mesh_max_resolution,
                )
            elif sfm is not None:  # photos without poses: the sfm phase first
                found = recover_scene(store, job_id, scene_id, sfm, run_dir, reporter, patiently)
                if found is None:  # cancelled, or this runner is shutting down
                    status = "cancelled"
                else:
                    status = _run_training(config, found, run_dir, reporter)
            else:
                scene_dir = patiently(
                    "fetch the scene", lambda: store.local(scene_files_key(scene_id))
                )
                status = _run_training(config, scene_dir, run_dir, reporter)
            state = JobState.SUCCEEDED if status == "succeeded" else JobState.CANCELLED
        except Exception as exc:
            log.exception("job %s failed", job_id)
            store_down = isinstance(exc, StoreUnavailableError)
            error = _public_error(exc, settings.store_root, settings.cache_root)
        if run_dir is not None and not store_down and not reporter.lost:
            try:  # whatever the outcome: the next runner resumes from what is sent here
                patiently("send the run folder", lambda: store.push(run_key))
            except StoreUnavailableError as exc:
                store_down, state = True, JobState.FAILED
                error = _public_error(exc, settings.store_root, settings.cache_root)
    finally:
        heartbeat.stopped.set()
        heartbeat.join()
    try:
        return _settle(reporter, job_id, state, error, run_dir if not store_down else None)
    finally:
        if kind == JobKind.MESH and parent_id is not None:
            store.drop_local(job_run_key(parent_id))
            if sfm is not None:
                store.drop_local(job_scene_key(parent_id))
        if not reporter.lost:  # a runner that took over may be working in it
            store.drop_local(run_key)  # the store has it; a bucket's local copy is spent
            if sfm is not None and kind == JobKind.TRAIN:
                store.drop_local(job_scene_key(job_id))


def _settle(
    reporter: _JobReporter, job_id: str, state: str, error: str | None, run_dir: Path | None
) -> str | None:
    """Record how the run ended: released to the queue, or finished with its artifacts
    (``run_dir`` None: the run folder could not be stored, so none are listed)."""
    if reporter.lost:
        log.warning("job %s: lease lost; leaving the job to its new runner", job_id)
        return None
    if reporter.interrupted and state == JobState.CANCELLED and not reporter.cancelled:
        if _release(reporter):
            log.info(
                "job %s: interrupted by shutdown at iteration %s; re-queued",
                job_id,
                reporter.pending.get("iteration"),
            )
            return JobState.QUEUED
        return None
    try:
        artifacts = collect_artifacts(run_dir) if run_dir is not None else []
    except OSError as exc:
        artifacts, state = [], JobState.FAILED
        error = f"cannot read run folder: {exc}"
    if not _finish(reporter, state, error, artifacts):
        log.warning("job %s: lease lost before finishing", job_id)
        return None
    log.info("job %s: %s", job_id, state)
    return state
