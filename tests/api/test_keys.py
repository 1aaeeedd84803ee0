"""API keys over HTTP, and the real ``glint keys create`` / ``glint serve`` commands."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import httpx

from api.auth import hash_key
from api.service.db import Database
from api.service.models import ApiKey
from tests.api.support import LiveServer, free_port, list_all, multipart

REPO = Path(__file__).resolve().parents[2]


def test_health_needs_no_key(server: LiveServer) -> None:
    r = httpx.get(f"{server.url}/v1/health")
    assert float(r.headers["server-timing"].removeprefix("app;dur=")) >= 0
    assert r.status_code == 200 and r.json() == {
        "status": "ok",
        "database": "ok",
        "store": "ok",
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


def test_key_commands_start_without_torch(tmp_path: Path) -> None:
    """Creating, listing and revoking a key computes nothing, so it must not pay for
    torch's import (the thread layout every computing command applies)."""
    code = (
        "import sys; from core.cli import main; "
        "rcs = [main(['keys', 'create', 'owner-t']), main(['keys', 'list'])]; "
        "print(rcs, 'torch' in sys.modules)"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO), "GLINT_DATA_DIR": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[0, 0] False", out.stdout


def _problem(r: httpx.Response, status: int, slug: str) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == "application/problem+json"
    body = r.json()
    assert body["type"] == f"urn:glint:problem:{slug}", body
    return body


def test_scopes(server: LiveServer) -> None:
    admin_key = server.new_key("scoped")  # what glint keys create makes: an admin key
    with server.client(admin_key) as admin:
        me = admin.get("/v1/keys/me").json()
        assert (me["scope"], me["name"]) == ("admin", "scoped")
        made = {
            scope: admin.post("/v1/keys", json={"name": scope, "scope": scope}).json()
            for scope in ("read", "write")
        }
        assert admin.post("/v1/keys", json={"name": "default"}).json()["scope"] == "write"
        sid = admin.post("/v1/scenes", json={"name": "theirs"}).json()["id"]
    reader = server.client(made["read"]["key"])
    writer = server.client(made["write"]["key"])
    try:
        # read: every GET, and viewing
        assert reader.get("/v1/keys/me").json()["scope"] == "read"
        assert reader.get(f"/v1/scenes/{sid}").status_code == 200
        assert reader.get("/v1/jobs").status_code == 200
        assert reader.post("/v1/jobs/job_x/viewer-token").status_code == 404  # not 403
        # ... and no write: 403 naming the scope needed, nothing changed
        before = reader.get("/v1/scenes").json()["total"]
        for r in (
            reader.post("/v1/scenes", json={"name": "nope"}),
            reader.delete(f"/v1/scenes/{sid}"),
            reader.post("/v1/jobs", json={"scene_id": sid}),
            reader.post(f"/v1/scenes/{sid}/files", files=multipart([("a.txt", b"x")])),
        ):
            body = _problem(r, 403, "insufficient-scope")
            assert "needs a key with scope 'write'" in body["detail"]
            assert body["errors"][0]["field"] == "header.authorization"
        assert reader.get("/v1/scenes").json()["total"] == before
        assert reader.get(f"/v1/scenes/{sid}/files").json()["total"] == 0
        # write: changes scenes, but makes no keys and revokes no other key
        assert writer.post("/v1/scenes", json={"name": "mine"}).status_code == 201
        _problem(writer.post("/v1/keys", json={"name": "x"}), 403, "insufficient-scope")
        r = writer.delete(f"/v1/keys/{made['read']['id']}")
        assert "needs a key with scope 'admin'" in _problem(r, 403, "insufficient-scope")["detail"]
        _problem(reader.delete(f"/v1/keys/{me['key_id']}"), 403, "insufficient-scope")
        # any key revokes itself; an admin key revokes others; either fails at once
        assert reader.delete(f"/v1/keys/{made['read']['id']}").status_code == 204
        _problem(reader.get("/v1/keys/me"), 401, "unauthorized")
        with server.client(admin_key) as admin:
            assert admin.delete(f"/v1/keys/{made['write']['id']}").status_code == 204
        _problem(writer.get("/v1/keys/me"), 401, "unauthorized")
    finally:
        reader.close()
        writer.close()


def test_a_revocation_elsewhere_takes_effect_at_once(server: LiveServer) -> None:
    """Revoked by another replica or the CLI (straight in the database): no cache window."""
    key = server.new_key("elsewhere")
    with server.client(key) as c:
        key_id = c.get("/v1/keys/me").json()["key_id"]
        assert c.get("/v1/scenes").status_code == 200
        with server.database.write() as s:
            s.get(ApiKey, key_id).revoked_at = datetime.now(UTC)
        _problem(c.get("/v1/scenes"), 401, "unauthorized")


def test_keys_show_name_scope_and_last_use(server: LiveServer) -> None:
    key = server.new_key("seen")
    with server.client(key) as c:
        c.post("/v1/keys", json={"name": "spare", "scope": "read"})
        listed = {k["name"]: k for k in list_all(c, "/v1/keys")}
    assert set(listed) == {"seen", "spare"}
    assert listed["spare"]["last_used_at"] is None and listed["spare"]["scope"] == "read"
    used = listed["seen"]["last_used_at"]
    assert used is not None and listed["seen"]["scope"] == "admin"
    assert {"created_at", "revoked_at", "prefix"} <= set(listed["seen"])
    with server.client(key) as c:  # within GLINT_KEY_LAST_USED_S: not written again
        c.get("/v1/keys/me")
        again = {k["name"]: k for k in list_all(c, "/v1/keys")}
    assert again["seen"]["last_used_at"] == used


def test_cli_keys_list_and_revoke(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    from core.cli import main

    common = ["--data-dir", str(tmp_path)]
    assert main(["keys", "create", "carol", "--scope", "read", "--label", "dash", *common]) == 0
    key = capsys.readouterr().out.strip()
    assert main(["keys", "create", "dave", *common]) == 0
    capsys.readouterr()
    assert main(["keys", "list", *common]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:4] == ["id", "owner", "name", "scope"]
    rows = {line.split()[1]: line.split() for line in lines[1:]}
    assert rows["carol"][2:4] == ["dash", "read"] and rows["dave"][3] == "admin"
    key_id = rows["carol"][0]
    assert main(["keys", "revoke", key_id, *common]) == 0
    assert "revoked" in capsys.readouterr().out
    assert main(["keys", "list", "carol", *common]) == 0
    assert key_id not in capsys.readouterr().out  # live keys only
    assert main(["keys", "list", "carol", "--all", *common]) == 0
    assert key_id in capsys.readouterr().out
    assert main(["keys", "revoke", "key_nope", *common]) == 2
    assert "no key 'key_nope'" in capsys.readouterr().err
    db = Database(f"sqlite:///{tmp_path / 'glint.db'}")
    with db.read() as s:
        row = s.query(ApiKey).filter_by(key_hash=hash_key(key)).one()
        assert row.revoked_at is not None and row.scope == "read"
    db.dispose()
