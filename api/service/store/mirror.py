"""Local copies of bucket objects: what the loaders, the trainer and the viewer read.

A :class:`LocalMirror` keeps ``{root}/{key}`` for the objects a process needs, laid out
like the keys (so a run folder's ``scene.json``, relative to the run, points at the
scene's copy as it does in the store). Beside each copy, ``{root}/.state/{key}`` records
the object's ETag and the copy's size and mtime: a copy is fetched again only when the
object changed, and :meth:`LocalMirror.push` sends only the files a process changed.

The bucket is the truth: :meth:`pull` makes the local folder equal to the bucket's
prefix (local edits and leftovers of a crashed run are replaced or removed), and
:meth:`push` makes the prefix equal to the local folder (files removed locally are
removed from the bucket). Files still being written (``*.tmp`` in their path) are
neither pushed nor removed.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Iterable
from pathlib import Path
from typing import Protocol

from api.service.store.base import StoredObject, is_staging
from api.service.store.keys import check_key


class RemoteObjects(Protocol):
    """What a mirror needs of the bucket side."""

    def list(self, prefix: str) -> list[StoredObject]: ...
    def stat(self, key: str) -> StoredObject | None: ...
    def download(self, key: str, dest: Path) -> StoredObject: ...
    def upload_file(self, key: str, src: Path) -> str: ...
    def delete_keys(self, keys: list[str]) -> None: ...


class LocalMirror:
    """Copies of ``remote``'s objects under ``root`` (one process kind per root)."""

    def __init__(self, remote: RemoteObjects, root: Path) -> None:
        self.remote = remote
        self.root = Path(root).resolve()
        self.state_root = self.root / ".state"

    # -- state of one copy -------------------------------------------------------
    def _state_path(self, key: str) -> Path:
        return self.state_root / f"{key}.json"

    def _read_state(self, key: str) -> dict[str, int | str] | None:
        try:
            data = json.loads(self._state_path(key).read_text())
        except (OSError, ValueError):
            return None
        return data if isinstance(data, dict) else None

    def _write_state(self, key: str, etag: str, path: Path) -> None:
        st = path.stat()
        state = {"etag": etag, "size": st.st_size, "mtime_ns": st.st_mtime_ns}
        target = self._state_path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex}.tmp")
        tmp.write_text(json.dumps(state))
        os.replace(tmp, target)

    def _forget(self, key: str) -> None:
        self._state_path(key).unlink(missing_ok=True)

    @staticmethod
    def _unchanged(path: Path, state: dict[str, int | str] | None) -> bool:
        """The copy is still what was fetched or pushed (size and mtime as recorded)."""
        if state is None:
            return False
        try:
            st = path.stat()
        except OSError:
            return False
        return st.st_size == state.get("size") and st.st_mtime_ns == state.get("mtime_ns")

    def _local_files(self, prefix: str) -> dict[str, Path]:
        base = self.root / prefix
        out: dict[str, Path] = {}
        if not base.is_dir():
            return out
        for dirpath, _dirs, files in os.walk(base):
            for name in files:
                p = Path(dirpath) / name
                rel = p.relative_to(self.root).as_posix()
                if not p.is_symlink() and not is_staging(rel):
                    out[rel] = p
        return out

    def _tracked(self, prefix: str) -> set[str]:
        base = self.state_root / prefix
        if not base.is_dir():
            return set()
        out = set()
        for p in base.rglob("*.json"):
            rel = p.relative_to(self.state_root).as_posix().removesuffix(".json")
            if not is_staging(rel):
                out.add(rel)
        return out

    # -- bucket → here -------------------------------------------------------------
    def pull(self, prefix: str, names: Iterable[str] | None = None) -> Path:
        """Make ``{root}/{prefix}`` hold the prefix's objects (only ``names``, relative to
        the prefix, when given; then nothing else is touched); returns that folder."""
        check_key(prefix)
        wanted = None if names is None else {f"{prefix}/{n}" for n in names}
        remote = {o.key: o for o in self.remote.list(prefix)}
        if wanted is not None:
            remote = {k: o for k, o in remote.items() if k in wanted}
        for key, obj in remote.items():
            self._fetch(key, obj)
        if wanted is None:  # the folder is the bucket's: what the bucket lacks goes
            for key, path in self._local_files(prefix).items():
                if key not in remote:
                    path.unlink(missing_ok=True)
                    self._forget(key)
            for key in self._tracked(prefix) - set(remote):
                self._forget(key)
        folder = self.root / prefix
        folder.mkdir(parents=True, exist_ok=True)
        return folder

    def pull_file(self, key: str) -> Path | None:
        """A fresh copy of one object (one HEAD when it did not change), None if absent."""
        check_key(key)
        obj = self.remote.stat(key)
        path = self.root / key
        if obj is None:
            path.unlink(missing_ok=True)
            self._forget(key)
            return None
        self._fetch(key, obj)
        return path

    def _fetch(self, key: str, obj: StoredObject) -> None:
        path = self.root / key
        state = self._read_state(key)
        if state is not None and state.get("etag") == obj.etag and self._unchanged(path, state):
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        got = self.remote.download(key, path)
        self._write_state(key, got.etag, path)

    # -- here → bucket -------------------------------------------------------------
    def push(self, prefix: str) -> int:
        """Send the files under ``{root}/{prefix}`` that changed since they were fetched or
        last pushed, and remove from the bucket what was removed here; how many went."""
        check_key(prefix)
        local = self._local_files(prefix)
        sent = 0
        for key, path in sorted(local.items()):
            if self._unchanged(path, self._read_state(key)):
                continue
            etag = self.remote.upload_file(key, path)
            self._write_state(key, etag, path)
            sent += 1
        gone = sorted(self._tracked(prefix) - set(local))
        if gone:
            self.remote.delete_keys(gone)
            for key in gone:
                self._forget(key)
        return sent

    def drop(self, prefix: str) -> None:
        """Forget the local copy of a prefix or a file (the bucket keeps the objects)."""
        check_key(prefix)
        target = self.root / prefix
        if target.is_file():
            target.unlink(missing_ok=True)
        else:
            shutil.rmtree(target, ignore_errors=True)
        shutil.rmtree(self.state_root / prefix, ignore_errors=True)
        self._forget(prefix)
