"""Unpack an uploaded zip or tar archive into staged scene files, refusing anything unsafe.

Checks, all before or while bytes are written (never after):

* paths: relative, no ``..``, no absolute or drive paths, no backslashes, no control
  characters (:func:`api.paths.clean_relpath`); no duplicates; a zip member whose name
  holds a NUL byte is refused (``zipfile`` would silently cut the name there); ``./``
  prefixes and the archive's root folder (``.``, what ``tar -C dir .`` writes) are fine;
* member types: regular files and folders only: no symlinks, hard links, devices,
  FIFOs or sparse files (a link could point out of the scene folder);
* expansion: declared sizes per file and in total within the scene's budget, the
  file count within its budget, and the compression ratio bounded (zip bombs); the
  bytes actually written are counted too, since headers can lie;
* encrypted zip members are refused.

Nothing is ever extracted with ``extractall``: each member is copied into its own
pending store write, which the caller commits only when the whole archive passed.
"""

from __future__ import annotations

import re
import stat
import tarfile
import zipfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from api.paths import UnsafePathError, clean_relpath
from api.problems import ApiError, FieldError
from api.service.store import ArtifactStore
from api.uploads import Staged, StagedSet, too_large

RATIO_FLOOR_BYTES = 1 << 20  # ratios are only judged above this many uncompressed bytes
COPY_CHUNK = 1 << 20
ARCHIVE_TYPES = frozenset(
    {
        "application/zip",
        "application/x-zip-compressed",
        "application/x-tar",
        "application/gzip",
        "application/x-gzip",
        "application/x-gtar",
        "application/x-compressed-tar",
        "application/x-bzip2",
        "application/x-xz",
        "application/octet-stream",
    }
)


@dataclass(frozen=True)
class ArchiveLimits:
    max_files: int
    max_file_bytes: int
    max_total_bytes: int
    max_ratio: float
    max_path_length: int


_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def shown(member: str) -> str:
    """A member name fit for a message: control characters (NUL...) escaped, bounded."""
    out = _CONTROL.sub(lambda m: f"\\x{ord(m.group()):02x}", member)
    return out if len(out) <= 300 else out[:297] + "..."


def unsafe(detail: str, member: str) -> ApiError:
    """422 naming the member (in ``detail`` and as the ``file`` of ``errors``)."""
    name = shown(member)
    return ApiError(
        422,
        "unsafe-archive",
        f"archive member '{name}': {detail}",
        errors=[FieldError(field="body", file=name, message=detail)],
    )


def bad_archive(detail: str) -> ApiError:
    return ApiError(422, "bad-archive", detail)


class _Budget:
    """Running totals of one archive against its limits."""

    def __init__(self, limits: ArchiveLimits, archive_bytes: int) -> None:
        self.limits = limits
        self.archive_bytes = max(archive_bytes, 1)
        self.files = 0
        self.total = 0
        self.seen: set[str] = set()

    def path(self, name: str) -> str:
        try:
            path = clean_relpath(name, self.limits.max_path_length)
        except UnsafePathError as exc:
            raise unsafe(str(exc), name) from None
        if path in self.seen:
            raise unsafe("appears twice in the archive", name)
        self.seen.add(path)
        return path

    def folder(self, name: str) -> None:
        """Check a folder member; the archive's root (``.``, ``./``) needs no check."""
        if all(part in ("", ".") for part in name.split("/")):
            return
        try:
            clean_relpath(name, self.limits.max_path_length)
        except UnsafePathError as exc:
            raise unsafe(str(exc), name) from None

    def add(self, name: str, size: int, compressed: int | None = None) -> None:
        lim = self.limits
        self.files += 1
        self.total += size
        # the ratio first: for a bomb it is the diagnosis that helps
        ratio = size / max(compressed or 0, 1)
        if compressed is not None and size > RATIO_FLOOR_BYTES and ratio > lim.max_ratio:
            raise too_large(
                f"archive member '{name}' expands {ratio:.0f}x "
                f"(limit {lim.max_ratio:.0f}x): refusing a likely zip bomb"
            )
        if self.total > RATIO_FLOOR_BYTES and self.total / self.archive_bytes > lim.max_ratio:
            raise too_large(
                f"archive expands {self.total / self.archive_bytes:.0f}x "
                f"(limit {lim.max_ratio:.0f}x): refusing a likely zip bomb"
            )
        if self.files > lim.max_files:
            raise too_large(f"archive holds more than {lim.max_files} files (the scene's limit)")
        if size > lim.max_file_bytes:
            raise too_large(f"archive member '{name}' ({size} bytes) is over the file limit")
        if self.total > lim.max_total_bytes:
            raise too_large(
                f"archive expands to more than {lim.max_total_bytes} bytes (the scene's limit)"
            )


