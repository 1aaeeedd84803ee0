"""kill -9 of a runner, with real processes: the job says its runner is gone within 30 s,
is requeued, resumes from its checkpoint on another runner, and nothing stays behind in
Redis; a job whose runners keep dying ends failed saying so. Both for ``glint worker``
(Celery on a real redis-server) and for the embedded runner (``glint serve`` killed and
started again)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from api.service.broker import QUEUE
from api.service.settings import Settings
from tests.api.support import LiveServer, free_port, list_all, make_settings, wait_for
from tests.worker.flow import job, ready_scene, submit, wait_iteration, wait_state
from tests.worker.support import RedisServer, WorkerProcess, Workers, needs_redis

STAMP = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ"
DEFAULTS = Settings.model_fields  # the shipped timings, not the suite's fast ones


def _default(name: str) -> str:
    return str(DEFAULTS[name].default)


# Long enough that the runner cannot train from the iteration a test sees to the end
# before the kill lands (a CI run saw a 60-iteration job reach its end in that window).
RUN_ITERATIONS = 400


def _resumed_from(log: str, job_id: str) -> list[int]:
    return [int(m) for m in re.findall(rf"job {job_id}: resumed from iteration (\d+)", log)]


def _metrics_iterations(store_root: Path, job_id: str) -> list[int]:
    path = store_root / "jobs" / job_id / "run" / "metrics.jsonl"
    return [json.loads(line)["iteration"] for line in path.read_text().splitlines() if line]


# --- Celery workers -------------------------------------------------------------------


@pytest.fixture(scope="module")
def server(
    tmp_path_factory: pytest.TempPathFactory, redis_server: RedisServer
) -> Iterator[LiveServer]:
    """The API (celery queue) with the shipped reaper timings and 2 attempts per job."""
    settings = make_settings(
        tmp_path_factory.mktemp("api"), redis_url=redis_server.url, max_attempts=2
    )
    assert settings.stale_after_s == DEFAULTS["stale_after_s"].default
    srv = LiveServer(settings, None).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def workers(
    server: LiveServer, redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Workers]:
    ws = Workers(
        server, redis_server.url, tmp_path_factory.mktemp("worker-logs"), GLINT_MAX_ATTEMPTS="2"
    )
    yield ws
    ws.stop_all()


@pytest.fixture(scope="module")
def client(server: LiveServer) -> Iterator[httpx.Client]:
    with server.client(server.new_key("crash-tests")) as c:
        yield c


@pytest.fixture(scope="module")
def scene_id(client: httpx.Client, scene: list[tuple[str, bytes]]) -> str:
    return ready_scene(client, scene)


def _broker(redis_url: str) -> dict[str, int]:
    """What Redis holds: unacknowledged deliveries (hash and index) and waiting messages."""
    import redis

    r = redis.Redis.from_url(redis_url)
    try:
        return {
            "unacked": r.hlen("unacked"),
            "index": r.zcard("unacked_index"),
            "queue": r.llen(QUEUE),
        }
    finally:
        r.close()


def _holder(client: httpx.Client, job_id: str, workers: Workers) -> WorkerProcess:
    node = wait_for(
        lambda: [w["id"] for w in list_all(client, "/v1/workers") if w["current_job"] == job_id]
    )[0]
    return next(w for w in workers.procs.values() if w.node == node)


@needs_redis
@pytest.mark.slow
def test_killed_worker_job_leaves_running_within_30s_and_resumes_from_its_checkpoint(
    server: LiveServer,
    workers: Workers,
    redis_server: RedisServer,
    client: httpx.Client,
    scene_id: str,
) -> None:
    """The only worker dies mid-training; a supervisor starts another one at once. Every
    reaper (the API's and the new worker's) runs with the shipped timings."""
    (a,) = workers.ensure("solo-a")
    job_id = submit(client, scene_id, iterations=RUN_ITERATIONS, checkpoint_every=10)
    wait_iteration(client, job_id, 12)  # the checkpoint at 10 is written
    assert _broker(redis_server.url)["unacked"] == 1  # acks_late: held while it runs
    a.kill()
    t_kill = time.monotonic()
    b = workers.start(
        "solo-b",
        GLINT_STALE_AFTER_S=_default("stale_after_s"),
        GLINT_REAPER_INTERVAL_S=_default("reaper_interval_s"),
    )

    def noticed() -> dict[str, Any] | None:
        j = job(client, job_id)
        return j if "stopped heartbeating" in (j["error"] or "") else None

    seen = wait_for(noticed, timeout=35, every=0.1)
    took = time.monotonic() - t_kill
    assert took < 30, f"the job looked alive {took:.1f} s after its worker died"
    assert seen["state"] == "queued" or seen["attempts"] == 2  # not the dead runner's any more
    assert re.fullmatch(
        rf"runner {re.escape(a.node)}:\d+ stopped heartbeating at {STAMP}; "
        r"requeued \(attempt 2 of 2\)",
        seen["error"],
    ), seen["error"]

    done = wait_state(client, job_id, timeout=60)
    assert done["state"] == "succeeded", done["error"]
    assert done["iteration"] == RUN_ITERATIONS and done["attempts"] == 2 and done["error"] is None
    b.wait_ready()
    (resumed,) = _resumed_from(b.log(), job_id)
    assert 10 <= resumed < RUN_ITERATIONS  # from its checkpoint, not from scratch
    its = _metrics_iterations(server.settings.store_root, job_id)
    assert its == sorted(set(its)) and its[-1] == RUN_ITERATIONS
    # the dead worker's delivery was dropped, the new one acknowledged: nothing left
    wait_for(lambda: _broker(redis_server.url) == {"unacked": 0, "index": 0, "queue": 0}, 10)


@needs_redis
@pytest.mark.slow
def test_a_job_whose_runners_keep_dying_fails_with_the_reason(
    workers: Workers, redis_server: RedisServer, client: httpx.Client, scene_id: str
) -> None:
    workers.ensure("c", "d")
    job_id = submit(client, scene_id, iterations=5000, checkpoint_every=10)
    wait_iteration(client, job_id, 2)
    first = _holder(client, job_id, workers)
    first.kill()

    def running_again() -> dict[str, Any] | None:
        j = job(client, job_id)
        return j if j["state"] == "running" and j["attempts"] == 2 else None

    again = wait_for(running_again, timeout=30, every=0.05)
    assert again["error"].endswith("requeued (attempt 2 of 2)")
    second = _holder(client, job_id, workers)
    assert second is not first
    second.kill()
    workers.start("e")  # someone has to notice: the new worker's reaper (or the API's)

    failed = wait_state(client, job_id, {"failed", "succeeded", "cancelled"}, timeout=40)
    assert failed["state"] == "failed"
    assert re.fullmatch(
        rf"the runner died 2 times: last seen on worker {re.escape(second.node)}:\d+ at {STAMP}",
        failed["error"],
    ), failed["error"]
    assert failed["finished_at"] is not None
    wait_for(lambda: _broker(redis_server.url) == {"unacked": 0, "index": 0, "queue": 0}, 20)


# --- the embedded runner: glint serve killed and started again ------------------------

SERVE = (
    "import logging, sys; logging.basicConfig(level=logging.INFO, "
    "format='%(asctime)s %(name)s %(levelname)s %(message)s'); "
    "from core.cli import main; sys.exit(main(sys.argv[1:]))"
)


class Serve:
    """``glint serve`` (local queue, SQLite) as a process that can be killed and restarted."""

    def __init__(self, root: Path, **env: str) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("GLINT_")}
        self.env.update(
            GLINT_DATA_DIR=str(root),
            GLINT_QUEUE_BACKEND="local",
            GLINT_PORT=str(self.port),
            GLINT_HEARTBEAT_S="0.5",
            GLINT_PROGRESS_INTERVAL_S="0.2",
            GLINT_CANCEL_POLL_S="0.1",
            OMP_NUM_THREADS="1",
            PYTHONUNBUFFERED="1",
            **env,
        )
        self.log_path = root / "serve.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> Serve:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", SERVE, "serve", "--log-level", "warning"],
            env=self.env,
            stdout=open(self.log_path, "ab"),  # noqa: SIM115 (the process owns it)
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

        def up() -> bool:
            assert self.proc is not None and self.proc.poll() is None, self.log()[-3000:]
            try:
                return httpx.get(f"{self.url}/v1/health", timeout=1).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for(up, timeout=60, every=0.1)
        return self

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def kill(self) -> None:
        assert self.proc is not None
        os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.kill()

    def key(self) -> str:
        from api.auth import create_key
        from api.service.db import Database

        db = Database(f"sqlite:///{self.root / 'glint.db'}")
        try:
            with db.write() as s:
                return create_key(s, "embedded-crash")[1]
        finally:
            db.dispose()

    def client(self, key: str) -> httpx.Client:
        return httpx.Client(
            base_url=self.url, headers={"Authorization": f"Bearer {key}"}, timeout=60
        )


@pytest.fixture
def serve(tmp_path: Path) -> Iterator[Serve]:
    srv = Serve(tmp_path / "data", GLINT_MAX_ATTEMPTS="2")
    yield srv
    srv.stop()


@pytest.mark.slow
def test_killed_embedded_runner_is_requeued_on_restart_and_resumes(
    serve: Serve, scene: list[tuple[str, bytes]]
) -> None:
    key = serve.start().key()
    with serve.client(key) as c:
        job_id = submit(c, ready_scene(c, scene), iterations=RUN_ITERATIONS, checkpoint_every=10)
        wait_iteration(c, job_id, 12)
    serve.kill()
    serve.start()  # recovery on start: this process is the only runner
    with serve.client(key) as c:
        seen = job(c, job_id)
        assert seen["state"] in ("queued", "running") and seen["attempts"] in (1, 2)
        assert re.fullmatch(
            rf"runner \S+:\d+:\d+ stopped heartbeating at {STAMP}; requeued \(attempt 2 of 2\)",
            seen["error"],
        ), seen["error"]
        done = wait_state(c, job_id, timeout=60)
    assert done["state"] == "succeeded", done["error"]
    assert done["iteration"] == RUN_ITERATIONS and done["attempts"] == 2
    (resumed,) = _resumed_from(serve.log(), job_id)
    assert 10 <= resumed < RUN_ITERATIONS
    its = _metrics_iterations(serve.root / "store", job_id)
    assert its == sorted(set(its)) and its[-1] == RUN_ITERATIONS


@pytest.mark.slow
def test_embedded_job_that_keeps_killing_its_process_fails_with_the_reason(
    serve: Serve, scene: list[tuple[str, bytes]]
) -> None:
    key = serve.start().key()
    with serve.client(key) as c:
        job_id = submit(c, ready_scene(c, scene), iterations=5000, checkpoint_every=10)
        wait_iteration(c, job_id, 2)
    serve.kill()
    serve.start()
    with serve.client(key) as c:
        wait_for(lambda: job(c, job_id)["attempts"] == 2 and job(c, job_id)["state"] == "running")
    serve.kill()
    serve.start()
    with serve.client(key) as c:
        failed = job(c, job_id)
    assert failed["state"] == "failed" and failed["attempts"] == 2
    assert re.fullmatch(
        rf"the runner died 2 times: last seen on worker \S+:\d+:\d+ at {STAMP}", failed["error"]
    ), failed["error"]
