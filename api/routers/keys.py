"""Health (no key needed) and API keys: who am I, list, create another, revoke.

Keys are created on the command line (``glint keys create NAME``) for a new owner;
an owner's ``admin`` key can mint more here (to rotate without downtime, or to hand out
``read``-only keys) and revoke any key of the owner. Any key may revoke itself. A new
key's secret appears once, in the creation response. Scopes: see :mod:`api.auth`.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Path, Request, Response
from sqlalchemy import select, text

from api import auth
from api.deps import (
    SCOPE_EXTRA,
    DatabaseDep,
    JsonBody,
    PrincipalDep,
    SessionDep,
    SettingsDep,
    forbidden,
)
from api.job_webhook import checked
from api.pages import Limit, Offset, page_rows
from api.problems import ApiError, not_found, responses
from api.schemas import Health, KeyCreate, KeyCreated, KeyOut, KeyWebhookOut, Me, Page, WebhookIn
from api.service.models import ApiKey
from api.strict_json import StrictJsonRoute

router = APIRouter(tags=["keys"], route_class=StrictJsonRoute)


@router.get(
    "/health",
    response_model=Health,
    responses=responses(503),
    summary="Liveness; database and artifact store reachability (no key needed)",
)
def health(database: DatabaseDep, request: Request) -> Health:
    """200 when the database and the store both answer; 503 ``database-unavailable`` or
    ``store-unavailable`` (unreachable, credentials refused, no bucket) within seconds."""
    from core import __version__

    try:
        with database.read() as s:
            s.execute(text("SELECT 1"))
    except Exception as exc:
        raise ApiError(
            503, "database-unavailable", f"database unreachable: {type(exc).__name__}"
        ) from None
    request.app.state.store_probe.require(fresh=True)  # StoreUnavailableError: 503
    return Health(status="ok", database="ok", store="ok", version=__version__)


@router.get(
    "/keys/me", response_model=Me, responses=responses(401), summary="The caller's owner and key"
)
def me(principal: PrincipalDep, session: SessionDep) -> Me:
    return Me(
        owner=principal.owner,
        key_id=principal.key_id,
        name=principal.name,
        scope=principal.scope,  # type: ignore[arg-type]
        webhook_url=session.scalar(select(ApiKey.webhook_url).where(ApiKey.id == principal.key_id)),
    )


@router.put(
    "/keys/me/webhook",
    response_model=KeyWebhookOut,
    responses=responses(400, 401, 403, 415, 422),
    dependencies=[JsonBody],
    summary="Set the default webhook of jobs created with this key (the secret is shown once)",
)
def set_key_webhook(
    body: WebhookIn, principal: PrincipalDep, session: SessionDep, settings: SettingsDep
) -> KeyWebhookOut:
    """Jobs created with this key and no ``webhook`` of their own get this one (copied onto
    the job when it is created: changing it later leaves existing jobs as they are)."""
    hook = checked(body, settings, "body.url")
    row = session.get(ApiKey, principal.key_id)
    if row is None:  # revoked and gone between the lookup and now
        raise not_found("key", principal.key_id)
    row.webhook_url, row.webhook_secret = hook.url, hook.secret
    session.commit()
    return KeyWebhookOut(url=row.webhook_url, secret=row.webhook_secret)


@router.delete(
    "/keys/me/webhook",
    status_code=204,
    response_class=Response,
    responses=responses(401, 403),
    summary="Remove this key's default webhook (jobs that have it keep theirs)",
)
def delete_key_webhook(principal: PrincipalDep, session: SessionDep) -> Response:
    row = session.get(ApiKey, principal.key_id)
    if row is not None and row.webhook_url is not None:
        row.webhook_url = row.webhook_secret = None
        session.commit()
    return Response(status_code=204)


@router.get(
    "/keys",
    response_model=Page[KeyOut],
    responses=responses(401, 422),
    summary="List my owner's keys (oldest first)",
)
def list_keys(
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    limit: Limit = 50,
    offset: Offset = 0,
) -> Page[KeyOut]:
    limit = min(limit, settings.page_size_max)
    query = (
        select(ApiKey).where(ApiKey.owner == principal.owner).order_by(ApiKey.created_at, ApiKey.id)
    )
    rows, total = page_rows(session, query, limit, offset)
    items = [KeyOut.model_validate(r) for r in rows]
    return Page[KeyOut](items=items, total=total, limit=limit, offset=offset)


@router.post(
    "/keys",
    status_code=201,
    response_model=KeyCreated,
    responses=responses(400, 401, 403, 415, 422),
    dependencies=[JsonBody],
    openapi_extra={SCOPE_EXTRA: "admin"},
    summary="Create another key for my owner (admin keys only; the key is shown once)",
)
def create_key(body: KeyCreate, principal: PrincipalDep, session: SessionDep) -> KeyCreated:
    row, key = auth.create_key(session, principal.owner, body.name, body.scope)
    session.commit()
    return KeyCreated(**KeyOut.model_validate(row).model_dump(), key=key)


@router.delete(
    "/keys/{key_id}",
    status_code=204,
    response_class=Response,
    responses=responses(401, 403, 404, 422),
    openapi_extra={SCOPE_EXTRA: "read"},  # any key may revoke itself; others: admin
    summary="Revoke a key of my owner: the one in use (any key), or another (admin keys)",
)
def revoke_key(
    key_id: Annotated[str, Path(max_length=40)],
    request: Request,
    principal: PrincipalDep,
    session: SessionDep,
) -> Response:
    row = session.scalar(select(ApiKey).where(ApiKey.id == key_id, ApiKey.owner == principal.owner))
    if row is None:
        raise not_found("key", key_id)
    if key_id != principal.key_id and not auth.allows(principal.scope, "admin"):
        raise forbidden(principal, "admin", f"revoking key '{key_id}' (not the one in use)")
    if row.revoked_at is None:
        row.revoked_at = datetime.now(UTC)
        session.commit()
    return Response(status_code=204)
