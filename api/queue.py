"""How jobs reach a runner: one small interface, pluggable backends.

The API only ever calls ``enqueue(job_id)`` after the job row is committed as
``queued``; the runner (:func:`api.jobs_runner.run_job`) claims it from the
database, so a backend may deliver a job more than once without harm. The embedded
default runs jobs on a thread of the API process (``glint serve`` on one machine, no
broker); another backend (Celery) is chosen with ``GLINT_QUEUE_BACKEND=module:factory``
or registered by name with :func:`register_backend`.
"""

from __future__ import annotations

import importlib
import logging
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    from api.settings import Settings

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
        from api.jobs_runner import run_job

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


QueueFactory = Callable[["Settings"], JobQueue]
_BACKENDS: dict[str, QueueFactory] = {"local": LocalQueue}
# built-in backends living in other packages, imported only when chosen (the API
# process must not import Celery, let alone torch, unless it uses them)
_LAZY_BACKENDS = {"celery": "worker.queue:CeleryQueue"}


def register_backend(name: str, factory: QueueFactory) -> None:
    """Make ``GLINT_QUEUE_BACKEND=name`` build its queue with ``factory(settings)``."""
    _BACKENDS[name] = factory


def make_queue(settings: Settings) -> JobQueue:
    """The queue named by ``settings.queue_backend``: a registered name or ``module:factory``.

    ``auto`` (the default) is ``celery`` when a broker (``redis_url``) is configured and
    ``local`` (the embedded queue: no external service) otherwise.
    """
    name = settings.queue_backend
    if name == "auto":
        name = "celery" if settings.redis_url else "local"
    factory = _BACKENDS.get(name)
    if factory is None:
        name = _LAZY_BACKENDS.get(name, name)
    if factory is None and ":" in name:
        module, _, attr = name.partition(":")
        factory = getattr(importlib.import_module(module), attr)
    if factory is None:
        known = ", ".join(sorted(_BACKENDS))
        raise ValueError(
            f"unknown queue backend {name!r} (known: auto, {known}, celery, or 'module:factory')"
        )
    return factory(settings)
