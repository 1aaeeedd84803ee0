"""Webhook pieces on their own: signing, the address guard, backoff, the claim."""

from __future__ import annotations

import ipaddress
import socket
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select, update

from api.service.db import Database
from api.service.migrate import upgrade
from api.service.models import DeliveryState, Job, Scene, WebhookDelivery
from api.service.recovery import settle_dead_runners
from api.service.settings import Settings
from api.service.webhook_dispatch import Claimed, backoff_s, claim, due, record, send
from api.service.webhook_guard import (
    ForbiddenAddressError,
    check_literal,
    forbidden_reason,
    resolve_public,
)
from api.service.webhooks import new_secret, signature_header, verify_signature

SECRET = "whsec_0123456789abcdef"
BODY = b'{"event":"job.succeeded"}'
T = 1700000000


# --- signing -------------------------------------------------------------------------


def test_signature_is_the_documented_hmac() -> None:
    """HMAC-SHA256(secret, b"1700000000." + body), checked against openssl's:
    printf '%s' '1700000000.{"event":"job.succeeded"}' | openssl dgst -sha256 -hmac SECRET"""
    expected = "fc254f4db74fd1e317ca0b00b1402c48f1e55cdfd71b955cad8c82553f74a2e6"
    assert signature_header(SECRET, BODY, T) == f"t={T},v1={expected}"


def test_verify_signature() -> None:
    header = signature_header(SECRET, BODY, T)
    assert verify_signature(SECRET, header, BODY, now=T + 10)
    assert not verify_signature(SECRET, header, BODY + b" ", now=T)  # body changed
    assert not verify_signature("whsec_another_secret_", header, BODY, now=T)
    assert not verify_signature(SECRET, header, BODY, now=T + 301)  # too old: a replay
    assert verify_signature(SECRET, header, BODY, tolerance_s=600, now=T + 301)
    for bad in ("", "v1=abc", f"t=x,v1={header[-64:]}", f"t={T}", "garbage"):
        assert not verify_signature(SECRET, bad, BODY, now=T), bad
    # several v1 values (e.g. while a receiver rotates secrets): one match is enough
    assert verify_signature(SECRET, f"t={T},v1={'0' * 64},{header.split(',')[1]}", BODY, now=T)


def test_new_secret() -> None:
    a, b = new_secret(), new_secret()
    assert a != b and a.startswith("whsec_") and len(a) == 6 + 32
    int(a[6:], 16)


# --- the address guard ---------------------------------------------------------------

FORBIDDEN = [
    "127.0.0.1",
    "127.255.0.9",
    "10.1.2.3",
    "172.16.0.1",
    "172.31.255.254",
    "192.168.1.1",
    "169.254.169.254",  # cloud metadata
    "100.64.0.1",  # CGNAT
    "224.0.0.1",
    "240.0.0.1",
    "0.0.0.0",
    "::1",
    "::",
    "fd00::1",  # unique local
    "fe80::1",
    "ff02::1",
    "::ffff:127.0.0.1",  # IPv4-mapped
    "::ffff:169.254.169.254",
    "2002:7f00:1::",  # 6to4 of 127.0.0.1
    "64:ff9b::a9fe:a9fe",  # NAT64 of 169.254.169.254
]
PUBLIC = ["8.8.8.8", "1.1.1.1", "93.184.216.34", "2606:4700:4700::1111", "::ffff:8.8.8.8"]


@pytest.mark.parametrize("address", FORBIDDEN)
def test_internal_addresses_are_forbidden(address: str) -> None:
    assert forbidden_reason(ipaddress.ip_address(address)) is not None


@pytest.mark.parametrize("address", PUBLIC)
def test_public_addresses_are_allowed(address: str) -> None:
    assert forbidden_reason(ipaddress.ip_address(address)) is None


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:8080/hook",
        "https://localhost/hook",
        "http://LOCALHOST./x",
        "http://api.localhost/x",
        "http://[::1]:9000/",
        "http://[::ffff:10.0.0.1]/",
        "http://169.254.169.254/latest/meta-data",
        "http://2130706433/",  # 127.0.0.1 as one number
        "http://0x7f.1/",
        "http://127.1/",
    ],
)
def test_literal_internal_hosts_are_refused_unless_allowed(url: str) -> None:
    with pytest.raises(ForbiddenAddressError):
        check_literal(url, allow_private=False)
    check_literal(url, allow_private=True)