def _copy(src: BinaryIO, staged: Staged, declared: int) -> None:
    """Copy a member, refusing to write more bytes than its header declared; then seal
    it (a bucket store sends its last part now: the archive's files are not held)."""
    while chunk := src.read(COPY_CHUNK):
        if staged.pending.size + len(chunk) > declared:
            raise too_large(f"archive member '{staged.path}' is larger than its header says")
        staged.pending.write(chunk)
    staged.pending.seal()


def _zip_members(zf: zipfile.ZipFile, budget: _Budget) -> Iterator[tuple[zipfile.ZipInfo, str]]:
    """Every file member, checked; the whole directory is checked before any is yielded."""
    out = []
    for info in zf.infolist():
        name = info.filename
        if "\x00" in info.orig_filename:  # ZipInfo cut the name at the NUL
            raise unsafe("NUL byte in the name", info.orig_filename)
        if info.flag_bits & 0x1:
            raise unsafe("is encrypted", name)
        mode = info.external_attr >> 16
        kind = stat.S_IFMT(mode)
        if info.create_system == 3 and kind not in (0, stat.S_IFREG, stat.S_IFDIR):
            what = "is a symbolic link" if kind == stat.S_IFLNK else "is not a regular file"
            raise unsafe(what, name)
        if info.is_dir():
            budget.folder(name)
            continue
        path = budget.path(name)
        budget.add(name, info.file_size, info.compress_size)
        out.append((info, path))
    yield from out


def _extract_zip(
    archive: Path, store: ArtifactStore, key_for: Callable[[str], str], budget: _Budget
) -> StagedSet:
    staged = StagedSet()
    try:
        with zipfile.ZipFile(archive) as zf:
            for info, path in _zip_members(zf, budget):
                item = Staged(path, store.begin(key_for(path)))
                staged.files.append(item)
                with zf.open(info) as src:
                    _copy(src, item, info.file_size)
    except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
        staged.abort()
        raise bad_archive(f"corrupt or unsupported zip archive: {exc}") from None
    except BaseException:
        staged.abort()
        raise
    return staged


def _extract_tar(
    archive: Path, store: ArtifactStore, key_for: Callable[[str], str], budget: _Budget
) -> StagedSet:
    staged = StagedSet()
    try:
        with tarfile.open(archive, "r:*") as tf:
            for m in tf:  # members are checked before the next header is read
                if m.issym() or m.islnk():
                    raise unsafe(f"is a {'symbolic' if m.issym() else 'hard'} link", m.name)
                if m.isdir():
                    budget.folder(m.name)
                    continue
                if not m.isreg() or m.issparse():
                    raise unsafe("is not a regular file", m.name)
                path = budget.path(m.name)
                budget.add(m.name, m.size)
                item = Staged(path, store.begin(key_for(path)))
                staged.files.append(item)
                src = tf.extractfile(m)
                assert src is not None
                with src:
                    _copy(src, item, m.size)
                if item.pending.size != m.size:
                    raise bad_archive(f"archive member '{m.name}' is truncated")
    except (tarfile.TarError, zlib.error, EOFError, OSError, ValueError) as exc:
        staged.abort()
        raise bad_archive(f"corrupt or unsupported tar archive: {exc}") from None
    except BaseException:
        staged.abort()
        raise
    return staged


def sniff(archive: Path) -> str | None:
    """'zip', 'tar' (plain or gzip/bzip2/xz compressed) or None, from the bytes."""
    with open(archive, "rb") as fh:
        head = fh.read(512)
    if head[:4] in (b"PK\x03\x04", b"PK\x05\x06"):
        return "zip"
    if head[:2] == b"\x1f\x8b" or head[:3] == b"BZh" or head[:6] == b"\xfd7zXZ\x00":
        return "tar"
    if len(head) == 512 and head[257:262] == b"ustar":
        return "tar"
    return None


def extract_archive(
    archive: Path, store: ArtifactStore, key_for: Callable[[str], str], limits: ArchiveLimits
) -> StagedSet:
    """Stage every file of a zip or tar archive, or raise a problem (nothing left behind)."""
    kind = sniff(archive)
    if kind is None:
        raise bad_archive("body is not a zip or tar (optionally gzip/bzip2/xz) archive")
    budget = _Budget(limits, archive.stat().st_size)
    staged = (_extract_zip if kind == "zip" else _extract_tar)(archive, store, key_for, budget)
    if not staged.files:
        raise bad_archive("archive holds no files")
    return staged
