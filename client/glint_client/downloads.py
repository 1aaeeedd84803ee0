"""Downloading artifacts: several at once, resumable, each checked against its SHA-256.

Each file is written to ``NAME.part`` and renamed only once its checksum matches the
listing, so a file under its real name is always whole. A ``.part`` left by an
interrupted run (or a connection cut mid-file) is continued with a ``Range`` request;
``If-Range`` carries the listed checksum (the server's ETag), so if the artifact
changed meanwhile the server sends it whole instead of a mismatched tail. Files already
present with the right checksum are not fetched again.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path, PurePosixPath
from urllib.parse import quote

import httpx

from glint_client.errors import GlintClientError, IntegrityError, ServerUnreachable
from glint_client.files import sha256_of
from glint_client.http import Http
from glint_client.models import Artifact

ByteCallback = Callable[[int], None]
BLOCK = 1 << 16


def local_path(dest: Path, name: str) -> Path:
    """Where artifact ``name`` goes under ``dest``; refuses names that would leave it."""
    rel = PurePosixPath(name)
    if rel.is_absolute() or ".." in rel.parts or not rel.parts or "\\" in name:
        raise GlintClientError(f"artifact name '{name}' is not a safe relative path")
    return dest.joinpath(*rel.parts)


class Downloader:
    """Fetches artifacts of one job, ``parallel`` at a time.

    ``resumes`` is how often one file's transfer may be cut off and continued before
    the download fails; ``on_bytes(n)`` reports bytes on disk (from worker threads).
    """

    def __init__(
        self,
        http: Http,
        *,
        parallel: int = 4,
        resumes: int = 5,
        on_bytes: ByteCallback | None = None,
    ) -> None:
        self.http = http
        self.parallel = max(1, parallel)
        self.resumes = resumes
        self._on_bytes = on_bytes
        self._lock = threading.Lock()
        self._stop = threading.Event()  # one file failed or the caller was interrupted

    def _progress(self, n: int) -> None:
        if self._on_bytes and n:
            with self._lock:
                self._on_bytes(n)

    def download_all(self, job_id: str, artifacts: Sequence[Artifact], dest: Path) -> list[Path]:
        """Every artifact into ``dest`` (its sub-folders kept); returns the paths."""
        dest.mkdir(parents=True, exist_ok=True)
        for a in artifacts:
            local_path(dest, a["name"])  # refuse a bad name before fetching anything
        self._stop.clear()
        with ThreadPoolExecutor(self.parallel, thread_name_prefix="glint-download") as pool:
            futures = [pool.submit(self.fetch, job_id, a, dest) for a in artifacts]
            try:
                return [f.result() for f in futures]
            finally:
                self._stop.set()  # the others stop at their next block (their .part stays)
                for f in futures:
                    f.cancel()

    def fetch(self, job_id: str, art: Artifact, dest: Path) -> Path:
        target = local_path(dest, art["name"])
        size, sha = int(art["size"]), str(art["sha256"])
        if target.is_file() and target.stat().st_size == size and sha256_of(target) == sha:
            self._progress(size)
            return target
        target.parent.mkdir(parents=True, exist_ok=True)
        part = target.with_name(target.name + ".part")
        for fresh in (False, True):  # a checksum mismatch gets one whole new try
            if fresh:
                part.unlink(missing_ok=True)
            self._transfer(job_id, art, part)
            if sha256_of(part) == sha:
                part.replace(target)
                return target
            self._progress(-part.stat().st_size)
        part.unlink(missing_ok=True)
        raise IntegrityError(
            f"{art['name']}: the SHA-256 of the downloaded bytes differs from the listed "
            f"{sha} (twice); the stored artifact may be damaged"
        )

    def _transfer(self, job_id: str, art: Artifact, part: Path) -> None:
        """Bring ``part`` to the artifact's full size, continuing across cut-offs."""
        size = int(art["size"])
        url = f"/v1/jobs/{job_id}/artifacts/{quote(art['name'], safe='/')}"
        have = part.stat().st_size if part.exists() else 0
        if have > size:
            part.unlink()
            have = 0
        self._progress(have)
        cuts = 0
        while have < size or not part.exists():
            headers = {}
            if have:
                headers = {"Range": f"bytes={have}-", "If-Range": f'"{art["sha256"]}"'}
            try:
                with self.http.stream("GET", url, headers=headers) as r:
                    if r.status_code != 206:  # whole file: start over
                        self._progress(-have)
                        have = 0
                    with part.open("ab" if have else "wb") as out:
                        for block in r.iter_bytes(BLOCK):
                            if self._stop.is_set():
                                raise GlintClientError("download stopped")
                            out.write(block)
                            have += len(block)
                            self._progress(len(block))
                if have < size:
                    raise httpx.RemoteProtocolError("the body ended early")
            except (httpx.TransportError, ServerUnreachable) as exc:
                cuts += 1
                if cuts > self.resumes:
                    if isinstance(exc, ServerUnreachable):
                        raise
                    raise self.http.unreachable(exc) from exc
                time.sleep(min(0.5 * 2**cuts, 10.0))
                have = part.stat().st_size if part.exists() else 0
