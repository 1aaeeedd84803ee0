"""The recorded kernel signatures (scripts/kernel_signatures.tsv) still name kernels that
take them, and recording, reading and compiling a list round-trips through numba's cache."""

from __future__ import annotations

import importlib
import shutil
import sys
from pathlib import Path

import pytest

from core.kernels import signatures as ks


def test_every_recorded_signature_names_a_kernel_with_that_many_arguments() -> None:
    entries = ks.read()
    assert len(entries) >= 100  # a whole test run's worth, not a stub
    stale = [f"{e.module}.{e.function}" for e in entries if not ks.arity_matches(e)]
    assert stale == [], "re-record: python scripts/warm_kernels.py --record (after a test run)"


def test_balance_splits_the_cost_evenly_and_loses_nothing() -> None:
    entries = [ks.Entry("m", f"f{i}", c, "()") for i, c in enumerate([9, 7, 5, 4, 3, 2, 2, 1])]
    a, b = ks.balance(entries, 2)
    assert sorted(a + b, key=lambda e: e.function) == sorted(entries, key=lambda e: e.function)
    assert abs(sum(e.cost for e in a) - sum(e.cost for e in b)) <= 1
    assert ks.balance(entries, 3)[2]  # every share gets work when there is enough


def test_a_malformed_line_names_the_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "sigs.tsv"
    path.write_text(ks.HEADER + "core.x\tf\t12\t(int64,)\ncore.y\tg\tbig\t(int64,)\n")
    with pytest.raises(ValueError, match=r"sigs.tsv:3: expected module, function, bytes"):
        ks.read(path)
    assert ks.read(tmp_path / "missing.tsv") == []


def test_record_then_compile_round_trips_through_the_cache(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pkg = tmp_path / "glint_sig_probe"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "kern.py").write_text(
        "from numba import njit\n\n\n@njit(cache=True)\ndef add(a, b):\n    return a + b\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    mod = importlib.import_module("glint_sig_probe.kern")
    try:
        mod.add(1, 2.5)
        mod.add(1.0, 2.5)
        entries = ks.record(tmp_path, ("glint_sig_probe",))
        assert [(e.module, e.function) for e in entries] == [("glint_sig_probe.kern", "add")] * 2
        assert sorted(e.signature for e in entries) == ["(float64, float64)", "(int64, float64)"]
        assert all(e.cost > 0 for e in entries)
        listed = tmp_path / "sigs.tsv"
        ks.write(entries, listed)
        assert ks.read(listed) == entries

        # a fresh process's view: no cache, the module imported anew
        shutil.rmtree(pkg / "__pycache__")
        del sys.modules["glint_sig_probe.kern"]
        stale = ks.Entry("glint_sig_probe.kern", "gone", 1, "(int64,)")
        changed = ks.Entry("glint_sig_probe.kern", "add", 1, "(int64,)")
        done, msgs = ks.compile_entries([*ks.read(listed), stale, changed])
        assert done == 2
        assert len(msgs) == 2 and "no such function" in msgs[0] and "changed" in msgs[1]
        assert ks.record(tmp_path, ("glint_sig_probe",)) == entries  # the cache is back
    finally:
        for name in ("glint_sig_probe.kern", "glint_sig_probe"):
            sys.modules.pop(name, None)
