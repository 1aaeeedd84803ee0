"""What to upload: a scene folder, an archive (unpacked here, so its files go up in
resumable chunks), or a list of photos; each file with the path it takes in the scene.

Hidden files and folders (``.DS_Store``, ``.git``) and macOS's ``__MACOSX`` are left
out: they are never part of a capture and would only make commit's checks noisier.
"""

from __future__ import annotations

import hashlib
import shutil
import tarfile
import tempfile
import zipfile
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from glint_client.errors import GlintClientError

ARCHIVE_SUFFIXES = (".zip", ".tar", ".tgz", ".tar.gz", ".tbz2", ".tar.bz2", ".txz", ".tar.xz")
HASH_BLOCK = 1 << 20


@dataclass(frozen=True)
class LocalFile:
    """A file to send: ``path`` in the scene (POSIX, relative), ``source`` on disk."""

    path: str
    source: Path
    size: int


def is_archive(path: Path) -> bool:
    return path.is_file() and path.name.lower().endswith(ARCHIVE_SUFFIXES)


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        while block := f.read(HASH_BLOCK):
            h.update(block)
    return h.hexdigest()


def _skipped(parts: Iterable[str]) -> bool:
    return any(p.startswith(".") or p == "__MACOSX" for p in parts)


def folder_files(root: Path) -> list[LocalFile]:
    """Every file under ``root`` (symbolic links followed), by scene path."""
    out = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if _skipped(rel.parts) or not p.is_file():
            continue
        out.append(LocalFile(rel.as_posix(), p, p.stat().st_size))
    return out


def photo_files(photos: Sequence[Path]) -> list[LocalFile]:
    """Loose photos (no poses): each at the scene's top level under its own name."""
    out: dict[str, LocalFile] = {}
    for p in photos:
        if not p.is_file():
            raise GlintClientError(f"{p}: not a file")
        if p.name in out:
            raise GlintClientError(f"two photos are named '{p.name}' ({out[p.name].source}, {p})")
        out[p.name] = LocalFile(p.name, p, p.stat().st_size)
    return sorted(out.values(), key=lambda f: f.path)


def _safe_member(name: str) -> PurePosixPath | None:
    """The member's relative path, or None for directory entries and skipped names;
    raises on names that would escape the folder (``..``, absolute, drive letters)."""
    if "\\" in name or "\x00" in name:
        raise GlintClientError(f"archive member '{name!r}' has an unsafe name")
    path = PurePosixPath(name)
    parts = [p for p in path.parts if p not in ("", ".")]
    if path.is_absolute() or ".." in parts or (parts and ":" in parts[0]):
        raise GlintClientError(f"archive member '{name}' points outside the archive")
    if not parts or _skipped(parts):
        return None
    return PurePosixPath(*parts)


def _copy_into(dest: Path, rel: PurePosixPath, data: Iterator[bytes] | None) -> None:
    target = dest.joinpath(*rel.parts)
    target.parent.mkdir(parents=True, exist_ok=True)
    with target.open("wb") as out:
        for block in data or ():
            out.write(block)


def _blocks(f: object) -> Iterator[bytes]:
    read = f.read  # type: ignore[attr-defined]
    while block := read(HASH_BLOCK):
        yield block


def unpack(archive: Path, dest: Path) -> None:
    """Extract regular files only (no links, devices or paths outside ``dest``)."""
    name = archive.name.lower()
    if name.endswith(".zip"):
        with zipfile.ZipFile(archive) as z:
            for info in z.infolist():
                if info.is_dir() or (rel := _safe_member(info.filename)) is None:
                    continue
                if (info.external_attr >> 16) & 0o170000 == 0o120000:
                    raise GlintClientError(f"archive member '{info.filename}' is a symbolic link")
                with z.open(info) as f:
                    _copy_into(dest, rel, _blocks(f))
        return
    try:
        with tarfile.open(archive) as t:
            for member in t:
                if member.isdir() or (rel := _safe_member(member.name)) is None:
                    continue
                if not member.isfile():
                    raise GlintClientError(
                        f"archive member '{member.name}' is not a regular file (a link or device)"
                    )
                f = t.extractfile(member)
                _copy_into(dest, rel, _blocks(f) if f else None)
    except tarfile.TarError as exc:
        raise GlintClientError(f"{archive}: not a readable archive ({exc})") from exc


def _unwrap(root: Path) -> Path:
    """An archive of a folder holds one folder with everything inside: look through it."""
    entries = list(root.iterdir())
    if len(entries) == 1 and entries[0].is_dir():
        return entries[0]
    return root


@contextmanager
def scene_files(sources: Sequence[Path]) -> Iterator[list[LocalFile]]:
    """The files of a capture given as a folder, an archive or photos.

    An archive is unpacked into a temporary folder that lives as long as the context:
    its files are then uploaded like a folder's (chunked, resumable: unpacking again
    after a crash gives the same bytes, hence the same checksums, and the server finds
    the unfinished uploads).
    """
    if not sources:
        raise GlintClientError("nothing to upload: give a folder, an archive or photos")
    for s in sources:
        if not s.exists():
            raise GlintClientError(f"{s}: no such file or folder")
    if len(sources) == 1 and sources[0].is_dir():
        files = folder_files(sources[0])
        if not files:
            raise GlintClientError(f"{sources[0]}: the folder holds no files")
        yield files
        return
    if len(sources) == 1 and is_archive(sources[0]):
        tmp = Path(tempfile.mkdtemp(prefix="glint-unpack-"))
        try:
            try:
                unpack(sources[0], tmp)
            except (zipfile.BadZipFile, OSError) as exc:
                raise GlintClientError(f"{sources[0]}: cannot unpack ({exc})") from exc
            files = folder_files(_unwrap(tmp))
            if not files:
                raise GlintClientError(f"{sources[0]}: the archive holds no files")
            yield files
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return
    if any(s.is_dir() for s in sources):
        raise GlintClientError("give one folder, or one archive, or photos (files), not a mix")
    yield photo_files(sources)
