"""How long a job stays wrongly ``running`` after its worker is killed, measured.

    python -m bench.crash_recovery --json crash.json --root /tmp/glint-crash

Starts a redis-server (a free loopback port), the API on uvicorn in this process (SQLite,
a store folder, the Celery queue) and ``glint worker --device cpu`` processes, all
with the default timing settings unless ``--set NAME=VALUE`` (``GLINT_*`` variables)
says otherwise. It submits a short job, waits until it has trained past its first
checkpoint, ``kill -9``s the worker running it and then watches the job row (every
0.05 s) and Redis: when the job stops being ``running``, when it is ``queued`` again,
when another worker has claimed it, resumed it (the checkpoint's iteration written) and
trains it again, when it succeeded, and what is left in Redis's ``unacked`` hash.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import uvicorn

ROOT = Path(__file__).resolve().parents[1]
GLINT = [
    sys.executable,
    "-c",
    "import sys; from core.cli import main; sys.exit(main(sys.argv[1:]))",
]
JOB_CONFIG = {
    "iterations": 400,
    "init_points": 300,
    "envmap_resolution": 8,
    "checkpoint_every": 10,
    "eval": {"every": 1000, "views": 1},
    "densify": {"enabled": False},
    "outputs": {"mesh": False},
}


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(pred, timeout: float, what: str, every: float = 0.05):  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(every)
    raise RuntimeError(f"timed out waiting for {what}")


def run(redis_bin: str, root: Path, overrides: dict[str, str], survivor: str) -> dict[str, Any]:
    import redis as redis_py

    from api.auth import create_key
    from api.main import create_app
    from api.service.models import Job
    from api.service.settings import Settings
    from core.scene.synthetic import write_synthetic_scene

    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    rport = _port()
    redis_proc = subprocess.Popen(
        [redis_bin, "--port", str(rport), "--bind", "127.0.0.1", "--save", "",
         "--appendonly", "no"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    redis_url = f"redis://127.0.0.1:{rport}/0"
    env_vals = {
        "GLINT_DATA_DIR": str(root / "data"),
        "GLINT_REDIS_URL": redis_url,
        "GLINT_QUEUE_BACKEND": "celery",
        **overrides,
    }
    fields = {k.removeprefix("GLINT_").lower(): v for k, v in env_vals.items()}
    settings = Settings(**fields)
    app = create_app(settings)
    port = _port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    workers: dict[str, subprocess.Popen[bytes]] = {}
    logs: dict[str, Path] = {}
    rc = redis_py.Redis(port=rport)
    try:
        thread.start()
        _wait(lambda: server.started, 30, "the API")
        env = {k: v for k, v in os.environ.items() if not k.startswith("GLINT_")}
        env.update(env_vals, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])

        def start(name: str) -> None:
            logs[name] = root / f"worker-{name}.log"
            workers[name] = subprocess.Popen(
                [*GLINT, "worker", "--device", "cpu", "--name", f"{name}@crash"],
                cwd=ROOT, env=env, stdout=open(logs[name], "w"),  # noqa: SIM115
                stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip

        start("a")
        if survivor == "running":
            start("b")
        with app.state.database.write() as s:
            _, key = create_key(s, "crash-bench")
        scene = write_synthetic_scene(
            root / "scene", "sphere", "glossy", n_train=6, n_test=2, size=24
        )
        c = httpx.Client(
            base_url=f"http://127.0.0.1:{port}",
            headers={"Authorization": f"Bearer {key}"},
            timeout=60,
        )
        sid = c.post("/v1/scenes", json={"name": "crash sphere"}).json()["id"]
        octet = "application/octet-stream"
        files = [("files", (p.relative_to(scene).as_posix(), io.BytesIO(p.read_bytes()), octet))
                 for p in sorted(scene.rglob("*")) if p.is_file()]  # fmt: skip
        c.post(f"/v1/scenes/{sid}/files", files=files).raise_for_status()
        c.post(f"/v1/scenes/{sid}/commit").raise_for_status()
        n = len(workers)
        _wait(lambda: len(c.get("/v1/workers").json()["items"]) == n, 120, "the workers")
        job_id = c.post("/v1/jobs", json={"scene_id": sid, "config": JOB_CONFIG}).json()["id"]

        def row() -> Job:
            with app.state.database.read() as s:
                job = s.get(Job, job_id)
                assert job is not None
                s.expunge(job)
                return job

        first = _wait(lambda: (j := row()).state == "running" and j.iteration >= 15 and j, 300,
                      "the job to pass its first checkpoint")  # fmt: skip
        victim = first.worker.split(":")[0].split("@")[0]
        unacked_before = rc.hlen("unacked")
        os.kill(workers[victim].pid, signal.SIGKILL)
        t_kill = time.monotonic()
        workers[victim].wait(10)
        if survivor == "restarted":  # a supervisor starts a worker again at once
            start("b")
        killed = row()
        seen = killed.heartbeat_at
        heartbeat_age = None if seen is None else round(time.time() - seen.timestamp(), 2)
        timeline: dict[str, float] = {}
        samples: list[tuple[float, str, int]] = []
        notes: dict[str, str | None] = {}
        last = claimed = killed
        while time.monotonic() - t_kill < 600:
            j = row()
            t = round(time.monotonic() - t_kill, 2)
            if (j.state, j.attempts) != (last.state, last.attempts):
                samples.append((t, j.state, j.attempts))
            if j.state != "running" and "left_running" not in timeline:
                timeline["left_running"] = t
                notes["left_running"] = j.error
            if j.state == "queued" and "queued" not in timeline:
                timeline["queued"] = t
            if j.state == "queued" and survivor == "none":
                timeline["unacked_when_queued"] = rc.hlen("unacked")
                timeline["queue_length_when_queued"] = rc.llen("glint")
                notes["final_state"], notes["final_error"] = j.state, j.error
                break
            if j.state == "running" and j.attempts > killed.attempts:
                if "claimed_again" not in timeline:
                    timeline["claimed_again"] = t
                    timeline["unacked_at_claim"] = rc.hlen("unacked")
                    claimed = j
                elif "resumed" not in timeline and j.iteration != claimed.iteration:
                    timeline["resumed"] = t  # the resumed event wrote the checkpoint's iteration
                elif "training_again" not in timeline and j.iteration > last.iteration:
                    timeline["training_again"] = t
            if j.state in ("succeeded", "failed", "cancelled"):
                timeline["finished"] = t
                notes["final_state"], notes["final_error"] = j.state, j.error
                break
            last = j
            time.sleep(0.05)
        time.sleep(1.0)
        other = "b" if victim == "a" else "a"
        text = logs[other].read_text() if other in logs else ""
        resumed = re.findall(rf"job {job_id}: resumed from iteration (\d+)", text)
        return {
            "survivor": survivor,
            "settings": {
                k: getattr(settings, k)
                for k in (
                    "heartbeat_s",
                    "stale_after_s",
                    "reaper_interval_s",
                    "worker_heartbeat_s",
                    "visibility_timeout_s",
                )
                + (("max_attempts",) if hasattr(settings, "max_attempts") else ())
            },
            "killed_at_iteration": killed.iteration,
            "heartbeat_age_at_kill_s": heartbeat_age,
            "unacked_before_kill": unacked_before,
            "seconds_after_kill": timeline,
            "transitions": samples,
            "notes": notes,
            "resumed_from_iteration": [int(x) for x in resumed],
            "unacked_at_end": rc.hlen("unacked"),
            "unacked_index_at_end": rc.zcard("unacked_index"),
            "queue_length_at_end": rc.llen("glint"),
        }
    finally:
        for w in workers.values():
            if w.poll() is None:
                w.terminate()
                try:
                    w.wait(30)
                except subprocess.TimeoutExpired:
                    w.kill()
        server.should_exit = True
        thread.join(15)
        rc.close()
        redis_proc.terminate()
        redis_proc.wait(10)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--redis-server", default=shutil.which("redis-server") or "redis-server")
    ap.add_argument("--root", type=Path, default=Path("/tmp/glint-crash"))
    ap.add_argument("--set", action="append", default=[], metavar="GLINT_NAME=VALUE")
    ap.add_argument(
        "--survivor",
        choices=["running", "restarted", "none"],
        default="running",
        help="a second worker is up from the start (default), is started right after the "
        "kill (a supervisor's restart), or there is none (only the API notices; the run "
        "ends when the job is queued again)",
    )
    ap.add_argument("--json", help="write the result here")
    args = ap.parse_args(argv)
    overrides = dict(kv.split("=", 1) for kv in args.set)
    res = run(args.redis_server, args.root, overrides, args.survivor)
    print(json.dumps(res, indent=2, default=str))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
