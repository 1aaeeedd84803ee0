"""API latency under concurrency, and the API's memory while it receives a huge upload.

    python -m bench.api_latency [--clients 100] [--requests 5000] [--duration 30]
                                [--upload-bytes 2G] [--no-upload]

Starts ``glint serve`` (one uvicorn process, SQLite in a temporary data dir) and:

1. hammers ``GET /v1/jobs/{id}`` (authenticated, a running job's row) from
   ``--clients`` concurrent keep-alive connections (httpx, asyncio) until
   ``--requests`` answers or ``--duration`` seconds; prints p50/p90/p99 latency and
   requests per second as the clients see them, and the server's own time per
   request (its ``Server-Timing`` header). Client and server share the machine's
   cores, so on a small machine these numbers are a floor, not a ceiling;
2. streams one multipart upload of ``--upload-bytes`` generated on the fly (the same
   1 MiB buffer sent repeatedly: the benchmark never holds the file either) and samples
   the server's resident memory every 50 ms; prints the baseline, the peak during the
   upload and the throughput. The file is deleted through the API afterwards and the
   temporary data dir removed.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
CHUNK = bytes(1 << 20)


def parse_size(text: str) -> int:
    units = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}
    text = text.strip().upper().removesuffix("B")
    if text and text[-1] in units:
        return int(float(text[:-1]) * units[text[-1]])
    return int(text)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rss_kib(pid: int, field: str = "VmRSS") -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"{field} not found for pid {pid}")


def seed(data_dir: Path) -> tuple[str, str]:
    """A key and a job with progress, written straight into a fresh database.

    The job is terminal so the embedded queue's start-up recovery leaves it alone; its
    response is as large as a running job's.
    """
    sys.path.insert(0, str(REPO))
    from api.auth import create_key
    from api.service.db import Database
    from api.service.migrate import upgrade
    from api.service.models import Job, Scene, new_id

    db = Database(f"sqlite:///{data_dir / 'glint.db'}")
    upgrade(db.engine)
    with db.write() as s:
        _row, key = create_key(s, "bench")
        scene = Scene(id=new_id("scn"), owner="bench", name="bench", state="ready")
        s.add(scene)
        s.flush()
        job = Job(
            id=new_id("job"),
            owner="bench",
            scene_id=scene.id,
            state="succeeded",
            config={"iterations": 30000},
            total_iterations=30000,
            iteration=12345,
            phase="multiview",
            n_gaussians=250_000,
            loss=0.05,
            metrics={"psnr": 31.2, "ssim": 0.95, "iteration": 12000},
            elapsed_s=600.0,
            eta_s=860.0,
        )
        s.add(job)
        job_id = job.id
    db.dispose()
    return key, job_id


def start_server(data_dir: Path, port: int, upload_bytes: int) -> subprocess.Popen:
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "GLINT_DATA_DIR": str(data_dir),
        "GLINT_MAX_FILE_BYTES": str(upload_bytes + 1),
        "GLINT_MAX_SCENE_BYTES": str(upload_bytes + (1 << 20)),
    }
    code = "import sys; from core.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "serve", "--port", str(port), "--log-level", "warning"],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/v1/health").status_code == 200:
                return proc
        except httpx.ConnectError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("glint serve did not come up")


async def latency(url: str, key: str, job_id: str, clients: int, total: int, duration: float):
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    headers = {"Authorization": f"Bearer {key}"}
    times: list[float] = []
    app_ms: list[float] = []  # the server's own time (Server-Timing header)
    errors = 0
    timeout = httpx.Timeout(120.0)
    async with httpx.AsyncClient(
        base_url=url, headers=headers, limits=limits, timeout=timeout
    ) as client:
        await asyncio.gather(*(client.get(f"/v1/jobs/{job_id}") for _ in range(clients)))  # warm
        deadline = time.perf_counter() + duration
        counter = iter(range(total))

        async def worker() -> None:
            nonlocal errors
            for _ in counter:
                if time.perf_counter() > deadline:
                    return
                t0 = time.perf_counter()
                r = await client.get(f"/v1/jobs/{job_id}")
                times.append(time.perf_counter() - t0)
                errors += r.status_code != 200
                app_ms.append(float(r.headers["server-timing"].split("dur=")[1]))

        t0 = time.perf_counter()
        await asyncio.gather(*(worker() for _ in range(clients)))
        wall = time.perf_counter() - t0
    times.sort()
    q = statistics.quantiles(times, n=100)
    qa = statistics.quantiles(app_ms, n=100)
    return {
        "app_p50_ms": qa[49],
        "app_p99_ms": qa[98],
        "requests": len(times),
        "errors": errors,
        "p50_ms": q[49] * 1e3,
        "p90_ms": q[89] * 1e3,
        "p99_ms": q[98] * 1e3,
        "max_ms": times[-1] * 1e3,
        "rps": len(times) / wall,
    }


def upload(url: str, key: str, pid: int, size: int) -> dict:
    headers = {"Authorization": f"Bearer {key}"}
    with httpx.Client(base_url=url, headers=headers, timeout=600) as c:
        sid = c.post("/v1/scenes", json={"name": "big"}).json()["id"]
        boundary = "glintbenchboundary"
        head = (
            f'--{boundary}\r\nContent-Disposition: form-data; name="files"; '
            f'filename="big.bin"\r\nContent-Type: application/octet-stream\r\n\r\n'
        ).encode()
        tail = f"\r\n--{boundary}--\r\n".encode()

        def body() -> Iterator[bytes]:
            yield head
            left = size
            while left > 0:
                n = min(left, len(CHUNK))
                yield CHUNK if n == len(CHUNK) else CHUNK[:n]
                left -= n
            yield tail

        baseline = rss_kib(pid)
        peak = baseline
        done = threading.Event()

        def sample() -> None:
            nonlocal peak
            while not done.wait(0.05):
                peak = max(peak, rss_kib(pid))

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        t0 = time.perf_counter()
        r = c.post(
            f"/v1/scenes/{sid}/files",
            content=body(),
            headers={
                "Content-Type": f"multipart/form-data; boundary={boundary}",
                "Content-Length": str(len(head) + size + len(tail)),
            },
        )
        wall = time.perf_counter() - t0
        done.set()
        sampler.join()
        assert r.status_code == 201, r.text
        assert r.json()["files"][0]["size"] == size
        assert c.delete(f"/v1/scenes/{sid}/files/big.bin").status_code == 204
    return {
        "bytes": size,
        "rss_baseline_mib": baseline / 1024,
        "rss_peak_mib": peak / 1024,
        "rss_growth_mib": (peak - baseline) / 1024,
        "hwm_mib": rss_kib(pid, "VmHWM") / 1024,
        "seconds": wall,
        "mib_per_s": size / (1 << 20) / wall,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clients", type=int, default=100)
    p.add_argument("--requests", type=int, default=5000, help="stop after this many answers")
    p.add_argument("--duration", type=float, default=30.0, help="or after this many seconds")
    p.add_argument("--upload-bytes", default="2G", help="e.g. 2G, 500M (generated on the fly)")
    p.add_argument("--no-upload", action="store_true")
    p.add_argument("--port", type=int, default=0)
    args = p.parse_args(argv)
    size = parse_size(args.upload_bytes)
    port = args.port or free_port()
    with tempfile.TemporaryDirectory(prefix="glint-bench-") as tmp:
        data_dir = Path(tmp)
        key, job_id = seed(data_dir)
        proc = start_server(data_dir, port, size)
        try:
            url = f"http://127.0.0.1:{port}"
            lat = asyncio.run(latency(url, key, job_id, args.clients, args.requests, args.duration))
            print(f"machine: {os.cpu_count()} cores; server: 1 uvicorn process, SQLite (WAL)")
            print(f"\nGET /v1/jobs/{{id}}, {args.clients} concurrent clients, loopback")
            print(
                "| requests | errors | p50 ms | p90 ms | p99 ms | max ms | req/s "
                "| in-app p50 ms | in-app p99 ms |"
            )
            print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
            print(
                f"| {lat['requests']} | {lat['errors']} | {lat['p50_ms']:.1f} | "
                f"{lat['p90_ms']:.1f} | {lat['p99_ms']:.1f} | {lat['max_ms']:.1f} | "
                f"{lat['rps']:.0f} | {lat['app_p50_ms']:.1f} | {lat['app_p99_ms']:.1f} |"
            )
            if not args.no_upload:
                up = upload(url, key, proc.pid, size)
                print(f"\nstreamed multipart upload of {size / (1 << 20):.0f} MiB")
                print("| RSS before MiB | RSS peak MiB | growth MiB | VmHWM MiB | s | MiB/s |")
                print("|---:|---:|---:|---:|---:|---:|")
                print(
                    f"| {up['rss_baseline_mib']:.0f} | {up['rss_peak_mib']:.0f} | "
                    f"{up['rss_growth_mib']:.1f} | {up['hwm_mib']:.0f} | {up['seconds']:.1f} | "
                    f"{up['mib_per_s']:.0f} |"
                )
                leftovers = [p for p in (data_dir / "store").rglob("*") if p.is_file()]
                print(f"store files left after delete: {len(leftovers)}")
        finally:
            proc.terminate()
            proc.wait(30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
