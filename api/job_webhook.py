"""Which webhook a new job gets: the one in its request (checked), its key's default, or none.

A URL is checked where it is given: http(s) only (the schema), and, unless the operator
allows it (``GLINT_WEBHOOK_ALLOW_PRIVATE``), not ``localhost`` nor a literal loopback,
private, link-local or otherwise internal address (422 naming the field). Host names are
checked again at every delivery, when they are resolved (:mod:`api.service.webhook_guard`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session

from api.auth import Principal
from api.problems import ApiError, FieldError
from api.schemas import JobOut, WebhookIn
from api.service.models import ApiKey
from api.service.settings import Settings
from api.service.webhook_guard import ForbiddenAddressError, check_literal
from api.service.webhooks import new_secret


@dataclass(frozen=True)
class JobWebhook:
    """A webhook for a row (a job's or a key's): URL and secret, both None for none."""

    url: str | None = None
    secret: str | None = None
    made_secret: bool = False  # the server made the secret now: answer it, this once

    def columns(self) -> dict[str, Any]:
        return {"webhook_url": self.url, "webhook_secret": self.secret}


def checked(requested: WebhookIn, settings: Settings, field: str) -> JobWebhook:
    """``requested`` with its secret (one made when it has none), or 422 naming ``field``
    when its address is forbidden."""
    try:
        check_literal(requested.url, allow_private=settings.webhook_allow_private)
    except (ForbiddenAddressError, ValueError) as exc:
        message = str(exc)
        raise ApiError(
            422,
            "validation-error",
            f"invalid request: {field}: {message}",
            errors=[FieldError(field=field, message=message)],
        ) from None
    if requested.secret is not None:
        return JobWebhook(requested.url, requested.secret)
    return JobWebhook(requested.url, new_secret(), made_secret=True)


def job_webhook(
    session: Session, principal: Principal, requested: WebhookIn | None, settings: Settings
) -> JobWebhook:
    """The webhook of a job created now: its own, else its key's default, else none."""
    if requested is not None:
        return checked(requested, settings, "body.webhook.url")
    key = session.get(ApiKey, principal.key_id)
    if key is not None and key.webhook_url is not None:
        return JobWebhook(key.webhook_url, key.webhook_secret)
    return JobWebhook()


def with_made_secret(out: JobOut, hook: JobWebhook) -> JobOut:
    """The 201 response of a job: a secret the server made is in it (and nowhere else)."""
    if hook.made_secret and out.webhook is not None:
        out.webhook.secret = hook.secret
    return out
