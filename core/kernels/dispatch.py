"""When a compiled CPU kernel may take a call: one test for every ``compiled=None``."""

from __future__ import annotations

import torch
from torch import Tensor

_FLOATS = (torch.float32, torch.float64)


def cpu_float(*tensors: Tensor) -> bool:
    """All on the CPU and float32/float64: what the numba kernels are compiled for
    (anything else, e.g. a CUDA tensor, takes the torch path)."""
    return all(t.device.type == "cpu" and t.dtype in _FLOATS for t in tensors)
