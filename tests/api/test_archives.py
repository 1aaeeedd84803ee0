"""Archive unpacking and path rules, below HTTP: what passes and what is refused."""

from __future__ import annotations

import shutil
import subprocess
import tarfile
from pathlib import Path

import pytest

from api.archives import ArchiveLimits, extract_archive
from api.paths import UnsafePathError, clean_relpath
from api.problems import ApiError
from api.service.store import LocalStore
from tests.api.archives import (
    make_tar,
    make_zip,
    tar_of_folder,
    tar_with,
    zip_bomb,
    zip_with_nul,
    zip_with_symlink,
)

LIMITS = ArchiveLimits(
    max_files=10, max_file_bytes=1 << 20, max_total_bytes=4 << 20, max_ratio=50, max_path_length=80
)


def _extract(tmp_path: Path, data: bytes, limits: ArchiveLimits = LIMITS):
    store = LocalStore(tmp_path / "store")
    archive = tmp_path / "upload"
    archive.write_bytes(data)
    try:
        return extract_archive(archive, store, lambda p: f"scenes/s/files/{p}", limits), store
    finally:
        leftovers = (
            [p for p in store.tmp_dir.rglob("*") if p.is_file()] if store.tmp_dir.exists() else []
        )
        assert all(p.suffix == ".part" for p in leftovers)


def _refused(tmp_path: Path, data: bytes, status: int, needle: str, **kw) -> None:
    with pytest.raises(ApiError) as err:
        _extract(tmp_path, data, ArchiveLimits(**{**LIMITS.__dict__, **kw}))
    assert err.value.status == status and needle in err.value.detail, err.value.detail
    store_tmp = tmp_path / "store" / "tmp"
    assert not store_tmp.exists() or not any(store_tmp.iterdir()), "staged files left behind"


@pytest.mark.parametrize(
    ("name", "expected"),
    [("a/b.png", "a/b.png"), ("./a//b.png", "a/b.png"), ("x/./y", "x/y"), ("é.png", "é.png")],
)
def test_clean_paths(name: str, expected: str) -> None:
    assert clean_relpath(name) == expected


@pytest.mark.parametrize(
    "name", ["", "/", "/etc/passwd", "C:/x", "a/../../b", "..", "a\\b", "a\x00b", "./", "x" * 300]
)
def test_unsafe_paths(name: str) -> None:
    with pytest.raises(UnsafePathError):
        clean_relpath(name)


def test_good_zip_and_tar_stage_every_file(tmp_path: Path) -> None:
    files = [("transforms_train.json", b"{}"), ("train/r_0.png", b"png")]
    archives = (make_zip(files), make_tar(files), make_tar(files, "w"), make_tar(files, "w:xz"))
    for i, data in enumerate(archives):
        (tmp_path / str(i)).mkdir()
        staged, store = _extract(tmp_path / str(i), data)
        assert sorted(f.path for f in staged.files) == sorted(n for n, _ in files)
        assert not store.exists("scenes/s/files/train/r_0.png")  # staged, not committed
        for f in staged.files:
            f.pending.commit()
        assert store.path("scenes/s/files/train/r_0.png").read_bytes() == b"png"


def test_refusals(tmp_path: Path) -> None:
    _refused(tmp_path, make_zip([("../x", b"1")]), 422, "'..' in path")
    _refused(tmp_path, make_tar([("/etc/x", b"1")]), 422, "absolute path")
    _refused(tmp_path, zip_with_symlink(), 422, "symbolic link")
    _refused(tmp_path, tar_with(tarfile.SYMTYPE), 422, "symbolic link")
    _refused(tmp_path, tar_with(tarfile.LNKTYPE), 422, "hard link")
    _refused(tmp_path, tar_with(tarfile.FIFOTYPE), 422, "not a regular file")
    _refused(tmp_path, tar_with(tarfile.BLKTYPE), 422, "not a regular file")
    _refused(tmp_path, make_zip([("a", b"1"), ("./a", b"2")]), 422, "appears twice")
    _refused(tmp_path, zip_bomb(), 413, "zip bomb")
    _refused(tmp_path, make_zip([(f"f{i}", b"1") for i in range(11)]), 413, "more than 10 files")
    _refused(tmp_path, make_tar([("big", bytes(2 << 20))], "w"), 413, "over the file limit")
    _refused(
        tmp_path,
        make_zip([(f"f{i}", bytes(900_000)) for i in range(6)]),
        413,
        "zip bomb",  # many small members: the whole archive's ratio gives it away
    )
    _refused(tmp_path, b"PK\x03\x04 not really", 422, "corrupt")
    _refused(tmp_path, make_zip([]), 422, "no files")


