"""What a worker process does besides running tasks: liveness row and job reaper.

One :class:`WorkerRuntime` per worker process. A small housekeeping thread

* upserts this worker's row in ``workers`` every ``worker_heartbeat_s`` (device,
  current job), which ``GET /v1/workers`` lists, and
* every ``reaper_interval_s`` runs the reaper (:func:`api.service.recovery.reap`):
  ``running`` jobs whose heartbeat is older than ``stale_after_s`` lost their runner
  (they go back to ``queued``, saying so, and the next runner resumes them from their
  checkpoint; after ``max_attempts`` dead runners they fail); the dead runner's
  unacknowledged message is dropped from Redis; ``queued`` jobs untouched for
  ``queued_grace_s`` that have no message waiting in the broker (a send that failed,
  a Redis that lost its data) are sent again.

Every worker runs a reaper (and so does the API with the Celery queue): they race
through conditional UPDATEs, so each lost job is re-sent once per period, and a
duplicate message would be a no-op anyway.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from datetime import UTC, datetime, timedelta

from celery import Celery
from sqlalchemy import delete, update

from api.service.broker import QUEUE, TASK_TRAIN
from api.service.db import database_for
from api.service.models import JobState, Worker
from api.service.recovery import reap
from api.service.settings import Settings

log = logging.getLogger("glint.worker")

EXPIRY_HEARTBEATS = 3  # a worker silent for this many heartbeat periods is gone


def _now() -> datetime:
    return datetime.now(UTC)


class WorkerRuntime:
    """This process's worker identity, its current job, and its housekeeping thread."""

    def __init__(self, app: Celery, settings: Settings, name: str | None = None) -> None:
        self.app = app
        self.settings = settings
        self.device = settings.worker_device
        self.name = name or f"glint-{self.device.replace(':', '')}@{socket.gethostname()}"
        self.database = database_for(settings.db_url)
        self.stop = threading.Event()  # set on worker shutdown: jobs checkpoint and go back
        self.current_job: str | None = None
        self._closed = threading.Event()
        self._started_at = _now()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    # -- tasks ------------------------------------------------------------------
    def run(self, job_id: str) -> str | None:
        """Run one job (or do nothing if it is not claimable); its final state."""
        from api.service.runner import run_job

        self.current_job = job_id
        self.beat()
        try:
            state = run_job(
                job_id,
                self.settings,
                database=self.database,
                worker=f"{self.name}:{os.getpid()}",
                stop=self.stop,
                device=self.device,
            )
        finally:
            self.current_job = None
            self.beat()
        if state == JobState.QUEUED:  # shutdown interrupted it: hand it to another worker
            self.send(job_id)
        return state

    def send(self, job_id: str) -> None:
        try:
            self.app.send_task(TASK_TRAIN, args=[job_id], queue=QUEUE)
        except Exception:  # the reaper re-sends it after queued_grace_s
            log.exception("job %s: re-send failed", job_id)

    # -- housekeeping -----------------------------------------------------------
    def start(self, name: str | None = None) -> None:
        """Register this worker and start heartbeat + reaper (on Celery's worker_ready)."""
        if name:
            self.name = name
        if self.settings.auto_migrate:
            from api.service.migrate import upgrade

            try:
                upgrade(self.database.engine)
            except Exception:  # another process may be migrating; the API does it too
                log.warning("database migration failed", exc_info=True)
        self.beat()
        self._thread = threading.Thread(target=self._loop, name="glint-housekeeping", daemon=True)
        self._thread.start()
        log.info("worker %s ready on %s", self.name, self.device)

    def _loop(self) -> None:
        beat_every, reap_every = self.settings.worker_heartbeat_s, self.settings.reaper_interval_s
        next_beat, next_reap = time.monotonic() + beat_every, time.monotonic()  # start() beat
        while not self._closed.wait(max(min(next_beat, next_reap) - time.monotonic(), 0.0)):
            if time.monotonic() >= next_beat:
                next_beat = time.monotonic() + beat_every
                self.beat()
            if time.monotonic() >= next_reap:
                next_reap = time.monotonic() + reap_every
                self.reap()

    def beat(self) -> None:
        """Upsert this worker's row (best effort: a missed beat is retried next period)."""
        now = _now()
        expires = now + timedelta(seconds=EXPIRY_HEARTBEATS * self.settings.worker_heartbeat_s)
        values = {
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "device": self.device,
            "current_job": self.current_job,
            "heartbeat_at": now,
            "expires_at": expires,
            "started_at": self._started_at,
        }
        with self._lock:
            try:
                with self.database.write() as s:
                    res = s.execute(update(Worker).where(Worker.id == self.name).values(**values))
                    if res.rowcount == 0:
                        s.add(Worker(id=self.name, **values))
            except Exception:
                log.warning("worker heartbeat failed", exc_info=True)

    def reap(self) -> list[str]:
        """Settle jobs whose runner died, drop its message, re-send lost jobs; the ids sent."""
        try:
            reaped = reap(self.database, self.settings, self.send)
        except Exception:
            log.warning("reaper scan failed", exc_info=True)
            return []
        return reaped.requeued + reaped.resent

    def close(self) -> None:
        """Stop housekeeping and remove this worker's row (it is no longer alive)."""
        self.stop.set()
        self._closed.set()
        if self._thread is not None:
            self._thread.join(10)
        with self._lock:
            try:
                with self.database.write() as s:
                    s.execute(delete(Worker).where(Worker.id == self.name))
            except Exception:
                log.warning("cannot deregister worker %s", self.name, exc_info=True)
