"""``CeleryQueue``: the API's :class:`api.queue.JobQueue` backend ``celery``.

It sends ``glint.train(job_id)`` by name, so the API never imports the task module
(nor torch). Sending twice is harmless: the runner claims the job in the database.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from api.queue import register_backend
from worker.broker import QUEUE, TASK_TRAIN, make_app

if TYPE_CHECKING:
    from api.settings import Settings


class CeleryQueue:
    """Hands jobs to Celery workers through Redis."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.app = make_app(settings)

    def enqueue(self, job_id: str) -> None:
        self.app.send_task(TASK_TRAIN, args=[job_id], queue=QUEUE)

    def close(self) -> None:
        self.app.close()


register_backend("celery", CeleryQueue)