def test_encrypted_zip_member_is_refused(tmp_path: Path) -> None:
    data = bytearray(make_zip([("secret.json", b"{}")]))
    # zipfile cannot write encrypted members: set the 'encrypted' flag bit by hand
    data[6] |= 0x1  # local file header
    central = data.find(b"PK\x01\x02")
    data[central + 8] |= 0x1  # central directory entry
    _refused(tmp_path, bytes(data), 422, "encrypted")


def test_lying_tar_header_is_caught(tmp_path: Path) -> None:
    """A member whose data ends early (truncated archive) is refused, not half-kept."""
    data = make_tar([("a.bin", bytes(100_000))], "w")
    _refused(tmp_path, data[:20_000], 422, "corrupt")


def test_nul_in_a_zip_member_name_is_refused_naming_it(tmp_path: Path) -> None:
    with pytest.raises(ApiError) as err:
        _extract(tmp_path, zip_with_nul())
    e = err.value
    assert (e.status, e.slug) == (422, "unsafe-archive")
    assert "evil.json\\x00.png" in e.detail and "NUL byte" in e.detail
    assert e.errors and e.errors[0].file == "evil.json\\x00.png"
    store_tmp = tmp_path / "store" / "tmp"
    assert not store_tmp.exists() or not any(store_tmp.iterdir()), "staged files left behind"


FOLDER = [("transforms_train.json", b"{}"), ("train/r_0.png", b"png"), ("a/b/c.txt", b"c")]


@pytest.mark.parametrize("mode", ["w", "w:gz"])
def test_tar_of_a_folder_with_dot_members_is_accepted(tmp_path: Path, mode: str) -> None:
    """``tar -C dir .``: the '.' folder and './' prefixes are normalised away."""
    staged, _ = _extract(tmp_path, tar_of_folder(FOLDER, mode))
    assert sorted(f.path for f in staged.files) == sorted(n for n, _ in FOLDER)
    staged.abort()


@pytest.mark.skipif(shutil.which("tar") is None, reason="no tar command")
def test_the_tar_command_on_a_folder_is_accepted(tmp_path: Path) -> None:
    src = tmp_path / "scene"
    for name, data in FOLDER:
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        (src / name).write_bytes(data)
    out = tmp_path / "scene.tgz"
    subprocess.run(["tar", "-C", str(src), "-czf", str(out), "."], check=True)
    (tmp_path / "x").mkdir()
    staged, _ = _extract(tmp_path / "x", out.read_bytes())
    assert sorted(f.path for f in staged.files) == sorted(n for n, _ in FOLDER)
    staged.abort()


def test_zip_with_dot_prefixes_is_accepted(tmp_path: Path) -> None:
    staged, _ = _extract(tmp_path, make_zip([("./" + n, d) for n, d in FOLDER]))
    assert sorted(f.path for f in staged.files) == sorted(n for n, _ in FOLDER)
    staged.abort()


def test_dot_style_archives_still_refuse_escapes(tmp_path: Path) -> None:
    _refused(tmp_path, tar_of_folder([("../x", b"1")]), 422, "'..' in path")
    _refused(tmp_path, tar_of_folder([("a/../../x", b"1")]), 422, "'..' in path")
    _refused(tmp_path, make_tar([("./../x", b"1")]), 422, "'..' in path")
    _refused(tmp_path, tar_with(tarfile.DIRTYPE, name="./.."), 422, "'..' in path")
    _refused(tmp_path, tar_with(tarfile.DIRTYPE, name="/etc"), 422, "absolute path")
    _refused(tmp_path, tar_with(tarfile.SYMTYPE, name="./link", linkname="../../.."), 422, "link")
    hard = tar_with(tarfile.LNKTYPE, name="./hard", linkname="/etc/passwd")
    _refused(tmp_path, hard, 422, "link")
