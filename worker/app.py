"""The worker's Celery app: ``celery -A worker.app worker`` (or ``glint worker``).

Importing this module configures the app from ``GLINT_*`` and registers the task
and the worker signals; only worker processes import it. torch is not imported here:
the trainer is imported by :func:`api.service.runner.run_job` inside the task, so even
a prefork pool would fork before CUDA exists (``glint worker`` uses the solo pool).
"""

from __future__ import annotations

import logging
from typing import Any

from celery import signals

from api.service.broker import TASK_TRAIN, make_app
from api.service.settings import Settings, apply_to_core
from worker.runtime import WorkerRuntime

log = logging.getLogger("glint.worker")

settings = Settings()
apply_to_core(settings)
app = make_app(settings)
runtime = WorkerRuntime(app, settings)


@app.task(name=TASK_TRAIN, acks_late=True, reject_on_worker_lost=True, ignore_result=True)
def train(job_id: str) -> str | None:
    """Run job ``job_id`` to its end (or do nothing if another runner has it or it is done).

    Idempotent: a redelivered or duplicate message finds the job claimed or finished
    in the database and returns None.
    """
    return runtime.run(job_id)


@signals.worker_ready.connect
def _on_ready(sender: Any = None, **_: Any) -> None:
    runtime.start(getattr(sender, "hostname", None))


@signals.worker_shutting_down.connect
def _on_shutting_down(**_: Any) -> None:
    # a warm shutdown waits for the running task: make it checkpoint and return now
    log.info("shutdown requested: checkpointing the current job")
    runtime.stop.set()


@signals.worker_shutdown.connect
def _on_shutdown(**_: Any) -> None:
    runtime.close()
