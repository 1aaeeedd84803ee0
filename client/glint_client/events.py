"""Following a job: the server-sent event stream, parsed, with reconnects.

The server sends ``event: job`` (the job's JSON, ``id:`` its version) on every change,
``: keepalive`` comments while nothing changes, and ``event: end`` after a terminal
state, then closes. A stream cut off for any other reason (network, a restarted or
replaced API server) is opened again with ``Last-Event-ID``, so the versions already
seen are not sent again; the follower gives up only after ``give_up_s`` without a
working connection.
"""

from __future__ import annotations

import json
import random
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import cast

import httpx

from glint_client.errors import ServerError, ServerUnreachable
from glint_client.http import Http
from glint_client.models import Job


@dataclass
class Event:
    event: str
    data: str
    id: str | None = None
    retry_ms: int | None = None


def parse(lines: Iterable[str]) -> Iterator[Event]:
    """Server-sent events from a stream's lines (the WHATWG rules: ``field: value``,
    comments start with ``:``, a blank line dispatches, ``data`` lines join with \\n)."""
    event, data, ident, retry = "", [], None, None
    for raw in lines:
        line = raw.rstrip("\r\n")
        if not line:
            if data or event:
                yield Event(event or "message", "\n".join(data), ident, retry)
            event, data, retry = "", [], None
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if name == "event":
            event = value
        elif name == "data":
            data.append(value)
        elif name == "id" and "\x00" not in value:
            ident = value
        elif name == "retry" and value.isdigit():
            retry = int(value)
    if data:
        yield Event(event or "message", "\n".join(data), ident, retry)


class JobFollower:
    """Iterate over a job's states as they change, until its end.

    After the loop, ``end_state`` is the state the server's ``end`` event named
    (``succeeded``, ``failed``, ``cancelled``, or ``deleted``); ``reconnects`` counts
    the streams opened again.
    """

    def __init__(
        self,
        http: Http,
        job_id: str,
        *,
        last_event_id: str | None = None,
        read_timeout_s: float = 60.0,
        give_up_s: float = 120.0,
    ) -> None:
        self.http = http
        self.job_id = job_id
        self.last_event_id = last_event_id
        self.read_timeout_s = read_timeout_s
        self.give_up_s = give_up_s
        self.end_state: str | None = None
        self.reconnects = 0
        self._retry_s = 1.0

    def __iter__(self) -> Iterator[Job]:
        failing_since: float | None = None
        attempt = 0
        while True:
            headers = {"Accept": "text/event-stream", "Cache-Control": "no-cache"}
            if self.last_event_id is not None:
                headers["Last-Event-ID"] = self.last_event_id
            timeout = httpx.Timeout(10.0, read=self.read_timeout_s)
            try:
                with self.http.stream(
                    "GET", f"/v1/jobs/{self.job_id}/events", headers=headers, timeout=timeout
                ) as response:
                    failing_since, attempt = None, 0
                    for ev in parse(response.iter_lines()):
                        if ev.retry_ms is not None:
                            self._retry_s = max(ev.retry_ms / 1000.0, 0.1)
                        if ev.event == "job":
                            if ev.id is not None:
                                self.last_event_id = ev.id
                            yield cast(Job, json.loads(ev.data))
                        elif ev.event == "end":
                            self.end_state = str(json.loads(ev.data).get("state"))
                            return
            except (httpx.TransportError, ServerUnreachable, ServerError) as exc:
                now = time.monotonic()
                failing_since = failing_since or now
                if now - failing_since > self.give_up_s:
                    if isinstance(exc, httpx.TransportError):
                        raise self.http.unreachable(exc) from exc
                    raise
            # closed without an end (server restarted, proxy timeout): open it again
            self.reconnects += 1
            delay = min(self._retry_s * 2 ** min(attempt, 4), 10.0)
            time.sleep(delay * random.uniform(0.8, 1.2))
            attempt += 1
