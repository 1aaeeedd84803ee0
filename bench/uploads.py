"""Uploads, measured: one request (multipart) against resumable chunks, and what a
client that dies halfway sends again.

    python -m bench.uploads --mb 256 --repeat 3

Starts ``glint serve`` as shipped (SQLite, the directory store) in a temporary data
folder and sends one file of ``--mb`` MB (random bytes, from disk) into a new scene:

* ``multipart``: one ``POST /v1/scenes/{id}/files`` request, streamed (httpx);
* ``chunks N MiB``: ``glint_client``'s resumable upload (announce with the SHA-256,
  ``PATCH`` chunks of N MiB, the server joins and checks them), the hashing included;
* ``resumed``: a client killed after half the chunks, then a new client: the bytes the
  second one sends (counted on the wire) and its time.

Wall time is the median of ``--repeat``; MB/s is the file's size over it. Client and
server share this machine's cores, so the figures are the whole trip on one host.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
from glint_client import Client

from bench.api_load import Server

MB = 1_000_000
BLOCK = 1 << 20
REPO = Path(__file__).resolve().parents[1]


class _Died(BaseException):
    """The client process dies (no retry logic catches a BaseException)."""


class _Counting(httpx.HTTPTransport):
    """Counts request body bytes of chunk PATCHes; raises after ``die_after`` of them."""

    def __init__(self, die_after: int | None = None) -> None:
        super().__init__()
        self.sent = 0
        self.patches = 0
        self.die_after = die_after

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.method == "PATCH":
            if self.die_after is not None and self.patches >= self.die_after:
                raise _Died
            self.patches += 1
            self.sent += len(request.read())
        return super().handle_request(request)


def _file_chunks(path: Path) -> Iterator[bytes]:
    with path.open("rb") as f:
        while data := f.read(BLOCK):
            yield data


def _multipart(url: str, key: str, sid: str, path: Path) -> None:
    boundary = "glintbench"
    head = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="files"; '
        f'filename="{path.name}"\r\nContent-Type: application/octet-stream\r\n\r\n'
    ).encode()
    tail = f"\r\n--{boundary}--\r\n".encode()

    def body() -> Iterator[bytes]:
        yield head
        yield from _file_chunks(path)
        yield tail

    r = httpx.post(
        f"{url}/v1/scenes/{sid}/files",
        content=body(),
        headers={
            "Authorization": f"Bearer {key}",
            "Content-Type": f"multipart/form-data; boundary={boundary}",
            "Content-Length": str(len(head) + path.stat().st_size + len(tail)),
        },
        timeout=600,
    )
    r.raise_for_status()


def _scene(c: Client) -> str:
    return str(c.create_scene("bench")["id"])


def run(mb: int, repeat: int, chunk_mib: list[int], root: Path) -> list[dict[str, Any]]:
    data = root / "payload.bin"
    with data.open("wb") as f:
        for _ in range(mb):
            f.write(os.urandom(MB))
    server = Server(root / "serve", REPO)
    (root / "serve").mkdir()
    key = server.glint("keys", "create", "bench").strip()
    server.start()
    rows: list[dict[str, Any]] = []
    try:
        with Client(server.url, key) as c:

            def timed(label: str, fn: Any) -> None:
                times = []
                for _ in range(repeat):
                    sid = _scene(c)
                    t0 = time.perf_counter()
                    fn(sid)
                    times.append(time.perf_counter() - t0)
                    c.delete_scene(sid)
                wall = statistics.median(times)
                rows.append({"how": label, "seconds": wall, "mb_s": mb / wall, "sent_mb": mb})
                print(f"{label:>16}: {wall:6.2f} s  {mb / wall:7.1f} MB/s", file=sys.stderr)

            timed("multipart", lambda sid: _multipart(server.url, key, sid, data))
            for n in chunk_mib:
                timed(
                    f"chunks {n} MiB",
                    lambda sid, n=n: c.upload(sid, [data], chunk_bytes=n << 20),
                )
            n = chunk_mib[0]
            chunks = -(-mb * MB // (n << 20))
            sid = _scene(c)
            dying = _Counting(die_after=chunks // 2)
            try:
                with Client(server.url, key, transport=dying) as first:
                    first.upload(sid, [data], chunk_bytes=n << 20)
            except _Died:
                pass
            again = _Counting()
            t0 = time.perf_counter()
            with Client(server.url, key, transport=again) as second:
                second.upload(sid, [data], chunk_bytes=n << 20)
            wall = time.perf_counter() - t0
            rows.append(
                {
                    "how": f"resumed ({n} MiB chunks)",
                    "seconds": wall,
                    "mb_s": again.sent / MB / wall,
                    "sent_mb": again.sent / MB,
                    "before_mb": dying.sent / MB,
                }
            )
            print(
                f"resumed: first client sent {dying.sent / MB:.1f} MB then died; the second "
                f"sent {again.sent / MB:.1f} MB of {mb} in {wall:.2f} s",
                file=sys.stderr,
            )
    finally:
        server.stop()
    return rows


def table(rows: list[dict[str, Any]], mb: int) -> str:
    out = [
        f"| upload of one {mb} MB file | wall s (median) | MB/s | MB sent |",
        "|---|---:|---:|---:|",
    ]
    for r in rows:
        out.append(f"| {r['how']} | {r['seconds']:.2f} | {r['mb_s']:.1f} | {r['sent_mb']:.1f} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--mb", type=int, default=256, help="file size in MB (default 256)")
    p.add_argument("--repeat", type=int, default=3, help="runs per row (median)")
    p.add_argument(
        "--chunk-mib", type=int, nargs="+", default=[8, 64], help="chunk sizes to measure"
    )
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="glint-bench-uploads-") as tmp:
        rows = run(args.mb, args.repeat, args.chunk_mib, Path(tmp))
    print(table(rows, args.mb))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
