"""Client-supplied file paths (multipart filenames, archive members) made safe.

A scene file path is relative, POSIX, inside the scene folder: no absolute paths,
no drive letters, no ``..``, no backslashes or control characters. ``.`` components
and a leading ``./`` (what ``tar -C dir .`` writes) are dropped.
"""

from __future__ import annotations

import re

_DRIVE = re.compile(r"^[A-Za-z]:")
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


class UnsafePathError(ValueError):
    """The path would escape the scene folder or cannot be stored."""


def clean_relpath(name: str, max_length: int = 255) -> str:
    """The normalised relative path for ``name``, or :class:`UnsafePathError` saying why."""
    if not name:
        raise UnsafePathError("empty path")
    if _CONTROL.search(name):
        raise UnsafePathError("control characters in path")
    if "\\" in name:
        raise UnsafePathError("backslash in path (use '/')")
    if name.startswith("/") or _DRIVE.match(name):
        raise UnsafePathError("absolute path")
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise UnsafePathError("'..' in path")
    if not parts:
        raise UnsafePathError("path names no file")
    out = "/".join(parts)
    if len(out) > max_length:
        raise UnsafePathError(f"path longer than {max_length} characters")
    if any(len(p.encode("utf-8")) > 255 for p in parts):
        raise UnsafePathError("a path component is longer than 255 bytes")
    return out
