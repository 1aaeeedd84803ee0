"""How jobs reach a runner: one small interface, pluggable backends.

The API only ever calls ``enqueue(job_id)`` after the job row is committed as
``queued``; the runner (:func:`api.service.runner.run_job`) claims it from the
database, so a backend may deliver a job more than once without harm. The embedded
default runs jobs in child processes of the API (``api.service.job_process``; ``glint
serve`` on one machine, no broker); ``celery`` hands jobs to Celery workers through
Redis. Which one runs is a field of :class:`Settings` (``GLINT_QUEUE_BACKEND``);
tests hand the app factory their own queue instead.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
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
    """Runs jobs in child processes of this one, at most ``local_workers`` at once (the
    embedded default).

    Each job runs in ``python -m api.service.job_process JOB_ID`` at a lowered CPU
    priority (``embedded_job_nice``): training holds neither the API's GIL nor, on a busy
    machine, its CPU. A small thread pool waits on the children. ``close()`` sends them
    ``SIGTERM``: they checkpoint and put their jobs back to ``queued``. A child that dies
    (killed, out of memory) has its job settled like any dead runner's: requeued with the
    reason, or failed at ``max_attempts``.
    """

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._pool = ThreadPoolExecutor(settings.local_workers, thread_name_prefix="glint-job")
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._children: dict[int, subprocess.Popen[bytes]] = {}

    def enqueue(self, job_id: str) -> None:
        self._pool.submit(self._run, job_id)

    def _spawn(self, job_id: str) -> subprocess.Popen[bytes]:
        level = logging.getLogger("glint.runner").getEffectiveLevel()
        cmd = [sys.executable, "-m", "api.service.job_process", job_id]
        proc = subprocess.Popen(
            [*cmd, str(os.getpid()), str(level)], stdin=subprocess.PIPE, close_fds=True
        )
        assert proc.stdin is not None
        try:
            proc.stdin.write(self.settings.model_dump_json().encode())
            proc.stdin.close()
        except OSError:  # it died at once; its exit status tells
            pass
        return proc

    def _run(self, job_id: str) -> None:
        if self._stop.is_set():
            return  # shutting down: the job stays queued for the next start
        try:
            with self._lock:
                if self._stop.is_set():
                    return
                proc = self._spawn(job_id)
                self._children[proc.pid] = proc
            try:
                code = proc.wait()
            finally:
                with self._lock:
                    self._children.pop(proc.pid, None)
            if code != 0:
                log.error("job %s: its process %d exited with status %s", job_id, proc.pid, code)
                self._settle(job_id, proc.pid)
        except Exception:  # the runner records failures itself; this is a last resort
            log.exception("job %s: runner crashed", job_id)

    def _settle(self, job_id: str, pid: int) -> None:
        """The child died: a job it still holds goes back to the queue (or fails)."""
        import socket

        from api.service.db import database_for
        from api.service.recovery import log_settled, settle_dead_runners

        if self._stop.is_set():
            return  # a child killed while we stop: the next start settles its job
        runner = f"{socket.gethostname()}:{pid}:"
        settled = settle_dead_runners(
            database_for(self.settings.db_url), self.settings, job_id=job_id, runner=runner
        )
        log_settled(settled)
        if settled.requeued:
            self.enqueue(job_id)

    def close(self, timeout: float = 60.0) -> None:
        """Stop promptly: running jobs checkpoint and go back to ``queued``."""
        with self._lock:
            self._stop.set()
            children = list(self._children.values())
        for proc in children:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for proc in children:
            try:
                proc.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                log.error("job process %d did not stop in %.0f s; killed", proc.pid, timeout)
                proc.kill()
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
