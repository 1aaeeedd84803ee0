"""The local artifact store: atomic writes, clean aborts, safe keys, listing, deletion."""

from __future__ import annotations

import hashlib
import os
import time
from pathlib import Path

import pytest

from api.service.store import LocalStore, StoreError, check_key


def test_put_is_atomic_and_hashes(tmp_path: Path) -> None:
    store = LocalStore(tmp_path)
    res = store.put("scenes/s/files/a/b.bin", [b"ab", b"cd"])
    assert res.size == 4 and res.sha256 == hashlib.sha256(b"abcd").hexdigest()
    with store.open("scenes/s/files/a/b.bin") as fh:
        assert fh.read() == b"abcd"
    assert [o.key for o in store.list("scenes/s")] == ["scenes/s/files/a/b.bin"]


def test_aborted_write_leaves_nothing(tmp_path: Path) -> None:
    store = LocalStore(tmp_path)
    pending = store.begin("x/y.bin")
    pending.write(b"partial")
    assert not store.exists("x/y.bin")  # invisible until commit
    pending.abort()
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]

    def boom():
        yield b"data"
        raise RuntimeError("client went away")

    with pytest.raises(RuntimeError):
        store.put("x/z.bin", boom())
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]


def test_commit_onto_a_folder_is_refused_cleanly(tmp_path: Path) -> None:
    store = LocalStore(tmp_path)
    store.put("k/a/b", [b"1"])
    with pytest.raises(StoreError):
        store.put("k/a", [b"2"])
    with pytest.raises(StoreError):
        store.put("k/a/b/c", [b"3"])
    assert [o.key for o in store.list("k")] == ["k/a/b"]
    assert not list(store.tmp_dir.iterdir())


@pytest.mark.parametrize("key", ["", "/abs", "a/../b", "..", "a//b", "a\\b", "./a", "a/\x00"])
def test_bad_keys(key: str) -> None:
    with pytest.raises(StoreError):
        check_key(key)


def test_delete_file_and_tree(tmp_path: Path) -> None:
    store = LocalStore(tmp_path)
    store.put("jobs/j/run/a.txt", [b"a"])
    store.put("jobs/j/run/renders/b.png", [b"b"])
    store.delete("jobs/j/run/renders/b.png")
    assert not (tmp_path / "jobs/j/run/renders").exists()  # emptied folder pruned
    assert (tmp_path / "jobs/j").is_dir()  # but not the job's own folder
    store.delete("jobs/j")
    store.delete("jobs/j")  # absent: fine
    assert store.list("jobs") == []


def test_sweep_tmp_removes_only_old_leftovers(tmp_path: Path) -> None:
    store = LocalStore(tmp_path)
    old, new = store.begin("a"), store.begin("b")
    old.write(b"x")
    new.write(b"y")
    stale = next(p for p in store.tmp_dir.iterdir() if p.name == old._tmp.name)
    os.utime(stale, (time.time() - 90_000, time.time() - 90_000))
    assert store.sweep_tmp() == 1
    assert [p.name for p in store.tmp_dir.iterdir()] == [new._tmp.name]
    new.abort()


def test_a_commit_survives_a_delete_pruning_its_folder(tmp_path: Path, monkeypatch) -> None:
    """A delete prunes the folders it emptied. With parallel chunked uploads of one
    scene, that can remove ``uploads/`` between another commit's mkdir and its move;
    the commit makes the folder again instead of failing (it answered 500)."""
    import api.service.store.local as local

    store = LocalStore(tmp_path)
    store.put("scenes/s/uploads/u1/c0", [b"first"])
    pending = store.begin("scenes/s/uploads/u2/c0")
    pending.write(b"second")
    real_replace, raced = os.replace, []

    def replace_after_a_prune(src, dst):  # type: ignore[no-untyped-def]
        if not raced:  # u1 finishes in between: its delete empties and prunes uploads/
            raced.append(True)
            Path(dst).parent.rmdir()  # (the folder our mkdir had just made was empty)
            store.delete("scenes/s/uploads/u1")
            assert not (tmp_path / "scenes/s/uploads").exists()
        return real_replace(src, dst)

    monkeypatch.setattr(local.os, "replace", replace_after_a_prune)
    assert pending.commit().size == 6
    with store.open("scenes/s/uploads/u2/c0") as fh:
        assert fh.read() == b"second"
