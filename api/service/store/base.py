"""The artifact store's interface: what the API and the runner need, whatever holds the bytes.

Two implementations: :class:`~api.service.store.local.LocalStore` (a directory: the
embedded default, or a volume every process mounts) and
:class:`~api.service.store.s3.S3Store` (an S3-compatible bucket, for API and workers on
different hosts). Keys are relative POSIX paths (:mod:`api.service.store.keys`).

Code that needs files on disk (the scene loaders, the trainer, the viewer) asks for a
*local copy*: :meth:`ArtifactStore.local` (a folder) or :meth:`ArtifactStore.local_file`
(one file). For a directory store that is the stored file itself; for a bucket it is a
cache on this host, kept equal to the bucket, and :meth:`ArtifactStore.push` sends what
the process wrote there back.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Protocol


class StoreError(Exception):
    """A key is malformed or collides with an existing file or folder."""


class StoreUnavailableError(Exception):
    """The store cannot be used right now: unreachable, credentials refused, no bucket.

    Transient from the caller's point of view: the API answers 503 ``store-unavailable``
    and a runner retries with backoff (``Settings.store_retry_s``).
    """


@dataclass(frozen=True)
class StoredObject:
    key: str
    size: int
    mtime: float
    etag: str = ""  # opaque version tag (S3 ETag); empty for files of a directory store


@dataclass(frozen=True)
class WriteResult:
    size: int
    sha256: str


class PendingWrite(Protocol):
    """A file being written: ``write`` chunks, ``seal`` when the last one is in (optional:
    frees what is buffered), then ``commit`` (atomic: visible at once, whole) or ``abort``."""

    size: int

    def write(self, data: bytes) -> None: ...
    def seal(self) -> None: ...
    def commit(self) -> WriteResult: ...
    def abort(self) -> None: ...


def write_all(pending: PendingWrite, chunks: Iterable[bytes]) -> WriteResult:
    """Write every chunk and commit; abort on any failure, so nothing half-written is kept."""
    try:
        for chunk in chunks:
            pending.write(chunk)
    except BaseException:
        pending.abort()
        raise
    return pending.commit()


class ArtifactStore(Protocol):
    """What the API and the runner need from a store."""

    def describe(self) -> str: ...
    def check(self) -> None: ...
    def begin(self, key: str) -> PendingWrite: ...
    def put(self, key: str, chunks: Iterable[bytes]) -> WriteResult: ...
    def open(self, key: str) -> BinaryIO: ...
    def read_range(self, key: str, start: int, length: int) -> Iterator[bytes]: ...
    def stat(self, key: str) -> StoredObject | None: ...
    def exists(self, key: str) -> bool: ...
    def delete(self, key: str) -> None: ...
    def list(self, prefix: str) -> list[StoredObject]: ...
    def children(self, prefix: str) -> list[str]: ...
    def local(self, prefix: str, names: Iterable[str] | None = None) -> Path: ...
    def local_file(self, key: str) -> Path | None: ...
    def local_path(self, key: str) -> Path: ...
    def push(self, prefix: str) -> int: ...
    def drop_local(self, prefix: str) -> None: ...
    def sweep_abandoned(self, older_than_s: float) -> int: ...


def is_staging(relative: str) -> bool:
    """A file still being written by its producer (``*.tmp`` in its path): never an
    artifact, never pushed."""
    return any(part.endswith(".tmp") for part in relative.split("/"))
