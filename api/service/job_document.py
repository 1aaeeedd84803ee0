"""A job as ``GET /v1/jobs/{id}`` shows it, as plain values: one mapping for both readers.

The API's response model (``api.views.job_out``) and the body of a webhook event
(:mod:`api.service.webhooks`, which the service layer writes without the API's
schemas) are built from :func:`job_document`, so an event carries exactly the job a
client would have read.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from sqlalchemy import Row

from api.service.models import Job, JobState, WebhookDelivery

DELIVERIES_SHOWN = 10  # a job shows its latest deliveries; GET /v1/jobs/{id}/webhooks lists all
SUMMARY_FIELDS = ("id", "event", "state", "attempts", "last_status", "created_at", "delivered_at")


def job_progress(job: Job | Row[Any]) -> float:
    if job.state == JobState.SUCCEEDED:
        return 1.0
    if job.total_iterations <= 0:
        return 0.0
    return max(0.0, min(1.0, job.iteration / job.total_iterations))


def delivery_summary(delivery: WebhookDelivery | Row[Any]) -> dict[str, Any]:
    """What a job shows of one of its webhook deliveries."""
    return {name: getattr(delivery, name) for name in SUMMARY_FIELDS}


def webhook_document(
    job: Job | Row[Any], deliveries: Iterable[WebhookDelivery | Row[Any]] | None = None
) -> dict[str, Any] | None:
    """The job's ``webhook``: its URL and latest deliveries, newest first (never the
    secret); None without one. ``deliveries`` defaults to an ORM job's own."""
    if job.webhook_url is None:
        return None
    if deliveries is None:
        deliveries = job.webhook_deliveries if isinstance(job, Job) else ()
    latest = sorted(deliveries, key=lambda d: (d.created_at, d.id), reverse=True)
    return {
        "url": job.webhook_url,
        "deliveries": [delivery_summary(d) for d in latest[:DELIVERIES_SHOWN]],
    }


def job_document(
    job: Job | Row[Any], deliveries: Iterable[WebhookDelivery | Row[Any]] | None = None
) -> dict[str, Any]:
    """Every field of a job's API representation, from its ORM object or a row of the
    jobs table (a row's ``deliveries`` are passed in: it has no relationship)."""
    return {
        "id": job.id,
        "kind": job.kind,
        "parent_id": job.parent_id,
        "scene_id": job.scene_id,
        "state": job.state,
        "cancel_requested": job.cancel_requested,
        "phase": job.phase,
        "iteration": job.iteration,
        "total_iterations": job.total_iterations,
        "progress": job_progress(job),
        "n_gaussians": job.n_gaussians,
        "loss": job.loss,
        "metrics": job.metrics,
        "elapsed_s": job.elapsed_s,
        "eta_s": job.eta_s,
        "time_budget_s": (job.config or {}).get("time_budget"),
        "time_left_s": (job.metrics or {}).get("time_left"),
        "error": job.error,
        "attempts": job.attempts,
        "version": job.version,
        "config": job.config,
        "plan": job.plan,
        "stage": job.stage,
        "sfm": job.sfm,
        "webhook": webhook_document(job, deliveries),
        "created_at": job.created_at,
        "updated_at": job.updated_at,
        "started_at": job.started_at,
        "finished_at": job.finished_at,
    }
