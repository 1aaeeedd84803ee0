"""The compose stack's processes on loopback: one tiny job from upload to report.md.

Runs what deploy/compose.yaml + compose.cpu.yaml declare (this machine has no GPU):
``glint <api command>`` and ``glint <worker command>`` as subprocesses, with the
``environment`` compose gives them, hosts and paths mapped to loopback:
``postgres:5432`` -> a throwaway database on 127.0.0.1:5432 (SQLite when no PostgreSQL
is reachable, said in the test's output), ``redis:6379`` -> a private ``redis-server``
on a free port, ``minio:9000`` -> moto's S3 server on a free port (its bucket made as
``minio-init`` makes it; its credentials for MinIO's), ``/var/lib/glint`` -> a tmp
folder of each service's own (they share no volume), the API port -> a free port.
"""

from __future__ import annotations

import io
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
import warnings
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.deploy.support import compose, env_example, service_env
from tests.s3_server import S3Server

pytestmark = pytest.mark.timeout(240)

PG_ADMIN = os.environ.get("GLINT_TEST_PG", "postgresql://postgres@127.0.0.1:5432/postgres")
REDIS_SERVER = shutil.which("redis-server") or "/usr/bin/redis-server"
JOB_CONFIG = {
    "iterations": 20,
    "init_points": 300,
    "envmap_resolution": 8,
    "densify": {"enabled": False},
}
IMAGE_DATA_DIR = "/var/lib/glint"
HEALTHCHECK = Path(__file__).resolve().parents[2] / "docker" / "worker_healthcheck.py"


def _glint() -> list[str]:
    exe = Path(sys.executable).parent / "glint"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "core.cli"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(predicate, timeout: float, what: str, every: float = 0.2):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"{what}: not within {timeout} s")


def _stop(proc: subprocess.Popen, grace: float = 20.0) -> None:
    """SIGTERM this process's own group (started with a new session), then SIGKILL."""
    if proc.poll() is not None:
        return
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(grace)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


def _tail(path: Path, n: int = 4000) -> str:
    return path.read_text(errors="replace")[-n:] if path.exists() else ""


@pytest.fixture(scope="module")
def stack() -> dict:
    return compose("compose.yaml", "compose.cpu.yaml")


@pytest.fixture(scope="module")
def worker_cli() -> None:
    r = subprocess.run([*_glint(), "worker", "--help"], capture_output=True, text=True, timeout=120)
    if r.returncode != 0:
        pytest.skip("glint worker not available")


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    if not Path(REDIS_SERVER).exists():
        pytest.skip("redis-server not installed")
    port = _free_port()
    workdir = tmp_path_factory.mktemp("redis")
    args = ["--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"]
    proc = subprocess.Popen(
        [REDIS_SERVER, *args, "--dir", str(workdir)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )

    def up() -> bool:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5) as s:
                s.sendall(b"PING\r\n")
                return s.recv(16).startswith(b"+PONG")
        except OSError:
            return False

    try:
        _wait(up, 20, "redis-server start")
        yield f"redis://127.0.0.1:{port}/0"
    finally:
        _stop(proc, 5)


