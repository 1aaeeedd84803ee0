"""A job's webhook deliveries: one per end of the job, with where each one stands.

The job itself shows its webhook URL and latest deliveries (``GET /v1/jobs/{id}``); this
lists them all, with the last error and the next attempt of each. Keys' default webhooks
are set in :mod:`api.routers.keys`; sending is :mod:`api.service.webhook_dispatch`.
"""

from __future__ import annotations

from fastapi import APIRouter
from sqlalchemy import select

from api.deps import PrincipalDep, SessionDep, SettingsDep
from api.pages import Limit, Offset, page_rows
from api.problems import responses
from api.routers.jobs import AUTH, JobId, owned_job
from api.schemas import Page, WebhookDeliveryOut
from api.service.models import WebhookDelivery
from api.strict_json import StrictJsonRoute

router = APIRouter(prefix="/jobs", tags=["webhooks"], route_class=StrictJsonRoute)


@router.get(
    "/{job_id}/webhooks",
    response_model=Page[WebhookDeliveryOut],
    responses=responses(*AUTH, 422),
    summary="List a job's webhook deliveries (newest first): state, attempts, last error",
)
def list_deliveries(
    job_id: JobId,
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    limit: Limit = 50,
    offset: Offset = 0,
) -> Page[WebhookDeliveryOut]:
    job = owned_job(session, principal, job_id)
    limit = min(limit, settings.page_size_max)
    query = (
        select(WebhookDelivery)
        .where(WebhookDelivery.job_id == job.id)
        .order_by(WebhookDelivery.created_at.desc(), WebhookDelivery.id.desc())
    )
    rows, total = page_rows(session, query, limit, offset)
    items = [WebhookDeliveryOut.model_validate(r, from_attributes=True) for r in rows]
    return Page[WebhookDeliveryOut](items=items, total=total, limit=limit, offset=offset)
