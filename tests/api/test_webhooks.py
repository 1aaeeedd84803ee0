"""Webhooks end to end: a real HTTP receiver gets one signed event per job end.

The server here allows private addresses (its receiver listens on 127.0.0.1) and retries
fast (backoff 0.05 s, 3 attempts); the default server (``server``, settings as shipped)
shows that the same address is refused there.
"""

from __future__ import annotations

import json
import socket
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from email.message import Message
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from api.service.models import WebhookDelivery
from api.service.webhooks import signature_header, verify_signature, wake_dispatchers
from tests.api.support import (
    TINY_CONFIG,
    LiveServer,
    ThreadQueue,
    list_all,
    make_settings,
    multipart,
    wait_for,
)

MAX_ATTEMPTS = 3
SECRET = "a-receiver-secret-0123"


@dataclass(frozen=True)
class Received:
    path: str
    headers: Message
    body: bytes

    @property
    def event(self) -> dict[str, Any]:
        return json.loads(self.body)


class Receiver:
    """A webhook receiver on loopback: records every request; paths under /fail answer
    500, every other path 204."""

    def __init__(self) -> None:
        self.requests: list[Received] = []
        self.lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
                with receiver.lock:
                    receiver.requests.append(Received(self.path, self.headers, body))
                self.send_response(500 if self.path.startswith("/fail") else 204)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args: Any) -> None:  # quiet
                pass

        self.http = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.http.serve_forever, daemon=True)

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.http.server_address[1]}{path}"

    def of(self, job_id: str) -> list[Received]:
        with self.lock:
            return [r for r in self.requests if r.event["job"]["id"] == job_id]


@pytest.fixture(scope="module")
def receiver() -> Iterator[Receiver]:
    r = Receiver()
    r.thread.start()
    yield r
    r.http.shutdown()


