"""Freed buffers stay in the process once ``keep_freed_memory`` has run (and go back to
the OS without it): the page faults a CPU training step no longer pays."""

from __future__ import annotations

import subprocess
import sys

import pytest

PROBE = """
import os, sys
from core.kernels.allocator import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
page = os.sysconf("SC_PAGE_SIZE")
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * page
bufs = []
for _ in range(10):  # 80 MiB in 8 MiB buffers, every page touched
    b = bytearray(8 << 20)
    b[::page] = b"\\x01" * len(range(0, len(b), page))
    bufs.append(b)
full = rss()
del bufs, b
print((full - rss()) / 2**20)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_buffers_stay_mapped_only_with_the_setting():
    def released(mode: str) -> float:
        out = subprocess.run(
            [sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True
        )
        return float(out.stdout)

    assert released("default") > 60.0  # glibc hands 8 MiB blocks straight back
    assert released("keep") < 10.0
