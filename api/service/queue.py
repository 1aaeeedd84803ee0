"""How jobs reach a runner: one small interface, pluggable backends.

The API only ever calls ``enqueue(job_id)`` after the job row is committed as
``queued``; the runner (:func:`api.service.runner.run_job`) claims it from the
database, so a backend may deliver a job more than once without harm. The embedded
default runs jobs on a thread of the API process (``glint serve`` on one machine, no
broker); ``celery`` hands jobs to Celery workers through Redis. Which one runs is a
field of :class:`Settings` (``GLINT_QUEUE_BACKEND``); tests hand the app factory
their own queue instead.
"""

from __future__ import annotations

import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    from api.service.settings import Settings

log = logging.getLogger("glint.queue")


@runtime_checkable
class JobQueue(Protocol):
    """Hands a queued job to some runner, eventually; must not block on the run."""

    def enqueue(self, job_id: str) -> None: ...


class LocalQueue:
    """Runs jobs on a small thread pool inside this process (the embedded default)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._pool = ThreadPoolExecutor(settings.local_workers, thread_name_prefix="glint-job")
        self._stop = threading.Event()

    def enqueue(self, job_id: str) -> None:
        self._pool.submit(self._run, job_id)

    def _run(self, job_id: str) -> None:
        from api.service.runner import run_job

        if self._stop.is_set():
            return  # shutting down: the job stays queued for the next start
        try:
            run_job(job_id, self.settings, stop=self._stop)
        except Exception:  # the runner records failures itself; this is a last resort
            log.exception("job %s: runner crashed", job_id)

    def close(self) -> None:
        """Stop promptly: running jobs checkpoint and go back to ``queued``."""
        self._stop.set()
        self._pool.shutdown(wait=True, cancel_futures=True)


class CeleryQueue:
    """Hands jobs to Celery workers through Redis: ``glint.train(job_id)`` is sent by
    name, so the API never imports the task module (nor torch). Sending twice is
    harmless: the runner claims the job in the database."""

    def __init__(self, settings: Settings) -> None:
        from api.service.broker import QUEUE, TASK_TRAIN, make_app

        self.settings = settings
        self.app = make_app(settings)
        self.task, self.queue = TASK_TRAIN, QUEUE

    def enqueue(self, job_id: str) -> None:
        self.app.send_task(self.task, args=[job_id], queue=self.queue)

    def close(self) -> None:
        self.app.close()


def queue_kind(settings: Settings) -> str:
    """``settings.queue_backend`` with ``auto`` resolved: ``celery`` when a broker
    (``redis_url``) is configured, ``local`` (no external service) otherwise."""
    name = settings.queue_backend
    if name == "auto":
        return "celery" if settings.redis_url else "local"
    return name


def make_queue(settings: Settings) -> JobQueue:
    """The queue :func:`queue_kind` names (Celery is imported only when chosen: the API
    process must not import it unless it uses it)."""
    kind = queue_kind(settings)
    if kind == "celery":
        return CeleryQueue(settings)
    if kind == "local":
        return LocalQueue(settings)
    raise ValueError(f"unknown queue backend {kind!r}; expected auto, local or celery")
