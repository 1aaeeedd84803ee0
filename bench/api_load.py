"""Job-status latency under load, with and without a job training on the embedded queue.

    python -m bench.api_load [--clients 100] [--duration 20] [--with-job | --without-job]
                             [--interval 0[,1...]] [--wrk] [--iterations 5000] [--size 64]
                             [--views 24] [--repo DIR]

Starts ``glint serve`` as it ships by default (no ``GLINT_REDIS_URL``: SQLite and the
embedded queue) on a free port with a temporary data dir, creates a key with
``glint keys create``, uploads a synthetic scene (``--size`` px, ``--views`` views) and
commits it. Then, per mode and interval, ``--clients`` concurrent keep-alive clients
(httpx, asyncio, one process) poll ``GET /v1/jobs/{id}`` for ``--duration`` seconds, each
back to back (``--interval 0``, the default: a closed loop, whose latency is the number
of clients over the throughput) or at most once per ``--interval`` seconds (a status
poller's pace; clients start spread over the first interval):

* ``without job``: the job polled was cancelled before it started; nothing trains;
* ``with job``: the job trains (``--iterations``) throughout the window; the row says how
  many iterations it made meanwhile (``still running`` unless it finished too early).

``--wrk`` runs the closed loops (interval 0) with ``wrk`` (C, one thread, ``--clients``
connections; Debian package ``wrk``) instead: the asyncio client spends more CPU per
request than the server and, sharing the cores, measured itself (it topped out near
75 req/s on 2 cores where wrk drove the same server at 500). Paced runs (interval > 0)
always use the asyncio client, which keeps up with 100 requests a second.

Prints one Markdown row per mode and interval: requests/s, errors (non-200 answers and transport
errors, e.g. timeouts), client p50/p90/p99/max latency, the server's own p99 (its
``Server-Timing`` header, time in the app until the headers leave), the 1-minute load
average when the window ended, and the client. Client and server share the machine's
cores. ``--repo`` serves another checkout's code (e.g. a ``git worktree`` of an older
commit) with this benchmark's client.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parents[1]
CLI = "import sys; from core.cli import main; sys.exit(main(sys.argv[1:]))"
HEAD = (
    "| mode | clients | interval s | s | requests | errors | req/s | p50 ms | p90 ms | p99 ms "
    "| max ms | server p99 ms | job | load | client |"
)
RULE = "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---|"

# wrk's script: the key's header, non-200 answers counted, each answer's Server-Timing kept;
# done() prints one line of JSON for load_wrk
WRK_LUA = """
wrk.headers["Authorization"] = "Bearer " .. os.getenv("GLINT_BENCH_KEY")
threads = {}
function setup(thread) table.insert(threads, thread) end
function init(args) non200 = 0; server_ms = {} end
function response(status, headers, body)
  if status ~= 200 then non200 = non200 + 1 end
  local t = headers["server-timing"]
  local d = t and t:match("dur=([%d%.]+)")
  if d then server_ms[#server_ms + 1] = tonumber(d) end
end
function done(summary, latency, requests)
  local bad, ms = 0, {}
  for _, t in ipairs(threads) do
    bad = bad + t:get("non200")
    for _, v in ipairs(t:get("server_ms")) do ms[#ms + 1] = v end
  end
  local e = summary.errors
  io.write(string.format(
    'WRK {"requests": %d, "us": %d, "non200": %d, "socket": %d, "p50": %d, "p90": %d, '
    .. '"p99": %d, "max": %d, "server_ms": [%s]}\\n',
    summary.requests, summary.duration, bad, e.connect + e.read + e.write + e.timeout,
    latency:percentile(50), latency:percentile(90), latency:percentile(99), latency.max,
    table.concat(ms, ",")))
end
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def percentile(values: list[float], q: float) -> float:
    """The ``q``-quantile (0..1) of ``values`` (nearest rank); NaN when empty."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * len(ordered)) - 1))]


@dataclass
class Load:
    mode: str
    clients: int
    interval: float
    seconds: float
    requests: int
    errors: int
    latencies: list[float]  # seconds, answered requests
    server_ms: list[float]
    job: str = "-"
    # client p50/p90/p99/max in ms when the client gives only those (wrk), not latencies
    quantiles: tuple[float, float, float, float] | None = None
    load: float = float("nan")  # 1-minute load average as the window ended
    client: str = "httpx"

    def row(self) -> str:
        ms = [t * 1e3 for t in self.latencies]
        p50, p90, p99, top = self.quantiles or (
            percentile(ms, 0.5),
            percentile(ms, 0.9),
            percentile(ms, 0.99),
            max(ms, default=float("nan")),
        )
        return (
            f"| {self.mode} | {self.clients} | {self.interval:g} | {self.seconds:.0f} | "
            f"{self.requests} | {self.errors} | {self.requests / self.seconds:.0f} | "
            f"{p50:.1f} | {p90:.1f} | {p99:.1f} | {top:.1f} | "
            f"{percentile(self.server_ms, 0.99):.1f} | {self.job} | {self.load:.1f} | "
            f"{self.client} |"
        )


class Server:
    """``glint serve`` with the shipped defaults, in a temporary data dir."""

    def __init__(self, data_dir: Path, repo: Path) -> None:
        self.data_dir, self.repo = data_dir, repo
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("GLINT_")}
        self.env.update(PYTHONPATH=str(repo), GLINT_DATA_DIR=str(data_dir))
        self.log = data_dir / "serve.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def glint(self, *args: str) -> str:
        done = subprocess.run(
            [sys.executable, "-c", CLI, *args],
            cwd=self.repo,
            env=self.env,
            capture_output=True,
            text=True,
            check=True,
        )
        return done.stdout

    def start(self) -> Server:
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-c",
                CLI,
                "serve",
                "--port",
                str(self.port),
                "--log-level",
                "warning",
            ],
            cwd=self.repo,
            env=self.env,
            stdout=open(self.log, "ab"),  # noqa: SIM115 (the process owns it)
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                break
            try:
                if httpx.get(f"{self.url}/v1/health", timeout=2).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"glint serve did not come up:\n{self.log.read_text()[-3000:]}")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def upload_scene(c: httpx.Client, root: Path, size: int, views: int) -> str:
    from core.scene.synthetic import write_synthetic_scene

    n_test = max(1, views // 6)
    folder = write_synthetic_scene(
        root, "sphere", "glossy", n_train=views - n_test, n_test=n_test, size=size
    )
    files = [
        ("files", (p.relative_to(folder).as_posix(), io.BytesIO(p.read_bytes()), "application/x"))
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    ]
    r = c.post("/v1/scenes", json={"name": "load"})
    r.raise_for_status()
    scene_id = r.json()["id"]
    c.post(f"/v1/scenes/{scene_id}/files", files=files).raise_for_status()
    r = c.post(f"/v1/scenes/{scene_id}/commit", timeout=300)
    r.raise_for_status()
    assert r.json()["state"] == "ready", r.text
    return str(scene_id)


def submit(c: httpx.Client, scene_id: str, iterations: int) -> str:
    config = {
        "iterations": iterations,
        "eval": {"every": max(iterations // 4, 1), "views": 1},
        "checkpoint_every": max(iterations // 4, 1),
        "outputs": {"mesh": False},
    }
    r = c.post("/v1/jobs", json={"scene_id": scene_id, "config": config})
    r.raise_for_status()
    return str(r.json()["id"])


def wait_job(c: httpx.Client, job_id: str, ok: Any, timeout: float = 300.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        j = c.get(f"/v1/jobs/{job_id}").json()
        if ok(j):
            return dict(j)
        if time.monotonic() > deadline:
            raise RuntimeError(f"job {job_id} is {j['state']} at {j['iteration']}: {j['error']}")
        time.sleep(0.2)


async def load(
    url: str,
    key: str,
    job_id: str,
    clients: int,
    duration: float,
    timeout: float,
    mode: str,
    interval: float = 0.0,
) -> Load:
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    headers = {"Authorization": f"Bearer {key}"}
    path = f"/v1/jobs/{job_id}"
    out = Load(mode, clients, interval, duration, 0, 0, [], [])
    async with httpx.AsyncClient(
        base_url=url, headers=headers, limits=limits, timeout=timeout
    ) as client:
        await asyncio.gather(*(client.get(path) for _ in range(clients)), return_exceptions=True)
        start = time.perf_counter()
        deadline = start + duration

        async def poll(offset: float) -> None:
            await asyncio.sleep(offset)
            next_at = time.perf_counter()
            while True:
                wait = next_at - time.perf_counter()
                if wait > 0:
                    await asyncio.sleep(wait)
                t0 = time.perf_counter()
                if t0 >= deadline:
                    return
                next_at = t0 + interval
                try:
                    r = await client.get(path)
                except httpx.HTTPError:
                    out.errors += 1
                    out.requests += 1
                    continue
                out.requests += 1
                if r.status_code != 200:
                    out.errors += 1
                    continue
                out.latencies.append(time.perf_counter() - t0)
                timing = r.headers.get("server-timing", "")
                if "dur=" in timing:
                    out.server_ms.append(float(timing.split("dur=")[1].split(",")[0]))

        await asyncio.gather(*(poll(interval * i / clients) for i in range(clients)))
        out.seconds = time.perf_counter() - start
    return out


def load_wrk(
    url: str, key: str, job_id: str, clients: int, duration: float, timeout: float, mode: str
) -> Load:
    """A closed loop of ``clients`` connections by ``wrk`` (one thread) for ``duration`` s."""
    with tempfile.NamedTemporaryFile("w", suffix=".lua", delete=False) as f:
        f.write(WRK_LUA)
    try:
        done = subprocess.run(
            [
                "wrk",
                "-t1",
                f"-c{clients}",
                f"-d{duration:g}s",
                f"--timeout={timeout:g}s",
                "-s",
                f.name,
                f"{url}/v1/jobs/{job_id}",
            ],
            env={**os.environ, "GLINT_BENCH_KEY": key},
            capture_output=True,
            text=True,
            check=True,
        )
    finally:
        os.unlink(f.name)
    line = next(x for x in done.stdout.splitlines() if x.startswith("WRK "))
    w = json.loads(line[4:])
    out = Load(mode, clients, 0.0, w["us"] / 1e6, w["requests"], w["non200"] + w["socket"], [], [])
    out.server_ms = [float(v) for v in w["server_ms"]]
    out.quantiles = (w["p50"] / 1e3, w["p90"] / 1e3, w["p99"] / 1e3, w["max"] / 1e3)
    out.client = "wrk"
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--clients", type=int, default=100)
    p.add_argument("--duration", type=float, default=20.0, help="seconds of load per mode")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--with-job", action="store_true", help="only the mode with a job")
    mode.add_argument("--without-job", action="store_true", help="only the mode without")
    p.add_argument(
        "--interval",
        default="0",
        help="seconds between one client's polls, comma-separated for several runs per mode "
        "(0: back to back)",
    )
    p.add_argument(
        "--wrk",
        action="store_true",
        help="closed loops (interval 0) with wrk instead of the asyncio client",
    )
    p.add_argument("--iterations", type=int, default=5000, help="of the training job")
    p.add_argument("--size", type=int, default=64, help="synthetic scene image side, px")
    p.add_argument("--views", type=int, default=24, help="synthetic scene views")
    p.add_argument("--timeout", type=float, default=30.0, help="per request, seconds")
    p.add_argument("--repo", type=Path, default=REPO, help="checkout whose code is served")
    args = p.parse_args(argv)
    intervals = [float(v) for v in args.interval.split(",")]
    if args.wrk and shutil.which("wrk") is None:
        p.error("--wrk needs wrk on PATH (Debian: apt-get install wrk)")
    modes = ["without job", "with job"]
    if args.with_job:
        modes = ["with job"]
    elif args.without_job:
        modes = ["without job"]

    rows: list[Load] = []
    with tempfile.TemporaryDirectory(prefix="glint-load-") as tmp:
        data_dir = Path(tmp) / "data"
        data_dir.mkdir()
        server = Server(data_dir, args.repo.resolve())
        key = server.glint("keys", "create", "bench").split()[0]
        server.start()
        try:
            headers = {"Authorization": f"Bearer {key}"}
            with httpx.Client(base_url=server.url, headers=headers, timeout=60) as c:
                scene_id = upload_scene(c, Path(tmp) / "scene", args.size, args.views)
                for m in modes:
                    job_id = submit(c, scene_id, args.iterations)
                    if m == "without job":
                        c.post(f"/v1/jobs/{job_id}/cancel").raise_for_status()
                        wait_job(c, job_id, lambda j: j["state"] == "cancelled")
                        time.sleep(2.0)  # let the queue's process for it come and go
                    else:
                        wait_job(  # training, past its first (slower) steps
                            c, job_id, lambda j: j["state"] == "running" and j["iteration"] >= 10
                        )
                    for interval in intervals:
                        before = c.get(f"/v1/jobs/{job_id}").json()["iteration"]
                        common = (server.url, key, job_id, args.clients, args.duration)
                        if args.wrk and interval == 0:
                            row = load_wrk(*common, args.timeout, m)
                        else:
                            row = asyncio.run(load(*common, args.timeout, m, interval))
                        row.load = os.getloadavg()[0]
                        if m == "with job":
                            after = c.get(f"/v1/jobs/{job_id}").json()
                            state = after["state"]
                            state = "still running" if state == "running" else state
                            row.job = f"{after['iteration'] - before} iterations, {state}"
                        rows.append(row)
                    if m == "with job":
                        c.post(f"/v1/jobs/{job_id}/cancel")
                        wait_job(c, job_id, lambda j: j["state"] not in ("queued", "running"))
        finally:
            server.stop()
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    print(
        f"GET /v1/jobs/{{id}}, {args.clients} concurrent clients, {args.duration:.0f} s per mode; "
        f"glint serve (SQLite, embedded queue) from {args.repo}; {os.cpu_count()} cores; {when}"
    )
    print(HEAD)
    print(RULE)
    for row in rows:
        print(row.row())
    return 0


if __name__ == "__main__":
    sys.exit(main())
