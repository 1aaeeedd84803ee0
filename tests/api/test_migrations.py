"""Alembic migrations build exactly the schema the models describe, up and down."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import inspect, text
from sqlalchemy.exc import IntegrityError

from api.service.db import Database
from api.service.migrate import alembic_config, upgrade
from api.service.models import ApiKey, Base


@pytest.fixture(params=["sqlite", "postgresql"])
def url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'm.db'}"
    from tests.api.conftest import _pg_database

    gen = _pg_database()  # a database of its own: this test drops every table
    request.addfinalizer(lambda: next(gen, None))
    return next(gen)


def test_upgrade_matches_models_and_downgrades(url: str) -> None:
    db = Database(url)
    try:
        upgrade(db.engine)
        upgrade(db.engine)  # idempotent
        with db.engine.connect() as conn:
            ctx = MigrationContext.configure(conn, opts={"compare_type": True})
            assert compare_metadata(ctx, Base.metadata) == []
            head = ScriptDirectory.from_config(alembic_config(url)).get_current_head()
            assert head is not None and ctx.get_current_revision() == head
        with db.engine.connect() as conn:
            cfg = alembic_config(url)
            cfg.attributes["connection"] = conn
            command.downgrade(cfg, "base")
            conn.commit()
        tables = set(inspect(db.engine).get_table_names()) - {"alembic_version"}
        assert tables == set()
        upgrade(db.engine)
        assert {"api_keys", "scenes", "scene_files", "jobs", "artifacts"} <= set(
            inspect(db.engine).get_table_names()
        )
    finally:
        db.dispose()


def test_sqlite_pragmas(tmp_path: Path) -> None:
    db = Database(f"sqlite:///{tmp_path / 'p.db'}")
    with db.engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    db.dispose()


def test_keys_from_before_scopes_become_admin_keys(url: str) -> None:
    """Migration 0004: a key made before scopes existed keeps doing everything it did."""
    db = Database(url)
    try:
        upgrade(db.engine, "0003")
        with db.engine.begin() as conn:
            conn.execute(
                text(
                    "INSERT INTO api_keys (id, owner, name, key_hash, prefix, created_at) "
                    "VALUES ('key_old', 'alice', 'alice', :h, 'glk_abcdef', :t)"
                ),
                {"h": "0" * 64, "t": datetime.now(UTC).replace(tzinfo=None)},
            )
        upgrade(db.engine)
        with db.read() as s:
            row = s.get(ApiKey, "key_old")
            assert (row.scope, row.last_used_at, row.owner) == ("admin", None, "alice")
        with pytest.raises(IntegrityError), db.engine.begin() as conn:  # no default any more
            conn.execute(
                text(
                    "INSERT INTO api_keys (id, owner, name, key_hash, prefix, created_at) "
                    "VALUES ('key_new', 'bob', 'bob', :h, 'glk_abcdef', :t)"
                ),
                {"h": "1" * 64, "t": datetime.now(UTC).replace(tzinfo=None)},
            )
    finally:
        db.dispose()
