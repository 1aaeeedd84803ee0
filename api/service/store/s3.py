"""The artifact store in an S3-compatible bucket (AWS S3, MinIO, Ceph RGW, R2...).

``GLINT_STORE_URL=s3://bucket/prefix`` selects it. Objects are ``{prefix}/{key}``.

* **Writes** are multipart uploads straight to the object's key: parts of
  ``store_part_bytes`` go out as they fill (the API holds one part per upload, whatever
  the file's size) and the object exists only once ``commit`` completes the upload, so a
  reader never sees half an object; ``abort`` drops the parts. An empty file is one
  empty PUT at commit.
* **Reads** stream (``read_range`` is a ranged GET, for HTTP Range downloads).
* **Local copies** (:class:`~api.service.store.mirror.LocalMirror` under the cache
  directory) serve the code that reads files: scene loaders, trainer, viewer.
* **Errors** that mean the store cannot be used (unreachable, credentials refused, no
  bucket, a 5xx) become :class:`StoreUnavailableError`; a missing key is None/absent.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, BinaryIO

from api.service.store.base import StoredObject, StoreUnavailableError, WriteResult, write_all
from api.service.store.keys import check_key
from api.service.store.mirror import LocalMirror
from api.service.store.s3_client import NOT_FOUND_CODES, S3Location, error_code, unavailable

READ_CHUNK = 256 * 1024
DELETE_BATCH = 1000  # DeleteObjects takes at most this many keys
UPLOAD_THREADS = 4  # parallel parts of a file upload (bench/store_io.py: 1.6x on 100 MB)


class _S3PendingWrite:
    """One object being uploaded in parts; invisible until :meth:`commit`."""

    def __init__(self, store: S3Store, key: str) -> None:
        self._store = store
        self._key = key
        self._s3_key = store.location.key(key)
        self._buffer = bytearray()
        self._parts: list[dict[str, Any]] = []
        self._upload_id: str | None = None
        self._hash = hashlib.sha256()
        self._sealed = False
        self._done = False
        self.size = 0
        self.etag = ""  # the object's, once committed

    def write(self, data: bytes) -> None:
        assert not self._sealed, "write after seal/commit/abort"
        self._hash.update(data)
        self.size += len(data)
        self._buffer += data
        part = self._store.part_bytes
        while len(self._buffer) >= part:
            chunk = bytes(self._buffer[:part])
            del self._buffer[:part]
            self._send_part(chunk)

    def _send_part(self, data: bytes) -> None:
        s = self._store
        with s.errors():
            if self._upload_id is None:
                res = s.client.create_multipart_upload(Bucket=s.location.bucket, Key=self._s3_key)
                self._upload_id = res["UploadId"]
            number = len(self._parts) + 1
            res = s.client.upload_part(
                Bucket=s.location.bucket,
                Key=self._s3_key,
                UploadId=self._upload_id,
                PartNumber=number,
                Body=data,
            )
        self._parts.append({"ETag": res["ETag"], "PartNumber": number})

    def seal(self) -> None:
        """The last bytes are in: send them as the (short) last part, holding nothing."""
        if self._sealed:
            return
        self._sealed = True
        if self._buffer:
            data = bytes(self._buffer)
            self._buffer = bytearray()
            self._send_part(data)

    def commit(self) -> WriteResult:
        assert not self._done, "commit after commit/abort"
        self.seal()
        self._done = True
        s = self._store
        try:
            with s.errors():
                if self._upload_id is None:  # an empty file: nothing was uploaded
                    res = s.client.put_object(Bucket=s.location.bucket, Key=self._s3_key, Body=b"")
                else:
                    res = s.client.complete_multipart_upload(
                        Bucket=s.location.bucket,
                        Key=self._s3_key,
                        UploadId=self._upload_id,
                        MultipartUpload={"Parts": self._parts},
                    )
        except BaseException:
            self._abort_upload()
            raise
        self.etag = str(res.get("ETag", ""))
        return WriteResult(self.size, self._hash.hexdigest())

    def abort(self) -> None:
        self._sealed = self._done = True
        self._buffer = bytearray()
        self._abort_upload()

    def _abort_upload(self) -> None:
        """Drop the uploaded parts (best effort: the sweep aborts what this could not)."""
        if self._upload_id is None:
            return
        s = self._store
        with contextlib.suppress(Exception):
            s.client.abort_multipart_upload(
                Bucket=s.location.bucket, Key=self._s3_key, UploadId=self._upload_id
            )
        self._upload_id = None


class S3Store:
    """Keys of an S3-compatible bucket under a prefix, with local copies under ``cache``."""

    def __init__(
        self,
        location: S3Location,
        client: Any,
        check_client: Any,
        cache: Path,
        *,
        part_bytes: int = 8 << 20,
        endpoint: str | None = None,
    ) -> None:
        self.location = location
        self.client = client
        self.check_client = check_client
        self.part_bytes = part_bytes
        self.endpoint = endpoint
        self.where = f"{location} at {endpoint or 'AWS S3'}"
        self.mirror = LocalMirror(self, cache)

    def describe(self) -> str:
        return self.where

    @contextlib.contextmanager
    def errors(self) -> Iterator[None]:
        """Translate what says 'the store cannot be used' into StoreUnavailableError."""
        try:
            yield
        except StoreUnavailableError:
            raise
        except Exception as exc:
            translated = unavailable(exc, self.where)
            if translated is not None:
                raise translated from exc
            raise

    def check(self) -> None:
        """One listing with a short timeout and no retry: reachable, credentials accepted,
        bucket present; else :class:`StoreUnavailableError` saying which."""
        prefix = f"{self.location.prefix}/" if self.location.prefix else ""
        with self.errors():
            self.check_client.list_objects_v2(Bucket=self.location.bucket, Prefix=prefix, MaxKeys=1)

    # -- writing ---------------------------------------------------------------------
    def begin(self, key: str) -> _S3PendingWrite:
        return _S3PendingWrite(self, check_key(key))

    def put(self, key: str, chunks: Iterable[bytes]) -> WriteResult:
        return write_all(self.begin(key), chunks)

    def upload_file(self, key: str, src: Path) -> str:
        """Upload a local file (one PUT, or parts for a large one); its new ETag.

        A file on disk can be read at any offset, so its parts go out in parallel
        (boto3's transfer manager, ``UPLOAD_THREADS`` at a time): a runner's checkpoint
        push blocks training, and one connection rarely fills a link to S3."""
        check_key(key)
        size = src.stat().st_size
        s3_key = self.location.key(key)
        with self.errors():
            if size <= self.part_bytes:
                res = self.client.put_object(
                    Bucket=self.location.bucket, Key=s3_key, Body=src.read_bytes()
                )
                return str(res.get("ETag", ""))
            from boto3.s3.transfer import TransferConfig

            config = TransferConfig(
                multipart_threshold=self.part_bytes,
                multipart_chunksize=self.part_bytes,
                max_concurrency=UPLOAD_THREADS,
            )
            self.client.upload_file(str(src), self.location.bucket, s3_key, Config=config)
            res = self.client.head_object(Bucket=self.location.bucket, Key=s3_key)
        return str(res.get("ETag", ""))

    # -- reading ---------------------------------------------------------------------
    def open(self, key: str) -> BinaryIO:
        with self.errors():
            res = self.client.get_object(Bucket=self.location.bucket, Key=self.location.key(key))
        return res["Body"]  # type: ignore[no-any-return]

    def read_range(self, key: str, start: int, length: int) -> Iterator[bytes]:
        """``length`` bytes from ``start`` as one ranged GET, streamed in chunks."""
        if length <= 0:
            return
        with self.errors():
            res = self.client.get_object(
                Bucket=self.location.bucket,
                Key=self.location.key(check_key(key)),
                Range=f"bytes={start}-{start + length - 1}",
            )
            body = res["Body"]
            try:
                yield from body.iter_chunks(READ_CHUNK)
            finally:
                body.close()

    def download(self, key: str, dest: Path) -> StoredObject:
        """Stream one object into ``dest`` (replaced whole, never half-written)."""
        tmp = dest.with_name(f".{dest.name}.{uuid.uuid4().hex}.tmp")
        try:
            with self.errors():
                res = self.client.get_object(
                    Bucket=self.location.bucket, Key=self.location.key(key)
                )
                size = 0
                with open(tmp, "wb") as fh:
                    for chunk in res["Body"].iter_chunks(1 << 20):
                        fh.write(chunk)
                        size += len(chunk)
            os.replace(tmp, dest)
        finally:
            tmp.unlink(missing_ok=True)
        mtime = res["LastModified"].timestamp() if res.get("LastModified") else 0.0
        return StoredObject(key, size, mtime, str(res.get("ETag", "")))

    def stat(self, key: str) -> StoredObject | None:
        try:
            with self.errors():
                res = self.client.head_object(
                    Bucket=self.location.bucket, Key=self.location.key(check_key(key))
                )
        except Exception as exc:
            if error_code(exc) in NOT_FOUND_CODES:
                return None
            raise
        mtime = res["LastModified"].timestamp() if res.get("LastModified") else 0.0
        return StoredObject(key, int(res["ContentLength"]), mtime, str(res.get("ETag", "")))

    def exists(self, key: str) -> bool:
        """An object, or a 'folder' (any object under ``key/``)."""
        if self.stat(key) is not None:
            return True
        with self.errors():
            res = self.client.list_objects_v2(
                Bucket=self.location.bucket, Prefix=self.location.key(key) + "/", MaxKeys=1
            )
        return bool(res.get("KeyCount") or res.get("Contents"))

    def _pages(self, prefix: str, **kw: Any) -> Iterator[dict[str, Any]]:
        paginator = self.client.get_paginator("list_objects_v2")
        with self.errors():
            yield from paginator.paginate(
                Bucket=self.location.bucket, Prefix=self.location.key(check_key(prefix)) + "/", **kw
            )

    def list(self, prefix: str) -> list[StoredObject]:
        """Objects under ``prefix`` (recursively), keys relative to the store, sorted."""
        out = []
        for page in self._pages(prefix):
            for o in page.get("Contents", []):
                out.append(
                    StoredObject(
                        self.location.unkey(o["Key"]),
                        int(o["Size"]),
                        o["LastModified"].timestamp(),
                        str(o.get("ETag", "")),
                    )
                )
        return sorted(out, key=lambda o: o.key)

    def children(self, prefix: str) -> list[str]:
        """Names right under ``prefix`` that hold objects (``scenes`` → scene ids)."""
        names = []
        for page in self._pages(prefix, Delimiter="/"):
            for cp in page.get("CommonPrefixes", []):
                names.append(self.location.unkey(cp["Prefix"]).rstrip("/").rsplit("/", 1)[-1])
        return sorted(names)

    # -- removing --------------------------------------------------------------------
    def delete_keys(self, keys: list[str]) -> None:
        for i in range(0, len(keys), DELETE_BATCH):
            batch = [{"Key": self.location.key(k)} for k in keys[i : i + DELETE_BATCH]]
            with self.errors():
                res = self.client.delete_objects(
                    Bucket=self.location.bucket, Delete={"Objects": batch, "Quiet": True}
                )
            failed = res.get("Errors") or []
            if failed:
                first = failed[0]
                raise StoreUnavailableError(
                    f"{self.where}: cannot delete {len(failed)} object(s), e.g. "
                    f"{first.get('Key')}: {first.get('Code')}"
                )

    def delete(self, key: str) -> None:
        """Remove an object or everything under ``key/`` (absent keys are fine), and the
        local copy."""
        check_key(key)
        keys = [o.key for o in self.list(key)]
        if self.stat(key) is not None:
            keys.append(key)
        self.delete_keys(keys)
        self.mirror.drop(key)

    def sweep_abandoned(self, older_than_s: float) -> int:
        """Abort multipart uploads under the prefix started over ``older_than_s`` ago (an
        API process that died mid-upload leaves its parts, which cost storage)."""
        import datetime as dt

        cutoff = dt.datetime.now(dt.UTC) - dt.timedelta(seconds=older_than_s)
        prefix = f"{self.location.prefix}/" if self.location.prefix else ""
        paginator = self.client.get_paginator("list_multipart_uploads")
        n = 0
        with self.errors():
            for page in paginator.paginate(Bucket=self.location.bucket, Prefix=prefix):
                for up in page.get("Uploads", []):
                    if up["Initiated"] < cutoff:
                        self.client.abort_multipart_upload(
                            Bucket=self.location.bucket, Key=up["Key"], UploadId=up["UploadId"]
                        )
                        n += 1
        return n

    # -- local copies ------------------------------------------------------------------
    def local(self, prefix: str, names: Iterable[str] | None = None) -> Path:
        return self.mirror.pull(prefix, names)

    def local_path(self, key: str) -> Path:
        """Where the local copy of ``key`` lives (or will): no request made."""
        return self.mirror.root / check_key(key)

    def local_file(self, key: str) -> Path | None:
        return self.mirror.pull_file(key)

    def push(self, prefix: str) -> int:
        return self.mirror.push(prefix)

    def drop_local(self, prefix: str) -> None:
        self.mirror.drop(prefix)
