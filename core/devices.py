"""Which torch device a run may use here, and where a finished run is reopened.

A run records the device and rasteriser backend of the machine that trained it: a
GPU worker writes ``cuda``. Training must refuse a device this machine lacks with a
message naming the field (not torch's "Torch not compiled with CUDA enabled" from
deep inside a step), while tools that only read a finished run (``glint mesh``,
``glint eval``, the viewer) should still work on a laptop: they fall back to the CPU
and to a backend that runs there, and say so.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import torch

from core.errors import GlintError

DEVICE_RE = re.compile(r"^(cpu|cuda(:\d+)?)$")
DEVICE_HINT = "'cpu', 'cuda' or 'cuda:N'"


class DeviceUnavailableError(GlintError):
    """The configured device does not exist on this machine."""


def device_problem(device: torch.device | str) -> str | None:
    """None when tensors can live on ``device`` here, else why not."""
    device = torch.device(device)
    if device.type == "cpu":
        return None
    if device.type != "cuda":
        return f"'{device}' is not a device Glint runs on (expected {DEVICE_HINT})"
    if torch.version.cuda is None and torch.version.hip is None:
        return "this torch build is CPU-only"
    count = torch.cuda.device_count()
    if count == 0:
        return "no CUDA device is visible: no driver, or CUDA_VISIBLE_DEVICES is empty"
    if device.index is not None and device.index >= count:
        return f"only {count} CUDA device(s) are visible (cuda:0 to cuda:{count - 1})"
    return None


def require_device(name: str, field_name: str = "device") -> torch.device:
    """``name`` as a torch device, or a DeviceUnavailableError naming the field.

    ``field_name`` is a config field (``device``) or a command-line option (``--device``).
    """
    what = f"option '{field_name}'" if field_name.startswith("-") else f"field '{field_name}'"
    if not DEVICE_RE.match(name):
        raise DeviceUnavailableError(f"{what}: expected {DEVICE_HINT}, got '{name}'")
    reason = device_problem(name)
    if reason is not None:
        raise DeviceUnavailableError(f"{what}: '{name}' cannot be used here: {reason}; use 'cpu'")
    return torch.device(name)


@dataclass
class Placement:
    """Device and backend to reopen a run with, and what changed from its record."""

    device: str
    backend: str
    notes: list[str] = field(default_factory=list)


def reopen_placement(
    device: str, backend: str, *, device_override: str | None = None,
    backend_override: str | None = None,
) -> Placement:  # fmt: skip
    """Where to reopen a run recorded with ``device``/``backend`` on this machine.

    Overrides are the user's explicit choice and must work here (errors otherwise);
    the recorded values are kept where they work and replaced, with a note, where not.
    """
    from core.raster import fallback_backend, resolve_backend

    notes: list[str] = []
    if device_override is not None:
        dev = str(require_device(device_override, "--device"))
    elif DEVICE_RE.match(device) and device_problem(device) is None:
        dev = device
    else:
        reason = device_problem(device) if DEVICE_RE.match(device) else "not a device"
        notes.append(
            f"the run trained on '{device}', which this machine lacks ({reason}); using cpu"
        )
        dev = "cpu"
    if backend_override is not None:
        return Placement(dev, resolve_backend(backend_override, dev), notes)
    chosen, why = fallback_backend(backend, dev)
    if why is not None:
        notes.append(f"{why}; rendering with '{chosen}'")
    return Placement(dev, backend if why is None else chosen, notes)
