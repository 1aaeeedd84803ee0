"""Named stages of a training step, as ranges torch's profiler records.

``with stage("gbuffer"): ...`` costs a few microseconds when no profiler runs (a step
takes tens of milliseconds), and lets ``bench/step_breakdown.py`` say where a step's
time goes: each stage's own forward time, and the backward time of the autograd nodes
its operations created.
"""

from __future__ import annotations

from torch.profiler import record_function

PREFIX = "glint::"


def stage(name: str) -> record_function:
    """A profiler range named ``glint::<name>`` (a context manager)."""
    return record_function(PREFIX + name)
