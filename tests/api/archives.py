"""Archive builders for tests: good ones and every kind of hostile one, in memory."""

from __future__ import annotations

import io
import stat
import tarfile
import zipfile


def make_zip(files: list[tuple[str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in files:
            info = zipfile.ZipInfo(name)  # keeps the name verbatim ('../x', '/abs')
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, data)
    return buf.getvalue()


def make_tar(files: list[tuple[str, bytes]], mode: str = "w:gz") -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode=mode) as tf:
        for name, data in files:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def zip_with_symlink(target: str = "/etc/passwd") -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("transforms_train.json", b"{}")
        info = zipfile.ZipInfo("train/r_0.png")
        info.create_system = 3
        info.external_attr = (stat.S_IFLNK | 0o777) << 16
        zf.writestr(info, target)
    return buf.getvalue()


def tar_with(kind: bytes, name: str = "train/r_0.png", linkname: str = "/etc/passwd") -> bytes:
    """A tar holding one special member (SYMTYPE, LNKTYPE, CHRTYPE, FIFOTYPE, ...)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tf:
        ok = tarfile.TarInfo("transforms_train.json")
        ok.size = 2
        tf.addfile(ok, io.BytesIO(b"{}"))
        info = tarfile.TarInfo(name)
        info.type = kind
        info.linkname = linkname
        tf.addfile(info)
    return buf.getvalue()


def zip_bomb(size: int = 8 << 20) -> bytes:
    """One member of ``size`` zero bytes (compresses ~1000x), written without holding it."""
    buf = io.BytesIO()
    chunk = bytes(1 << 20)
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf, zf.open("zeros.bin", "w") as out:
        for _ in range(size // len(chunk)):
            out.write(chunk)
    return buf.getvalue()


def zip_with_nul(name: str = "evil.json\x00.png") -> bytes:
    """A zip whose second member's name holds a NUL byte (zipfile cannot write one)."""
    stand_in = name.replace("\x00", "\x01")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("transforms_train.json", b"{}")
        zf.writestr(zipfile.ZipInfo(stand_in), b"{}")
    # the same length: the local header and the central directory both get the NUL
    return buf.getvalue().replace(stand_in.encode(), name.encode())


def tar_of_folder(files: list[tuple[str, bytes]], mode: str = "w:gz") -> bytes:
    """What ``tar -C dir -czf - .`` writes: a '.' folder, then './'-prefixed members."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode=mode) as tf:
        folders = {"."} | {
            "./" + "/".join(n.split("/")[:i]) for n, _ in files for i in range(1, n.count("/") + 1)
        }
        for folder in sorted(folders):
            info = tarfile.TarInfo(folder)
            info.type = tarfile.DIRTYPE
            tf.addfile(info)
        for name, data in files:
            info = tarfile.TarInfo("./" + name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()
