"""One job from the API to its artifacts through a real ``glint worker`` on Redis.

    python -m bench.gpu_worker_trip --device cuda:0 --json trip.json --root /tmp/trip

Starts a redis-server (the given binary, a free loopback port, no persistence), the API
on uvicorn in this process (SQLite, a store folder), and ``glint worker --device D``
as a child process; uploads a tiny generated scene, submits a short job, waits for it
and checks its artifacts (checkpoint, 3DGS PLY, mesh). Used by the GPU kit.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import uvicorn

ROOT = Path(__file__).resolve().parents[1]
GLINT = [
    sys.executable,
    "-c",
    "import sys; from core.cli import main; sys.exit(main(sys.argv[1:]))",
]
JOB_CONFIG = {
    "iterations": 30,
    "init_points": 500,
    "envmap_resolution": 8,
    "densify": {"enabled": False},
    "outputs": {"mesh_resolution": 48},
}


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(pred, timeout: float, what: str):  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(0.2)
    raise RuntimeError(f"timed out waiting for {what}")


def _start_redis(redis_bin: str, port: int, log: Path) -> subprocess.Popen:
    """redis-server on ``port``, answering PING, or an error that quotes its own output.

    A binary carried from another system may miss shared libraries there: a folder
    ``redis-libs`` beside it (scripts/gpu_wheels.sh fills it) goes on its library path.
    """
    env = dict(os.environ)
    libs = Path(redis_bin).parent / "redis-libs"
    if libs.is_dir():
        env["LD_LIBRARY_PATH"] = os.pathsep.join(
            filter(None, [str(libs), env.get("LD_LIBRARY_PATH")])
        )
    fh = open(log, "w")  # noqa: SIM115  (the child holds it; closed with the process)
    proc = subprocess.Popen(
        [redis_bin, "--port", str(port), "--bind", "127.0.0.1", "--save", "",
         "--appendonly", "no"],
        stdout=fh, stderr=subprocess.STDOUT, env=env,
    )  # fmt: skip
    fh.close()

    def answers() -> bool:
        if proc.poll() is not None:
            raise RuntimeError(f"redis-server exited {proc.returncode}: {log.read_text()[-800:]}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1) as s:
                s.sendall(b"PING\r\n")
                return s.recv(16).startswith(b"+PONG")
        except OSError:
            return False

    _wait(answers, 20, f"redis-server on port {port} (see {log})")
    return proc


def trip(redis_bin: str, device: str, root: Path) -> dict:
    from api.auth import create_key
    from api.main import create_app
    from api.service.settings import Settings
    from core.scene.synthetic import write_synthetic_scene

    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    rport = _port()
    redis = _start_redis(redis_bin, rport, root / "redis.log")
    redis_url = f"redis://127.0.0.1:{rport}/0"
    env_vals = {
        "GLINT_DATA_DIR": str(root / "data"),
        "GLINT_REDIS_URL": redis_url,
        "GLINT_QUEUE_BACKEND": "celery",
    }
    settings = Settings(
        data_dir=root / "data", redis_url=redis_url, queue_backend="celery", heartbeat_s=1.0
    )
    app = create_app(settings)
    port = _port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    worker = None
    t0 = time.perf_counter()
    try:
        thread.start()
        _wait(lambda: server.started, 30, "the API")
        env = dict(os.environ, **env_vals)
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
        log = open(root / "worker.log", "w")  # noqa: SIM115  (closed in finally)
        worker = subprocess.Popen(
            [*GLINT, "worker", "--device", device, "--name", f"kit-{device.replace(':', '')}@trip"],
            cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
        with app.state.database.write() as s:
            _, key = create_key(s, "gpu-kit")
        scene = write_synthetic_scene(
            root / "scene", "sphere", "glossy", n_train=6, n_test=2, size=24
        )
        c = httpx.Client(
            base_url=f"http://127.0.0.1:{port}",
            headers={"Authorization": f"Bearer {key}"},
            timeout=60,
        )
        sid = c.post("/v1/scenes", json={"name": "kit sphere"}).json()["id"]
        octet = "application/octet-stream"
        files = [("files", (p.relative_to(scene).as_posix(), io.BytesIO(p.read_bytes()), octet))
                 for p in sorted(scene.rglob("*")) if p.is_file()]  # fmt: skip
        c.post(f"/v1/scenes/{sid}/files", files=files).raise_for_status()
        c.post(f"/v1/scenes/{sid}/commit").raise_for_status()
        _wait(lambda: c.get("/v1/workers").json()["items"], 120, "the worker to report itself")
        job = c.post("/v1/jobs", json={"scene_id": sid, "config": JOB_CONFIG}).json()

        def done():  # type: ignore[no-untyped-def]
            j = c.get(f"/v1/jobs/{job['id']}").json()
            return j if j["state"] in ("succeeded", "failed", "cancelled") else None

        final = _wait(done, 300, "the job")
        arts = c.get(f"/v1/jobs/{job['id']}/artifacts", params={"limit": 200}).json()
        names = [a["name"] for a in arts["items"]]
        workers = c.get("/v1/workers").json()["items"]
        ok = final["state"] == "succeeded" and {
            "checkpoint.pt",
            "point_cloud.ply",
            "mesh.glb",
        } <= set(names)
        if not ok:
            raise RuntimeError(f"job {final['state']}: {final.get('error')}; artifacts {names}")
        # the job's own config says what was submitted; the run's says where it trained
        trained = c.get(f"/v1/jobs/{job['id']}/artifacts/config.json").json()["device"]
        if trained != device:
            raise RuntimeError(f"the worker runs on {device}, but the job trained on {trained}")
        return {
            "job": final["id"],
            "state": final["state"],
            "submitted_device": final["config"].get("device", "cpu"),
            "trained_device": trained,
            "worker": workers[0]["id"] if workers else None,
            "artifacts": len(names),
            "seconds": round(time.perf_counter() - t0, 1),
        }
    finally:
        if worker is not None:
            worker.terminate()
            try:
                worker.wait(30)
            except subprocess.TimeoutExpired:
                worker.kill()
        server.should_exit = True
        thread.join(15)
        redis.terminate()
        redis.wait(10)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--redis-server", default=shutil.which("redis-server") or "redis-server")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--root", type=Path, default=Path("/tmp/glint-worker-trip"))
    ap.add_argument("--json", help="write the result here")
    args = ap.parse_args(argv)
    res = trip(args.redis_server, args.device, args.root)
    print(json.dumps(res, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")


if __name__ == "__main__":
    main()