def test_host_names_and_bad_urls_at_creation() -> None:
    check_literal("https://hooks.example.com/glint?x=1", allow_private=False)  # resolved later
    for bad in ("ftp://example.com/", "https:///path", "http://exa mple.com/", "http://h:99999/"):
        with pytest.raises(ValueError) as err:
            check_literal(bad, allow_private=False)
        assert not isinstance(err.value, ForbiddenAddressError), bad
    with pytest.raises(ValueError, match="longer than 2048"):
        check_literal("https://example.com/" + "a" * 2048, allow_private=False)


def _resolving(monkeypatch: pytest.MonkeyPatch, table: dict[str, list[str]]) -> None:
    real = socket.getaddrinfo

    def fake(host: str, port: Any, *args: Any, **kw: Any) -> list[Any]:
        if host not in table:
            return real(host, port, *args, **kw)
        return [
            (socket.AF_INET6 if ":" in a else socket.AF_INET, socket.SOCK_STREAM, 6, "", (a, port))
            for a in table[host]
        ]

    monkeypatch.setattr(socket, "getaddrinfo", fake)


def test_a_name_resolving_inside_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    _resolving(
        monkeypatch,
        {
            "hooks.example.com": ["93.184.216.34"],
            "sneaky.example.com": ["93.184.216.34", "10.0.0.7"],
        },
    )
    assert str(resolve_public("hooks.example.com", 443, allow_private=False)) == "93.184.216.34"
    with pytest.raises(ForbiddenAddressError, match=r"resolves to 10\.0\.0\.7, which is a private"):
        resolve_public("sneaky.example.com", 443, allow_private=False)
    assert str(resolve_public("sneaky.example.com", 443, allow_private=True)) == "93.184.216.34"


def test_delivery_to_a_forbidden_address_fails_at_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """No request is made, and the outcome is final (no retry), saying why."""
    import httpx

    _resolving(monkeypatch, {"metadata.example.com": ["169.254.169.254"]})

    def no_request(request: httpx.Request) -> httpx.Response:
        raise AssertionError(f"a request was made to {request.url}")

    settings = Settings(webhook_allow_private=False)
    with httpx.Client(transport=httpx.MockTransport(no_request)) as client:
        for url in ("http://metadata.example.com/x", "http://127.0.0.1:1/x"):
            claimed = Claimed("whd_x", "job_x", url, "job.failed", {}, SECRET, 1)
            outcome = send(client, claimed, settings)
            assert outcome.final and outcome.status is None
            assert outcome.error is not None and "refused" in outcome.error
            assert "GLINT_WEBHOOK_ALLOW_PRIVATE" in outcome.error


