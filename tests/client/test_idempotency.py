"""Creates that are retried are not duplicated: the same Idempotency-Key gives one job,
and the client's own retry after a lost answer reuses its key."""

from __future__ import annotations

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
