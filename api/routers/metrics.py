"""A job's error against run time, as JSON, while it trains and after.

The rows of the run's ``metrics.jsonl`` (one per evaluation: iteration, training and
evaluation seconds, phase, Gaussians, held-out PSNR/SSIM, geometry error or
consistency, Chamfer distance at its probe points), so a client can draw the curves
the report draws. ``offset`` pages through them; a client following a running job
asks again from ``offset = total``. ``points`` thins a long series evenly (first and
last rows always kept) instead.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Query
from pydantic import Field

from api.deps import PrincipalDep, SessionDep, SettingsDep, StoreDep
from api.pages import Limit, Offset
from api.problems import responses
from api.routers.jobs import owned_job
from api.schemas import Page
from api.service.runner import json_safe
from api.service.store import job_run_key
from api.strict_json import StrictJsonRoute
from core.outputs.report import read_metrics

router = APIRouter(prefix="/jobs", tags=["jobs"], route_class=StrictJsonRoute)
JobId = Annotated[str, Path(max_length=40, description="job id (job_...)")]

METRICS_FILE = "metrics.jsonl"


class MetricsPage(Page[dict[str, Any]]):
    geometry: str | None = Field(
        description="'error' (scored against the scene's ground truth), 'consistency' "
        "(no ground truth: depth-normal and multi-view consistency) or null (no rows yet)"
    )
    time_budget_s: float | None = Field(description="the job's time budget, if it has one")


def thin(rows: list[dict[str, Any]], points: int) -> list[dict[str, Any]]:
    """At most ``points`` rows, evenly spaced, the first and last kept."""
    if len(rows) <= points:
        return rows
    if points == 1:
        return rows[-1:]
    step = (len(rows) - 1) / (points - 1)
    return [rows[round(i * step)] for i in range(points)]


@router.get(
    "/{job_id}/metrics",
    response_model=MetricsPage,
    responses=responses(401, 404, 422),
    summary="A job's held-out image and geometry error against run time",
)
def job_metrics(
    job_id: JobId,
    principal: PrincipalDep,
    session: SessionDep,
    store: StoreDep,
    settings: SettingsDep,
    limit: Limit = 500,
    offset: Offset = 0,
    points: Annotated[
        int | None,
        Query(ge=1, le=10_000, description="thin the whole series evenly to this many rows"),
    ] = None,
) -> MetricsPage:
    job = owned_job(session, principal, job_id)
    budget = (job.config or {}).get("time_budget")
    session.rollback()  # done with the database; the file read may take a moment
    # a bucket's copy is fetched again when it changed (runners send it at every row)
    path = store.local_file(f"{job_run_key(job_id)}/{METRICS_FILE}")
    rows = read_metrics(path) if path is not None else []
    geometry = next((r["geometry"] for r in reversed(rows) if r.get("geometry")), None)
    limit = min(limit, settings.page_size_max)
    total = len(rows)
    if points is not None:
        rows, offset, limit = thin(rows, points), 0, points
    else:
        rows = rows[offset : offset + limit]
    return MetricsPage(
        items=[json_safe(r) for r in rows],
        total=total,
        limit=limit,
        offset=offset,
        geometry=geometry,
        time_budget_s=budget,
    )
