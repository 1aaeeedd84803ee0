"""Worker test machinery: an own redis-server (persistent, restartable) and real
``glint worker`` processes with their logs."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from tests.api.support import free_port

REDIS_SERVER = shutil.which("redis-server") or (
    "/usr/bin/redis-server" if os.path.exists("/usr/bin/redis-server") else None
)
needs_redis = pytest.mark.skipif(
    REDIS_SERVER is None, reason="redis-server not found (run scripts/services.sh)"
)


class RedisServer:
    """redis-server on a free loopback port, append-only file in its own folder."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.port = free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> RedisServer:
        assert REDIS_SERVER
        self.root.mkdir(parents=True, exist_ok=True)
        log = open(self.root / "redis.log", "ab")  # noqa: SIM115 (the process owns it)
        self.proc = subprocess.Popen(
            [
                REDIS_SERVER,
                "--port",
                str(self.port),
                "--bind",
                "127.0.0.1",
                "--dir",
                str(self.root),
                "--appendonly",
                "yes",
                "--appendfsync",
                "always",
                "--save",
                "",
                "--daemonize",
                "no",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        import redis

        client = redis.Redis(port=self.port, socket_timeout=1)
        deadline = time.monotonic() + 20
        while True:
            try:
                if client.ping():
                    break
            except redis.RedisError:
                if time.monotonic() > deadline or self.proc.poll() is not None:
                    raise RuntimeError("redis-server did not start") from None
                time.sleep(0.05)
        client.close()
        return self

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()  # SIGTERM: redis flushes the AOF and exits
            self.proc.wait(20)
        self.proc = None

    def restart(self, down_s: float = 1.0) -> None:
        self.stop()
        time.sleep(down_s)
        self.start()


def _glint() -> list[str]:
    exe = Path(sys.executable).parent / "glint"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "core.cli"]


class WorkerProcess:
    """``glint worker`` as a subprocess; its log is a file the tests read."""

    def __init__(self, name: str, env: dict[str, str], log_dir: Path) -> None:
        self.name = name
        self.node = f"{name}@test"
        self.log_path = log_dir / f"{name}.log"
        self.proc = subprocess.Popen(
            [*_glint(), "worker", "--device", "cpu", "--name", self.node, "--log-level", "info"],
            env=env,
            stdout=open(self.log_path, "ab"),  # noqa: SIM115 (the process owns it)
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_ready(self, timeout: float = 60.0) -> WorkerProcess:
        deadline = time.monotonic() + timeout
        while f"worker {self.node} ready" not in self.log():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"worker {self.node} did not start:\n{self.log()[-3000:]}")
            time.sleep(0.1)
        return self

    def kill(self) -> None:
        """SIGKILL: no checkpoint, no ack, no goodbye (a crashed machine)."""
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)

    def stop(self, timeout: float = 30.0) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()


def worker_env(settings: Any, redis_url: str, **extra: str) -> dict[str, str]:
    """The environment for a worker sharing the test API's database and store."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GLINT_")}
    env.update(
        GLINT_DATA_DIR=str(settings.data_dir),
        GLINT_STORE_DIR=str(settings.store_root),
        GLINT_DATABASE_URL=settings.db_url,
        GLINT_REDIS_URL=redis_url,
        GLINT_HEARTBEAT_S="0.5",
        GLINT_STALE_AFTER_S="3",
        GLINT_PROGRESS_INTERVAL_S="0.2",
        GLINT_CANCEL_POLL_S="0.1",
        GLINT_WORKER_HEARTBEAT_S="0.5",
        GLINT_REAPER_INTERVAL_S="0.5",
        GLINT_QUEUED_GRACE_S="3",
        OMP_NUM_THREADS="1",
        PYTHONUNBUFFERED="1",
    )
    env.update(extra)
    return env


class Workers:
    """Starts ``glint worker`` processes on demand; stops them all at the end."""

    def __init__(self, server: Any, redis_url: str, log_dir: Path, **env: str) -> None:
        self.env = worker_env(server.settings, redis_url, **env)
        self.log_dir = log_dir
        self.procs: dict[str, WorkerProcess] = {}

    def start(self, name: str, **env: str) -> WorkerProcess:
        """A new worker process; ``env`` overrides this one's ``GLINT_*`` variables."""
        w = WorkerProcess(name, {**self.env, **env}, self.log_dir)
        self.procs[name] = w
        return w

    def ensure(self, *names: str) -> list[WorkerProcess]:
        started = [
            self.start(n)
            for n in names
            if n not in self.procs or self.procs[n].proc.poll() is not None
        ]
        for w in started:
            w.wait_ready()
        return [self.procs[n] for n in names]

    def logs(self) -> str:
        return "\n".join(w.log() for w in self.procs.values())

    def stop_all(self) -> None:
        for w in self.procs.values():
            w.stop()
