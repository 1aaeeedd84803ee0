"""Alembic environment: the URL comes from the Alembic config, else from Settings.

On PostgreSQL the upgrade holds an advisory lock, so several API replicas starting
at once migrate one after the other instead of racing.
"""

from __future__ import annotations

from alembic import context
from sqlalchemy import text

from api.service.db import make_engine
from api.service.models import Base

PG_LOCK_ID = 0x6C696E74  # "lint": any constant shared by all Glint processes

config = context.config
target_metadata = Base.metadata


def _url() -> str:
    url = config.get_main_option("sqlalchemy.url")
    if url:
        return url
    from api.service.settings import Settings

    return Settings().db_url


def run_offline() -> None:
    context.configure(url=_url(), target_metadata=target_metadata, literal_binds=True)
    with context.begin_transaction():
        context.run_migrations()


def run_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    engine = make_engine(_url())
    try:
        with engine.connect() as conn:
            _run(conn)
    finally:
        engine.dispose()


def _run(connection) -> None:  # type: ignore[no-untyped-def]
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",
    )
    with context.begin_transaction():
        if connection.dialect.name == "postgresql":
            connection.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": PG_LOCK_ID})
        context.run_migrations()


if context.is_offline_mode():
    run_offline()
else:
    run_online()
