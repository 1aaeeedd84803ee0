"""One page of a list: every list endpoint answers ``Page`` and takes ``limit``/``offset``.

``{"items": [...], "total": n, "limit": l, "offset": o}``: ``total`` counts every item
matching the filters, ``limit`` is the page size used (the one asked for, at most
``GLINT_PAGE_SIZE_MAX``); the next page starts at ``offset + limit`` while that is below
``total``.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Query
from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session

Limit = Annotated[
    int, Query(ge=1, le=1000, description="items per page (at most GLINT_PAGE_SIZE_MAX)")
]
Offset = Annotated[int, Query(ge=0, le=2**31, description="items to skip (from 0)")]


def page_rows(
    session: Session, query: Select[Any], limit: int, offset: int, *, scalars: bool = True
) -> tuple[list[Any], int]:
    """The rows of one page of an ordered ``query``, and how many rows it has in all."""
    total = session.scalar(select(func.count()).select_from(query.order_by(None).subquery()))
    paged = query.limit(limit).offset(offset)
    rows = list(session.scalars(paged)) if scalars else list(session.execute(paged).all())
    return rows, int(total or 0)
