"""Test machinery for the client: an httpx transport that counts what goes over the wire
and can play a dying client or a lost answer."""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx


class Killed(BaseException):
    """The client process dies: not an Exception, so no retry logic catches it."""


class _Counted(httpx.SyncByteStream):
    """A response body that reports its bytes as they are read (streams stay streams),
    cut off with a read error after ``cut_after`` chunks when that is set."""

    def __init__(
        self, inner: httpx.SyncByteStream, add: Callable[[int], None], cut_after: int | None
    ) -> None:
        self.inner = inner
        self.add = add
        self.cut_after = cut_after

    def __iter__(self) -> Iterator[bytes]:
        for i, chunk in enumerate(self.inner):
            if self.cut_after is not None and i >= self.cut_after:
                raise httpx.ReadError("connection cut (test)")
            self.add(len(chunk))
            yield chunk

    def close(self) -> None:
        self.inner.close()


class CountingTransport(httpx.HTTPTransport):
    """Counts request body bytes per method and path, and response body bytes per path.

    ``before(request, n)`` runs before the n-th request (1-based) is sent and may raise
    (``Killed``) or return True to drop the answer after the server has acted on it
    (raising ``httpx.ReadTimeout``, as a timeout after the server did the work would).
    ``cut(request, n)`` may return a chunk count after which the answer's body breaks off.
    """

    def __init__(
        self,
        before: Callable[[httpx.Request, int], bool | None] | None = None,
        cut: Callable[[httpx.Request, int], int | None] | None = None,
    ) -> None:
        super().__init__()
        self.before = before
        self.cut = cut  # (request, n) -> cut the response body after this many chunks
        self.requests: list[tuple[str, str, int]] = []  # method, path, body bytes sent
        self.headers: list[httpx.Headers] = []
        self.received: dict[str, int] = {}  # response body bytes by path
        self._lock = threading.Lock()

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        with self._lock:
            n = len(self.requests) + 1
        lose_answer = bool(self.before and self.before(request, n))
        body = request.read()
        with self._lock:
            self.requests.append((request.method, request.url.path, len(body)))
            self.headers.append(request.headers)
        response = super().handle_request(request)
        if lose_answer:
            response.read()
            response.close()
            raise httpx.ReadTimeout("answer lost (test)", request=request)
        path = request.url.path
        cut_after = self.cut(request, n) if self.cut else None
        response.stream = _Counted(
            response.stream,  # type: ignore[arg-type]
            lambda k: self._add_received(path, k),
            cut_after,
        )
        return response

    def _add_received(self, path: str, n: int) -> None:
        with self._lock:
            self.received[path] = self.received.get(path, 0) + n

    def downloaded(self, path_part: str = "/artifacts/") -> int:
        """Response body bytes of requests whose path contains ``path_part``."""
        with self._lock:
            return sum(n for p, n in self.received.items() if path_part in p)

    def sent(self, method: str, path_part: str = "") -> int:
        """Body bytes sent by requests of ``method`` whose path contains ``path_part``."""
        return sum(n for m, p, n in self.requests if m == method and path_part in p)

    def count(self, method: str, path_part: str = "") -> int:
        return sum(1 for m, p, _ in self.requests if m == method and path_part in p)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