def test_delivery_connects_to_the_checked_address(monkeypatch: pytest.MonkeyPatch) -> None:
    """The request goes to the address that was checked, with the name in Host (and SNI)."""
    import httpx

    _resolving(monkeypatch, {"hooks.example.com": ["93.184.216.34"]})
    seen: list[httpx.Request] = []

    def receiver(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(302, headers={"Location": "http://10.0.0.1/"})

    with httpx.Client(transport=httpx.MockTransport(receiver)) as client:
        url = "https://hooks.example.com:8443/glint?x=1"
        claimed = Claimed("whd_x", "job_x", url, "job.failed", {"a": 1}, SECRET, 1)
        outcome = send(client, claimed, Settings())
    (request,) = seen
    assert str(request.url) == "https://93.184.216.34:8443/glint?x=1"
    assert request.headers["host"] == "hooks.example.com:8443"
    assert request.extensions["sni_hostname"] == "hooks.example.com"
    assert verify_signature(SECRET, request.headers["glint-signature"], request.content)
    assert outcome.status == 302 and not outcome.final  # a redirect is not followed
    assert outcome.error is not None and "redirects are not followed" in outcome.error


# --- retries and claims --------------------------------------------------------------


def test_backoff_doubles_up_to_the_cap() -> None:
    s = Settings(webhook_backoff_s=5, webhook_backoff_max_s=600)
    assert [backoff_s(s, n) for n in range(1, 9)] == [5, 10, 20, 40, 80, 160, 320, 600]


@pytest.fixture
def database(tmp_path: Path) -> Database:
    db = Database(f"sqlite:///{tmp_path / 'w.db'}")
    upgrade(db.engine)
    return db


def _delivery(db: Database) -> str:
    now = datetime.now(UTC)
    with db.write() as s:
        s.add(Scene(id="scn_w", owner="o", name="w"))
        s.flush()  # the job's scene first (no relationship tells the session so)
        s.add(
            Job(
                id="job_w",
                owner="o",
                scene_id="scn_w",
                config={},
                total_iterations=1,
                state="cancelled",
                webhook_url="https://hooks.example.com/x",
                webhook_secret=SECRET,
            )
        )
        s.flush()
        s.add(
            WebhookDelivery(
                id="whd_w",
                job_id="job_w",
                owner="o",
                url="https://hooks.example.com/x",
                event="job.cancelled",
                payload={"id": "whd_w"},
                next_attempt_at=now - timedelta(seconds=1),
            )
        )
    return "whd_w"


def test_the_reaper_records_the_ends_it_writes(database: Database) -> None:
    """A job whose runners kept dying ends failed in the reaper: its event is recorded
    there, once; a job it puts back in the queue has not ended."""
    settings = Settings(max_attempts=2, heartbeat_s=1, stale_after_s=2)
    stale = datetime.now(UTC) - timedelta(minutes=5)
    with database.write() as s:
        s.add(Scene(id="scn_r", owner="o", name="r"))
        s.flush()
        for job_id, deaths in (("job_dies", 1), ("job_again", 0)):
            s.add(
                Job(
                    id=job_id,
                    owner="o",
                    scene_id="scn_r",
                    config={},
                    total_iterations=1,
                    state="running",
                    runner_deaths=deaths,
                    heartbeat_at=stale,
                    webhook_url="https://hooks.example.com/x",
                    webhook_secret=SECRET,
                )
            )
    settled = settle_dead_runners(database, settings)
    assert (settled.failed, settled.requeued) == (["job_dies"], ["job_again"])
    settle_dead_runners(database, settings)  # nothing more to settle: nothing more recorded
    with database.read() as s:
        rows = list(s.scalars(select(WebhookDelivery)))
    assert [(r.job_id, r.event, r.state) for r in rows] == [("job_dies", "job.failed", "pending")]
    assert rows[0].payload["job"]["state"] == "failed"
    assert "the runner died 2 times" in rows[0].payload["job"]["error"]


def test_an_attempt_is_claimed_once(database: Database) -> None:
    """Two dispatchers (replicas) that both saw the delivery due: one of them sends it."""
    settings = Settings(webhook_max_attempts=2, webhook_backoff_s=0)
    delivery = _delivery(database)
    assert due(database, 10) == [(delivery, 0)]
    first = claim(database, settings, delivery, 0)
    assert first is not None and first.attempts == 1 and first.secret == SECRET
    assert claim(database, settings, delivery, 0) is None
    assert due(database, 10) == []  # leased while it is being sent
    from api.service.webhook_dispatch import Outcome

    assert record(database, settings, first, Outcome(500, "answered 500")) == "pending"
    second = claim(database, settings, delivery, 1)
    assert second is not None and claim(database, settings, delivery, 1) is None
    # the second attempt outlives its lease (a stalled process): a third dispatcher takes it
    with database.write() as s:
        s.execute(update(WebhookDelivery).values(next_attempt_at=datetime.now(UTC) - timedelta(1)))
    third = claim(database, settings, delivery, 2)
    assert third is not None and third.attempts == 3
    assert record(database, settings, second, Outcome(200)) is None  # too late: fenced off
    assert record(database, settings, third, Outcome(503, "answered 503")) == "failed"
    with database.read() as s:
        row = s.get(WebhookDelivery, delivery)
        job = s.get(Job, "job_w")
    assert row is not None and job is not None
    assert (row.state, row.attempts, row.last_status) == (DeliveryState.FAILED, 3, 503)
    assert row.last_error == "answered 503" and row.next_attempt_at is None
    assert job.version == 1 + 2  # each recorded attempt changes what the job shows
