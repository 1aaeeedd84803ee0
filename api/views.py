"""Database rows → response models (the routes and the event stream share these)."""

from __future__ import annotations

from typing import Any

from sqlalchemy import Row, func, select
from sqlalchemy.orm import Session

from api.schemas import JobOut, SceneOut
from api.service.models import Job, JobState, Scene, SceneFile


def scene_totals(session: Session, scene_ids: list[str]) -> dict[str, tuple[int, int]]:
    """{scene id: (file count, total bytes)} in one query."""
    if not scene_ids:
        return {}
    rows = session.execute(
        select(SceneFile.scene_id, func.count(), func.coalesce(func.sum(SceneFile.size), 0))
        .where(SceneFile.scene_id.in_(scene_ids))
        .group_by(SceneFile.scene_id)
    )
    return {sid: (int(n), int(total)) for sid, n, total in rows}


def scene_out(scene: Scene, totals: tuple[int, int] = (0, 0)) -> SceneOut:
    return SceneOut(
        id=scene.id,
        name=scene.name,
        state=scene.state,  # type: ignore[arg-type]
        format=scene.format,
        file_count=totals[0],
        total_bytes=totals[1],
        report=scene.report,  # type: ignore[arg-type]
        last_error=scene.last_error,  # type: ignore[arg-type]
        created_at=scene.created_at,
        updated_at=scene.updated_at,
        committed_at=scene.committed_at,
    )


def scene_out_one(session: Session, scene: Scene) -> SceneOut:
    return scene_out(scene, scene_totals(session, [scene.id]).get(scene.id, (0, 0)))


def job_progress(job: Job | Row[Any]) -> float:
    if job.state == JobState.SUCCEEDED:
        return 1.0
    if job.total_iterations <= 0:
        return 0.0
    return max(0.0, min(1.0, job.iteration / job.total_iterations))


def job_out(job: Job | Row[Any]) -> JobOut:
    """The response model of a job, from its ORM object or a row of the jobs table."""
    return JobOut(
        id=job.id,
        kind=job.kind,  # type: ignore[arg-type]
        parent_id=job.parent_id,
        scene_id=job.scene_id,
        state=job.state,  # type: ignore[arg-type]
        cancel_requested=job.cancel_requested,
        phase=job.phase,
        iteration=job.iteration,
        total_iterations=job.total_iterations,
        progress=job_progress(job),
        n_gaussians=job.n_gaussians,
        loss=job.loss,
        metrics=job.metrics,
        elapsed_s=job.elapsed_s,
        eta_s=job.eta_s,
        time_budget_s=(job.config or {}).get("time_budget"),
        time_left_s=(job.metrics or {}).get("time_left"),
        error=job.error,
        attempts=job.attempts,
        version=job.version,
        config=job.config,
        plan=job.plan,
        stage=job.stage,
        sfm=job.sfm,
        created_at=job.created_at,
        updated_at=job.updated_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
    )
