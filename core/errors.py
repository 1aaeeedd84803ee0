"""Error types users can act on: each names the file and the field at fault."""

from __future__ import annotations

from pathlib import Path


class GlintError(Exception):
    """Base class of every error Glint raises on purpose."""


class AssetError(GlintError, ValueError):
    """A relightable asset cannot be made from this input; the message says why."""


class SceneError(GlintError):
    """A scene on disk is malformed: missing files, bad poses, unreadable images.

    ``file`` is the offending path (or the scene folder), ``field`` the JSON key,
    column or property at fault (``None`` when the whole file is bad).
    """

    def __init__(self, message: str, *, file: str | Path | None = None, field: str | None = None):
        self.file = str(file) if file is not None else None
        self.field = field
        self.reason = message
        parts = []
        if self.file:
            parts.append(self.file)
        if field:
            parts.append(f"field '{field}'")
        prefix = ": ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class BackendUnavailableError(GlintError):
    """A rasteriser backend was requested by name but cannot run here."""
