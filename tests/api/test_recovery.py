"""What the reaper does with a job whose runner died, and with its message in Redis.

Against a real database (SQLite and PostgreSQL) and, for the broker, a real
redis-server and a real consumer process killed before it acknowledged its message.
"""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy import select

from api.service.broker import QUEUE, unacked_deliveries
from api.service.db import Database
from api.service.migrate import upgrade
from api.service.models import Job, JobState, Scene, SceneState, new_id
from api.service.queue import CeleryQueue
from api.service.recovery import (
    died_error,
    orphaned_deliveries,
    reap,
    requeue_orphans,
    requeued_note,
    settle_dead_runners,
)
from api.service.runner import claim
from api.service.settings import Settings
from tests.api.support import LiveServer, RecordingQueue, make_settings
from tests.worker.support import RedisServer, needs_redis

STAMP = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ"


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Database]:
    url = f"sqlite:///{tmp_path / 'recovery.db'}"
    if request.param == "postgresql":
        url = request.getfixturevalue("pg_url")
    db = Database(url)
    upgrade(db.engine)
    yield db
    db.dispose()


def _settings(db: Database, **kw: object) -> Settings:
    return make_settings(Path("/nonexistent"), db.url, **kw)


def _job(db: Database, owner: str = "t", **values: object) -> str:
    sid, jid = new_id("scn"), new_id("job")
    with db.write() as s:
        s.add(Scene(id=sid, owner=owner, name="s", state=SceneState.READY))
        s.flush()
        s.add(Job(id=jid, owner=owner, scene_id=sid, config={}, total_iterations=10))
        s.flush()
        job = s.get(Job, jid)
        for k, v in values.items():
            setattr(job, k, v)
    return jid


def _get(db: Database, jid: str) -> Job:
    with db.read() as s:
        job = s.scalar(select(Job).where(Job.id == jid))
        assert job is not None
        s.expunge(job)
        return job


def _silence(db: Database, jid: str, seconds: float) -> datetime:
    """Make the job's runner look silent for ``seconds``; its last heartbeat."""
    seen = datetime.now(UTC) - timedelta(seconds=seconds)
    with db.write() as s:
        s.get(Job, jid).heartbeat_at = seen
    return seen


def test_defaults_notice_a_dead_runner_within_30_seconds() -> None:
    """Worst case from the crash to the job leaving ``running``: the runner died just
    after a heartbeat, the job turns stale ``stale_after_s`` later, and a reaper pass
    comes at most ``reaper_interval_s`` after that."""
    d = Settings()
    assert d.stale_after_s + d.reaper_interval_s <= 25
    assert d.stale_after_s >= 4 * d.heartbeat_s  # a live runner may miss three beats
    assert d.max_attempts == 3
    with pytest.raises(ValueError, match="at least twice heartbeat_s"):
        Settings(heartbeat_s=15, stale_after_s=20)


def test_a_dead_runner_s_job_is_requeued_saying_so(database: Database) -> None:
    settings = _settings(database)
    live, dead = _job(database), _job(database)
    assert claim(database, live, "w-live:1") and claim(database, dead, "w-dead:2")
    seen = _silence(database, dead, settings.stale_after_s + 1)
    before = _get(database, dead)

    out = settle_dead_runners(database, settings)
    assert dead in out.requeued and live not in out.requeued + out.failed
    job = _get(database, dead)
    assert (job.state, job.lease, job.runner_deaths) == ("queued", None, 1)
    assert job.version == before.version + 1 and job.attempts == 1
    assert job.error == requeued_note("w-dead:2", seen, 2, 3)
    assert re.fullmatch(
        rf"runner w-dead:2 stopped heartbeating at {STAMP}; requeued \(attempt 2 of 3\)",
        job.error,
    )
    assert _get(database, live).state == "running"
    # a second pass finds nothing more to do; the next runner keeps the note while it runs
    assert dead not in settle_dead_runners(database, settings).requeued
    assert claim(database, dead, "w-next:3")
    job = _get(database, dead)
    assert job.state == "running" and job.attempts == 2 and "attempt 2 of 3" in job.error


def test_a_job_that_keeps_killing_its_runner_fails_at_max_attempts(database: Database) -> None:
    settings = _settings(database, max_attempts=3)
    jid = _job(database)
    for n in (1, 2, 3):
        assert claim(database, jid, f"w{n}:{n}")
        seen = _silence(database, jid, 60)
        out = settle_dead_runners(database, settings)
        job = _get(database, jid)
        assert job.runner_deaths == n
        if n < 3:
            assert jid in out.requeued and job.state == "queued"
            assert job.error.endswith(f"requeued (attempt {n + 1} of 3)")
    assert jid in out.failed
    assert (job.state, job.lease, job.attempts) == ("failed", None, 3)
    assert job.finished_at is not None
    assert job.error == died_error(3, "w3:3", seen)
    assert re.fullmatch(rf"the runner died 3 times: last seen on worker w3:3 at {STAMP}", job.error)
    assert claim(database, jid, "w4:4") is None


def test_a_job_being_cancelled_when_its_runner_died_ends_cancelled(database: Database) -> None:
    settings = _settings(database)
    jid = _job(database)
    assert claim(database, jid, "w:1")
    with database.write() as s:
        s.get(Job, jid).cancel_requested = True
    _silence(database, jid, 60)
    assert jid in settle_dead_runners(database, settings).cancelled
    job = _get(database, jid)
    assert job.state == "cancelled" and job.finished_at is not None
    assert "stopped heartbeating" in job.error and "cancelled" in job.error


