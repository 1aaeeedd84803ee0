"""The artifact store interface, held to one contract on both implementations: the
directory store and the S3 store against a real S3 endpoint (moto's server, with
credentials checked). Bucket-only behaviour (multipart parts, abandoned uploads, an
outage, wrong credentials) follows."""

from __future__ import annotations

import hashlib
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from api.service.settings import Settings
from api.service.store import (
    ArtifactStore,
    LocalStore,
    StoreUnavailableError,
    make_store,
    retrying,
)
from tests.s3_server import PART_BYTES, S3Server


@pytest.fixture(scope="module")
def s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    srv = S3Server(tmp_path_factory.mktemp("moto")).start()
    yield srv
    srv.stop()


def _s3_store(s3: S3Server, root: Path, bucket: str | None = None, **kw: object) -> ArtifactStore:
    settings = Settings(data_dir=root, **s3.settings(bucket or s3.bucket(), **kw))
    return make_store(settings, "runner")


@pytest.fixture(params=["local", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> ArtifactStore:
    if request.param == "local":
        return LocalStore(tmp_path / "store")
    return _s3_store(request.getfixturevalue("s3"), tmp_path)


def test_write_is_invisible_until_commit(store: ArtifactStore) -> None:
    data = os.urandom(PART_BYTES + 12345)  # more than one part
    pending = store.begin("scenes/s/files/big.bin")
    pending.write(data[:100])
    pending.write(data[100:])
    pending.seal()
    assert not store.exists("scenes/s/files/big.bin")
    assert store.list("scenes/s") == []  # nothing half-written is ever listed
    res = pending.commit()
    assert res.size == len(data) and res.sha256 == hashlib.sha256(data).hexdigest()
    assert [o.key for o in store.list("scenes/s")] == ["scenes/s/files/big.bin"]
    assert store.stat("scenes/s/files/big.bin").size == len(data)
    assert (
        b"".join(store.read_range("scenes/s/files/big.bin", PART_BYTES - 5, 10))
        == (data[PART_BYTES - 5 : PART_BYTES + 5])
    )
    empty = store.put("scenes/s/files/empty", [])
    assert empty.size == 0 and store.stat("scenes/s/files/empty").size == 0


def test_abort_leaves_nothing(store: ArtifactStore) -> None:
    pending = store.begin("jobs/j/run/checkpoint.pt")
    pending.write(os.urandom(PART_BYTES + 1))
    pending.abort()
    assert store.list("jobs/j") == [] and not store.exists("jobs/j/run/checkpoint.pt")


def test_children_delete_and_local_copies(store: ArtifactStore) -> None:
    store.put("jobs/a/run/x.txt", [b"x"])
    store.put("jobs/b/run/renders/y.png", [b"y"])
    store.put("scenes/s/files/t.json", [b"{}"])
    assert store.children("jobs") == ["a", "b"]
    run = store.local("jobs/b/run")
    assert (run / "renders" / "y.png").read_bytes() == b"y"
    # the runner writes into the local copy and pushes it back; what it removed goes too
    (run / "renders" / "y.png").unlink()
    (run / "checkpoint.pt").write_bytes(b"ck1")
    (run / ".checkpoint.pt.123.tmp").write_bytes(b"half")  # still being written: never sent
    store.push("jobs/b/run")
    assert [o.key for o in store.list("jobs/b")] == ["jobs/b/run/checkpoint.pt"]
    assert store.local_file("jobs/b/run/checkpoint.pt").read_bytes() == b"ck1"
    assert store.local_file("jobs/b/run/missing.pt") is None
    store.delete("jobs/b")
    assert store.children("jobs") == ["a"] and store.list("jobs/b") == []
    store.delete("jobs/b")  # absent: fine


def test_bucket_copy_follows_the_bucket(s3: S3Server, tmp_path: Path) -> None:
    """Two hosts (two caches) on one bucket: what one pushes, the other's copy gets;
    local edits that were not pushed are replaced (the bucket is the truth)."""
    bucket = s3.bucket()
    worker_a = _s3_store(s3, tmp_path / "a", bucket)
    worker_b = _s3_store(s3, tmp_path / "b", bucket)
    run_a = worker_a.local("jobs/j/run")
    (run_a / "checkpoint.pt").write_bytes(b"iteration 10")
    (run_a / "metrics.jsonl").write_bytes(b'{"iteration": 10}\n')
    big = os.urandom(2 * PART_BYTES + 3)  # a file of several parts: sent in parallel
    (run_a / "renders.bin").write_bytes(big)
    assert worker_a.push("jobs/j/run") == 3
    assert worker_a.push("jobs/j/run") == 0  # unchanged files are not sent again
    run_b = worker_b.local("jobs/j/run")
    assert (run_b / "checkpoint.pt").read_bytes() == b"iteration 10"
    assert (run_b / "renders.bin").read_bytes() == big
    (run_b / "checkpoint.pt").write_bytes(b"iteration 20")
    worker_b.push("jobs/j/run")
    (run_a / "stray.txt").write_bytes(b"not in the bucket")
    run_a = worker_a.local("jobs/j/run")
    assert (run_a / "checkpoint.pt").read_bytes() == b"iteration 20"
    assert not (run_a / "stray.txt").exists()
    only = worker_a.local("jobs/j/run", ["checkpoint.pt"])
    assert only == run_a
    worker_a.drop_local("jobs/j/run")
    assert not run_a.exists() and worker_a.list("jobs/j")  # the bucket keeps it


def test_wrong_credentials_and_unreachable_endpoints_are_unavailable(
    s3: S3Server, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bucket = s3.bucket()
    for var in [v for v in os.environ if v.startswith("AWS_")]:
        monkeypatch.delenv(var)
    monkeypatch.setenv("AWS_CONFIG_FILE", str(tmp_path / "none"))
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(tmp_path / "none"))
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")
    half = _s3_store(s3, tmp_path / "h", bucket, s3_secret_access_key="")  # the AWS chain
    with pytest.raises(StoreUnavailableError, match="no credentials"):
        half.check()
    wrong = _s3_store(s3, tmp_path / "w", bucket, s3_secret_access_key="not-the-secret")
    with pytest.raises(StoreUnavailableError, match="refused the credentials"):
        wrong.check()
    with pytest.raises(StoreUnavailableError, match="refused the credentials"):
        wrong.put("scenes/s/files/a", [b"a"])
    missing = _s3_store(s3, tmp_path / "m", "no-such-bucket-here")
    with pytest.raises(StoreUnavailableError, match="bucket does not exist"):
        missing.check()
    t0 = time.monotonic()
    closed = _s3_store(s3, tmp_path / "c", bucket, s3_endpoint_url="http://127.0.0.1:9")
    with pytest.raises(StoreUnavailableError, match="unreachable"):
        closed.check()
    assert time.monotonic() - t0 < 10


def test_multipart_upload_is_bounded_and_aborted(s3: S3Server, tmp_path: Path) -> None:
    """Parts go out as they fill: the writer holds at most one part, and an aborted write
    leaves no multipart upload behind in the bucket."""
    bucket = s3.bucket()
    store = _s3_store(s3, tmp_path, bucket)
    pending = store.begin("scenes/s/files/big.bin")
    for _ in range(3):
        pending.write(b"\0" * (PART_BYTES // 2 + 1))
        assert len(pending._buffer) < PART_BYTES  # what memory it holds: under one part
    assert len(s3.uploads(bucket)) == 1
    pending.abort()
    assert s3.uploads(bucket) == [] and s3.keys(bucket) == []
    # a small file sealed at its end (the multipart parser does it per file part) holds
    # nothing either: its bytes are a part in the bucket, the object not visible yet
    small = store.begin("scenes/s/files/small.bin")
    small.write(b"abc")
    small.seal()
    assert len(small._buffer) == 0 and len(s3.uploads(bucket)) == 1 and not s3.keys(bucket)
    assert small.commit().size == 3 and s3.keys(bucket) == ["glint/scenes/s/files/small.bin"]


def test_retrying_rides_out_an_outage(s3: S3Server, tmp_path: Path) -> None:
    """The endpoint stops answering; the operation is retried with backoff and succeeds
    once it is back."""
    store = _s3_store(s3, tmp_path, store_timeout_s=1.0)
    store.put("jobs/j/run/a.txt", [b"a"])
    s3.pause()
    timer = threading.Timer(3.0, s3.resume)
    timer.start()
    try:
        t0 = time.monotonic()
        stat = retrying(lambda: store.stat("jobs/j/run/a.txt"), what="test", patience_s=30)
        assert stat is not None and stat.size == 1
        assert time.monotonic() - t0 >= 2.5  # it did wait for the endpoint
    finally:
        timer.join()
        s3.resume()
    store.check()
    with pytest.raises(StoreUnavailableError):  # no patience: the first error is final
        retrying(
            lambda: _s3_store(s3, tmp_path / "x", s3_endpoint_url="http://127.0.0.1:9").check(),
            what="test",
            patience_s=0,
        )
