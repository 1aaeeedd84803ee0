"""The Celery app's configuration, shared by the API (to send) and the workers (to run).

Nothing here imports torch or the trainer, so the API process can build the app to
``send_task`` by name without pulling in the training stack.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from celery import Celery

if TYPE_CHECKING:
    from api.service.settings import Settings

TASK_TRAIN = "glint.train"
QUEUE = "glint"


def make_app(settings: Settings) -> Celery:
    """A Celery app on ``settings.redis_url`` with the delivery semantics Glint relies on."""
    if not settings.redis_url:
        raise ValueError("the celery queue needs a broker: set GLINT_REDIS_URL")
    vt = settings.visibility_timeout_s
    app = Celery("glint", broker=settings.redis_url, set_as_current=False)
    app.conf.update(
        task_default_queue=QUEUE,
        task_routes={TASK_TRAIN: {"queue": QUEUE}},
        task_serializer="json",
        accept_content=["json"],
        task_ignore_result=True,  # the database holds results; no result backend
        # a message is acknowledged after the task returns, and given back if the
        # worker process dies: the job is never lost between broker and database
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        # one job at a time per GPU worker, and no second message parked behind it
        worker_prefetch_multiplier=1,
        worker_concurrency=1,
        # unacked messages come back after this long, even if their task still runs;
        # see docs/worker.md for why a day
        broker_transport_options={"visibility_timeout": vt},
        broker_connection_retry_on_startup=True,
        broker_connection_max_retries=None,  # ride out a Redis restart, however long
        task_publish_retry=True,
        task_publish_retry_policy={
            "max_retries": 3,
            "interval_start": 0.2,
            "interval_step": 0.5,
            "interval_max": 1.0,
        },
        broker_connection_timeout=5,
    )
    return app


def pending_job_ids(settings: Settings, job_ids: list[str]) -> set[str]:
    """Those of ``job_ids`` that have a message waiting in the broker's ready list.

    Knowingly reads kombu's Redis layout (the queue is a list named after it, each
    element a JSON envelope whose headers carry the task's ``argsrepr``): the reaper
    uses it only to avoid piling up duplicate messages, so a wrong answer costs a
    harmless duplicate, never a lost job.
    """
    import redis

    assert settings.redis_url
    client = redis.Redis.from_url(settings.redis_url, socket_timeout=5)
    try:
        raw = b"\n".join(client.lrange(QUEUE, 0, -1))
    finally:
        client.close()
    return {j for j in job_ids if j.encode() in raw}


# kombu's Redis transport keeps each delivered, not yet acknowledged message in the hash
# ``unacked`` (delivery tag → [message, exchange, routing key]) and the delivery time in
# the sorted set ``unacked_index``; it hands a message back only after the visibility
# timeout. A worker killed mid-job leaves its message there: the reaper removes it.
UNACKED, UNACKED_INDEX = "unacked", "unacked_index"


def _job_of(raw: bytes) -> str | None:
    """The job id a ``glint.train`` message in ``unacked`` carries, or None."""
    import base64
    import json

    try:
        message = json.loads(raw)[0]
        if message.get("headers", {}).get("task") != TASK_TRAIN:
            return None
        body = message["body"]
        if message.get("properties", {}).get("body_encoding") == "base64":
            body = base64.b64decode(body)
        args = json.loads(body)[0]
        return str(args[0]) if args else None
    except (ValueError, KeyError, IndexError, TypeError):
        return None


def unacked_deliveries(settings: Settings) -> list[tuple[str, str | None, float]]:
    """``(delivery tag, job id or None, delivered at)`` of every unacknowledged message.

    Reads kombu's layout knowingly (see :func:`pending_job_ids`); a message that is not
    a ``glint.train`` one has no job id and is left alone.
    """
    import redis

    assert settings.redis_url
    client = redis.Redis.from_url(settings.redis_url, socket_timeout=5)
    try:
        held = client.hgetall(UNACKED)
        since = dict(client.zrange(UNACKED_INDEX, 0, -1, withscores=True))
    finally:
        client.close()
    return [(tag.decode(), _job_of(raw), float(since.get(tag, 0.0))) for tag, raw in held.items()]


def drop_unacked(settings: Settings, tags: list[str]) -> int:
    """Forget these deliveries (their worker is gone); how many were still there."""
    import redis

    if not tags:
        return 0
    assert settings.redis_url
    client = redis.Redis.from_url(settings.redis_url, socket_timeout=5)
    try:
        pipe = client.pipeline()
        pipe.hdel(UNACKED, *tags)
        pipe.zrem(UNACKED_INDEX, *tags)
        removed, _ = pipe.execute()
    finally:
        client.close()
    return int(removed)
