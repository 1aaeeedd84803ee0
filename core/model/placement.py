"""Where a finished run is reopened on this machine: its device and rasteriser backend.

A GPU worker's run records ``cuda``; tools that only read a run (``glint mesh``,
``glint eval``, the viewer) keep what works here and fall back, with a note, where not.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from core.devices import DEVICE_RE, device_problem, require_device
from core.render.raster import fallback_backend, resolve_backend


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
