"""The ``Idempotency-Key`` header on the creating routes (scenes, jobs, meshes).

Route code asks :func:`replayed` first (an id the key already created, to answer
instead of creating), creates its rows, then :func:`commit_or_replay` records the key
with them in one commit. See :mod:`api.service.idempotency` for the rules.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Header, Response
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from api.auth import Principal
from api.problems import ApiError, FieldError
from api.service import idempotency

REPLAYED_HEADER = "Idempotent-Replayed"

IdempotencyKey = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        max_length=idempotency.MAX_KEY_LENGTH,
        description="any unique string (a UUID): a retry with the same key and body answers "
        "the object the first request created instead of creating another",
    ),
]


def _checked(key: str) -> str:
    if not idempotency.valid_key(key):
        raise ApiError(
            422,
            "validation-error",
            "Idempotency-Key must be 1-255 printable ASCII characters",
            errors=[FieldError(field="header.idempotency-key", message="1-255 printable ASCII")],
        )
    return key


def replayed(
    session: Session,
    principal: Principal,
    route: str,
    key: str | None,
    body: Any,
    response: Response,
) -> str | None:
    """The id this key already created on ``route`` (marking the response as a replay)."""
    if key is None:
        return None
    try:
        found = idempotency.find(
            session, principal.owner, route, _checked(key), idempotency.body_digest(body)
        )
    except idempotency.KeyReusedError:
        raise ApiError(
            422,
            "idempotency-key-reused",
            f"Idempotency-Key '{key}' was already used on {route} with a different body; "
            "use a new key for a new request",
            errors=[FieldError(field="header.idempotency-key", message="used with another body")],
        ) from None
    if found is not None:
        response.headers[REPLAYED_HEADER] = "true"
    return found


def commit_or_replay(
    session: Session,
    principal: Principal,
    route: str,
    key: str | None,
    body: Any,
    resource_id: str,
    response: Response,
) -> str | None:
    """Commit the new rows with the key's record; on losing a race to a request with the
    same key, roll back and return the winner's id (None: ours was committed)."""
    if key is None:
        session.commit()
        return None
    digest = idempotency.body_digest(body)
    idempotency.remember(session, principal.owner, route, key, digest, resource_id)
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        winner = replayed(session, principal, route, key, body, response)
        if winner is None:
            raise
        return winner
    return None
