"""Resumable uploads: each file goes up in chunks that the server keeps as they arrive.

The protocol (docs/client.md, *Resumable uploads*): ``POST .../uploads`` with the file's
path, size and SHA-256 answers the upload — a new one, or the unfinished one the server
already has for exactly that file (its ``offset`` says how much arrived), or ``complete``
when the scene holds the file already. Then ``PATCH`` sends the next bytes at that
offset until the last chunk completes it; the server joins the chunks and checks the
checksum. So a client that died (or lost its connection) needs no state of its own to
go on: asking again tells it where to continue, and it never resends what arrived.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_EXCEPTION, Future, ThreadPoolExecutor, wait
from typing import Any, cast

from glint_client.errors import (
    ChecksumMismatch,
    GlintClientError,
    NotFound,
    OffsetMismatch,
    ServerError,
)
from glint_client.files import LocalFile, sha256_of
from glint_client.http import Http
from glint_client.models import Upload

DEFAULT_CHUNK_BYTES = 8 << 20
OFFSET_CONTENT_TYPE = "application/offset+octet-stream"
MAX_STALLS = 5  # chunks in a row that moved the offset nowhere: give up, do not spin
MAX_CHUNK_FAULTS = 3  # 5xx answers to one chunk in a row before the upload gives up

ByteCallback = Callable[[int], None]


class _StoppedError(Exception):
    """A file's upload ends early because another one failed (what arrived is kept)."""


class Uploader:
    """Sends a scene's files, ``parallel`` at a time, each in chunks of at most
    ``chunk_bytes`` (or the server's ``chunk_max_bytes``, when smaller).

    ``on_bytes(n)`` is called (from worker threads) as bytes are known to be on the
    server, including those found there already, so a bar over the total size is right.
    """

    def __init__(
        self,
        http: Http,
        *,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        parallel: int = 4,
        on_bytes: ByteCallback | None = None,
    ) -> None:
        if chunk_bytes < 1:
            raise ValueError("chunk_bytes must be at least 1")
        self.http = http
        self.chunk_bytes = chunk_bytes
        self.parallel = max(1, parallel)
        self._on_bytes = on_bytes
        self._lock = threading.Lock()
        self._stop = threading.Event()  # set when one file failed or the caller was interrupted

    def _progress(self, n: int) -> None:
        if self._on_bytes and n > 0:
            with self._lock:
                self._on_bytes(n)

    def upload_all(self, scene_id: str, files: Sequence[LocalFile]) -> list[Upload]:
        """Upload every file; on the first failure the others stop and it is raised
        (what arrived stays on the server: run again to continue)."""
        if self.parallel == 1 or len(files) <= 1:
            return [self.upload(scene_id, f) for f in files]
        self._stop.clear()
        pool = ThreadPoolExecutor(self.parallel, thread_name_prefix="glint-upload")
        futures: list[Future[Upload]] = [pool.submit(self.upload, scene_id, f) for f in files]
        try:
            done, _ = wait(futures, return_when=FIRST_EXCEPTION)
            for fut in done:  # the first failure (the others stop without one of their own)
                if fut.exception() is not None:
                    raise cast(BaseException, fut.exception())
            return [fut.result() for fut in futures]
        finally:
            self._stop.set()  # the others stop after their chunk in flight
            pool.shutdown(wait=True, cancel_futures=True)

    def start(self, scene_id: str, f: LocalFile, sha256: str) -> Upload:
        """Open the upload of ``f`` (or find the unfinished one, or learn it is there)."""
        body = {"path": f.path, "size": f.size, "sha256": sha256}
        r = self.http.request(
            "POST", f"/v1/scenes/{scene_id}/uploads", json=body, retry=True, ok=(200, 201)
        )
        return cast(Upload, r.json())

    def upload(self, scene_id: str, f: LocalFile) -> Upload:
        """One file, from wherever the server has it to its end."""
        sha256 = sha256_of(f.source)
        up = self.start(scene_id, f, sha256)
        self._progress(int(up["offset"]) if up["state"] != "complete" else f.size)
        restarted = False
        while True:
            try:
                return self._send(scene_id, f, up)
            except NotFound:
                # the server dropped the unfinished upload (expired, deleted): open anew
                if restarted:
                    raise
                restarted = True
                up = self.start(scene_id, f, sha256)
            except ChecksumMismatch as exc:
                raise GlintClientError(
                    f"{f.source}: its SHA-256 on the server differs from the one computed "
                    "here; the file changed while it was being sent. Upload it again."
                ) from exc

    def _send(self, scene_id: str, f: LocalFile, up: Upload) -> Upload:
        if up["state"] == "complete":
            return up
        upload_id = up["id"]
        url = f"/v1/scenes/{scene_id}/uploads/{upload_id}"
        chunk = min(self.chunk_bytes, int(up.get("chunk_max_bytes") or self.chunk_bytes))
        offset = int(up["offset"])
        stalls = faults = 0
        with f.source.open("rb") as src:
            while True:
                if offset >= f.size:
                    # everything arrived yet the upload is open: ask how it stands
                    up = cast(Upload, self.http.request("GET", url).json())
                    if up["state"] == "complete":
                        return up
                    if int(up["offset"]) >= f.size:
                        raise GlintClientError(
                            f"{f.path}: all {f.size} bytes are on the server but the upload "
                            "did not complete"
                        )
                    offset = int(up["offset"])
                if self._stop.is_set():
                    raise _StoppedError
                src.seek(offset)
                data = src.read(min(chunk, f.size - offset))
                if not data:
                    raise GlintClientError(f"{f.source}: the file shrank while being sent")
                headers = {"Upload-Offset": str(offset), "Content-Type": OFFSET_CONTENT_TYPE}
                try:
                    r = self.http.request("PATCH", url, content=data, headers=headers)
                except ServerError:
                    # a chunk refused by a server fault: the offset says whether it was
                    # kept (the server only ever moves it for a chunk it holds whole)
                    faults += 1
                    if faults > MAX_CHUNK_FAULTS:
                        raise
                    time.sleep(0.1 * 2**faults)
                    server = self._offset(url)
                    self._progress(server - offset)
                    offset = server
                    continue
                except OffsetMismatch as exc:
                    # a retried chunk that had arrived, or another client on the same file
                    server = exc.offset if exc.offset is not None else self._offset(url)
                    self._progress(server - offset)
                    stalls = stalls + 1 if server == offset else 0
                    offset = server
                else:
                    faults = 0
                    up = cast(Upload, r.json())
                    new = int(up["offset"]) if up["state"] != "complete" else f.size
                    self._progress(new - offset)
                    stalls = stalls + 1 if new <= offset else 0
                    offset = new
                    if up["state"] == "complete":
                        return up
                if stalls >= MAX_STALLS:
                    raise GlintClientError(
                        f"{f.path}: the server kept the upload at offset {offset} after "
                        f"{MAX_STALLS} chunks; giving up"
                    )

    def _offset(self, url: str) -> int:
        data: dict[str, Any] = self.http.request("GET", url).json()
        return int(data["offset"])
