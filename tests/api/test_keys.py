"""API keys over HTTP, and the real ``glint keys create`` / ``glint serve`` commands."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import httpx

from api.auth import hash_key
from api.service.db import Database
from api.service.models import ApiKey
from tests.api.support import LiveServer, free_port, list_all

REPO = Path(__file__).resolve().parents[2]


def test_health_needs_no_key(server: LiveServer) -> None:
    r = httpx.get(f"{server.url}/v1/health")
    assert float(r.headers["server-timing"].removeprefix("app;dur=")) >= 0
    assert r.status_code == 200 and r.json() == {
        "status": "ok",
        "database": "ok",
        "version": r.json()["version"],
    }


def test_keys_create_list_revoke(server: LiveServer) -> None:
    key = server.new_key("keyholder")
    with server.client(key) as c:
        me = c.get("/v1/keys/me").json()
        assert me["owner"] == "keyholder"
        r = c.post("/v1/keys", json={"name": "ci"})
        assert r.status_code == 201
        new = r.json()
        assert new["key"].startswith("glk_") and new["key"].startswith(new["prefix"])
        listed = list_all(c, "/v1/keys")
        assert {k["id"] for k in listed} == {me["key_id"], new["id"]}
        assert all("key" not in k and "key_hash" not in k for k in listed)
        # the new key acts for the same owner; revoking it leaves this one working
        with server.client(new["key"]) as c2:
            assert c2.get("/v1/keys/me").json()["owner"] == "keyholder"
            assert c.delete(f"/v1/keys/{new['id']}").status_code == 204
            assert c2.get("/v1/keys/me").status_code == 401
        assert c.get("/v1/keys/me").status_code == 200
    with server.client(server.new_key("intruder")) as other:
        assert other.delete(f"/v1/keys/{me['key_id']}").status_code == 404
    # only the hash is stored
    with server.database.read() as s:
        row = s.get(ApiKey, new["id"])
        assert row.key_hash == hash_key(new["key"]) and new["key"] not in row.key_hash


def _glint(*args: str, env: dict[str, str]) -> subprocess.Popen:
    code = "import sys; from core.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.Popen(
        [sys.executable, "-c", code, *args],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_cli_keys_create_and_serve(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "GLINT_DATA_DIR": str(tmp_path)}
    p = _glint("keys", "create", "cli-owner", env=env)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 0, err
    key = out.strip()
    assert key.startswith("glk_") and "shown only now" in err
    db = Database(f"sqlite:///{tmp_path / 'glint.db'}")
    with db.read() as s:
        assert s.query(ApiKey).filter_by(key_hash=hash_key(key)).one().owner == "cli-owner"
    db.dispose()

    port = free_port()
    server = _glint("serve", "--port", str(port), "--log-level", "warning", env=env)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                r = httpx.get(
                    f"http://127.0.0.1:{port}/v1/keys/me",
                    headers={"Authorization": f"Bearer {key}"},
                )
                break
            except httpx.ConnectError:
                assert server.poll() is None, server.communicate()[1]
                assert time.monotonic() < deadline, "glint serve did not come up"
                time.sleep(0.2)
        assert r.status_code == 200 and r.json()["owner"] == "cli-owner"
    finally:
        server.terminate()
        server.wait(30)
    assert (tmp_path / "store").is_dir()
