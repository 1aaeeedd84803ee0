"""Byte-range and ETag rules for downloads."""

from __future__ import annotations

import pytest

from api.ranges import RangeNotSatisfiableError, etag_matches, parse_range


@pytest.mark.parametrize(
    ("header", "size", "expected"),
    [
        ("bytes=0-9", 100, (0, 9)),
        ("bytes=90-", 100, (90, 99)),
        ("bytes=-10", 100, (90, 99)),
        ("bytes=-1000", 100, (0, 99)),
        ("bytes=50-5000", 100, (50, 99)),
        ("bytes= 3 - 4", 100, (3, 4)),
        ("bytes=0-1,5-6", 100, None),  # several ranges: whole file
        ("items=0-1", 100, None),  # unknown unit: ignored
    ],
)
def test_parse_range(header: str, size: int, expected) -> None:
    assert parse_range(header, size) == expected


@pytest.mark.parametrize(
    "header", ["bytes=100-", "bytes=5-2", "bytes=-0", "bytes=abc", "bytes=-", "bytes="]
)
def test_unsatisfiable(header: str) -> None:
    with pytest.raises(RangeNotSatisfiableError) as err:
        parse_range(header, 100)
    assert err.value.status == 416 and err.value.headers == {"Content-Range": "bytes */100"}


def test_etag_matching() -> None:
    assert etag_matches('"abc"', '"abc"')
    assert etag_matches('W/"abc", "x"', '"abc"')
    assert etag_matches("*", '"abc"')
    assert not etag_matches('"abd"', '"abc"')
    assert not etag_matches(None, '"abc"')
