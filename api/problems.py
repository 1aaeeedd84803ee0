"""RFC 9457 problem details: one exception type, one response model, the handlers.

Every error the API returns is ``application/problem+json`` with ``type`` (a stable
``urn:glint:problem:<slug>`` that clients can switch on), ``title``, ``status``,
``detail``, ``instance`` (the request path) and, where fields are at fault, ``errors``:
a list naming each field (a dotted path into the request or a scene file) and what is
wrong with it. FastAPI's default handlers are replaced so validation errors, unknown
routes and wrong methods use the same shape.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Mount

from api.service.store import StoreUnavailableError

PROBLEM_JSON = "application/problem+json"
log = logging.getLogger("glint.api")

TITLES = {
    400: "Bad request",
    401: "Unauthorized",
    403: "Forbidden",
    404: "Not found",
    405: "Method not allowed",
    406: "Not acceptable",
    409: "Conflict",
    411: "Length required",
    412: "Precondition failed",
    413: "Content too large",
    415: "Unsupported media type",
    416: "Range not satisfiable",
    422: "Unprocessable content",
    429: "Too many requests",
    431: "Request header fields too large",
    500: "Internal server error",
    501: "Not implemented",
    503: "Service unavailable",
}

# The ``type`` slug of errors raised as plain HTTP exceptions (by Starlette, FastAPI or a
# mounted app), one per status, so every error carries a stable type.
STATUS_SLUGS = {
    400: "bad-request",
    401: "unauthorized",
    403: "forbidden",
    404: "not-found",
    405: "method-not-allowed",
    406: "not-acceptable",
    409: "conflict",
    411: "length-required",
    412: "precondition-failed",
    413: "too-large",
    414: "uri-too-long",
    415: "unsupported-media-type",
    416: "range-not-satisfiable",
    422: "validation-error",
    429: "too-many-requests",
    431: "headers-too-large",
    500: "internal-error",
    501: "not-implemented",
    503: "service-unavailable",
}
METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


class FieldError(BaseModel):
    """One thing wrong with one field of the request (or of an uploaded scene file)."""

    field: str | None = Field(
        None, description="dotted path, e.g. 'body.config.iterations' or 'frames[2].file_path'"
    )
    message: str
    file: str | None = Field(None, description="scene file at fault, relative to the scene")


class Problem(BaseModel):
    """An RFC 9457 problem detail."""

    type: str = Field("about:blank", examples=["urn:glint:problem:not-found"])
    title: str
    status: int
    detail: str | None = None
    instance: str | None = None
    errors: list[FieldError] | None = None


class ApiError(Exception):
    """Raise anywhere in a request to answer with a problem detail."""

    def __init__(
        self,
        status: int,
        slug: str,
        detail: str,
        *,
        errors: list[FieldError] | None = None,
        headers: dict[str, str] | None = None,
        title: str | None = None,
        extensions: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.slug = slug
        self.detail = detail
        self.errors = errors
        self.headers = headers
        self.title = title or TITLES.get(status, "Error")
        # RFC 9457 extension members a client acts on (e.g. an upload's current "offset")
        self.extensions = extensions


def not_found(what: str, ident: str) -> ApiError:
    """The same answer for 'does not exist' and 'belongs to someone else'."""
    return ApiError(404, "not-found", f"{what} '{ident}' not found")


def problem_response(
    request: Request,
    status: int,
    slug: str,
    detail: str | None,
    *,
    title: str | None = None,
    errors: list[FieldError] | None = None,
    headers: dict[str, str] | None = None,
    extensions: dict[str, Any] | None = None,
) -> JSONResponse:
    body = Problem(
        type=f"urn:glint:problem:{slug}",
        title=title or TITLES.get(status, "Error"),
        status=status,
        detail=detail,
        instance=request.url.path,
        errors=errors,
    )
    content = body.model_dump(exclude_none=True)
    for name, value in (extensions or {}).items():
        content.setdefault(name, value)  # never overrides a standard member
    return JSONResponse(
        content,
        status_code=status,
        media_type=PROBLEM_JSON,
        headers=headers,
    )


def _loc(loc: tuple[Any, ...] | list[Any]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def field_errors(errors: list[dict[str, Any]], prefix: tuple[Any, ...] = ()) -> list[FieldError]:
    """Pydantic error dicts as :class:`FieldError` with dotted field paths."""
    return [FieldError(field=_loc(prefix + tuple(e["loc"])), message=e["msg"]) for e in errors]


async def _api_problem(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ApiError)
    return problem_response(
        request,
        exc.status,
        exc.slug,
        exc.detail,
        title=exc.title,
        errors=exc.errors,
        headers=exc.headers,
        extensions=exc.extensions,
    )


async def _validation(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errs = list(exc.errors())
    bad_json = [e for e in errs if e.get("type") == "json_invalid"]
    if bad_json:
        ctx = bad_json[0].get("ctx") or {}
        where = ctx.get("error", "")
        return problem_response(
            request,
            400,
            "malformed-json",
            f"request body is not valid JSON{': ' + str(where) if where else ''}",
            errors=[FieldError(field="body", message="malformed JSON")],
        )
    fields = field_errors(errs)
    first = fields[0] if fields else None
    detail = f"invalid request: {first.field}: {first.message}" if first else "invalid request"
    if len(fields) > 1:
        detail += f" (and {len(fields) - 1} more)"
    return problem_response(request, 422, "validation-error", detail, errors=fields)


def allowed_methods(request: Request, also: str = "") -> list[str]:
    """Every method some route serves at the request's path (for ``Allow``).

    Starlette names only the methods of the first route whose path matched, but one
    path often has several routes (``GET`` and ``POST /v1/scenes``): each route is
    asked whether it would take the path with each method. Mounted apps (static files)
    match any method, so they speak for themselves through ``also`` (their ``Allow``).
    """
    methods = {m.strip().upper() for m in also.split(",") if m.strip()}
    for method in METHODS:
        scope = {
            "type": "http",
            "method": method,
            "path": request.url.path,
            "root_path": request.scope.get("root_path", ""),
            "headers": [],
            "query_string": b"",
            "app": request.app,
        }
        for route in request.app.router.routes:
            if not isinstance(route, Mount) and route.matches(scope)[0] == Match.FULL:
                methods.add(method)
                break
    return [m for m in METHODS if m in methods]


async def _http(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    detail = exc.detail if isinstance(exc.detail, str) else None
    headers = dict(getattr(exc, "headers", None) or {})
    if exc.status_code == 404 and detail == "Not Found":
        detail = f"no route for {request.method} {request.url.path}"
    elif exc.status_code == 405:
        allow = allowed_methods(request, headers.pop("Allow", headers.pop("allow", "")))
        headers["Allow"] = ", ".join(allow)
        detail = f"{request.method} is not allowed on {request.url.path}; use {headers['Allow']}"
    slug = STATUS_SLUGS.get(exc.status_code, f"http-{exc.status_code}")
    return problem_response(request, exc.status_code, slug, detail, headers=headers or None)


async def _store_unavailable(request: Request, exc: Exception) -> JSONResponse:
    """The artifact store is down (unreachable, credentials refused, no bucket): 503 at
    once, whichever route found out; the request changed nothing it could not undo."""
    log.warning("store unavailable on %s %s: %s", request.method, request.url.path, exc)
    return problem_response(
        request, 503, "store-unavailable", f"artifact store unavailable: {exc}; try again later"
    )


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return problem_response(request, 500, "internal-error", "an unexpected error occurred")


def install_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ApiError, _api_problem)
    app.add_exception_handler(RequestValidationError, _validation)
    app.add_exception_handler(StarletteHTTPException, _http)
    app.add_exception_handler(StoreUnavailableError, _store_unavailable)
    app.add_exception_handler(Exception, _unexpected)


def responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses=`` entries declaring problem+json bodies for ``codes``."""
    descriptions = {
        400: "Malformed request (e.g. JSON syntax)",
        401: "Missing or invalid API key",
        403: "The key's scope does not allow it",
        404: "Not found (or owned by another key's owner)",
        409: "Conflicts with the resource's state",
        413: "Upload larger than the configured limits",
        415: "Unsupported content type",
        416: "Range not satisfiable",
        422: "Invalid content (fields named in `errors`)",
        503: "A dependency (database, queue, artifact store) is unavailable",
    }
    return {
        code: {
            "model": Problem,
            "description": descriptions.get(code, TITLES.get(code, "Error")),
            "content": {PROBLEM_JSON: {"schema": {"$ref": "#/components/schemas/Problem"}}},
        }
        for code in codes
    }
