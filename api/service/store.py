"""The artifact store: a local directory behind a small interface.

Keys are relative POSIX paths. The layout is shared by the API and the workers (one
volume mounted by both)::

    {root}/scenes/{scene_id}/files/...   uploaded scene files (the scene folder)
    {root}/jobs/{job_id}/run/...         the run folder train_scene writes into
    {root}/tmp/...                       staging: uploads land here, then rename

Writes are staged in ``tmp/`` and renamed into place on commit (same filesystem), so a
reader never sees a half-written file and an aborted upload leaves nothing behind.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Protocol


class StoreError(Exception):
    """A key is malformed or collides with an existing file or folder."""


def scene_files_key(scene_id: str) -> str:
    return f"scenes/{scene_id}/files"


def scene_key(scene_id: str) -> str:
    return f"scenes/{scene_id}"


def job_run_key(job_id: str) -> str:
    return f"jobs/{job_id}/run"


def job_key(job_id: str) -> str:
    return f"jobs/{job_id}"


@dataclass(frozen=True)
class StoredObject:
    key: str
    size: int
    mtime: float


@dataclass(frozen=True)
class WriteResult:
    size: int
    sha256: str


class PendingWrite(Protocol):
    """A file being written: ``write`` chunks, then ``commit`` (atomic) or ``abort``."""

    size: int

    def write(self, data: bytes) -> None: ...
    def commit(self) -> WriteResult: ...
    def abort(self) -> None: ...


class ArtifactStore(Protocol):
    """What the API and the runner need from a store; :class:`LocalStore` implements it."""

    def begin(self, key: str) -> PendingWrite: ...
    def put(self, key: str, chunks: Iterable[bytes]) -> WriteResult: ...
    def open(self, key: str) -> BinaryIO: ...
    def path(self, key: str) -> Path: ...
    def exists(self, key: str) -> bool: ...
    def delete(self, key: str) -> None: ...
    def list(self, prefix: str) -> list[StoredObject]: ...


def check_key(key: str) -> str:
    """``key`` if it is a clean relative POSIX path, else :class:`StoreError`."""
    if not key or "\\" in key or "\x00" in key or key.startswith("/"):
        raise StoreError(f"invalid store key {key!r}")
    if any(p in ("", ".", "..") for p in key.split("/")):
        raise StoreError(f"invalid store key {key!r}")
    return key


class _LocalPendingWrite:
    def __init__(self, store: LocalStore, key: str) -> None:
        self._store = store
        self._key = key
        self._tmp = store.tmp_dir / f"{uuid.uuid4().hex}.part"
        self._tmp.parent.mkdir(parents=True, exist_ok=True)
        self._fh: BinaryIO | None = open(self._tmp, "wb")  # noqa: SIM115 (closed in commit/abort)
        self._hash = hashlib.sha256()
        self.size = 0

    def write(self, data: bytes) -> None:
        assert self._fh is not None, "write after commit/abort"
        self._fh.write(data)
        self._hash.update(data)
        self.size += len(data)

    def commit(self) -> WriteResult:
        assert self._fh is not None, "commit after commit/abort"
        self._fh.close()
        self._fh = None
        target = self._store.path(self._key)
        try:
            if target.is_dir():
                raise StoreError(f"'{self._key}' is a folder")
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(self._tmp, target)
        except (NotADirectoryError, FileExistsError, IsADirectoryError) as exc:
            self._tmp.unlink(missing_ok=True)
            raise StoreError(f"'{self._key}' collides with an existing file or folder") from exc
        except BaseException:
            self._tmp.unlink(missing_ok=True)
            raise
        return WriteResult(self.size, self._hash.hexdigest())

    def abort(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
        self._tmp.unlink(missing_ok=True)


class LocalStore:
    """The store on a local (or shared, mounted) directory."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).resolve()
        self.tmp_dir = self.root / "tmp"
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        return self.root / check_key(key)

    def begin(self, key: str) -> _LocalPendingWrite:
        check_key(key)
        return _LocalPendingWrite(self, key)

    def put(self, key: str, chunks: Iterable[bytes]) -> WriteResult:
        pending = self.begin(key)
        try:
            for chunk in chunks:
                pending.write(chunk)
        except BaseException:
            pending.abort()
            raise
        return pending.commit()

    def open(self, key: str) -> BinaryIO:
        return open(self.path(key), "rb")

    def exists(self, key: str) -> bool:
        return self.path(key).exists()

    def delete(self, key: str) -> None:
        """Remove a file or a folder with everything under it; absent keys are fine."""
        p = self.path(key)
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        self._prune_empty_parents(p.parent)

    def list(self, prefix: str) -> list[StoredObject]:
        """Files under ``prefix`` (recursively), keys relative to the store root, sorted."""
        base = self.path(prefix)
        if not base.is_dir():
            return []
        out = []
        for dirpath, _dirs, files in os.walk(base):
            for name in files:
                p = Path(dirpath) / name
                st = p.stat()
                out.append(
                    StoredObject(p.relative_to(self.root).as_posix(), st.st_size, st.st_mtime)
                )
        return sorted(out, key=lambda o: o.key)

    def sweep_tmp(self, older_than_s: float = 24 * 3600) -> int:
        """Delete staging files left by crashed processes; returns how many went."""
        if not self.tmp_dir.is_dir():
            return 0
        cutoff = time.time() - older_than_s
        n = 0
        for p in self.tmp_dir.rglob("*"):
            if p.is_file() and p.stat().st_mtime < cutoff:
                p.unlink(missing_ok=True)
                n += 1
        return n

    def _prune_empty_parents(self, p: Path) -> None:
        """Drop empty folders left by a delete, down to ``{kind}/{id}`` (kept for writers)."""
        while self.root in p.parents and len(p.relative_to(self.root).parts) > 2:
            try:
                p.rmdir()
            except OSError:
                return
            p = p.parent
