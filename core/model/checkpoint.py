"""Training checkpoints: written atomically, never with NaN, validated on load.

A checkpoint is one ``torch.save`` file holding::

    {"format": "glint-checkpoint", "version": 1,
     "gaussians": {"params": {name: Tensor}, "sh_degree": int},
     "extra": {...}}  # optimizer state dicts, iteration, RNG states, config, env map

Workers resume from the last checkpoint after being killed, so a save must leave
either the old file or the complete new one, never a torn file: it writes a temp
file in the same directory, fsyncs it, renames it over the target (atomic on POSIX
and Windows), then fsyncs the directory. ``extra`` is restricted to what
``torch.load(weights_only=True)`` can read back (tensors, numbers, strings, bytes,
None, lists/tuples/dicts of those), checked at save time so a checkpoint that could
not be loaded is never written. Convert NumPy RNG state with
``np.random.Generator.bit_generator.state`` (a dict of ints) and configs with
``model_dump()`` first.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import torch
from torch import Tensor

from core.errors import GlintError
from core.render.gaussians import PARAM_SHAPES, Gaussians

CHECKPOINT_FORMAT = "glint-checkpoint"
CHECKPOINT_VERSION = 1

_ATOMS = (bool, int, float, str, bytes, type(None), torch.dtype, torch.device, torch.Size)


class CheckpointError(GlintError):
    """A checkpoint cannot be written or read; names the file and the field at fault."""

    def __init__(self, message: str, *, file: str | Path | None = None, field: str | None = None):
        self.file = str(file) if file is not None else None
        self.field = field
        self.reason = message
        parts = [p for p in (self.file, f"field '{field}'" if field else None) if p]
        prefix = ": ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class NonFiniteError(CheckpointError, ValueError):
    """A parameter (or a float tensor in ``extra``) holds NaN or Inf; nothing was written."""


@dataclass
class Checkpoint:
    """What :func:`load_checkpoint` returns."""

    gaussians: Gaussians
    extra: dict[str, Any] = field(default_factory=dict)
    version: int = CHECKPOINT_VERSION
    path: Path | None = None


def atomic_write(path: str | Path, write: Callable[[BinaryIO], Any]) -> None:
    """Call ``write(f)`` on a temp file beside ``path``, fsync, rename over ``path``.

    On any exception the temp file is removed and an existing ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # os.open with 0o666 (not mkstemp's 0o600) so the umask decides who may read the
    # result: API and workers may run as different users on a shared volume.
    tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(6)}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    # Make the rename itself durable; not supported everywhere (e.g. Windows).
    with contextlib.suppress(OSError):
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def _check_finite(t: Tensor, name: str, file: Path) -> None:
    if (t.is_floating_point() or t.is_complex()) and not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).sum())
        raise NonFiniteError(
            f"{bad} NaN/Inf value(s); refusing to write the checkpoint", file=file, field=name
        )


def _check_extra(obj: Any, name: str, file: Path, check_finite: bool) -> None:
    """Reject what ``weights_only`` loading cannot read, and non-finite float tensors."""
    if isinstance(obj, Tensor):
        if check_finite:
            _check_finite(obj, name, file)
    elif isinstance(obj, Mapping):
        for k, v in obj.items():
            if not isinstance(k, (str, int)):
                raise CheckpointError(f"key {k!r} is not a str or int", file=file, field=name)
            _check_extra(v, f"{name}.{k}", file, check_finite)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _check_extra(v, f"{name}[{i}]", file, check_finite)
    elif not isinstance(obj, _ATOMS):
        raise CheckpointError(
            f"{type(obj).__name__} cannot be stored (tensors, numbers, strings and "
            "lists/tuples/dicts of those only)",
            file=file,
            field=name,
        )


def save_checkpoint(
    path: str | Path,
    gaussians: Gaussians,
    extra: Mapping[str, Any] | None = None,
    *,
    check_extra_finite: bool = True,
) -> Path:
    """Atomically write ``gaussians`` and caller state ``extra``; returns ``path``.

    Raises :class:`NonFiniteError` naming the parameter if any holds NaN/Inf (and,
    with ``check_extra_finite``, any float tensor in ``extra``), before touching disk.
    """
    path = Path(path)
    state = gaussians.state_dict()
    for name, t in state["params"].items():
        _check_finite(t, f"gaussians.params.{name}", path)
    extra = dict(extra or {})
    _check_extra(extra, "extra", path, check_extra_finite)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "gaussians": state,
        "extra": extra,
    }
    atomic_write(path, lambda f: torch.save(payload, f))
    return path


def load_checkpoint(
    path: str | Path, device: torch.device | str = "cpu", *, weights_only: bool = True
) -> Checkpoint:
    """Read and validate a checkpoint; tensors (also in ``extra``) land on ``device``.

    Raises :class:`CheckpointError` naming the file and the field for a missing or
    unreadable file, a foreign format, an unknown version or malformed parameters.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError("file not found", file=path)
    try:
        data = torch.load(path, map_location=device, weights_only=weights_only)
    except Exception as e:
        raise CheckpointError(f"not a readable checkpoint ({e})", file=path) from e
    if not isinstance(data, Mapping):
        raise CheckpointError(f"expected a dict, got {type(data).__name__}", file=path)
    if data.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"expected {CHECKPOINT_FORMAT!r}, got {data.get('format')!r}", file=path, field="format"
        )
    version = data.get("version")
    if version != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"unsupported version {version!r} (this Glint reads version {CHECKPOINT_VERSION})",
            file=path,
            field="version",
        )
    for key in ("gaussians", "extra"):
        if not isinstance(data.get(key), Mapping):
            raise CheckpointError("missing or not a dict", file=path, field=key)
    gstate = data["gaussians"]
    params = gstate.get("params")
    if not isinstance(params, Mapping):
        raise CheckpointError("missing or not a dict", file=path, field="gaussians.params")
    for name in PARAM_SHAPES:
        if name not in params:
            raise CheckpointError("missing", file=path, field=f"gaussians.params.{name}")
    for name, t in params.items():
        if not isinstance(t, Tensor):
            raise CheckpointError("not a tensor", file=path, field=f"gaussians.params.{name}")
    try:
        gaussians = Gaussians.from_state_dict(gstate, device)
    except (ValueError, KeyError, TypeError) as e:
        raise CheckpointError(str(e), file=path, field="gaussians.params") from e
    return Checkpoint(gaussians=gaussians, extra=dict(data["extra"]), version=version, path=path)