@pytest.fixture(scope="module")
def hooks(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    settings = make_settings(
        tmp_path_factory.mktemp("webhooks"),
        webhook_allow_private=True,
        webhook_backoff_s=0.05,
        webhook_backoff_max_s=0.2,
        webhook_max_attempts=MAX_ATTEMPTS,
        webhook_poll_s=0.05,
        webhook_timeout_s=5,
    )
    srv = LiveServer(settings, ThreadQueue(settings)).start()
    yield srv
    srv.queue.join(60)
    srv.stop()


OWNER = f"hooks-{uuid.uuid4().hex[:8]}"


@pytest.fixture(scope="module")
def ready_scene(hooks: LiveServer, scene: list[tuple[str, bytes]]) -> tuple[str, str]:
    """(key, scene id): a key of OWNER, who has a committed scene on the webhook server."""
    key = hooks.new_key(OWNER)
    with hooks.client(key) as c:
        sid = c.post("/v1/scenes", json={"name": "hooks"}).json()["id"]
        assert c.post(f"/v1/scenes/{sid}/files", files=multipart(scene)).is_success
        assert c.post(f"/v1/scenes/{sid}/commit").status_code == 200
    return key, sid


@pytest.fixture
def held(hooks: LiveServer) -> Iterator[ThreadQueue]:
    """The queue parks new jobs (they stay queued) until the test ends."""
    queue: ThreadQueue = hooks.queue
    queue.hold()
    yield queue
    queue.release()


def _deliveries(c: httpx.Client, job_id: str) -> list[dict[str, Any]]:
    return list_all(c, f"/v1/jobs/{job_id}/webhooks")


def _settled(c: httpx.Client, job_id: str, n: int = 1) -> list[dict[str, Any]]:
    """The job's deliveries once ``n`` exist and none is pending."""

    def done() -> list[dict[str, Any]] | None:
        items = _deliveries(c, job_id)
        ok = len(items) >= n and all(d["state"] != "pending" for d in items)
        return items if ok else None

    return wait_for(done, timeout=30, every=0.05)


def _check_signed(r: Received, secret: str, event: str, delivery: dict[str, Any]) -> None:
    assert r.headers["Content-Type"] == "application/json"
    assert r.headers["User-Agent"].startswith("Glint-Webhooks/")
    assert r.headers["Glint-Event"] == event
    assert r.headers["Glint-Delivery"] == delivery["id"]
    signature = r.headers["Glint-Signature"]
    assert verify_signature(secret, signature, r.body)
    assert not verify_signature(secret, signature, r.body.replace(b"job.", b"job_"))
    assert not verify_signature("another-secret-0123456", signature, r.body)
    assert r.event["id"] == delivery["id"] and r.event["event"] == event


def test_a_succeeded_job_sends_one_signed_event(
    hooks: LiveServer, ready_scene: tuple[str, str], receiver: Receiver
) -> None:
    key, sid = ready_scene
    url = receiver.url("/hooks/glint?source=test")
    with hooks.client(key) as c:
        body = {"scene_id": sid, "config": TINY_CONFIG, "webhook": {"url": url, "secret": SECRET}}
        r = c.post("/v1/jobs", json=body)
        assert r.status_code == 201, r.text
        job = r.json()
        assert job["webhook"] == {"url": url, "deliveries": []}  # its own secret: not echoed
        wait_for(lambda: c.get(f"/v1/jobs/{job['id']}").json()["state"] == "succeeded", 90)
        (delivery,) = _settled(c, job["id"])
        assert delivery["state"] == "delivered" and delivery["attempts"] == 1
        assert delivery["last_status"] == 204 and delivery["last_error"] is None
        assert delivery["event"] == "job.succeeded" and delivery["url"] == url
        assert delivery["delivered_at"] and delivery["next_attempt_at"] is None
        shown = c.get(f"/v1/jobs/{job['id']}").json()
    (got,) = receiver.of(job["id"])
    assert got.path == "/hooks/glint?source=test"
    _check_signed(got, SECRET, "job.succeeded", delivery)
    sent = got.event["job"]
    assert sent["state"] == "succeeded" and sent["progress"] == 1.0 and sent["finished_at"]
    assert "secret" not in json.dumps(shown["webhook"]) and SECRET not in got.body.decode()
    assert shown["webhook"]["deliveries"] == [
        {k: delivery[k] for k in shown["webhook"]["deliveries"][0]}
    ]
    # the event's job is the job as GET showed it then; since, only the delivery is new
    assert shown["version"] > sent["version"]
    for changed in ("version", "webhook"):
        sent.pop(changed), shown.pop(changed)
    assert sent == shown


def test_a_cancelled_job_with_a_made_secret(
    hooks: LiveServer, ready_scene: tuple[str, str], receiver: Receiver, held: ThreadQueue
) -> None:
    key, sid = ready_scene
    url = receiver.url("/cancelled")
    with hooks.client(key) as c:
        body, once = (
            {"scene_id": sid, "webhook": {"url": url}},
            {"Idempotency-Key": str(uuid.uuid4())},
        )
        r = c.post("/v1/jobs", json=body, headers=once)
        assert r.status_code == 201, r.text
        job = r.json()
        secret = job["webhook"]["secret"]  # made by the server, answered this once
        assert secret.startswith("whsec_") and len(secret) == 38
        assert "secret" not in c.get(f"/v1/jobs/{job['id']}").json()["webhook"]
        again = c.post("/v1/jobs", json=body, headers=once).json()  # a retry: the same job
        assert again["id"] == job["id"] and "secret" not in again["webhook"]
        listed = {j["id"]: j for j in list_all(c, "/v1/jobs")}
        assert "secret" not in listed[job["id"]]["webhook"]
        assert c.post(f"/v1/jobs/{job['id']}/cancel").json()["state"] == "cancelled"
        (delivery,) = _settled(c, job["id"])
        assert delivery["state"] == "delivered" and delivery["event"] == "job.cancelled"
    (got,) = receiver.of(job["id"])
    _check_signed(got, secret, "job.cancelled", delivery)
    assert got.event["job"]["state"] == "cancelled"


def test_each_end_of_a_resumed_job_is_an_event(
    hooks: LiveServer, ready_scene: tuple[str, str], receiver: Receiver, held: ThreadQueue
) -> None:
    key, sid = ready_scene
    with hooks.client(key) as c:
        body = {"scene_id": sid, "webhook": {"url": receiver.url("/again"), "secret": SECRET}}
        job = c.post("/v1/jobs", json=body).json()
        for n in (1, 2, 3):
            assert c.post(f"/v1/jobs/{job['id']}/cancel").json()["state"] == "cancelled"
            _settled(c, job["id"], n)
            if n < 3:
                assert c.post(f"/v1/jobs/{job['id']}/resume").json()["state"] == "queued"
        items = _deliveries(c, job["id"])
        page = c.get(f"/v1/jobs/{job['id']}/webhooks", params={"limit": 2, "offset": 2}).json()
        shown = c.get(f"/v1/jobs/{job['id']}").json()["webhook"]["deliveries"]
    assert [d["state"] for d in items] == ["delivered"] * 3
    assert len({d["id"] for d in items}) == 3
    times = [d["created_at"] for d in items]
    assert times == sorted(times, reverse=True)
    assert (page["total"], page["items"]) == (3, items[2:])
    assert [d["id"] for d in shown] == [d["id"] for d in items]  # newest first there too
    got = receiver.of(job["id"])
    assert sorted(r.headers["Glint-Delivery"] for r in got) == sorted(d["id"] for d in items)


def test_a_failing_receiver_is_retried_then_the_delivery_fails(
    hooks: LiveServer, ready_scene: tuple[str, str], receiver: Receiver, held: ThreadQueue
) -> None:
    key, sid = ready_scene
    with hooks.client(key) as c:
        body = {"scene_id": sid, "webhook": {"url": receiver.url("/fail"), "secret": SECRET}}
        job = c.post("/v1/jobs", json=body).json()
        c.post(f"/v1/jobs/{job['id']}/cancel")
        (delivery,) = _settled(c, job["id"])
        shown = c.get(f"/v1/jobs/{job['id']}").json()["webhook"]["deliveries"]
    assert delivery["state"] == "failed" and delivery["attempts"] == MAX_ATTEMPTS
    assert delivery["last_status"] == 500 and delivery["last_error"] == "answered 500"
    assert delivery["delivered_at"] is None and delivery["next_attempt_at"] is None
    assert [d["state"] for d in shown] == ["failed"]
    got = receiver.of(job["id"])
    assert len(got) == MAX_ATTEMPTS  # each attempt once, the same delivery each time
    assert {r.headers["Glint-Delivery"] for r in got} == {delivery["id"]}
    for r in got:
        assert verify_signature(SECRET, r.headers["Glint-Signature"], r.body)


def test_a_key_default_webhook(
    hooks: LiveServer, ready_scene: tuple[str, str], receiver: Receiver, held: ThreadQueue
) -> None:
    """A job with no webhook of its own takes its key's (URL and secret, copied); the
    owner's other keys are not concerned."""
    other_key, sid = ready_scene
    key = hooks.new_key(OWNER)
    url = receiver.url("/key-default")
    with hooks.client(key) as c, hooks.client(other_key) as other:
        assert c.get("/v1/keys/me").json()["webhook_url"] is None
        r = c.put("/v1/keys/me/webhook", json={"url": url})
        assert r.status_code == 200, r.text
        secret = r.json()["secret"]
        assert r.json()["url"] == url and secret.startswith("whsec_")
        assert c.get("/v1/keys/me").json()["webhook_url"] == url
        assert other.get("/v1/keys/me").json()["webhook_url"] is None
        unhooked = other.post("/v1/jobs", json={"scene_id": sid}).json()
        assert unhooked["webhook"] is None
        assert other.post(f"/v1/jobs/{unhooked['id']}/cancel").status_code == 200
        job = c.post("/v1/jobs", json={"scene_id": sid}).json()
        assert job["webhook"] == {"url": url, "deliveries": []}  # the key's secret: not shown
        c.post(f"/v1/jobs/{job['id']}/cancel")
        (delivery,) = _settled(c, job["id"])
        assert delivery["state"] == "delivered"
        (got,) = receiver.of(job["id"])
        _check_signed(got, secret, "job.cancelled", delivery)
        assert c.delete("/v1/keys/me/webhook").status_code == 204
        assert c.get("/v1/keys/me").json()["webhook_url"] is None
        unhooked = c.post("/v1/jobs", json={"scene_id": sid}).json()
        assert unhooked["webhook"] is None
        assert c.post(f"/v1/jobs/{unhooked['id']}/cancel").status_code == 200
        assert _deliveries(c, unhooked["id"]) == []  # no webhook, no delivery
        assert c.get(f"/v1/jobs/{job['id']}").json()["webhook"]["url"] == url  # kept
        with hooks.client(hooks.new_key("stranger")) as stranger:  # another owner's: 404
            assert stranger.get(f"/v1/jobs/{job['id']}/webhooks").status_code == 404


def _refused(r: httpx.Response, field: str) -> str:
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["type"] == "urn:glint:problem:validation-error"
    assert r.headers["content-type"] == "application/problem+json"
    assert [e["field"] for e in body["errors"]] == [field]
    return body["errors"][0]["message"]


def test_forbidden_addresses_are_refused_by_default(server: LiveServer, key: str) -> None:
    """Settings as shipped: loopback, private and metadata addresses are refused (422,
    naming the field) before anything is created; so are schemes other than http(s)."""
    assert server.settings.webhook_allow_private is False
    with server.client(key) as c:
        before = c.get("/v1/jobs").json()["total"]
        for url in (
            "http://127.0.0.1:8080/hook",
            "http://localhost/hook",
            "http://[::ffff:10.0.0.1]/",
            "http://169.254.169.254/latest/meta-data/",
        ):
            body = {"scene_id": "scn_whatever", "webhook": {"url": url}}
            message = _refused(c.post("/v1/jobs", json=body), "body.webhook.url")
            assert "public addresses only" in message
        body = {"scene_id": "scn_x", "webhook": {"url": "file:///etc/passwd"}}
        assert "http or https" in _refused(c.post("/v1/jobs", json=body), "body.webhook.url")
        body = {"scene_id": "scn_x", "webhook": {"url": "https://example.com/", "secret": "short"}}
        _refused(c.post("/v1/jobs", json=body), "body.webhook.secret")
        _refused(c.put("/v1/keys/me/webhook", json={"url": "http://10.1.2.3/"}), "body.url")
        assert c.get("/v1/keys/me").json()["webhook_url"] is None
        assert c.get("/v1/jobs").json()["total"] == before


def test_a_name_that_resolves_inside_fails_its_delivery(
    hooks: LiveServer,
    ready_scene: tuple[str, str],
    held: ThreadQueue,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A host name passes creation; at delivery it resolves to loopback, and without
    GLINT_WEBHOOK_ALLOW_PRIVATE the delivery fails at once (no request, no retry)."""
    key, sid = ready_scene
    monkeypatch.setattr(hooks.settings, "webhook_allow_private", False)
    name = "loopback-alias.example.test"  # a DNS name pointing at 127.0.0.1, as some do
    real = socket.getaddrinfo

    def resolve(host: str, *args: Any, **kw: Any) -> Any:
        return real("127.0.0.1" if host == name else host, *args, **kw)

    monkeypatch.setattr(socket, "getaddrinfo", resolve)
    with hooks.client(key) as c:
        url = f"http://{name}/hook"
        job = c.post("/v1/jobs", json={"scene_id": sid, "webhook": {"url": url}}).json()
        c.post(f"/v1/jobs/{job['id']}/cancel")
        (delivery,) = _settled(c, job["id"])
    assert delivery["state"] == "failed" and delivery["attempts"] == 1
    assert delivery["last_status"] is None
    assert "resolves to 127.0.0.1, which is a loopback address" in delivery["last_error"]
    assert "GLINT_WEBHOOK_ALLOW_PRIVATE" in delivery["last_error"]


def test_deleting_a_job_deletes_its_deliveries(
    hooks: LiveServer, ready_scene: tuple[str, str], receiver: Receiver, held: ThreadQueue
) -> None:
    key, sid = ready_scene
    with hooks.client(key) as c:
        body = {"scene_id": sid, "webhook": {"url": receiver.url("/gone"), "secret": SECRET}}
        job = c.post("/v1/jobs", json=body).json()
        c.post(f"/v1/jobs/{job['id']}/cancel")
        _settled(c, job["id"])
        assert c.delete(f"/v1/jobs/{job['id']}").status_code == 204
    with hooks.database.read() as s:
        left = s.scalars(select(WebhookDelivery.id).where(WebhookDelivery.job_id == job["id"]))
        assert list(left) == []


def test_a_job_end_in_the_api_wakes_its_dispatcher(
    hooks: LiveServer, ready_scene: tuple[str, str], receiver: Receiver, held: ThreadQueue
) -> None:
    """Polling is the fallback (ends recorded by workers elsewhere); an end this process
    records is sent at once."""
    key, sid = ready_scene
    hooks.settings.webhook_poll_s = 60.0
    try:
        with hooks.client(key) as c:
            wake_dispatchers()  # the dispatcher's next wait is a long one
            time.sleep(0.2)
            body = {"scene_id": sid, "webhook": {"url": receiver.url("/woken"), "secret": SECRET}}
            job = c.post("/v1/jobs", json=body).json()
            c.post(f"/v1/jobs/{job['id']}/cancel")
            wait_for(lambda: receiver.of(job["id"]), timeout=10, every=0.05)
    finally:
        hooks.settings.webhook_poll_s = 0.05
        wake_dispatchers()


def test_the_documented_receiver_example_verifies() -> None:
    """docs/api.md's receiver check, run against a signed request of this module."""
    doc = (Path(__file__).resolve().parents[2] / "docs" / "api.md").read_text()
    start = doc.index("# webhook receiver: check the signature")
    code = doc[doc.rindex("```python", 0, start) + len("```python") : doc.index("```", start)]
    scope: dict[str, Any] = {}
    exec(compile(code, "docs/api.md", "exec"), scope)
    body = b'{"id":"whd_1","event":"job.failed"}'
    assert scope["verify"](SECRET, signature_header(SECRET, body), body)
    assert not scope["verify"](SECRET, signature_header(SECRET, body), body + b"x")
