"""One HTTP session to the API: base URL, key, timeouts, and when a call may be retried.

A call is retried (with exponential backoff and jitter) only where repeating it cannot
do something twice: a connection that was never made (nothing was sent), or a call that
is idempotent — ``GET``/``HEAD``/``PUT``/``DELETE``, a chunk ``PATCH`` (the server checks
its offset), and a ``POST`` that carries an ``Idempotency-Key`` (the server answers a
repeat with what the first one made). Errors come back as :mod:`glint_client.errors`.
"""

from __future__ import annotations

import random
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any, BinaryIO

import httpx

from glint_client._version import __version__
from glint_client.errors import ServerUnreachable, from_response

# PATCH here is the upload chunk, which the server accepts only at its current offset
IDEMPOTENT_METHODS = frozenset({"GET", "HEAD", "PUT", "DELETE", "OPTIONS", "PATCH"})
# 503 queue-unavailable means the job *was* created (and kept): never repeat that blindly
RETRY_STATUSES = frozenset({429, 502, 503, 504})
NO_RETRY_SLUGS = frozenset({"queue-unavailable"})


def api_root(url: str) -> str:
    """``http://host:8000``, ``http://host:8000/`` and ``http://host:8000/v1`` all name
    the same server; paths are then written ``/v1/...``."""
    url = url.strip().rstrip("/")
    if not url:
        raise ValueError("no server URL given (--server or GLINT_SERVER)")
    if "://" not in url:
        url = "http://" + url
    if url.endswith("/v1"):
        url = url[: -len("/v1")]
    return url + "/"


class Http:
    """A thread-safe ``httpx.Client`` with the API's retry rules.

    ``retries`` is how many times a retryable failure is tried again (0: never);
    ``transport`` replaces httpx's (tests count bytes with it; proxies, mounts).
    """

    def __init__(
        self,
        url: str,
        key: str | None,
        *,
        timeout: float = 60.0,
        retries: int = 4,
        backoff: float = 0.5,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.base_url = api_root(url)
        self.retries = max(0, retries)
        self.backoff = backoff
        headers = {"User-Agent": f"glint-client/{__version__}"}
        if key:
            headers["Authorization"] = f"Bearer {key}"
        self.client = httpx.Client(
            base_url=self.base_url,
            headers=headers,
            timeout=httpx.Timeout(timeout, connect=min(timeout, 10.0)),
            transport=transport,
            limits=httpx.Limits(max_connections=32, max_keepalive_connections=16),
        )

    def close(self) -> None:
        self.client.close()

    # --- retries ------------------------------------------------------------------------

    def _delay(self, attempt: int, response: httpx.Response | None = None) -> float:
        if response is not None:
            after = response.headers.get("Retry-After", "")
            if after.isdigit():
                return min(float(after), 30.0)
        return min(self.backoff * 2**attempt, 10.0) * random.uniform(0.75, 1.25)

    @staticmethod
    def may_repeat(method: str, headers: Mapping[str, str] | None) -> bool:
        """Whether sending this call twice is harmless (see the module docstring)."""
        keyed = headers is not None and any(k.lower() == "idempotency-key" for k in headers)
        return method.upper() in IDEMPOTENT_METHODS or keyed

    def _retryable_status(self, response: httpx.Response, repeatable: bool) -> bool:
        if response.status_code not in RETRY_STATUSES:
            return False
        if response.status_code == 429:
            return True  # refused before any work was done
        if not repeatable:
            return False
        response.read()
        err = from_response(response)
        return err.slug not in NO_RETRY_SLUGS

    def request(
        self,
        method: str,
        path: str,
        *,
        params: Mapping[str, Any] | None = None,
        json: Any = None,
        content: bytes | BinaryIO | None = None,
        headers: Mapping[str, str] | None = None,
        ok: tuple[int, ...] = (),
        retry: bool | None = None,
    ) -> httpx.Response:
        """Send, retrying what may be retried; a status >= 400 not in ``ok`` raises the
        typed error. ``retry`` overrides the method/Idempotency-Key rule (a file given as
        ``content`` is only ever sent once: pass ``retry=False`` with it)."""
        repeatable = self.may_repeat(method, headers) if retry is None else retry
        attempt = 0
        while True:
            try:
                response = self.client.request(
                    method,
                    path.lstrip("/"),
                    params=params,
                    json=json,
                    content=content,
                    headers=dict(headers or {}),
                )
            except (httpx.ConnectError, httpx.ConnectTimeout, httpx.PoolTimeout) as exc:
                # nothing reached the server: always safe to try again
                if attempt >= self.retries:
                    raise self.unreachable(exc) from exc
            except httpx.TransportError as exc:
                if not repeatable or attempt >= self.retries:
                    raise self.unreachable(exc) from exc
            else:
                if attempt < self.retries and self._retryable_status(response, repeatable):
                    time.sleep(self._delay(attempt, response))
                    attempt += 1
                    continue
                if response.status_code >= 400 and response.status_code not in ok:
                    raise from_response(response)
                return response
            time.sleep(self._delay(attempt))
            attempt += 1

    @contextmanager
    def stream(
        self,
        method: str,
        path: str,
        *,
        headers: Mapping[str, str] | None = None,
        params: Mapping[str, Any] | None = None,
        timeout: httpx.Timeout | float | None = None,
        ok: tuple[int, ...] = (),
    ) -> Iterator[httpx.Response]:
        """A streamed response (downloads, events); errors raise like :meth:`request`.
        Callers resume themselves (Range, Last-Event-ID), so this does not retry."""
        extra: dict[str, Any] = {} if timeout is None else {"timeout": timeout}
        opened = False
        try:
            with self.client.stream(
                method, path.lstrip("/"), headers=dict(headers or {}), params=params, **extra
            ) as response:
                if response.status_code >= 400 and response.status_code not in ok:
                    response.read()
                    raise from_response(response)
                opened = True
                yield response
        except httpx.TransportError as exc:
            if opened:  # cut off mid-body: the caller resumes (Range, Last-Event-ID)
                raise
            raise self.unreachable(exc) from exc

    def unreachable(self, exc: Exception) -> ServerUnreachable:
        kind = type(exc).__name__
        return ServerUnreachable(
            f"no answer from {self.base_url} ({kind}: {exc or 'no detail'}); is the server "
            "running and the URL right (--server / GLINT_SERVER)?"
        )