@pytest.fixture(scope="module")
def database(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """(url, note): a throwaway PostgreSQL database, or SQLite when none is reachable."""
    try:
        import psycopg

        admin = psycopg.connect(PG_ADMIN, autocommit=True, connect_timeout=3)
    except Exception as exc:
        path = tmp_path_factory.mktemp("sqlite") / "glint.db"
        yield f"sqlite:///{path}", f"SQLite: PostgreSQL not reachable at {PG_ADMIN} ({exc})"
        return
    name = f"glint_deploy_test_{uuid.uuid4().hex[:12]}"
    admin.execute(f'CREATE DATABASE "{name}"')
    base = PG_ADMIN.rsplit("/", 1)[0].replace("postgresql://", "postgresql+psycopg://", 1)
    try:
        yield f"{base}/{name}", "PostgreSQL"
    finally:
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.close()


@pytest.fixture(scope="module")
def s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    srv = S3Server(tmp_path_factory.mktemp("moto")).start()
    yield srv
    srv.stop()


def _loopback_env(
    service: dict, *, database_url: str, redis_url: str, s3: S3Server, data_dir: Path, port: int
) -> dict[str, str]:
    """The service's compose environment with every container address mapped to loopback."""
    declared = service_env(service, env_example())
    mapped = {}
    for key, value in declared.items():
        if key == "GLINT_S3_ENDPOINT_URL":
            assert value == "http://minio:9000"
            value = s3.url
        elif key == "GLINT_S3_ACCESS_KEY_ID":
            value = s3.access_key
        elif key == "GLINT_S3_SECRET_ACCESS_KEY":
            assert value, "compose gives the services MinIO's key"
            value = s3.secret_key
        elif key == "GLINT_DATABASE_URL":
            assert value.startswith("postgresql+psycopg://") and "@postgres:5432/" in value
            value = database_url
        elif key == "GLINT_REDIS_URL":
            assert value.startswith("redis://redis:6379/")
            value = redis_url
        elif key == "GLINT_HOST":
            value = "127.0.0.1"
        elif key == "GLINT_PORT":
            value = str(port)
        elif value.startswith(IMAGE_DATA_DIR):
            value = str(data_dir) + value[len(IMAGE_DATA_DIR) :]
        mapped[key] = value
    env = {k: v for k, v in os.environ.items() if not k.startswith("GLINT_")}
    env.update(mapped)
    # one torch/BLAS thread: the test machine is small and shared
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    return env


def _worker_healthy(env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess:
    """The worker container's HEALTHCHECK (docker/worker_healthcheck.py), run here."""
    cmd = [sys.executable, str(HEALTHCHECK)]
    return subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True, timeout=60)


def _scene_files(tmp: Path) -> list[tuple[str, tuple[str, io.BytesIO, str]]]:
    from core.scene.synthetic import write_synthetic_scene

    root = write_synthetic_scene(tmp, "sphere", "glossy", n_train=8, n_test=2, size=24)
    octet = "application/octet-stream"
    return [
        ("files", (p.relative_to(root).as_posix(), io.BytesIO(p.read_bytes()), octet))
        for p in sorted(root.rglob("*"))
        if p.is_file()
    ]


def test_compose_processes_run_a_job(
    stack, worker_cli, redis_url, database, s3, tmp_path: Path
) -> None:
    database_url, db_note = database
    if db_note != "PostgreSQL":  # compose runs PostgreSQL: say loudly that this did not
        warnings.warn(f"loopback stack ran on {db_note}", stacklevel=1)
    port = _free_port()
    envs = {
        name: _loopback_env(
            stack["services"][name],
            database_url=database_url,
            redis_url=redis_url,
            s3=s3,
            data_dir=tmp_path / name,  # api-data, worker-data: no volume is shared
            port=port,
        )
        for name in ("api", "worker")
    }
    # the settings that tie the two together are the same on both sides
    for key in ("GLINT_DATABASE_URL", "GLINT_REDIS_URL", "GLINT_STORE_URL", "GLINT_QUEUE_BACKEND"):
        assert envs["api"][key] == envs["worker"][key], key
    assert envs["api"]["GLINT_QUEUE_BACKEND"] == "celery"
    assert envs["api"]["GLINT_DATA_DIR"] != envs["worker"]["GLINT_DATA_DIR"]
    # minio-init's step: the bucket compose points the services at
    bucket = envs["api"]["GLINT_STORE_URL"].removeprefix("s3://")
    assert bucket == env_example()["S3_BUCKET"]
    s3.client().create_bucket(Bucket=bucket)

    procs: list[subprocess.Popen] = []
    logs = {name: tmp_path / f"{name}.log" for name in ("api", "worker")}

    def start(name: str) -> subprocess.Popen:
        cmd = [*_glint(), *stack["services"][name]["command"]]
        with logs[name].open("wb") as log:
            proc = subprocess.Popen(
                cmd,
                env=envs[name],
                cwd=tmp_path,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        procs.append(proc)
        return proc

    def diagnostics() -> str:
        return "\n".join(f"--- {n} log ---\n{_tail(p)}" for n, p in logs.items())

    try:
        api = start("api")
        url = f"http://127.0.0.1:{port}"

        def healthy() -> bool:
            assert api.poll() is None, f"api exited {api.returncode}\n{diagnostics()}"
            try:
                return httpx.get(f"{url}/v1/health", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        _wait(healthy, 90, "api health")  # the API migrates the database first
        # before the worker runs, its health check fails (no live worker row)
        hc = _worker_healthy(envs["worker"], tmp_path)
        assert hc.returncode == 1 and "unhealthy" in hc.stdout, hc.stdout + hc.stderr
        start("worker")

        keys = subprocess.run(
            [*_glint(), "keys", "create", "deploy-test"],
            env=envs["api"],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=tmp_path,
        )
        assert keys.returncode == 0, keys.stderr
        key = keys.stdout.strip().splitlines()[0]

        with httpx.Client(
            base_url=url, headers={"Authorization": f"Bearer {key}"}, timeout=60
        ) as c:
            r = c.post("/v1/scenes", json={"name": "deploy sphere"})
            assert r.status_code == 201, r.text
            scene_id = r.json()["id"]
            r = c.post(f"/v1/scenes/{scene_id}/files", files=_scene_files(tmp_path / "scene"))
            assert r.status_code == 201, r.text
            r = c.post(f"/v1/scenes/{scene_id}/commit")
            assert r.status_code == 200 and r.json()["state"] == "ready", r.text
            r = c.post("/v1/jobs", json={"scene_id": scene_id, "config": JOB_CONFIG})
            assert r.status_code == 201, r.text
            job_id = r.json()["id"]

            states = []

            def finished() -> dict | None:
                for p in procs:
                    assert p.poll() is None, f"{p.args} exited {p.returncode}\n{diagnostics()}"
                job = c.get(f"/v1/jobs/{job_id}").json()
                states.append(job["state"])
                return job if job["state"] in ("succeeded", "failed", "cancelled") else None

            try:
                job = _wait(finished, 150, f"job {job_id}", every=0.5)
            except AssertionError as exc:
                raise AssertionError(f"{exc}\n{diagnostics()}") from None
            assert job["state"] == "succeeded", f"{job['error']}\n{diagnostics()}"

            listed = c.get(f"/v1/jobs/{job_id}/artifacts", params={"limit": 200}).json()
            arts = {a["name"]: a for a in listed["items"]}
            assert "report.md" in arts, sorted(arts)
            report = c.get(arts["report.md"]["url"])
            assert report.status_code == 200 and report.text.strip()
            assert "running" in states or "queued" in states  # it went through the queue

        # the worker container's health check passes against the same settings
        hc = _worker_healthy(envs["worker"], tmp_path)
        assert hc.returncode == 0, hc.stdout + hc.stderr
        assert "glint-cpu@" in hc.stdout

        # the worker wrote the run into the bucket the API serves from, not to its disk
        assert f"jobs/{job_id}/run/report.md" in s3.keys(bucket, f"jobs/{job_id}/")
        api_disk = [p for p in (tmp_path / "api").rglob("*") if job_id in str(p)]
        assert not [p for p in api_disk if p.is_file()], api_disk
    finally:
        for p in reversed(procs):
            _stop(p)