def test_embedded_restart_settles_every_running_job(database: Database) -> None:
    """At start-up the local queue's process is the only runner: a ``running`` job
    lost its runner however fresh its heartbeat, and counts against the limit."""
    settings = _settings(database, max_attempts=2)
    fresh, last_chance, waiting = _job(database), _job(database), _job(database)
    assert claim(database, fresh, "host:1:1")
    assert claim(database, last_chance, "host:1:2")
    with database.write() as s:
        s.get(Job, last_chance).runner_deaths = 1
    queued = requeue_orphans(database, settings)
    assert fresh in queued and waiting in queued and last_chance not in queued
    assert _get(database, fresh).error.endswith("requeued (attempt 2 of 2)")
    failed = _get(database, last_chance)
    assert failed.state == "failed" and failed.error.startswith("the runner died 2 times")


def test_resume_gives_a_failed_job_its_attempts_back(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    srv = LiveServer(settings, RecordingQueue()).start()
    try:
        key = srv.new_key("owner")
        jid = _job(srv.database, owner="owner", state=JobState.FAILED, runner_deaths=3)
        with srv.client(key) as c:
            r = c.post(f"/v1/jobs/{jid}/resume", json={})
            assert r.status_code == 200, r.text
            assert r.json()["state"] == "queued" and r.json()["error"] is None
        assert _get(srv.database, jid).runner_deaths == 0
    finally:
        srv.stop()


# --- the broker: a killed consumer's unacknowledged message -----------------------

KILLED_CONSUMER = textwrap.dedent(
    """
    import os, sys
    from api.service.broker import QUEUE, make_app
    from api.service.settings import Settings
    app = make_app(Settings(redis_url=sys.argv[1]))
    with app.connection() as conn:
        message = conn.SimpleQueue(QUEUE).get(timeout=10)  # delivered, not acknowledged
        print(message.headers["argsrepr"], flush=True)
        os._exit(0)  # like kill -9: no ack, no restore
    """
)


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    srv = RedisServer(tmp_path_factory.mktemp("redis")).start()
    yield srv.url
    srv.stop()


def _deliver_and_die(queue: CeleryQueue, job_id: str) -> None:
    """Send the job's message and let a consumer take it and die without an ack."""
    queue.enqueue(job_id)
    repo = Path(__file__).resolve().parents[2]
    out = subprocess.run(
        [sys.executable, "-c", KILLED_CONSUMER, queue.settings.redis_url or ""],
        cwd=repo,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert job_id in out.stdout, out.stderr


@needs_redis
def test_reaper_drops_a_dead_runner_s_message_and_sends_a_new_one(
    tmp_path: Path, redis_url: str
) -> None:
    import redis

    settings = make_settings(tmp_path, redis_url=redis_url)
    db = Database(settings.db_url)
    upgrade(db.engine)
    queue = CeleryQueue(settings)
    client = redis.Redis.from_url(redis_url)
    try:
        client.flushdb()
        dead, live, done = _job(db), _job(db), _job(db)
        for jid in (dead, live, done):
            _deliver_and_die(queue, jid)
            assert claim(db, jid, f"w-{jid[-4:]}:1")
        with db.write() as s:
            s.get(Job, done).state = JobState.SUCCEEDED  # ended, then its worker died
        assert {job for _, job, _ in unacked_deliveries(settings)} == {dead, live, done}
        assert client.llen(QUEUE) == 0
        _silence(db, dead, settings.stale_after_s + 1)

        # a finished job's delivery is left alone until it is older than stale_after_s
        assert orphaned_deliveries(db, settings, []) == []
        out = reap(db, settings, queue.enqueue)
        assert out.requeued == [dead] and out.dropped == 1
        held = {job for _, job, _ in unacked_deliveries(settings)}
        assert held == {live, done}  # the live runner's message stays
        assert [m for m in client.lrange(QUEUE, 0, -1) if dead.encode() in m]  # sent again
        assert _get(db, dead).error.endswith("requeued (attempt 2 of 3)")

        old = time.time() - settings.stale_after_s - 1
        client.zadd("unacked_index", {tag: old for tag, _, _ in unacked_deliveries(settings)})
        out = reap(db, settings, queue.enqueue)
        assert out.dropped == 1 and out.requeued == []
        assert [job for _, job, _ in unacked_deliveries(settings)] == [live]
        assert client.zcard("unacked_index") == 1
    finally:
        client.close()
        queue.close()
        db.dispose()


def test_api_runs_a_reaper_with_the_celery_queue_only(tmp_path: Path) -> None:
    """With Celery, the API requeues a dead runner's job even when no worker is alive."""
    dead_broker = "redis://127.0.0.1:9/0"  # sending fails: the reaper logs and goes on
    settings = make_settings(
        tmp_path, redis_url=dead_broker, stale_after_s=2.0, reaper_interval_s=0.2
    )
    srv = LiveServer(settings, None).start()
    try:
        assert type(srv.app.state.queue).__name__ == "CeleryQueue"
        jid = _job(srv.database)
        assert claim(srv.database, jid, "gone:1")
        _silence(srv.database, jid, 10)
        t0 = time.monotonic()
        while _get(srv.database, jid).state == "running":
            assert time.monotonic() - t0 < 10, "the API's reaper did not requeue the job"
            time.sleep(0.05)
        assert _get(srv.database, jid).error.endswith("requeued (attempt 2 of 3)")
    finally:
        srv.stop()
