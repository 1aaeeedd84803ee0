"""Database rows → response models (the routes and the event stream share these)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from sqlalchemy import Row, func, select
from sqlalchemy.orm import Session

from api.schemas import JobOut, SceneOut
from api.service.job_document import job_document
from api.service.models import Job, Scene, SceneFile, WebhookDelivery


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


def job_out(
    job: Job | Row[Any], deliveries: Iterable[WebhookDelivery | Row[Any]] | None = None
) -> JobOut:
    """The response model of a job, from its ORM object or a row of the jobs table (with
    its webhook deliveries, which a row does not carry)."""
    return JobOut(**job_document(job, deliveries))
