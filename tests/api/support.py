"""Test machinery: a real uvicorn on loopback, a controllable queue double, helpers."""

from __future__ import annotations

import io
import json
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import uvicorn

from api.auth import create_key
from api.main import create_app
from api.service.db import Database
from api.service.runner import run_job
from api.service.settings import Settings

TINY_CONFIG: dict[str, Any] = {
    "iterations": 20,
    "init_points": 300,
    "envmap_resolution": 8,
    "backend": "auto",
    "eval": {"every": 10, "views": 1},
    "checkpoint_every": 10,
    "densify": {"enabled": False},  # short runs would densify every step
    "outputs": {"mesh_resolution": 48},  # the mesh phase, at a size fit for 24² views
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ThreadQueue:
    """Queue double: each enqueued job runs the real ``run_job`` on its own thread.

    ``hold()`` parks new jobs (they stay ``queued`` in the database) until ``release()``,
    so tests can act on queued jobs deterministically. ``delivered`` records every id,
    duplicates included (delivery is at least once).
    """

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.delivered: list[str] = []
        self.held: list[str] = []
        self.threads: list[threading.Thread] = []
        self.results: dict[str, list[str | None]] = {}
        self._holding = False
        self._lock = threading.Lock()

    def enqueue(self, job_id: str) -> None:
        with self._lock:
            self.delivered.append(job_id)
            if self._holding:
                self.held.append(job_id)
                return
        self._start(job_id)

    def _start(self, job_id: str) -> None:
        def body() -> None:
            state = run_job(job_id, self.settings)
            with self._lock:
                self.results.setdefault(job_id, []).append(state)

        t = threading.Thread(target=body, name=f"test-job-{job_id}", daemon=True)
        self.threads.append(t)
        t.start()

    def hold(self) -> None:
        with self._lock:
            self._holding = True

    def release(self) -> None:
        with self._lock:
            self._holding = False
            held, self.held = self.held, []
        for job_id in held:
            self._start(job_id)

    def join(self, timeout: float = 120.0) -> None:
        deadline = time.monotonic() + timeout
        for t in list(self.threads):
            t.join(max(deadline - time.monotonic(), 0.1))


class RecordingQueue:
    """Queue double that only records ids (the jobs stay queued): for fuzzing."""

    def __init__(self) -> None:
        self.delivered: list[str] = []

    def enqueue(self, job_id: str) -> None:
        self.delivered.append(job_id)


class LiveServer:
    """The app on a real uvicorn in a background thread, on a free loopback port."""

    def __init__(self, settings: Settings, queue: Any) -> None:
        self.settings = settings
        self.queue = queue
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.app = create_app(settings, queue=queue)
        config = uvicorn.Config(
            self.app, host="127.0.0.1", port=self.port, log_level="warning", lifespan="on"
        )
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)

    def start(self) -> LiveServer:
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("uvicorn did not start")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(15)

    @property
    def database(self) -> Database:
        return self.app.state.database

    def new_key(self, owner: str) -> str:
        with self.database.write() as s:
            _row, key = create_key(s, owner)
        return key

    def client(self, key: str | None, **kw: Any) -> httpx.Client:
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=60.0, **kw)


def make_settings(root: Path, database_url: str | None = None, **overrides: Any) -> Settings:
    """Settings for a test server: everything under ``root``, small upload limits."""
    values: dict[str, Any] = {
        "data_dir": root,
        "store_dir": root / "store",
        "database_url": database_url or f"sqlite:///{root / 'glint.db'}",
        "max_file_bytes": 512 * 1024,
        "max_scene_bytes": 4 * 1024 * 1024,
        "max_scene_files": 40,
        "max_archive_bytes": 2 * 1024 * 1024,
        "max_archive_ratio": 50.0,
        "upload_chunk_bytes": 64 * 1024,
        "progress_interval_s": 0.2,
        "cancel_poll_s": 0.1,
        "heartbeat_s": 1.0,
        "sse_poll_s": 0.1,
    }
    values.update(overrides)
    return Settings(**values)


def scene_files(root: Path) -> list[tuple[str, bytes]]:
    """(relative path, bytes) of every file of a scene folder, sorted."""
    return sorted(
        (p.relative_to(root).as_posix(), p.read_bytes()) for p in root.rglob("*") if p.is_file()
    )


def multipart(files: list[tuple[str, bytes]]) -> list[tuple[str, tuple[str, io.BytesIO, str]]]:
    """httpx ``files=`` with each part's filename set to its scene path."""
    return [("files", (name, io.BytesIO(data), "application/octet-stream")) for name, data in files]


def wait_for(predicate: Callable[[], Any], timeout: float = 90.0, every: float = 0.1) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout} s")
        time.sleep(every)


def store_files(store_root: Path) -> list[str]:
    """Every file in the store, as relative POSIX paths."""
    return sorted(
        p.relative_to(store_root).as_posix() for p in store_root.rglob("*") if p.is_file()
    )


def list_all(client: httpx.Client, path: str, **params: Any) -> list[dict[str, Any]]:
    """Every item of a list endpoint, following its pages (``items``/``total``/``limit``)."""
    items: list[dict[str, Any]] = []
    offset = 0
    while True:
        r = client.get(path, params={**params, "limit": 200, "offset": offset})
        assert r.status_code == 200, (path, r.status_code, r.text)
        page = r.json()
        assert set(page) == {"items", "total", "limit", "offset"}, page
        items += page["items"]
        offset += page["limit"]
        if not page["items"] or offset >= page["total"]:
            return items


def job_events(client: httpx.Client, job_id: str, timeout: float = 180) -> list[tuple[str, dict]]:
    """Every server-sent event of a job's stream as (event, data), until the server ends it."""
    events: list[tuple[str, dict]] = []
    with client.stream("GET", f"/v1/jobs/{job_id}/events", timeout=timeout) as r:
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/event-stream")
        kind, data = None, []
        for line in r.iter_lines():
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: "):
                data.append(line[6:])
            elif line == "" and kind:
                events.append((kind, json.loads("\n".join(data))))
                kind, data = None, []
    return events
