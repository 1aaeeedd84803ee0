"""Test files in the order that balances two workers: the longest first.

``scripts/test.sh`` runs pytest-xdist with ``--dist loadfile --no-loadscope-reorder``:
each file goes whole to one worker (its module fixtures are built once), in
collection order, to whichever worker is free. xdist's own reorder puts files with
the most tests first, which left the few-but-long files (crash recovery, the GPU
kit's dry run, S3 outages) for the end, one worker finishing them alone for minutes.
Longest-first (LPT) keeps the tail short.

The costs are the seconds each file took in a recorded run (``tests/durations.json``);
a file not in it (a new test) counts ``UNKNOWN_S``. Refresh the record with
``GLINT_TEST_DURATIONS=tests/durations.json bash scripts/test.sh``.
"""

from __future__ import annotations

import json
import os
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

DURATIONS = Path(__file__).with_name("durations.json")
UNKNOWN_S = 1.0
ENV = "GLINT_TEST_DURATIONS"


def file_of(nodeid: str) -> str:
    """The test file of a node id (``tests/x.py::test_y[1]`` -> ``tests/x.py``)."""
    return nodeid.split("::", 1)[0]


def load_costs(path: Path = DURATIONS) -> dict[str, float]:
    """Seconds per test file from a recorded run; empty when there is no record."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return {str(k): float(v) for k, v in data.items() if isinstance(v, (int, float))}


def longest_first(nodeids: Sequence[str], costs: dict[str, float]) -> list[int]:
    """Indices of ``nodeids`` with whole files ordered by cost, longest first; a file's
    tests stay together and in their order; ties keep collection order."""
    first: dict[str, int] = {}
    for i, nid in enumerate(nodeids):
        first.setdefault(file_of(nid), i)

    def key(i: int) -> tuple[float, int, int]:
        f = file_of(nodeids[i])
        return (-costs.get(f, UNKNOWN_S), first[f], i)

    return sorted(range(len(nodeids)), key=key)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    order = longest_first([it.nodeid for it in items], load_costs())
    items[:] = [items[i] for i in order]


_spent: dict[str, float] = defaultdict(float)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if os.environ.get(ENV):
        _spent[file_of(report.nodeid)] += float(report.duration)


def pytest_sessionfinish(session: pytest.Session, exitstatus: Any) -> None:
    """With ``GLINT_TEST_DURATIONS`` set, write seconds per file (the controller only:
    under xdist it receives every worker's reports)."""
    target = os.environ.get(ENV)
    if not target or hasattr(session.config, "workerinput") or not _spent:
        return
    ranked = dict(sorted(((k, round(v, 2)) for k, v in _spent.items()), key=lambda kv: -kv[1]))
    Path(target).write_text(json.dumps(ranked, indent=1) + "\n")
