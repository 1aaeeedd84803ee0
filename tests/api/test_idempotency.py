"""Idempotency-Key on the creating POSTs: a retry answers the first request's object."""

from __future__ import annotations

import threading

import httpx

from tests.api.support import TINY_CONFIG, LiveServer, list_all, multipart


def _ready_scene(client: httpx.Client, scene: list[tuple[str, bytes]]) -> str:
    sid = client.post("/v1/scenes", json={"name": "idem"}).json()["id"]
    assert client.post(f"/v1/scenes/{sid}/files", files=multipart(scene)).status_code == 201
    assert client.post(f"/v1/scenes/{sid}/commit").status_code == 200
    return sid


def test_the_same_key_twice_makes_one_scene(client) -> None:
    headers = {"Idempotency-Key": "scene-0001"}
    first = client.post("/v1/scenes", json={"name": "a"}, headers=headers)
    again = client.post("/v1/scenes", json={"name": "a"}, headers=headers)
    assert first.status_code == again.status_code == 201
    assert again.json()["id"] == first.json()["id"]
    assert again.headers["Idempotent-Replayed"] == "true"
    assert "Idempotent-Replayed" not in first.headers
    assert len(list_all(client, "/v1/scenes")) == 1
    # another key, another scene; the same key with another body is refused
    other = client.post("/v1/scenes", json={"name": "a"}, headers={"Idempotency-Key": "k2"})
    assert other.json()["id"] != first.json()["id"]
    reused = client.post("/v1/scenes", json={"name": "b"}, headers=headers)
    assert reused.status_code == 422
    assert reused.json()["type"] == "urn:glint:problem:idempotency-key-reused"
    assert reused.json()["errors"][0]["field"] == "header.idempotency-key"
    assert len(list_all(client, "/v1/scenes")) == 2


def test_the_same_key_twice_gives_one_job(server: LiveServer, client, scene) -> None:
    sid = _ready_scene(client, scene)
    body = {"scene_id": sid, "config": TINY_CONFIG}
    headers = {"Idempotency-Key": "job-create-7f3a"}
    server.queue.hold()
    try:
        first = client.post("/v1/jobs", json=body, headers=headers)
        again = client.post("/v1/jobs", json=body, headers=headers)
    finally:
        server.queue.release()
    assert first.status_code == again.status_code == 201, again.text
    assert again.json()["id"] == first.json()["id"]
    assert [j["id"] for j in list_all(client, "/v1/jobs")] == [first.json()["id"]]
    assert server.queue.delivered.count(first.json()["id"]) == 1  # enqueued once
    server.queue.join(120)


def test_racing_requests_with_one_key_make_one_scene(client) -> None:
    answers: list[httpx.Response] = []
    headers = {"Idempotency-Key": "race-1"}

    def post() -> None:
        answers.append(client.post("/v1/scenes", json={"name": "r"}, headers=headers))

    threads = [threading.Thread(target=post) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert {a.status_code for a in answers} == {201}
    assert len({a.json()["id"] for a in answers}) == 1
    assert len(list_all(client, "/v1/scenes")) == 1


def test_keys_are_per_owner_and_checked(server: LiveServer, client) -> None:
    headers = {"Idempotency-Key": "shared-name"}
    mine = client.post("/v1/scenes", json={"name": "a"}, headers=headers).json()["id"]
    with server.client(server.new_key("someone-else")) as other:
        theirs = other.post("/v1/scenes", json={"name": "a"}, headers=headers)
        assert theirs.status_code == 201 and theirs.json()["id"] != mine
    bad = client.post("/v1/scenes", json={"name": "a"}, headers={"Idempotency-Key": "tab\there"})
    assert bad.status_code == 422
    assert bad.json()["errors"][0]["field"] == "header.idempotency-key"
