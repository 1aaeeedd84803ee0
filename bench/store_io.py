"""The S3 artifact store, measured: which client moves 100 MB faster, and what a 2 GB
upload costs the API's memory.

    python -m bench.store_io transfer --mb 100 --repeat 3
    python -m bench.store_io upload-rss --mb 2048

Both start their own S3 endpoint: moto's standalone server (``moto_server``, the test
endpoint; a Python server, so absolute throughput is the server's, not the network's:
compare the clients with each other, on the same server).

* ``transfer``: upload and download of one object of ``--mb`` MB, per client: Glint's
  ``S3Store`` on boto3 as the API streams an upload (sequential parts, one in memory)
  and as a runner pushes a file (4 parallel parts) and downloads (one streamed GET);
  boto3's transfer manager on its own (4 parallel parts both ways), and obstore (Rust,
  ``pip install obstore``; its default parallel multipart). Wall time and the client
  process's CPU time (user + system), median of ``--repeat``.
* ``upload-rss``: ``glint serve`` on the S3 store; one ``--mb`` MB file streamed in a
  multipart/form-data request; the server's RSS sampled every 0.1 s (``/proc``) before,
  during and after.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx

from bench.api_load import Server, free_port

MB = 1_000_000
BLOCK = 1 << 20
ACCESS = ("bench", "bench-secret")  # moto without IAM accepts any pair


class Moto:
    """``moto_server`` on a free port (no authentication: a benchmark endpoint)."""

    def __init__(self, root: Path) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        # moto's cyclic garbage collection closes the buffers of parts it still holds (a
        # 2 GB completion then fails with "seek of closed file"): off, in this process only
        cmd = [
            sys.executable,
            "-c",
            "import gc; gc.disable(); from moto.server import main; main()",
        ]
        env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
        env["TMPDIR"] = str(root)  # moto spools large objects to temporary files
        self.log = root / "moto.log"
        self.proc = subprocess.Popen(
            [*cmd, "-H", "127.0.0.1", "-p", str(self.port)],
            stdout=open(self.log, "ab"),  # noqa: SIM115 (the process owns it)
            stderr=subprocess.STDOUT,
            env=env,
        )
        deadline = time.monotonic() + 30
        while True:
            try:
                urllib.request.urlopen(f"{self.url}/moto-api/", timeout=1).read()
                return
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError("moto_server did not start") from None
                time.sleep(0.1)

    def client(self) -> Any:
        import boto3
        from botocore.config import Config

        return boto3.client(
            "s3",
            endpoint_url=self.url,
            region_name="us-east-1",
            aws_access_key_id=ACCESS[0],
            aws_secret_access_key=ACCESS[1],
            config=Config(s3={"addressing_style": "path"}),
        )

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(30)


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _timed(fn: Callable[[], None]) -> tuple[float, float]:
    w0, c0 = time.perf_counter(), _cpu()
    fn()
    return time.perf_counter() - w0, _cpu() - c0


def _chunks(path: Path) -> Iterator[bytes]:
    with open(path, "rb") as fh:
        while chunk := fh.read(BLOCK):
            yield chunk


def _glint_store(moto: Moto, bucket: str, data: Path) -> Any:
    from api.service.settings import Settings
    from api.service.store import make_store

    settings = Settings(
        data_dir=data,
        store_url=f"s3://{bucket}",
        s3_endpoint_url=moto.url,
        s3_region="us-east-1",
        s3_access_key_id=ACCESS[0],
        s3_secret_access_key=ACCESS[1],
    )
    return make_store(settings, "runner")


def transfer(mb: int, repeat: int, root: Path) -> list[dict[str, Any]]:
    from boto3.s3.transfer import TransferConfig

    moto = Moto(root)
    try:
        client = moto.client()
        bucket = "bench"
        client.create_bucket(Bucket=bucket)
        src = root / "object.bin"
        with open(src, "wb") as fh:
            block = os.urandom(BLOCK)
            for _ in range(mb * MB // BLOCK + 1):
                fh.write(block)
            fh.truncate(mb * MB)
        out = root / "back.bin"
        glint = _glint_store(moto, bucket, root / "glint")
        tm = TransferConfig(multipart_chunksize=8 << 20, max_concurrency=4)
        cases: dict[str, tuple[Callable[[], None], Callable[[], None]]] = {
            "boto3: Glint S3Store, API upload (streamed, one 8 MiB part at a time)": (
                lambda: glint.put("a/stream.bin", _chunks(src)),
                lambda: glint.download("a/stream.bin", out),
            ),
            "boto3: Glint S3Store, runner push (file, 4 parallel 8 MiB parts)": (
                lambda: glint.upload_file("a/glint.bin", src),
                lambda: glint.download("a/glint.bin", out),
            ),
            "boto3: transfer manager (4 parallel 8 MiB parts)": (
                lambda: client.upload_file(str(src), bucket, "a/tm.bin", Config=tm),
                lambda: client.download_file(bucket, "a/tm.bin", str(out), Config=tm),
            ),
        }
        try:
            import obstore
            from obstore.store import S3Store as ObStore

            ob = ObStore(
                bucket,
                endpoint=moto.url,
                region="us-east-1",
                access_key_id=ACCESS[0],
                secret_access_key=ACCESS[1],
                client_options={"allow_http": True},
            )

            def ob_get() -> None:
                with open(out, "wb") as fh:
                    for chunk in obstore.get(ob, "a/ob.bin").stream(min_chunk_size=BLOCK):
                        fh.write(chunk)

            cases["obstore (default parallel multipart)"] = (
                lambda: obstore.put(ob, "a/ob.bin", src),
                ob_get,
            )
        except ImportError:
            print("obstore not installed: pip install obstore", file=sys.stderr)
        rows = []
        for name, (up, down) in cases.items():
            ups = [_timed(up) for _ in range(repeat)]
            downs = [_timed(down) for _ in range(repeat)]
            assert out.stat().st_size == src.stat().st_size, name
            rows.append(
                {
                    "client": name,
                    "up_s": statistics.median(w for w, _ in ups),
                    "up_cpu_s": statistics.median(c for _, c in ups),
                    "down_s": statistics.median(w for w, _ in downs),
                    "down_cpu_s": statistics.median(c for _, c in downs),
                }
            )
        return rows
    finally:
        moto.stop()


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _body(total: int, boundary: str) -> Iterator[bytes]:
    yield (
        f'--{boundary}\r\nContent-Disposition: form-data; name="files"; filename="big.bin"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n"
    ).encode()
    block = os.urandom(BLOCK)
    left = total
    while left > 0:
        n = min(left, BLOCK)
        yield block[:n]
        left -= n
    yield f"\r\n--{boundary}--\r\n".encode()


def upload_rss(mb: int, root: Path) -> dict[str, Any]:
    moto = Moto(root)
    server: Server | None = None
    try:
        moto.client().create_bucket(Bucket="bench")
        repo = Path(__file__).resolve().parents[1]
        server = Server(root / "glint", repo)
        server.data_dir.mkdir(parents=True, exist_ok=True)
        server.env.update(
            GLINT_STORE_URL="s3://bench/glint",
            GLINT_S3_ENDPOINT_URL=moto.url,
            GLINT_S3_REGION="us-east-1",
            GLINT_S3_ACCESS_KEY_ID=ACCESS[0],
            GLINT_S3_SECRET_ACCESS_KEY=ACCESS[1],
            # moto answers CompleteMultipartUpload of 2 GB only after concatenating it
            # (AWS S3 keeps the connection alive meanwhile): wait for it, do not retry
            GLINT_STORE_TIMEOUT_S="300",
            GLINT_MAX_FILE_BYTES=str(4 << 30),
            GLINT_MAX_SCENE_BYTES=str(8 << 30),
        )
        server.start()
        assert server.proc is not None
        key = server.glint("keys", "create", "bench").split()[0]
        headers = {"Authorization": f"Bearer {key}"}
        with httpx.Client(base_url=server.url, headers=headers, timeout=600) as c:
            sid = c.post("/v1/scenes", json={"name": "big"}).json()["id"]
            warm = c.post(f"/v1/scenes/{sid}/files", files={"files": ("warm.bin", b"x" * BLOCK)})
            assert warm.status_code == 201, warm.text
            time.sleep(1.0)
            before = _rss_kib(server.proc.pid)
            samples: list[int] = []
            done = threading.Event()

            def sample() -> None:
                while not done.wait(0.1):
                    samples.append(_rss_kib(server.proc.pid))

            t = threading.Thread(target=sample, daemon=True)
            t.start()
            boundary = "benchboundary"
            total = mb * MB
            t0 = time.perf_counter()
            r = c.post(
                f"/v1/scenes/{sid}/files",
                content=_body(total, boundary),
                headers={"Content-Type": f"multipart/form-data; boundary={boundary}"},
            )
            seconds = time.perf_counter() - t0
            done.set()
            t.join()
            assert r.status_code == 201, (r.text, moto.log.read_text()[-3000:])
            assert r.json()["files"][0]["size"] == total
            after = _rss_kib(server.proc.pid)
        return {
            "mb": mb,
            "seconds": round(seconds, 1),
            "mb_per_s": round(mb / seconds, 1),
            "rss_before_mib": round(before / 1024, 1),
            "rss_peak_mib": round(max(samples, default=before) / 1024, 1),
            "rss_peak_delta_mib": round((max(samples, default=before) - before) / 1024, 1),
            "rss_after_mib": round(after / 1024, 1),
            "samples": len(samples),
        }
    finally:
        if server is not None:
            server.stop()
        moto.stop()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("transfer", help="boto3 vs obstore: upload and download of one object")
    t.add_argument("--mb", type=int, default=100)
    t.add_argument("--repeat", type=int, default=3)
    u = sub.add_parser("upload-rss", help="the API's RSS during one large streamed upload")
    u.add_argument("--mb", type=int, default=2048)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="glint-store-bench-") as tmp:
        root = Path(tmp)
        if args.cmd == "transfer":
            print(f"| client | {args.mb} MB up s | up CPU s | down s | down CPU s |")
            print("|---|---:|---:|---:|---:|")
            for row in transfer(args.mb, args.repeat, root):
                print(
                    f"| {row['client']} | {row['up_s']:.2f} | {row['up_cpu_s']:.2f} "
                    f"| {row['down_s']:.2f} | {row['down_cpu_s']:.2f} |"
                )
        else:
            print(upload_rss(args.mb, root))
    return 0


if __name__ == "__main__":
    sys.exit(main())
