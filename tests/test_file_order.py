"""The order test files reach the two workers in (tests/file_order.py)."""

from __future__ import annotations

import json

from tests.file_order import UNKNOWN_S, load_costs, longest_first

IDS = [
    "tests/a.py::t1",
    "tests/a.py::t2",
    "tests/b.py::t1",
    "tests/c.py::t1[0]",
    "tests/c.py::t1[1]",
    "tests/d.py::t1",
]


def test_longest_file_first_and_each_file_whole_in_its_order():
    costs = {"tests/a.py": 2.0, "tests/b.py": 30.0, "tests/c.py": 5.0, "tests/d.py": 0.1}
    order = [IDS[i] for i in longest_first(IDS, costs)]
    assert order == [
        "tests/b.py::t1",
        "tests/c.py::t1[0]",
        "tests/c.py::t1[1]",
        "tests/a.py::t1",
        "tests/a.py::t2",
        "tests/d.py::t1",
    ]


def test_unrecorded_files_count_the_default_and_ties_keep_collection_order():
    costs = {"tests/d.py": UNKNOWN_S + 1}
    order = [IDS[i] for i in longest_first(IDS, costs)]
    assert order[0] == "tests/d.py::t1"
    assert order[1:] == [i for i in IDS if not i.startswith("tests/d.py")]


def test_a_missing_or_broken_record_orders_nothing(tmp_path):
    assert load_costs(tmp_path / "none.json") == {}
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert load_costs(bad) == {}
    assert longest_first(IDS, {}) == list(range(len(IDS)))
    ok = tmp_path / "ok.json"
    ok.write_text(json.dumps({"tests/a.py": 3, "tests/b.py": "x"}))
    assert load_costs(ok) == {"tests/a.py": 3.0}
