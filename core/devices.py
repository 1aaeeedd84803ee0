"""Which torch device a run may use here.

A run records the device and rasteriser backend of the machine that trained it: a
GPU worker writes ``cuda``. Training must refuse a device this machine lacks with a
message naming the field (not torch's "Torch not compiled with CUDA enabled" from
deep inside a step), while tools that only read a finished run (``glint mesh``,
``glint eval``, the viewer) should still work on a laptop: they fall back to the CPU
and to a backend that runs there, and say so (``core.model.placement``).
"""

from __future__ import annotations

import re

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
