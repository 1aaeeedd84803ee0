"""The artifact store on a directory: the embedded default, or a volume every process mounts.

Layout: :mod:`api.service.store.keys`, plus ``{root}/tmp/...`` for staging. Writes are
staged in ``tmp/`` and renamed into place on commit (same filesystem), so a reader never
sees a half-written file and an aborted upload leaves nothing behind. The stored files
are their own local copies: :meth:`LocalStore.local` is the folder itself and
:meth:`LocalStore.push` has nothing to do.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

from api.service.store.base import (
    StoredObject,
    StoreError,
    StoreUnavailableError,
    WriteResult,
    is_staging,
    write_all,
)
from api.service.store.keys import check_key


def _replace_into(source: Path, target: Path, tries: int = 5) -> None:
    """Move ``source`` to ``target``, making its folders. A delete elsewhere in the store
    prunes folders it emptied (``_prune_empty_parents``), which can remove ``target``'s
    parent between the mkdir and the move: make it again and retry."""
    for attempt in range(tries):
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(source, target)
            return
        except FileNotFoundError:
            if attempt == tries - 1 or not source.exists():
                raise


class _LocalPendingWrite:
    def __init__(self, store: LocalStore, key: str) -> None:
        self._store = store
        self._key = key
        self._tmp = store.tmp_dir / f"{uuid.uuid4().hex}.part"
        self._tmp.parent.mkdir(parents=True, exist_ok=True)
        self._fh: BinaryIO | None = open(self._tmp, "wb")  # noqa: SIM115 (closed in seal/abort)
        self._hash = hashlib.sha256()
        self._done = False
        self.size = 0

    def write(self, data: bytes) -> None:
        assert self._fh is not None, "write after seal/commit/abort"
        self._fh.write(data)
        self._hash.update(data)
        self.size += len(data)

    def seal(self) -> None:
        """All bytes are in: close the file (a request of many files holds no handles)."""
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def commit(self) -> WriteResult:
        assert not self._done, "commit after commit/abort"
        self.seal()
        self._done = True
        target = self._store.path(self._key)
        try:
            if target.is_dir():
                raise StoreError(f"'{self._key}' is a folder")
            _replace_into(self._tmp, target)
        except (NotADirectoryError, FileExistsError, IsADirectoryError) as exc:
            self._tmp.unlink(missing_ok=True)
            raise StoreError(f"'{self._key}' collides with an existing file or folder") from exc
        except BaseException:
            self._tmp.unlink(missing_ok=True)
            raise
        return WriteResult(self.size, self._hash.hexdigest())

    def abort(self) -> None:
        self.seal()
        self._done = True
        self._tmp.unlink(missing_ok=True)


class LocalStore:
    """The store on a local (or shared, mounted) directory."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).resolve()
        self.tmp_dir = self.root / "tmp"
        self.root.mkdir(parents=True, exist_ok=True)

    def describe(self) -> str:
        return f"directory {self.root}"

    def check(self) -> None:
        """Raise :class:`StoreUnavailableError` unless the root is a writable folder."""
        if not self.root.is_dir() or not os.access(self.root, os.W_OK | os.X_OK):
            raise StoreUnavailableError(f"store directory {self.root} is missing or read-only")

    def path(self, key: str) -> Path:
        return self.root / check_key(key)

    def begin(self, key: str) -> _LocalPendingWrite:
        check_key(key)
        return _LocalPendingWrite(self, key)

    def put(self, key: str, chunks: Iterable[bytes]) -> WriteResult:
        return write_all(self.begin(key), chunks)

    def open(self, key: str) -> BinaryIO:
        return open(self.path(key), "rb")

    def read_range(self, key: str, start: int, length: int) -> Iterator[bytes]:
        """``length`` bytes from ``start``, in chunks of at most 256 KiB."""
        with self.open(key) as fh:
            fh.seek(start)
            left = length
            while left > 0:
                data = fh.read(min(256 * 1024, left))
                if not data:
                    return
                left -= len(data)
                yield data

    def stat(self, key: str) -> StoredObject | None:
        p = self.path(key)
        try:
            st = p.stat()
        except OSError:
            return None
        return StoredObject(key, st.st_size, st.st_mtime) if p.is_file() else None

    def exists(self, key: str) -> bool:
        return self.path(key).exists()

    def children(self, prefix: str) -> list[str]:
        """Names of the folders right under ``prefix`` (``scenes`` → scene ids), sorted."""
        base = self.path(prefix)
        return sorted(p.name for p in base.iterdir() if p.is_dir()) if base.is_dir() else []

    def local(self, prefix: str, names: Iterable[str] | None = None) -> Path:
        """The folder itself: stored files are their own local copies."""
        return self.path(prefix)

    def local_path(self, key: str) -> Path:
        return self.path(key)

    def local_file(self, key: str) -> Path | None:
        p = self.path(key)
        return p if p.is_file() else None

    def push(self, prefix: str) -> int:
        """Nothing to send: files written under :meth:`local` are stored already."""
        check_key(prefix)
        return 0

    def drop_local(self, prefix: str) -> None:
        """Nothing to drop: the local copy is the stored one."""

    def delete(self, key: str) -> None:
        """Remove a file or a folder with everything under it; absent keys are fine."""
        p = self.path(key)
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        self._prune_empty_parents(p.parent)

    def list(self, prefix: str) -> list[StoredObject]:
        """Files under ``prefix`` (recursively, not those still being written: ``*.tmp``),
        keys relative to the store root, sorted."""
        base = self.path(prefix)
        if not base.is_dir():
            return []
        out = []
        for dirpath, _dirs, files in os.walk(base):
            for name in files:
                p = Path(dirpath) / name
                key = p.relative_to(self.root).as_posix()
                if not is_staging(key):
                    out.append(StoredObject(key, p.stat().st_size, p.stat().st_mtime))
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

    def sweep_abandoned(self, older_than_s: float) -> int:
        """Staging files older than ``older_than_s``: what crashed writers left."""
        return self.sweep_tmp(older_than_s)

    def _prune_empty_parents(self, p: Path) -> None:
        """Drop empty folders left by a delete, down to ``{kind}/{id}`` (kept for writers)."""
        while self.root in p.parents and len(p.relative_to(self.root).parts) > 2:
            try:
                p.rmdir()
            except OSError:
                return
            p = p.parent
