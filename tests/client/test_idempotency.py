"""Creates that are retried are not duplicated: the same Idempotency-Key gives one job,
and the client's own retry after a lost answer reuses its key."""

from __future__ import annotations

import hashlib
import hmac
import queue
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path

import httpx
import pytest
from glint_client import Client, IdempotencyKeyReused, new_idempotency_key

from tests.api.support import LiveServer
from tests.client.conftest import QUICK_CONFIG
from tests.client.support import CountingTransport


def test_the_same_idempotency_key_twice_gives_one_job(glint: Client, scene_dir: Path) -> None:
    scene = glint.create_scene_from(scene_dir)
    key = new_idempotency_key()
    first = glint.create_job(scene["id"], QUICK_CONFIG, idempotency_key=key)
    again = glint.create_job(scene["id"], QUICK_CONFIG, idempotency_key=key)
    assert again["id"] == first["id"]
    assert [j["id"] for j in glint.list_jobs(scene_id=scene["id"])] == [first["id"]]
    with pytest.raises(IdempotencyKeyReused) as reused:  # same key, another body
        glint.create_job(scene["id"], {**QUICK_CONFIG, "iterations": 30}, idempotency_key=key)
    assert reused.value.field == "header.idempotency-key"
    assert glint.wait(first["id"])["state"] == "succeeded"


def test_a_create_whose_answer_was_lost_is_retried_without_a_duplicate(
    server: LiveServer, key: str, scene_dir: Path
) -> None:
    keys: list[str] = []

    def lose_first_answers(request: httpx.Request, n: int) -> bool:
        if request.method == "POST" and request.url.path in ("/v1/scenes", "/v1/jobs"):
            keys.append(request.headers["Idempotency-Key"])
            return len(keys) in (1, 3)  # the first try of each create: done, answer lost
        return False

    counter = CountingTransport(before=lose_first_answers)
    with Client(server.url, key, transport=counter, retries=2) as c:
        scene = c.create_scene_from(scene_dir)
        job = c.create_job(scene["id"], QUICK_CONFIG)
        assert keys[0] == keys[1] and keys[2] == keys[3] and keys[0] != keys[2]
        assert [s["id"] for s in c.list_scenes()] == [scene["id"]]
        assert [j["id"] for j in c.list_jobs()] == [job["id"]]
        assert c.wait(job["id"])["state"] == "succeeded"


def test_a_retried_create_keeps_the_webhook_secret(
    server: LiveServer, key: str, scene_dir: Path
) -> None:
    """The server answers a secret it made only once; the client makes its own, so a
    create whose answer was lost still knows the secret the events are signed with."""
    received: queue.Queue[tuple[str, bytes]] = queue.Queue()

    class Hook(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = self.rfile.read(int(self.headers["Content-Length"]))
            received.put((self.headers["Glint-Signature"], body))
            self.send_response(204)
            self.end_headers()

        def log_message(self, *args: object) -> None:
            pass

    hook_server = HTTPServer(("127.0.0.1", 0), Hook)
    threading.Thread(target=hook_server.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{hook_server.server_port}/glint"
    tries = []

    def lose_the_first_answer(request: httpx.Request, n: int) -> bool:
        if request.method == "POST" and request.url.path == "/v1/jobs":
            tries.append(request.read())
            return len(tries) == 1
        return False

    try:
        with Client(server.url, key, transport=CountingTransport(lose_the_first_answer)) as c:
            scene = c.create_scene_from(scene_dir)
            job = c.create_job(scene["id"], QUICK_CONFIG, webhook={"url": url})
            assert len(tries) == 2 and tries[0] == tries[1]  # one body, one secret
            secret = job["webhook"]["secret"]
            assert secret.startswith("whsec_")
            assert c.wait(job["id"])["state"] == "succeeded"
        signature, body = received.get(timeout=30)
    finally:
        hook_server.shutdown()
    stamp, v1 = (part.split("=", 1)[1] for part in signature.split(","))
    expected = hmac.new(secret.encode(), f"{stamp}.".encode() + body, hashlib.sha256)
    assert hmac.compare_digest(v1, expected.hexdigest())
