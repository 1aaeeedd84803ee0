"""``glint-remote`` as a user runs it: a separate process, against ``glint serve`` started
from the command line (the embedded default: SQLite, the local store, jobs in a child
process), with the key that ``glint keys create`` printed."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from glint_client.cli import EXIT_API, EXIT_OK

from tests.api.support import free_port
from tests.client.support import sha256

REPO = Path(__file__).resolve().parents[2]
GLINT = "import sys; from core.cli import main; sys.exit(main(sys.argv[1:]))"


@pytest.fixture(scope="module")
def serve(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """(url, key) of a `glint serve` process with a data folder of its own."""
    data = tmp_path_factory.mktemp("serve-data")
    env = {**os.environ, "PYTHONPATH": str(REPO), "GLINT_DATA_DIR": str(data)}
    made = subprocess.run(
        [sys.executable, "-c", GLINT, "keys", "create", "remote-user"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    key = made.stdout.strip()
    port = free_port()
    server = subprocess.Popen(
        [sys.executable, "-c", GLINT, "serve", "--port", str(port), "--log-level", "warning"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 90
    while True:
        try:
            if httpx.get(f"{url}/v1/health").status_code == 200:
                break
        except httpx.TransportError:
            pass
        assert server.poll() is None, server.communicate()[1]
        assert time.monotonic() < deadline, "glint serve did not come up"
        time.sleep(0.2)
    yield url, key
    server.terminate()
    server.wait(60)


def _remote(*args: str, url: str, key: str) -> subprocess.CompletedProcess[str]:
    exe = shutil.which("glint-remote", path=str(Path(sys.executable).parent))
    assert exe, "glint-remote is not installed beside this Python (pip install ./client)"
    env = {**os.environ, "GLINT_SERVER": url, "GLINT_KEY": key}
    return subprocess.run([exe, *args], env=env, capture_output=True, text=True, timeout=300)


def test_submit_wait_download_against_glint_serve(
    serve: tuple[str, str], scene_dir: Path, tmp_path: Path
) -> None:
    url, key = serve
    out = tmp_path / "result"
    tiny = ["--iterations", "20", "--set", "init_points=300", "--set", "envmap_resolution=8"]
    quick = ["--set", "densify.enabled=false", "--set", "outputs.mesh=false"]
    done = _remote(
        "submit", str(scene_dir), *tiny, *quick, "--download", str(out), url=url, key=key
    )
    assert done.returncode == EXIT_OK, done.stderr
    job_id = done.stdout.strip().splitlines()[-1]
    listed = _remote("download", job_id, "--list", "--json", url=url, key=key)
    names = {a["name"]: a["sha256"] for a in json.loads(listed.stdout)}
    assert "point_cloud.ply" in names and "checkpoint.pt" in names
    got = {p.relative_to(out).as_posix(): sha256(p) for p in out.rglob("*") if p.is_file()}
    assert got == names  # every artifact, checksums verified

    # a job the server refuses after the upload: the scene is kept and named, and
    # --scene starts the job on it without sending a file again
    bad = _remote("submit", str(scene_dir), "--set", "iterations=0", url=url, key=key)
    assert bad.returncode == EXIT_API
    assert "body.config.iterations" in bad.stderr
    scene_id = next(w for w in bad.stderr.split() if w.startswith("scn_"))
    assert f"--scene {scene_id}" in bad.stderr
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"}) as c:
        before = c.get(f"/v1/scenes/{scene_id}").json()
        again = _remote(
            "submit", str(scene_dir), "--scene", scene_id, *tiny, *quick, url=url, key=key
        )
        assert again.returncode == EXIT_OK, again.stderr
        after = c.get(f"/v1/scenes/{scene_id}").json()
        assert after["state"] == "ready" and after["updated_at"] == before["updated_at"]
        assert c.get(f"/v1/scenes/{scene_id}/uploads").json()["total"] == 0
        jobs = c.get("/v1/jobs", params={"scene_id": scene_id}).json()["items"]
        assert [j["state"] for j in jobs] in (["queued"], ["running"], ["succeeded"])
